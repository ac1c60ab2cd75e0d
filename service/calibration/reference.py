"""The reference instrument's log: a CSV ``t_s,force_N`` on its own clock.

Blank and non-numeric lines are skipped and counted (instruments write
status lines, repeated headers, half-written last lines); a reference
without any numeric line is an error naming the file.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

HEADER = ("t_s", "force_N")
MAX_LISTED_SKIPS = 20


@dataclass(frozen=True)
class Reference:
    """Samples in file order: ``t_s`` and ``force_N`` of shape (k,), the
    instrument's clock (s) and force (N); ``skipped`` lines (1-based numbers
    of the first MAX_LISTED_SKIPS in ``skipped_lines``)."""

    path: str
    t_s: np.ndarray
    force_N: np.ndarray
    skipped: int
    skipped_lines: tuple[int, ...]

    @property
    def rate_hz(self) -> float:
        return (len(self.t_s) - 1) / (self.t_s[-1] - self.t_s[0]) if len(self.t_s) > 1 else 0.0


def _numbers(line: str) -> tuple[float, float] | None:
    parts = line.split(",")
    if len(parts) != 2:
        return None
    try:
        t, f = float(parts[0]), float(parts[1])
    except ValueError:
        return None
    return (t, f) if math.isfinite(t) and math.isfinite(f) else None


def parse_reference(text: str, path: str = "<reference>") -> Reference:
    """Parse the CSV text; ValueError naming ``path`` and the line for a
    missing header, time running backwards, or no numeric line at all."""
    lines = text.splitlines()
    if not lines or tuple(c.strip() for c in lines[0].split(",")) != HEADER:
        raise ValueError(f"{path}:1: the reference needs the header 't_s,force_N', got {lines[0][:60] if lines else ''!r}")
    t, f, skipped = [], [], []
    for number, line in enumerate(lines[1:], start=2):
        values = _numbers(line.strip())
        if values is None:
            skipped.append(number)
            continue
        if t and values[0] <= t[-1]:
            raise ValueError(f"{path}:{number}: time {values[0]} s does not follow {t[-1]} s "
                             "(the reference must be in time order, without repeats)")
        t.append(values[0])
        f.append(values[1])
    if len(t) < 2:
        raise ValueError(f"{path}: the reference has {'no' if not t else 'only one'} numeric line "
                         f"({len(skipped)} lines skipped)")
    return Reference(path, np.array(t), np.array(f), len(skipped), tuple(skipped[:MAX_LISTED_SKIPS]))


def read_reference(path: str | Path) -> Reference:
    """Read a reference CSV (UTF-8); OSError if it cannot be read."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"no such reference file: {path}") from None
    return parse_reference(text, str(path))

"""The reference instrument's log: a CSV ``t_s,force_N`` (a balance or load
cell: a grid's session) or ``t_s,fx_N,fy_N,fz_N`` (a force/torque sensor: a
quad's) on its own clock.

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
HEADER_3D = ("t_s", "fx_N", "fy_N", "fz_N")
MAX_LISTED_SKIPS = 20


@dataclass(frozen=True)
class Reference:
    """Samples in file order: ``t_s`` and ``force_N`` of shape (k,), the
    instrument's clock (s) and force (N); ``skipped`` lines (1-based numbers
    of the first MAX_LISTED_SKIPS in ``skipped_lines``)."""

    path: str
    t_s: np.ndarray
    force_N: np.ndarray  # a 3-axis log's: Fz, the normal force
    skipped: int
    skipped_lines: tuple[int, ...]
    fxyz_N: np.ndarray | None = None  # (k, 3) of a 3-axis log
    zero_N: tuple[float, ...] | None = None  # the rest level per force column (reference_zero.py); None: not looked at
    zero_subtracted: bool = False  # zero_N was subtracted (--zero-reference), else the log is as written
    zero_warning: str | None = None  # the rest level is off 0 beyond tolerance, not subtracted: what to do

    @property
    def rate_hz(self) -> float:
        return (len(self.t_s) - 1) / (self.t_s[-1] - self.t_s[0]) if len(self.t_s) > 1 else 0.0


def _numbers(line: str, columns: int) -> tuple[float, ...] | None:
    parts = line.split(",")
    if len(parts) != columns:
        return None
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        return None
    return values if all(math.isfinite(v) for v in values) else None


def parse_reference(text: str, path: str = "<reference>") -> Reference:
    """Parse the CSV text; ValueError naming ``path`` and the line for a
    missing header, time running backwards, or no numeric line at all."""
    lines = text.splitlines()
    header = tuple(c.strip() for c in lines[0].split(",")) if lines else ()
    if header not in (HEADER, HEADER_3D):
        raise ValueError(f"{path}:1: the reference needs the header 't_s,force_N' or 't_s,fx_N,fy_N,fz_N', "
                         f"got {lines[0][:60] if lines else ''!r}")
    rows, skipped = [], []
    for number, line in enumerate(lines[1:], start=2):
        values = _numbers(line.strip(), len(header))
        if values is None:
            skipped.append(number)
            continue
        if rows and values[0] <= rows[-1][0]:
            raise ValueError(f"{path}:{number}: time {values[0]} s does not follow {rows[-1][0]} s "
                             "(the reference must be in time order, without repeats)")
        rows.append(values)
    if len(rows) < 2:
        raise ValueError(f"{path}: the reference has {'no' if not rows else 'only one'} numeric line "
                         f"({len(skipped)} lines skipped)")
    table = np.array(rows)
    fxyz = table[:, 1:] if header == HEADER_3D else None
    return Reference(path, table[:, 0], table[:, -1], len(skipped), tuple(skipped[:MAX_LISTED_SKIPS]), fxyz)


# Units an instrument may log under a force_N header, in N each. lbf and kgf are 2.2× apart, gram-force and
# mN likewise; a sensor is within ±25 % of the papers' curves (a tester's quads), so UNIT_TOLERANCE splits them.
UNITS_N = {"lbf": 4.448222, "kgf": 9.80665, "gram-force": 9.80665e-3, "mN": 1e-3, "kN": 1e3}
UNIT_TOLERANCE = 1.45


def unit_hint(ratio: float, board: str) -> str | None:
    """What to say of a reference that logs ``ratio`` (> 0) times the force
    the board's response gives (``board`` says how it was read): the unit it
    likely logs, when ``ratio`` is within UNIT_TOLERANCE of 1/its newtons;
    None when none is (N, a sensor unlike the papers', or no ratio)."""
    if not (math.isfinite(ratio) and ratio > 0):
        return None
    for unit, newtons in UNITS_N.items():
        if abs(math.log(ratio * newtons)) < math.log(UNIT_TOLERANCE):
            return (f"the reference logs {ratio:.3g}× the force {board}, as one in {unit} would "
                    f"({newtons:g} N each): convert it to N")
    return None


FLAT_TOP_SAMPLES = 5  # consecutive samples at exactly the log's largest value: one stretch
FLAT_TOP_STRETCHES = 3  # stretches in which an instrument at its limit shows (a held press's noise rarely repeats)


def flat_top(force_N: np.ndarray) -> tuple[float, int] | None:
    """(the largest force, the stretches it is held flat in) where it is so
    in FLAT_TOP_STRETCHES or more: an instrument that saturated there (a
    tester's, clipped at 8.00 N, calibrated 46 taxels to 8 N without a
    word; presses past it read as it); None otherwise."""
    top = float(np.max(force_N))
    at_top = np.concatenate([[False], force_N == top, [False]])
    edges = np.flatnonzero(np.diff(at_top.astype(np.int8)))
    stretches = int(np.count_nonzero(edges[1::2] - edges[::2] >= FLAT_TOP_SAMPLES))
    return (top, stretches) if stretches >= FLAT_TOP_STRETCHES else None


def flat_top_said(reference: Reference) -> str | None:
    """The summary's warning for a reference flat at its top (``flat_top``), or None."""
    found = flat_top(reference.force_N)
    if found is None:
        return None
    return (f"WARNING: the reference holds its largest force, {found[0]:.3f} N, flat in {found[1]} stretches: "
            f"saturated there? Forces above {found[0]:.3f} N are not calibrated (a press past it read as it)")


def read_reference(path: str | Path) -> Reference:
    """Read a reference CSV (UTF-8, with or without the byte-order mark a
    spreadsheet saving "CSV UTF-8" puts first); OSError if it cannot be read."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig", errors="replace")
    except FileNotFoundError:
        raise FileNotFoundError(f"no such reference file: {path}") from None
    return parse_reference(text, str(path))

"""A sensor's last zero, kept across service restarts: what its first tare is judged against.

Auto-tare takes whatever is on a sensor as its zero, so a service restarted
while a gripper holds an object made the grip the zero (taxel 27 read
4.51 N before a restart, 0.000 N after, unflagged; a quad's Fz 0.90 N →
0.00 N). The built-in calibration's C0 is nominal, so loaded_tare.py cannot
tell. The live service keeps each sensor's zero in the registry (per
identity and calibration, every 10 s and at stop: board.py) and, at the
sensor's first tare after it starts, judges the tared means against it:
channels above it by more than their noise (LOADED_SIGMAS σ of the two
means) plus what drift at the tracked bound (1 % ΔC/C0 a minute,
docs/reconstruction.md) could have added since it was saved keep the stored
zero and are flagged ``loaded_at_tare`` (the zero is only as good as that
bound: a tare unloaded gives a fresh one), the rest tare as usual. The
zero is saved with the drift tracked on it (drift.py; a quad's:
quad_drift.py); one on which none is tracked (below the full level) is as
old as its tare, and saved as made then. At the tare a grid's is first
moved by the free taxels' common level, by no more than drift at the bound
since (loaded_tare.common_c0: temperature moves every taxel alike, so a
plate over the whole array is not taken for it); a quad has no free
electrodes to tell temperature by (fewer than
COMMON_MIN_TAXELS), its four are judged as they are, and when one keeps
the zero all four do (loaded_tare.whole_quad: a shear lowers some under
the load, and a zero half stored, half tared read it as phantom shear:
−0.57 N after the release, ~13σ). Channels *below* it,
as many as loaded_tare.judge takes for a mismatch (2, or 5 % of a grid's),
say it is not this sensor's zero as it is now (another sensor without a
serial at the address, or cooler than the bound allows): it is not used.
Nor is one saved more than MAX_AGE_S ago: drift at the bound could then
explain COMMON_MAX_DRIFT (2 % ΔC/C0, ~1.6 N on a table-1 taxel, 0.58 N of a
quad's Fz), a larger shift than a temperature change is taken for anywhere
else. Nor one from a clock later than now. A replay never reads one (its
zeros are its recording's) nor keeps one, nor does a simulated board.

A sensor back at its address after another sensor was there (a board
swapped out and back in, identity.py) is judged the same way against the
zero it left with (as ``zeros_to_keep`` would have saved it then), or the
registry's where that is newer: A's quad, tared unloaded, came back 2 s
later under 2 N and read 0.000 N unflagged (its zero was never saved: A
ran less than the 10 s between saves, and a sensor that left is not saved).
That zero is dated, and its age judged, on its readings' host clock
(t_host), so that a replay judges it as live did.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..readings import SensorInfo
from .drift import MIN_REFERENCE_TAXELS
from .grid import GridProcessor
from .identity import Replacements, named
from .loaded_tare import COMMON_MAX_DRIFT, LOADED_SIGMAS, judge, kept_zero_sigma, mean_noise, whole_quad

DRIFT_PER_S = 0.01 / 60.0  # the tracked drift bound: 1 % ΔC/C0 per minute (docs/reconstruction.md)
MAX_AGE_S = COMMON_MAX_DRIFT / DRIFT_PER_S  # 120 s

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class StoredZero:
    """A zero as the registry keeps it (registry.zero)."""

    zero_pF: np.ndarray
    std_pF: np.ndarray
    frames: int
    saved: float  # Unix time
    left: bool = False  # the zero the sensor left its address with: ``saved`` on its readings' clock (t_host)

    @classmethod
    def from_row(cls, row: dict | None, channels: int, left: bool = False) -> StoredZero | None:
        """The registry's row as a zero of ``channels`` channels; None without one or for another shape."""
        if row is None or len(row["zero_pF"]) != channels or len(row["std_pF"]) != channels:
            return None
        return cls(_array(row["zero_pF"]), _array(row["std_pF"]), int(row["frames"]), float(row["saved"]), left)

    def unusable(self, now: float) -> str | None:
        """Why it cannot judge a tare at ``now`` (Unix time), None when it can."""
        age = now - self.saved
        if age < 0:
            return f"saved {-age:.0f} s after now (the clock went back?)"
        if age > MAX_AGE_S:
            return (f"saved {age:.0f} s ago: drift at 1 %/min could have moved it {100 * DRIFT_PER_S * age:.1f} % "
                    f"ΔC/C0, more than {100 * COMMON_MAX_DRIFT:g} % (older than {MAX_AGE_S:.0f} s)")
        return None


def judged(stored: StoredZero, mean_pF: np.ndarray, std_pF: np.ndarray, frames: int, now: float) -> dict:
    """A finished tare's means (n,) pF, spread ``std_pF``, against the stored
    zero: {age_s, kept (n,) bool (channels above it: their zero is
    ``zero_pF``'s), zero_pF (n,): the stored zero moved by the common level
    of a grid's free taxels (at most what drift at the bound explains),
    zero_sigma (n,): each kept channel's zero's σ in ΔC/C0, the drift at
    the bound since it was saved (loaded_tare.kept_zero_sigma), not_used:
    why not (then nothing is kept)}."""
    age = now - stored.saved
    report = {"age_s": round(age, 1), "kept": np.zeros(mean_pF.shape, dtype=bool), "zero_pF": stored.zero_pF,
              "not_used": stored.unusable(now)}
    if report["not_used"]:
        return report
    noise = np.hypot(mean_noise(std_pF, frames), mean_noise(stored.std_pF, stored.frames))
    drift = DRIFT_PER_S * age
    kept, below, zero = judge(stored.zero_pF, np.isfinite(stored.zero_pF), mean_pF, std_pF, frames,
                              lambda reference: LOADED_SIGMAS * noise + drift * reference, max_drift=drift)
    if below.any():  # loaded_tare.judge's mismatch: cooler than the bound allows, or another sensor's zero
        channels = np.flatnonzero(below).tolist()
        return {**report, "not_used": f"{len(channels)} channels read below it ({', '.join(map(str, channels[:8]))}"
                                      f"{', …' if len(channels) > 8 else ''}): another sensor's zero, or one cooler "
                                      "than drift since explains"}
    return {**report, "kept": kept, "zero_pF": zero, "zero_sigma": kept_zero_sigma(kept, stored.zero_pF, zero, drift)}


class StoredZeros:
    """The stored-zero half of sensor_states.SensorStates (its base): the
    lookup when a sensor is first seen or first named, the judgement of its
    first tare, the zeros to keep."""

    _sensors: dict
    level: str
    replacements: Replacements
    load_zero: Callable[[SensorInfo, str], dict | None] | None = None  # the registry's row for (sensor, calibration)

    def _stored_zero(self, info: SensorInfo, calibration_id: str) -> StoredZero | None:
        """The zero kept for a named sensor under this calibration: the one it left its address with
        (identity.py) or the registry's, the newer (none, or unreadable: None, with a warning)."""
        left = StoredZero.from_row(self.replacements.returning_zero(info, calibration_id), info.channels, left=True)
        if self.load_zero is None or not named(info):
            return left
        try:
            stored = StoredZero.from_row(self.load_zero(info, calibration_id), info.channels)
        except Exception as exc:  # noqa: BLE001 — a lost zero is a warning: the sensor tares as before
            log.warning("sensor %d: its stored zero cannot be read (%s); tared as if there were none", info.id, exc)
            return left
        return stored if left is None or (stored is not None and stored.saved > left.saved) else left

    def _judge_stored(self, state, stored: StoredZero, t_host: float) -> bool:
        """A first tare, its last reading received at ``t_host``, against the
        stored zero: the channels above it keep it (``loaded_at_tare``), a
        quad's four together (loaded_tare.whole_quad: a shear lowers some
        electrodes under a load); whether it judged the tare (else the
        calibration's C0 does)."""
        baseline = state.baseline
        now = t_host if stored.left else time.time()
        report = judged(stored, baseline.value, baseline.std, baseline.frames, now)
        kept, sigma = report.pop("kept"), report.pop("zero_sigma", None)
        if state.info.kind == "quad":
            kept = whole_quad(kept, np.isfinite(baseline.value) & np.isfinite(report["zero_pF"]))
            sigma = np.where(kept, np.max(sigma, initial=0.0), 0.0) if sigma is not None else None
        state.zero_kept = {**{k: v for k, v in report.items() if k != "zero_pF"}, "kept": np.flatnonzero(kept).tolist()}
        if report["not_used"]:
            log.warning("sensor %d: its stored zero is not used (%s)", state.info.id, report["not_used"])
            return False
        if kept.any():
            self._keep_zero(state, kept, report["zero_pF"], sigma)
            log.warning("sensor %d: channels %s were loaded at the tare, against the zero %s %.1f s before; "
                        "they keep it", state.info.id, state.zero_kept["kept"],
                        "it left its address with" if stored.left else "stored", report["age_s"])
        return True

    @staticmethod
    def _keep_zero(state, kept: np.ndarray, zero_pF: np.ndarray, sigma: np.ndarray) -> None:
        """The ``kept`` (n,) bool channels take ``zero_pF`` (n,) as their zero, flagged ``loaded_at_tare``,
        and its σ (n,) ΔC/C0 (loaded_tare.kept_zero_sigma) goes into their forces' σ until the next tare."""
        state.baseline.substitute(kept, zero_pF)
        state.loaded = kept
        state.processor.kept_zero = (state.baseline.value, sigma)

    def zeros_to_keep(self) -> dict[int, tuple[SensorInfo, str, dict]]:
        """{sensor: (info, calibration id, the zero in force as the registry keeps it)} of each named sensor
        whose tare is complete and judged, with the drift tracked on it; where none is tracked (below the full
        level, a grid of fewer than 3 taxels) the zero is as old as its tare, and saved as made then."""
        out, now = {}, time.time()
        for sid, state in list(self._sensors.items()):
            zero = self._zero_in_force(state, now, state.tared_at)
            if zero is not None:
                out[sid] = (state.info, state.calibration.id, zero)
        return out

    def _zero_left(self, state) -> dict | None:
        """The zero in force of a sensor leaving its address (another is described there), as ``zeros_to_keep``
        gives it, dated on its readings' clock: its last reading's t_host (its tare's, where no drift is tracked);
        None as there, or where that time is unknown (a recording begun after its tare, before they were kept)."""
        zero = self._zero_in_force(state, state.last_t_host, state.tared_t_host)
        return zero if zero is not None and np.isfinite(zero["saved"]) else None

    def _zero_in_force(self, state, now: float, tared_at: float) -> dict | None:
        """The sensor's zero as the registry keeps it (``row``) with the drift tracked on it, dated ``now``, or where
        none is tracked (below the full level, a grid of fewer than 3 taxels) ``tared_at``; None for a sensor
        unnamed, or whose tare is not complete and judged."""
        baseline = state.baseline
        if not (baseline.ready and state.tare_judged and not baseline.zeroless and named(state.info)):
            return None
        tracked = self.level == "full" and state.info.channels >= MIN_REFERENCE_TAXELS
        return row(baseline.value * (1.0 + _drift(state)), baseline.std, baseline.frames, now if tracked else tared_at)

    def zero_kept(self, sensor_id: int) -> dict | None:
        """The stored zero's part in the sensor's first tare: {age_s, kept, not_used}; None when there was none."""
        state = self._sensors.get(sensor_id)
        return None if state is None else state.zero_kept


def _drift(state) -> float:
    """The common-mode drift (ΔC/C0) tracked on the sensor's zero: a grid's
    (drift.py), a quad's (quad_drift.py: its tracker, if on this zero); 0 below the full level."""
    processor = state.processor
    if isinstance(processor, GridProcessor):
        return processor.drift.drift
    held = getattr(processor, "drift", None)
    return held[1].drift.drift if held is not None and held[0] is state.baseline.value else 0.0


def row(value_pF: np.ndarray, std_pF: np.ndarray, frames: int, now: float | None = None) -> dict:
    """A zero in force (n,) pF as the registry keeps it (NaN: None)."""
    return {"zero_pF": _listed(value_pF), "std_pF": _listed(std_pF), "frames": int(frames),
            "saved": time.time() if now is None else now}


def row_problem(row) -> str | None:
    """What makes ``row`` no zero as the registry keeps it (``row``: zero_pF and std_pF lists of numbers or None
    of one length, frames a count, saved a finite time), None when it is one: a recording's may be anything."""
    if not isinstance(row, dict):
        return f"its zero is not an object: {row!r:.60}"
    for name in ("zero_pF", "std_pF"):
        values = row.get(name)
        if not isinstance(values, list) or not all(_is_number(v) for v in values if v is not None):
            return f"its {name} is not a list of numbers: {values!r:.60}"
    if len(row["std_pF"]) != len(row["zero_pF"]):
        return f"its std_pF has {len(row['std_pF'])} values, its zero_pF {len(row['zero_pF'])}"
    if not (_is_number(row.get("frames")) and isinstance(row["frames"], int) and row["frames"] > 0):
        return f"its frames is not a count: {row.get('frames')!r:.60}"
    if not (_is_number(row.get("saved")) and np.isfinite(row["saved"])):
        return f"its saved is not a time: {row.get('saved')!r:.60}"
    return None


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _listed(values: np.ndarray) -> list[float | None]:
    return [None if v != v else v for v in np.asarray(values, dtype=float).tolist()]


def _array(values: list) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)

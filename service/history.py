"""The last seconds of one sensor's frames, kept in arrays.

Keeping 5 s of 1 kHz frames as ForceFrame objects meant ~40 000 live objects
for eight sensors, all surviving into the garbage collector's oldest
generation; its full passes over them stalled the event loop for up to
~90 ms. Here a sensor's history is a ring of numpy arrays (not traversed by
the collector) plus one tuple of flag names per frame (tuples of strings are
untracked by the collector), and ForceFrames are rebuilt only for the frames
a history request returns.
"""
from __future__ import annotations

import numpy as np

from .readings import SensorInfo
from .reconstruct import ForceFrame
from .reconstruct.taxel_flags import LOADED_AT_TARE, NO_READING, OUT_OF_RANGE, STALE

# Distinct flag sets seen (a few dozen at most: frame flags are a fixed vocabulary).
_FLAG_SETS: dict[tuple[str, ...], tuple[str, ...]] = {}
DEFAULT_BUDGET_BYTES = 256 << 20
DEFAULT_FRAMES = 5_000  # per sensor: 5 s at 1 kHz (~5.5 MB for an 8x8 grid)
BELOW_ZERO_S = 1.0
BELOW_ZERO_SHARE = 0.9  # of the window's frames: noise alone puts a reading below −5σ about once in 3.5 million
BELOW_ZERO_FRAMES = 20  # fewer frames in the window say nothing
BELOW_ZERO_POINTS = 100  # frames looked at, evenly spread over the window: /health runs on the event loop
# A channel null or flagged in more than this share of the window's frames is faulty, not a passing glitch.
FAULTY_SHARE = 0.5


class History:
    """Ring of the last ``capacity`` frames of one sensor.

    Parameters
    ----------
    info : the sensor; frames of another sensor are refused
    capacity : frames kept
    outputs : forces per frame (rows*cols for a grid, 3 for a quad)
    """

    def __init__(self, info: SensorInfo, capacity: int, outputs: int) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self.info = info
        self.capacity = capacity
        self._t_host = np.zeros(capacity)
        self._seq = np.zeros(capacity, dtype=np.int64)
        self._t_us = np.zeros(capacity, dtype=np.int64)
        self._t_scan = np.zeros(capacity)
        self._forces = np.zeros((capacity, outputs))
        self._sigma = np.zeros((capacity, outputs), dtype=np.float32)  # σ to a tenth of a per cent is plenty
        self._raw = np.zeros((capacity, info.channels))
        self._taxel_flags = np.zeros((capacity, outputs), dtype=np.uint8) if info.kind == "grid" else None
        self._flags: list[tuple[str, ...]] = [()] * capacity
        self._levels: list[str] = [""] * capacity
        self._calibrations: list[str] = [""] * capacity  # the frames' own id strings: one object per calibration
        self._count = 0  # frames ever appended

    def __len__(self) -> int:
        return min(self._count, self.capacity)

    @staticmethod
    def bytes_per_frame(info: SensorInfo, outputs: int) -> int:
        """What one kept frame costs: stamps, forces, σ, raw channels, flags, level and calibration."""
        return 4 * 8 + 12 * outputs + 8 * info.channels + (outputs if info.kind == "grid" else 0) + 3 * 8

    def shrink(self, capacity: int) -> None:
        """Keep only the newest ``capacity`` frames (and room for no more)."""
        if not 1 <= capacity < self.capacity:
            return
        kept = min(len(self), capacity)
        order = (self._count - kept + np.arange(kept)) % self.capacity  # oldest first
        arrays = ("_t_host", "_t_scan", "_seq", "_t_us", "_forces", "_sigma", "_raw") + (
            ("_taxel_flags",) if self._taxel_flags is not None else ())
        for name in arrays:
            old = getattr(self, name)
            new = np.zeros((capacity,) + old.shape[1:], dtype=old.dtype)
            new[:kept] = old[order]
            setattr(self, name, new)
        self._flags = [self._flags[i] for i in order.tolist()] + [()] * (capacity - kept)
        self._levels = [self._levels[i] for i in order.tolist()] + [""] * (capacity - kept)
        self._calibrations = [self._calibrations[i] for i in order.tolist()] + [""] * (capacity - kept)
        self.capacity, self._count = capacity, kept

    def append(self, frame: ForceFrame) -> None:
        """Store the sensor's next frame."""
        if frame.sensor is not self.info and frame.sensor != self.info:
            raise ValueError(f"history of sensor {self.info.id} was given a frame of sensor {frame.sensor.id}")
        i = self._count % self.capacity
        self._t_host[i], self._seq[i], self._t_us[i] = frame.t_host, frame.seq, frame.t_us
        self._t_scan[i] = frame.t_host_scan
        self._forces[i] = frame.forces_N
        self._sigma[i] = np.nan if frame.sigma_N is None else frame.sigma_N
        self._raw[i] = frame.capacitance_pF
        if self._taxel_flags is not None:
            self._taxel_flags[i] = 0 if frame.taxel_flags is None else frame.taxel_flags
        flags = tuple(frame.flags)
        self._flags[i] = _FLAG_SETS.setdefault(flags, flags)  # one tuple per distinct set of flags, not per frame
        self._levels[i] = frame.level
        self._calibrations[i] = frame.calibration
        self._count += 1

    def window(self, seconds: float, max_points: int) -> list[ForceFrame]:
        """Frames received in the last ``seconds`` before the newest one,
        evenly decimated to at most ``max_points``, oldest first."""
        return self.frames_at(self.window_slots(seconds, max_points))

    def window_slots(self, seconds: float, max_points: int) -> np.ndarray:
        """The ring slots ``window`` returns, oldest first, shape (k,)."""
        n = len(self)
        if n == 0:
            return np.zeros(0, dtype=np.int64)
        order = (self._count - n + np.arange(n)) % self.capacity  # ring slots, oldest first
        stamps = self._t_host[order]
        first = int(np.searchsorted(stamps, stamps[-1] - seconds, side="left"))
        kept = order[first:]
        if len(kept) <= max_points:  # the usual 5000-point read of a full ring: no decimation to compute
            return kept
        picks = np.unique(np.linspace(0, len(kept) - 1, max_points).round().astype(int))
        return kept[picks]

    def recent_slots(self, seconds: float) -> np.ndarray:
        """Ring slots of the last ``seconds`` (at most BELOW_ZERO_POINTS of
        them, evenly spread), or of the last BELOW_ZERO_FRAMES frames when
        fewer came in that time; empty while fewer were ever kept."""
        slots = self.window_slots(seconds, BELOW_ZERO_POINTS)
        if len(slots) < BELOW_ZERO_FRAMES:  # a slow board (RATE under 20 Hz): its last frames, however long they took
            if len(self) < BELOW_ZERO_FRAMES:
                return np.zeros(0, dtype=np.int64)
            slots = (self._count - BELOW_ZERO_FRAMES + np.arange(BELOW_ZERO_FRAMES)) % self.capacity
        return slots

    def below_zero(self, seconds: float = BELOW_ZERO_S) -> list[int]:
        """Outputs (a grid's taxels, row-major; a quad's 2 for Fz) that read
        below their tared zero — out of range at force 0 (grid.py, quad.py)
        — in BELOW_ZERO_SHARE of the frames ``recent_slots`` picks."""
        slots = self.recent_slots(seconds)
        if not len(slots):
            return []
        if self._taxel_flags is not None:
            below = (self._taxel_flags[slots] & OUT_OF_RANGE != 0) & (self._forces[slots] == 0.0)
        else:
            flagged = np.array(["normal_out_of_range" in self._flags[i] for i in slots.tolist()])
            below = (flagged & (self._forces[slots, 2] == 0.0))[:, None]
        share = np.count_nonzero(below, axis=0) / len(slots)
        hits = np.flatnonzero(share >= BELOW_ZERO_SHARE).tolist()
        return hits if self._taxel_flags is not None else [2] * bool(hits)

    def faulty(self, seconds: float = BELOW_ZERO_S, outside=None, kept=None) -> dict[str, list[int]]:
        """Channels (row-major) that were ``no_reading``, ``out_of_range``
        with no force (not below zero: ``below_zero``), ``stale`` or
        ``loaded_at_tare`` in more than FAULTY_SHARE of the frames
        ``recent_slots`` picks, by flag (those with any). A quad's flags are
        its frame's: its electrodes are told by their readings — a sentinel
        (NaN) is no reading, a stale one repeats one count, and ``outside``
        (the median reading (4,) pF → electrodes outside their plausible
        range) names those out of range, ``kept`` (() → electrodes) those
        loaded at the tare."""
        slots = self.recent_slots(seconds)
        if not len(slots):
            return {}
        if self._taxel_flags is not None:
            bits = self._taxel_flags[slots]
            masks = {"no_reading": bits & NO_READING != 0,
                     "out_of_range": (bits & OUT_OF_RANGE != 0) & np.isnan(self._forces[slots]),
                     "stale": bits & STALE != 0, "loaded_at_tare": bits & LOADED_AT_TARE != 0}
            found = {name: np.flatnonzero(np.count_nonzero(mask, axis=0) > FAULTY_SHARE * len(slots)).tolist()
                     for name, mask in masks.items()}
            return {name: channels for name, channels in found.items() if channels}
        raw = self._raw[slots]
        found = {"no_reading": np.flatnonzero(np.count_nonzero(np.isnan(raw), axis=0) > FAULTY_SHARE * len(slots)).tolist()}
        for name in ("out_of_range", "stale", "loaded_at_tare"):
            flagged = np.array([name in self._flags[i] for i in slots.tolist()])
            if np.count_nonzero(flagged) <= FAULTY_SHARE * len(slots):
                continue
            readings = raw[flagged]
            if name == "stale":  # one count all along; a sentinel is no reading, told above
                found[name] = np.flatnonzero((np.ptp(readings, axis=0) == 0) & ~np.isnan(readings[0])).tolist()
            elif name == "loaded_at_tare":
                found[name] = [] if kept is None else kept()
            elif outside is not None:
                found[name] = outside(np.median(readings, axis=0))
        return {name: channels for name, channels in found.items() if channels}

    def numbers(self, slots: np.ndarray) -> np.ndarray:
        """Which frame each written slot holds, counted from the ring's first
        (a shrink renumbers them, changing ``capacity``): a slot that holds
        the same number holds the same frame."""
        return self._count - 1 - (self._count - 1 - slots) % self.capacity

    def frames_at(self, slots: np.ndarray) -> list[ForceFrame]:
        """Frames rebuilt from ring slots (copies: the ring goes on)."""
        return [self._frame(int(i)) for i in slots]

    def _frame(self, i: int) -> ForceFrame:
        return ForceFrame(
            self.info, int(self._seq[i]), int(self._t_us[i]), float(self._t_host[i]), self._forces[i].copy(),
            self._raw[i].copy(), list(self._flags[i]), self._levels[i],
            None if self._taxel_flags is None else self._taxel_flags[i].copy(), self._calibrations[i],
            self._sigma[i].astype(float), float(self._t_scan[i]),
        )


class Histories(dict):
    """Every sensor's History by id, all within one memory budget.

    Each sensor may keep up to ``frames`` frames; when the sensors together
    would exceed ``budget_bytes``, each gets an equal share of the budget
    (fewer frames for a larger sensor), and the histories already kept
    shrink to their share, newest frames kept."""

    def __init__(self, budget_bytes: int = DEFAULT_BUDGET_BYTES, frames: int = DEFAULT_FRAMES) -> None:
        super().__init__()
        if budget_bytes < 1 or frames < 1:
            raise ValueError(f"a history budget needs budget_bytes >= 1 and frames >= 1, got {budget_bytes}, {frames}")
        self.budget_bytes = budget_bytes
        self.frames = frames

    def for_frame(self, frame: ForceFrame) -> History:
        """The history that takes ``frame`` (a new one for a new or changed sensor)."""
        history = self.get(frame.sensor.id)
        if history is not None and history.info is not frame.sensor and history.info == frame.sensor:
            history.info = frame.sensor  # a new INFO's equal description: later frames skip the comparison
        if history is None or history.info is not frame.sensor:
            share = self.budget_bytes // (len(self) + (history is None))
            outputs = frame.forces_N.size
            history = self[frame.sensor.id] = History(frame.sensor, self._capacity(share, frame.sensor, outputs), outputs)
            for other in self.values():
                other.shrink(self._capacity(share, other.info, other._forces.shape[1]))
        return history

    @property
    def bytes(self) -> int:
        return sum(h.capacity * History.bytes_per_frame(h.info, h._forces.shape[1]) for h in self.values())

    def _capacity(self, share: int, info: SensorInfo, outputs: int) -> int:
        return max(1, min(self.frames, share // History.bytes_per_frame(info, outputs)))

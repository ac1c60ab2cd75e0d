"""Load cycles per taxel and the sensitivity they cost (paper 001 §5.2).

Paper 001 loaded its quad sensor 10 000 times with 3 N: ΔC/C0 fell from 0.18
to 0.14 in the normal direction (−22.2 %) and from 0.023 to 0.018 in the
tangential one (−21.7 %), "rapidly in the first 1000 cycles", "relatively
stable after about 7500". We model the remaining sensitivity after n cycles
as

    s(n) = 1 − D·(1 − exp(−n/τ)),   D = 0.22, τ = 1000 cycles

(63 % of the loss within the first 1000 cycles, 99.9 % by 7500; D is the
mean of the two directions' losses, which agree within half a percent, so
one factor serves all three axes). This is a fit to the paper's three
statements, not to a measured curve: a calibration document may carry its
own ``fatigue`` {"drop": D, "tau_cycles": τ}, which replaces it. The model
is the quad's (paper 001's material); paper 000 reports no fatigue for the
8x8 PET/PDMS array, so a grid's cycles are counted and kept but its
sensitivity is not compensated unless its calibration says how.

A cycle is counted on the way down: a taxel's force (a quad's Fz) rises
above HIGH_N and then falls below LOW_N (hysteresis, so noise around one
threshold counts nothing). Every JUDGE_EVERY-th frame of a sensor is judged
(by its count in the stream, so however the stream is cut): a load lasts
far longer than 4 scans at any rate a board runs, and at 1 kHz per sensor the
live path's per-call cost, not the arithmetic, is what counting costs. Counts belong to a calibration: a new one starts
from zero (the registry keeps them per sensor and calibration). A frame's
factor is s(count before it), however frames are batched (``counts_before``
says where in a batch a cycle ends; quad_batch.py).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

HIGH_N = 1.0
LOW_N = 0.3
JUDGE_EVERY = 4
# Up to this many frames (live: one or two per sensor and read) are stepped
# through one by one, ~5 numpy calls each; more go through the whole-batch
# scan below (~15 calls, whatever the number of frames). Equal results.
FEW_FRAMES = 3


@dataclass(frozen=True)
class FatigueModel:
    drop: float  # fraction of the sensitivity lost after many cycles
    tau_cycles: float

    def factor(self, cycles: np.ndarray | int) -> np.ndarray:
        """s(n): remaining sensitivity after ``cycles`` (any shape)."""
        return 1.0 - self.drop * -np.expm1(-np.asarray(cycles, dtype=float) / self.tau_cycles)

    @classmethod
    def from_document(cls, fatigue: dict | None, default: FatigueModel | None) -> FatigueModel | None:
        """A calibration's ``fatigue`` entry (ValueError naming the bad field), else ``default``."""
        if fatigue is None:
            return default
        try:
            drop, tau = float(fatigue["drop"]), float(fatigue["tau_cycles"])
        except (TypeError, KeyError, ValueError):
            raise ValueError("fatigue: expected {drop: fraction, tau_cycles: cycles}") from None
        if not (0.0 <= drop < 0.9 and math.isfinite(tau) and tau > 0):
            raise ValueError(f"fatigue: drop {drop} must be in [0, 0.9) and tau_cycles {tau} positive")
        return cls(drop, tau)


PAPER_001 = FatigueModel(0.22, 1000.0)


class CycleCounter:
    """Load cycles of ``n`` taxels (a quad: 1, its Fz), with hysteresis."""

    def __init__(self, n: int, counts: np.ndarray | list | None = None) -> None:
        self.counts = np.zeros(n, dtype=np.int64) if counts is None else np.array(counts, dtype=np.int64)
        if self.counts.shape != (n,):
            raise ValueError(f"cycle counts: expected {n}, got {self.counts.size}")
        self.at_start = self.counts.tolist()  # the counts it was made with
        self._armed = np.zeros(n, dtype=bool)  # above HIGH_N since it was last below LOW_N
        self._any_armed = False
        self._seen = 0  # frames offered, for JUDGE_EVERY

    def where(self) -> dict:
        """Where the count stands ({cycles, cycles_seen, cycles_armed}): what a
        recording begun now stores, so that its replay counts as live did
        (which frames are judged, a load already on)."""
        return {"cycles": self.counts.tolist(), "cycles_seen": self._seen, "cycles_armed": self._armed.tolist()}

    def resume(self, where: dict) -> None:
        """Continue from ``where`` (ValueError when it is not this counter's size)."""
        counts, armed = np.array(where["cycles"], dtype=np.int64), np.array(where["cycles_armed"], dtype=bool)
        if counts.shape != self.counts.shape or armed.shape != self.counts.shape:
            raise ValueError(f"cycle counts: expected {self.counts.size}, got {counts.size}")
        self.counts, self._armed, self._seen = counts, armed, int(where["cycles_seen"])
        self._any_armed = bool(armed.any())

    def update(self, forces: np.ndarray) -> None:
        """Forces (N, n) in frame order (NaN: no reading, changes nothing);
        every JUDGE_EVERY-th frame of the stream is judged."""
        first = self._judged_from(len(forces))
        if first < len(forces):
            forces = forces[first::JUDGE_EVERY]
            self._count(forces, forces > HIGH_N)

    def counts_before(self, forces: np.ndarray) -> np.ndarray | None:
        """The counts (N, n) before each of frames ``forces`` (N, n) that
        ``update(forces)`` would step through, changing nothing; None when
        they stay the counts of now (the usual batch: no cycle ends in it).
        A quad's sensitivity factor per frame comes from them (quad_batch.py)."""
        first = -self._seen % JUDGE_EVERY
        judged = forces[first::JUDGE_EVERY]
        above = judged > HIGH_N
        if not len(judged) or (not self._any_armed and not np.count_nonzero(above)):
            return None
        filled = self._filled(judged, above)
        ended = (filled[:-1] == 1) & (filled[1:] == -1)  # (J, n): a cycle ends at judged frame j
        if not np.count_nonzero(ended):
            return None
        after = self.counts + np.cumsum(ended, axis=0)  # counts after each judged frame
        # Frame k sees the cycles ended at judged frames before it: judged frame j is frame first + j·JUDGE_EVERY.
        taken = np.searchsorted(first + JUDGE_EVERY * np.arange(len(judged)), np.arange(len(forces)), side="left")
        return np.vstack([self.counts[None], after])[taken]

    def _judged_from(self, frames: int) -> int:
        """Which of the next ``frames`` is the first judged (``frames`` or
        more: none); counts them as seen."""
        first = -self._seen % JUDGE_EVERY
        self._seen += frames
        return first

    def _count(self, forces: np.ndarray, above: np.ndarray) -> None:
        """The cycles in judged frames ``forces`` (N, n), ``above`` HIGH_N."""
        if not self._any_armed and not np.count_nonzero(above):
            return  # the usual frame: nothing loaded, nothing pending
        if len(forces) <= FEW_FRAMES:
            self._step(forces, above)
            return
        filled = self._filled(forces, above)
        self.counts += np.count_nonzero((filled[:-1] == 1) & (filled[1:] == -1), axis=0)
        self._armed = filled[-1] == 1
        self._any_armed = bool(self._armed.any())

    def _filled(self, forces: np.ndarray, above: np.ndarray) -> np.ndarray:
        """(N + 1, n) states of judged frames ``forces`` (N, n), after the
        counter's own: +1 above HIGH, −1 below LOW, between keeps the last;
        a cycle is each +1 → −1 step."""
        state = np.where(above, 1, np.where(forces < LOW_N, -1, 0)).astype(np.int8)
        state = np.vstack([np.where(self._armed, 1, -1).astype(np.int8)[None], state])
        rows = np.arange(len(state))[:, None]
        return np.take_along_axis(state, np.maximum.accumulate(np.where(state != 0, rows, 0), axis=0), axis=0)

    def _step(self, forces: np.ndarray, above: np.ndarray) -> None:
        """``update`` frame by frame: a cycle is an armed taxel falling below LOW_N."""
        armed = self._armed
        for row, up in zip(forces, above):
            fell = armed & (row < LOW_N)
            if np.count_nonzero(fell):
                self.counts += fell
                armed = armed ^ fell
            armed = armed | up
        self._armed = armed
        self._any_armed = bool(np.count_nonzero(armed))


def update_many(counters: list[CycleCounter], forces: np.ndarray, counts: list[int]) -> None:
    """``update`` of each counter with its rows of ``forces`` (R, n): counter
    k's are the next ``counts[k]`` rows. The same counts; the usual read
    (nothing loaded, nothing pending) costs two numpy calls for all."""
    spans, picks = [], []  # (counter, its judged rows a:b in picks), judged rows of ``forces``
    start = 0
    for counter, count in zip(counters, counts):
        first = counter._judged_from(count)
        if first < count:
            a = len(picks)
            picks += range(start + first, start + count, JUDGE_EVERY)
            spans.append((counter, a, len(picks)))
        start += count
    if not picks:
        return
    judged = forces[picks]
    above = judged > HIGH_N
    if not np.count_nonzero(above) and not any(counter._any_armed for counter, _, _ in spans):
        return
    hits = above.any(axis=1).tolist()
    single = []  # counters with one judged frame (a live read) that is loaded or pending: stepped together
    several: dict[int, list[tuple[CycleCounter, int]]] = {}  # judged frames → counters with as many, loaded or pending
    for counter, a, b in spans:
        if b - a > 1:
            if counter._any_armed or any(hits[a:b]):
                several.setdefault(b - a, []).append((counter, a))
        elif counter._any_armed or hits[a]:
            single.append((counter, a))
    for frames, members in several.items():
        _count_together(members, frames, judged, above)
    if single:
        _step_together(single, judged, above)


def _count_together(members: list[tuple[CycleCounter, int]], frames: int, judged: np.ndarray, above: np.ndarray) -> None:
    """``CycleCounter._count`` of ``frames`` judged frames for each (counter,
    its first row of ``judged``), all counters in one scan: a batch of grids
    that piled up costs ~15 numpy calls, not ~15 per sensor."""
    if len(members) == 1:
        counter, a = members[0]
        counter._count(judged[a:a + frames], above[a:a + frames])
        return
    rows = np.array([a for _, a in members])[:, None] + np.arange(frames)  # (C, frames)
    forces, up = judged[rows], above[rows]
    # As _count, along axis 1: +1 above HIGH, −1 below LOW, 0 between (keeps the last); a cycle is +1 → −1.
    state = np.where(up, 1, np.where(forces < LOW_N, -1, 0)).astype(np.int8)
    armed = np.array([counter._armed for counter, _ in members])
    state = np.concatenate([np.where(armed, 1, -1).astype(np.int8)[:, None], state], axis=1)
    steps = np.arange(frames + 1)[None, :, None]
    last = np.maximum.accumulate(np.where(state != 0, steps, 0), axis=1)
    filled = np.take_along_axis(state, last, axis=1)
    cycles = np.count_nonzero((filled[:, :-1] == 1) & (filled[:, 1:] == -1), axis=1)
    armed = filled[:, -1] == 1
    for (counter, _), counted, row, any_armed in zip(members, cycles, armed, armed.any(axis=1).tolist()):
        counter.counts += counted
        counter._armed, counter._any_armed = row, any_armed


def _step_together(single: list[tuple[CycleCounter, int]], judged: np.ndarray, above: np.ndarray) -> None:
    """``CycleCounter._step`` of one frame for each (counter, row of ``judged``)."""
    rows = [a for _, a in single]
    armed = np.array([counter._armed for counter, _ in single])
    fell = armed & (judged[rows] < LOW_N)
    if np.count_nonzero(fell):
        for i in np.flatnonzero(fell.any(axis=1)).tolist():
            single[i][0].counts += fell[i]
    armed = (armed ^ fell) | above[rows]
    for (counter, _), row, any_armed in zip(single, armed, armed.any(axis=1).tolist()):
        counter._armed, counter._any_armed = row, any_armed

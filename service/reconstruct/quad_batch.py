"""Quads of one model reconstructed together: one stacked (n×4) array per call.

At 1 kHz a read holds one frame per quad, so what a quad costs is the
Python around it, per sensor: finding its batch, stacking its baseline, its
noise and its fatigue factor. ``QuadBatches.frames`` does one batch (the
reference, for any readings); ``QuadPlan`` keeps how the last read of quads
went — which sensors in which batch, their constants stacked — and the next
read of the same sensors, each once, whose baselines, processors,
calibrations and cycle counts are all still the same objects and values,
goes through it without being grouped again (also k scans of them, which a
read holds when it waited while the loop was busy). The values are the same either
way (tests/test_live_quads.py). Stale electrodes (stuck.py) are counted
either way: the plan holds its quads' runs as rows of two stacked arrays,
which each processor's ``runs`` are views of, so one call steps them all.
A sensor's fatigue factor is its count's before each frame, as frame by
frame, when a load cycle ends among the frames of one call
(``per_frame_sensitivity``): its forces do not depend on how its frames
were batched, so a replay may join recorded reads.
"""
from __future__ import annotations

import numpy as np

from ..protocol import FLAG_SATURATED
from ..readings import Reading
from . import quad_drift
from .level0 import clipped
from .fatigue import update_many
from .force_frame import ForceFrame
from .sigma import zero_sigma_for
from .stuck import STUCK_FRAMES, run_lengths

MAX_FATIGUE_ROUNDS = 4


def fatigue_factor(state) -> float:
    """What load cycles left of a quad's sensitivity (1: no fatigue model);
    recomputed only when the count moved."""
    model = state.calibration.fatigue
    if model is None:
        return 1.0
    count = int(state.cycles.counts[0])
    if state.sensitivity_for is None or state.sensitivity_for[0] != count or state.sensitivity_for[1] is not model:
        state.sensitivity_for = (count, model, float(model.factor(count)))
    return state.sensitivity_for[2]


def per_frame_sensitivity(states: list, counts: list[int], fz: np.ndarray,
                          sensitivity: np.ndarray) -> np.ndarray | None:
    """Each row's fatigue factor (R,) where a load cycle ends within a
    sensor's rows (``counts[k]`` of ``states[k]``, Fz ``fz`` (R,) computed
    with ``sensitivity`` (R,)): from that row on, the factor of the new count,
    as frame by frame; None when no cycle ends (the usual batch). So a
    sensor's forces do not depend on how its frames were batched (a replay
    may join recorded reads)."""
    out, start = None, 0
    for state, count in zip(states, counts):
        model = state.calibration.fatigue
        if count > 1 and model is not None:
            before = state.cycles.counts_before(fz[start:start + count, None])
            if before is not None:
                moved = np.flatnonzero(before[:, 0] != before[0, 0])
                if moved.size:
                    if out is None:
                        out = np.array(sensitivity, dtype=float)
                    rows = start + moved
                    out[rows] = model.factor(before[moved, 0])
        start += count
    return out


def _with_fatigue(processor, states: list, counts: list[int], capacitance: np.ndarray, baseline, noise,
                  sensitivity: np.ndarray, stale) -> tuple:
    """(forces, quad flags, each row's factor) with each row's fatigue factor
    as frame by frame (per_frame_sensitivity): a factor that moved changes
    Fz, which may move where a cycle ends, so until they agree (at once, in
    practice)."""
    forces, quad_flags = processor.process(capacitance, baseline, noise, sensitivity, stale)
    for _ in range(MAX_FATIGUE_ROUNDS):
        moved = per_frame_sensitivity(states, counts, forces[:, 2], sensitivity)
        if moved is None or np.array_equal(moved, sensitivity):
            break
        sensitivity = moved
        forces, quad_flags = processor.process(capacitance, baseline, noise, sensitivity, stale)
    return forces, quad_flags, sensitivity


def without_clipped(readings: list[Reading], capacitance: np.ndarray, states: list, counts: list[int]) -> np.ndarray:
    """The readings' electrodes (R, 4) (``counts[k]`` rows of ``states[k]``),
    a frame with one at the converter's top (its board flag says a channel
    left the range: level0.clipped) made missing: one electrode's lower
    bound skews all three forces, so the frame has none (its board flag
    says why), and the repeated top count is no stale converter."""
    if not any(r.board_flags for r in readings):  # the usual read: one look per reading
        return capacitance
    zeros = np.repeat(np.array([state.baseline.value for state in states]), counts, axis=0)
    mask = clipped(capacitance, np.array([r.board_flags & FLAG_SATURATED for r in readings], dtype=bool), zeros)
    if mask is None:
        return capacitance
    return np.where(mask.any(axis=1)[:, None], np.nan, capacitance)


def stale_runs(states: list, capacitance: np.ndarray, counts: list[int]) -> tuple[np.ndarray | None, list]:
    """Stale electrodes (R, 4) of quads' readings ``capacitance`` (R, 4),
    ``counts[k]`` rows of ``states[k]`` (None: none stale), and what each
    sensor's runs become (``keep_runs``); a quad whose converter shows no
    noise is not counted. Changes nothing."""
    stale, kept, start = None, [], 0
    for state, count in zip(states, counts):
        rows = capacitance[start:start + count]
        start += count
        processor = state.processor
        if not processor.noisy(state.baseline.std):
            continue
        last, prior = processor.runs_before()
        runs = run_lengths(last[None], prior[None], rows[None])[0]
        kept.append((processor.runs, runs[-1], rows[-1]))
        hit = runs >= STUCK_FRAMES
        if np.count_nonzero(hit):
            if stale is None:
                stale = np.zeros(capacitance.shape, dtype=bool)
            stale[start - count:start] = hit
    return stale, kept


def keep_runs(kept: list) -> None:
    """Store ``stale_runs``' runs, in place (a plan's rows stay its rows)."""
    for (last, prior), runs, row in kept:
        last[...] = row
        prior[...] = runs


def drifted(level: str, states: list, counts: list[int], readings: list[Reading], capacitance: np.ndarray,
            baseline: np.ndarray, noise: np.ndarray, stale) -> tuple[np.ndarray, quad_drift.Steps | None]:
    """(each row's baseline (R, 4) scaled by its drift, the drift's steps) at
    the full level (quad_drift.py), changing nothing; (``baseline``, None) below it."""
    if level != "full":
        return baseline, None
    found = quad_drift.steps(states, counts, capacitance, baseline, noise, [r.t_us * 1e-6 for r in readings], stale)
    return baseline * (1.0 + found.drift[:, None]), found


def with_suspect(quad_flags: list[list[str]], forces: np.ndarray, found: quad_drift.Steps | None) -> list[list[str]]:
    """``drift_suspect`` added to the frames with forces that ``found`` says are."""
    if found is not None and np.count_nonzero(found.suspect):
        for i in np.flatnonzero(found.suspect & (forces[:, 2] == forces[:, 2])).tolist():
            quad_flags[i].append("drift_suspect")
    return quad_flags


def zero_sigmas(states: list) -> np.ndarray | None:
    """The σ (S,) in ΔC/C0 of each quad's Z from a zero kept at a loaded tare
    (sigma.zero_sigma_for: a common shift of its four electrodes moves Z by
    as much, X and Y not at all), 0 where tared; None where none is kept."""
    sigmas = [zero_sigma_for(state.processor.kept_zero, state.baseline.value) for state in states]
    if all(sigma is None for sigma in sigmas):
        return None
    return np.array([0.0 if sigma is None else float(np.nanmean(sigma)) for sigma in sigmas])


def zero_drift(found: quad_drift.Steps | None, zero: np.ndarray | None) -> np.ndarray | None:
    """The σ (N,) ΔC/C0 of each row's Z zero for QuadProcessor.sigma: the
    drift estimate's (``found``) and a kept zero's (``zero`` (N,)) in quadrature; None: neither."""
    drift = None if found is None else found.sigma
    if zero is None:
        return drift
    return zero if drift is None else np.hypot(drift, zero)


def _frames(level: str, states: list, readings: list[Reading], forces: np.ndarray, sigma: np.ndarray,
            quad_flags: list[list[str]], counts: list[int] | None = None) -> list[ForceFrame]:
    """The ForceFrames of ``readings``, ``counts[k]`` of them (default one) of ``states[k]``."""
    calibrations = [state.calibration.id for state in states]
    loaded = [["loaded_at_tare"] if state.loaded is not None and state.loaded.any() else [] for state in states]
    if counts is not None:
        calibrations = [c for c, n in zip(calibrations, counts) for _ in range(n)]
        loaded = [flag for flag, n in zip(loaded, counts) for _ in range(n)]
    return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, r.frame_flags() + q + a, level, None, c,
                       s, r.t_host_scan)
            for r, f, s, q, c, a in zip(readings, forces, sigma, quad_flags, calibrations, loaded)]


class QuadBatches:
    """Tared quads sharing one model, each with its readings → their frames."""

    def __init__(self, level: str) -> None:
        self.level = level
        self._stacks: dict[int, tuple[list, np.ndarray]] = {}  # batch size → (baselines, stacked): _baselines

    def frames(self, members: list[tuple[object, list[Reading]]]) -> list[ForceFrame]:
        """The members' frames in member order (several readings per sensor allowed)."""
        counts = [len(rs) for _, rs in members]
        readings = [r for _, rs in members for r in rs] if len(members) > 1 else members[0][1]
        states = [state for state, _ in members]
        baseline = self._baselines([state.baseline.value for state in states])
        noise = np.array([state.processor.noise(state.baseline.value, state.baseline.std) for state in states])
        sensitivity = np.array([fatigue_factor(state) for state in states])
        zero = zero_sigmas(states)
        processor = states[0].processor
        capacitance = without_clipped(readings, np.array([r.capacitance_pF for r in readings]), states, counts)
        stale, kept = stale_runs(states, capacitance, counts)
        several = len(readings) != len(members)
        if several:
            baseline, noise, sensitivity = (np.repeat(a, counts, axis=0) for a in (baseline, noise, sensitivity))
            zero = None if zero is None else np.repeat(zero, counts)
        baseline, found = drifted(self.level, states, counts, readings, capacitance, baseline, noise, stale)
        if several:
            forces, quad_flags, sensitivity = _with_fatigue(processor, states, counts, capacitance, baseline, noise,
                                                            sensitivity, stale)
        else:
            forces, quad_flags = processor.process(capacitance, baseline, noise, sensitivity, stale)
        sigma = processor.sigma(forces, noise, sensitivity, zero_drift(found, zero))
        quad_flags = with_suspect(quad_flags, forces, found)
        keep_runs(kept)
        if found is not None:
            quad_drift.keep(found.kept)
        update_many([state.cycles for state in states], forces[:, 2:3], counts)
        return _frames(self.level, states, readings, forces, sigma, quad_flags, counts)

    def _baselines(self, baselines: list[np.ndarray]) -> np.ndarray:
        """The baselines (S, 4) of a batch's quads, stacked again only when
        the sensors or one of their tares changed."""
        cached = self._stacks.get(len(baselines))
        if cached is None or any(a is not b for a, b in zip(cached[0], baselines)):
            cached = self._stacks[len(baselines)] = (baselines, np.array(baselines))
        return cached[1]


class _Batch:
    """One model's quads of the planned read: their places in it and their constants."""

    def __init__(self, level: str, positions: list[int], states: list) -> None:
        self.level = level
        self.positions = positions
        self.states = states
        self.processor = states[0].processor
        self.baseline = np.array([state.baseline.value for state in states])
        self.noise = np.array([state.processor.noise(state.baseline.value, state.baseline.std) for state in states])
        self.sensitivity = np.array([fatigue_factor(state) for state in states])
        self.zero = zero_sigmas(states)
        self.cycles = [state.cycles for state in states]
        self.ones = [1] * len(states)
        # Runs stacked when every quad's converter shows noise (the usual board); else counted per sensor.
        self.runs = None
        if all(state.processor.noisy(state.baseline.std) for state in states):
            last, prior = (np.array(a) for a in zip(*(state.processor.runs_before() for state in states)))
            for k, state in enumerate(states):
                state.processor.runs = (last[k], prior[k])
            self.runs = (last, prior)

    def stale(self, capacitance: np.ndarray, scans: int) -> tuple[np.ndarray | None, list]:
        """``stale_runs`` of the batch's readings (sensor after sensor, each with its ``scans``)."""
        if self.runs is None:
            return stale_runs(self.states, capacitance, [scans] * len(self.states))
        block = capacitance.reshape(len(self.states), scans, 4)
        runs = run_lengths(*self.runs, block)
        hit = runs >= STUCK_FRAMES
        return (hit.reshape(capacitance.shape) if np.count_nonzero(hit) else None), [(self.runs, runs[:, -1], block[:, -1])]


class QuadPlan:
    """A read of tared quads, one scan of each sensor or several (k scans,
    scan after scan, as reads pile up while the loop is busy), as the last
    one went.

    ``states``: the sensors of one scan, in order; ``batches``: (positions
    in a scan, the states there), one per model, as the general path
    grouped them."""

    def __init__(self, level: str, states: list, batches: list[tuple[list[int], list]]) -> None:
        self.level = level
        self.states = states
        # What each sensor's constants rest on: a change to any of them (a tare, a late channel's baseline,
        # a calibration, a load cycle counted) makes the plan miss, and the general path runs.
        self._basis = [(state.baseline.value, state.processor, state.calibration, state.cycles,
                        int(state.cycles.counts[0])) for state in states]
        self.batches = [_Batch(level, positions, members) for positions, members in batches]
        self._single = len(self.batches) == 1 and self.batches[0].positions == list(range(len(states)))

    def fits(self, items: list[tuple[object, Reading]]) -> bool:
        """Whether ``items`` are k scans of the planned sensors, in order, on the same basis."""
        n = len(self.states)
        if not items or len(items) % n:
            return False
        for (state, _), planned, (value, processor, calibration, cycles, count) in zip(items, self.states, self._basis):
            if (state is not planned or state.baseline.value is not value or state.processor is not processor
                    or state.calibration is not calibration or state.cycles is not cycles or cycles.counts[0] != count):
                return False
        states = self.states
        for i in range(n, len(items)):
            if items[i][0] is not states[i % n]:
                return False
        return True

    def frames(self, items: list[tuple[object, Reading]]) -> list[ForceFrame]:
        """The frames of a read that ``fits``, in its order. Every batch is
        computed before any load cycle is counted: if one raises, nothing has
        changed and the general path (which finds the culprit) counts once."""
        readings = [reading for _, reading in items]
        n = len(self.states)
        scans = len(items) // n
        if scans == 1 and self._single:
            return self._apply(self.batches[0], readings, self._computed(self.batches[0], readings, 1), 1)
        computed = []
        for batch in self.batches:
            # Sensor after sensor, each with its scans in order: the general path's order for a batch.
            places = [p + j * n for p in batch.positions for j in range(scans)]
            own = [readings[i] for i in places]
            computed.append((batch, places, own, self._computed(batch, own, scans)))
        out: list[ForceFrame | None] = [None] * len(items)
        for batch, places, own, result in computed:
            for i, frame in zip(places, self._apply(batch, own, result, scans)):
                out[i] = frame
        return out

    @staticmethod
    def _computed(batch: _Batch, readings: list[Reading], scans: int) -> tuple:
        """(forces, quad flags, σ, runs and drift to keep) of a batch's readings, changing nothing."""
        baseline, noise, sensitivity, zero = batch.baseline, batch.noise, batch.sensitivity, batch.zero
        processor = batch.processor
        counts = [scans] * len(batch.states)
        capacitance = without_clipped(readings, np.array([r.capacitance_pF for r in readings]), batch.states, counts)
        stale, kept = batch.stale(capacitance, scans)
        if scans > 1:
            baseline, noise, sensitivity = (np.repeat(a, scans, axis=0) for a in (baseline, noise, sensitivity))
            zero = None if zero is None else np.repeat(zero, scans)
        baseline, found = drifted(batch.level, batch.states, counts, readings, capacitance, baseline, noise, stale)
        if scans > 1:
            forces, quad_flags, sensitivity = _with_fatigue(processor, batch.states, counts, capacitance, baseline,
                                                            noise, sensitivity, stale)
        else:
            forces, quad_flags = processor.process(capacitance, baseline, noise, sensitivity, stale)
        sigma = processor.sigma(forces, noise, sensitivity, zero_drift(found, zero))
        return forces, with_suspect(quad_flags, forces, found), sigma, (kept, found)

    def _apply(self, batch: _Batch, readings: list[Reading], result: tuple, scans: int) -> list[ForceFrame]:
        """Keep the batch's runs, count its load cycles and make its frames."""
        forces, quad_flags, sigma, (kept, found) = result
        keep_runs(kept)
        if found is not None:
            quad_drift.keep(found.kept)
        counts = [scans] * len(batch.states) if scans > 1 else None
        update_many(batch.cycles, forces[:, 2:3], counts or batch.ones)
        return _frames(self.level, batch.states, readings, forces, sigma, quad_flags, counts)

"""Each sensor's state as the reconstruction keeps it: its calibration, tare and load cycles.

``SensorStates`` (the Reconstructor's base) makes a sensor's state when the
sensor is first seen: its calibration (set through ``set_calibration``,
else ``resolve``'s — the registry, a recording, ``--calibration`` chosen
above this layer — else the built-in one), the processor built on it
(calibration_upload.py), its tare window and its load-cycle counter with the
counts kept for that calibration (fatigue.py). A finished tare is judged
against the sensor's zero stored before the service started, the first
after it (stored_zero.py), else against the calibration's C0
(loaded_tare.py). Another sensor described at
its address (identity.py) is made anew the same way, as first seen.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..readings import SensorInfo
from .baseline import Baseline
from .calibration_upload import own_level, processor_for, tare_window, upload_document
from .fatigue import CycleCounter
from .grid import GridProcessor
from .identity import Replacements, identity, named
from .loaded_tare import judge, loaded_taxels
from .quad import QuadProcessor
from .quad_drift import resume, where
from .sensor_calibration import SensorCalibration, builtin, from_document
from .stored_zero import StoredZero, StoredZeros

log = logging.getLogger(__name__)

Resolver = Callable[[SensorInfo], "SensorCalibration | None"]


@dataclass
class SensorState:
    """One sensor's reconstruction state: what it is, its tare, its processor and calibration."""

    info: SensorInfo
    baseline: Baseline
    processor: GridProcessor | QuadProcessor
    calibration: SensorCalibration
    tare_judged: bool = False  # the finished tare was compared with the calibration's C0
    judge_tare: bool = True  # False after a forced tare: the user says the load is the zero
    loaded: np.ndarray | None = None  # (n,) taxels loaded at tare (their zero is the calibration's C0)
    cycles: CycleCounter | None = None  # load cycles per taxel (a quad: of Fz), fatigue.py
    sensitivity_for: tuple | None = None  # (cycles, model, factor): a quad's fatigue factor, kept until the count moves
    below_c0: list = field(default_factory=list)  # taxels below the calibration's C0 at the last tare (loaded_tare.py)
    stored_zero: StoredZero | None = None  # the zero kept before the service started, for its first tare
    zero_kept: dict | None = None  # what that tare made of it (stored_zero.py)
    judged_once: bool = False  # a tare of it was judged: the stored zero's turn is over
    tared_at: float = 0.0  # Unix time the last tare was judged: an untracked zero's age (stored_zero.py)


class SensorStates(StoredZeros):
    """The per-sensor half of the Reconstructor (module docstring)."""

    def __init__(self, level: str, mounting: str, tare_frames: int, resolve: Resolver | None) -> None:
        self.level = level
        self.mounting = mounting
        self.tare_frames = tare_frames
        self._sensors: dict[int, SensorState] = {}
        self.resolve = resolve
        self.load_cycles: Callable[[SensorInfo, str], list | None] | None = None  # counts kept for (sensor, calibration)
        self._chosen: dict[tuple, SensorCalibration] = {}  # by identity: set through set_calibration, over ``resolve``
        self.replacements = Replacements()  # other sensors described at an address, and counts of those that left
        self.calibration_problems: dict[int, str] = {}  # sensor → why its own calibration could not be used
        self._first_judge: dict[int, bool] = {}  # a forced tare recorded before the sensor's first frame (replay)
        self._preset: dict[int, dict] = {}  # zeros a recording began with, for sensors not seen yet (replay)

    def _calibration_applied(self, sensor_id: int) -> None:
        """A sensor's calibration was replaced (the Reconstructor gives a failing sensor another try)."""

    def set_calibration(self, info: SensorInfo, upload: dict, sensor: dict | None = None) -> dict:
        """Replace a sensor's calibration (an upload or a registry document,
        calibration_upload.upload_document); ValueError names the bad field
        and why (the API answers 422). The baseline is kept. Returns the
        document applied, with its id."""
        return self.apply_calibration(info, self.prepare_calibration(info, upload, sensor))

    def prepare_calibration(self, info: SensorInfo, upload: dict, sensor: dict | None = None) -> tuple:
        """The slow half of ``set_calibration`` (validation, the new
        processor), which touches no state: it may run while frames are
        being reconstructed."""
        document = upload_document(info, upload, self.mounting, sensor)
        calibration = from_document(document, info, self.mounting)
        return calibration, processor_for(info, self.level, self.mounting, calibration), document

    def apply_calibration(self, info: SensorInfo, prepared: tuple) -> dict:
        """The quick half: swap the calibration and the sensor's processor in."""
        calibration, processor, document = prepared
        self._chosen[identity(info)] = calibration
        state = self._sensors.get(info.id)
        if state is not None and identity(state.info) == identity(info):  # not one still reconstructed as another
            self._swap(state, calibration, processor)
        return document

    def _described_again(self, state: SensorState, info: SensorInfo) -> None:
        """A new INFO describes the sensor as before (``info`` equal, not the
        same object): later readings carry ``info``, so it is kept (they
        skip the comparison); and the INFO may name the board, which a board
        already streaming when the service connected had not before the
        sensor's first frames: its calibration is looked up again and one
        that differs is swapped in, the zero kept (one set through
        ``set_calibration`` stays). At the first reading after the INFO,
        live or in a replay however its reads are joined."""
        before, state.info = identity(state.info), info
        if before in self._chosen:  # the INFO only named the board: the sensor is the same
            self._chosen[identity(info)] = self._chosen.pop(before)
            return
        if self.resolve is None:
            return
        calibration = self._calibration_for(info)
        if calibration.id != state.calibration.id:
            self._swap(state, calibration, processor_for(info, self.level, self.mounting, calibration))
            log.info("sensor %d: calibration %s now that its board's INFO named it", info.id, calibration.id)

    def _swap(self, state: SensorState, calibration: SensorCalibration, processor) -> None:
        """``calibration`` and its ``processor`` in place of the sensor's, its zero kept."""
        runs = state.processor.stale_runs
        if runs is not None:  # a converter stuck before the new calibration is still stuck
            processor.restore_stale_runs(*runs)
        state.processor, state.calibration = processor, calibration
        state.baseline.own_level = own_level(state.info, self.mounting, calibration)  # its C0 pattern from now on
        state.cycles = self._cycles(state.info, calibration)  # counts belong to a calibration: a new one starts anew
        state.tare_judged, state.below_c0 = False, []  # judged again against the new C0
        self._calibration_applied(state.info.id)

    def tare_glitches(self, sensor_id: int) -> dict[int, int]:
        """{channel: readings left out of its zero as glitches} of the current
        tare (baseline.py): told, since a step in the window that did not
        restart it is left out the same way."""
        state = self._sensors.get(sensor_id)
        if state is None:
            return {}
        rejected = state.baseline.rejected
        return {int(k): int(rejected[k]) for k in np.flatnonzero(rejected)}

    def tare_restarts(self, sensor_id: int) -> int:
        """Tare windows begun again for a step (a load put down or let go) since the last tare."""
        state = self._sensors.get(sensor_id)
        return 0 if state is None else state.baseline.restarts

    def unzeroed(self, sensor_id: int) -> list[int]:
        """Channels the completed tare gave no zero (no plausible reading in
        its window): their forces are null, flagged, until one comes."""
        state = self._sensors.get(sensor_id)
        if state is None or not state.baseline.ready:
            return []
        return np.flatnonzero(np.isnan(state.baseline.value)).tolist()

    def implausible(self, sensor_id: int, capacitance_pF: np.ndarray) -> list[int]:
        """Channels whose reading (n,) pF lies outside the plausible ΔC/C0
        range against their zero (level0.py): read so, they give no force."""
        state = self._sensors.get(sensor_id)
        if state is None or not state.baseline.ready:
            return []
        low, high = state.processor.plausible
        relative = capacitance_pF / state.baseline.value - 1.0
        return np.flatnonzero((relative < low) | (relative > high)).tolist()

    def kind(self, sensor_id: int) -> str | None:
        """The sensor's kind ("grid", "quad"); None for a sensor not seen yet."""
        state = self._sensors.get(sensor_id)
        return None if state is None else state.info.kind

    def sensor_ids(self) -> list[int]:
        return sorted(self._sensors)

    def calibration(self, sensor_id: int) -> SensorCalibration | None:
        """The calibration sensor ``sensor_id`` is reconstructed with (None: not seen yet)."""
        state = self._sensors.get(sensor_id)
        return None if state is None else state.calibration

    def _calibration_for(self, info: SensorInfo) -> SensorCalibration:
        """Chosen by set_calibration, else ``resolve``'s, else the built-in one.
        A calibration that does not fit the sensor is set aside, with the
        reason kept, never a reason to stop the sensor's data."""
        key = identity(info)
        if key not in self._chosen and named(info) and ("board", None, info.id) in self._chosen:
            # set before any INFO named the address: the sensor first named there, as in _described_again
            self._chosen[key] = self._chosen.pop(("board", None, info.id))
        chosen = self._chosen.get(key)
        if chosen is not None and chosen.kind == info.kind and (
                chosen.grid is None or (chosen.grid.rows, chosen.grid.cols) == (info.rows, info.cols)):
            return chosen
        self.calibration_problems.pop(info.id, None)
        try:
            found = self.resolve(info) if self.resolve is not None else None
        except Exception as exc:  # noqa: BLE001 — a registry or document problem: the built-in one, said so
            self.calibration_problems[info.id] = f"{type(exc).__name__}: {exc}"
            log.warning("sensor %d: its calibration cannot be used (%s); the built-in one is", info.id, exc)
            found = None
        return found if found is not None else builtin(info, self.mounting)

    def _state(self, info: SensorInfo) -> SensorState:
        state = self._sensors.get(info.id)
        if state is not None and state.info is not info and state.info == info:
            self._described_again(state, info)
            if not state.judged_once:  # the INFO may name it only now: its stored zero is known by its name
                state.stored_zero = self._stored_zero(info, state.calibration.id)
        if state is None or state.info is not info:
            # A sensor that left for another address (a swap) takes its counter along: not kept as one that left.
            leaving = None if state is None or self._live_elsewhere(state.info) else state.cycles
            change = None if state is None else self.replacements.replaced(state.info, info, state.calibration.id,
                                                                           leaving)
            if change is not None:
                log.warning("sensor %d: %s where %s was: tared afresh, its calibration and load cycles looked up "
                            "for it", info.id, change["to"], change["from"])
            calibration = self._calibration_for(info)
            window = tare_window(info, self.mounting, calibration)
            state = SensorState(info, Baseline(info.channels, self.tare_frames, window,
                                               own_level(info, self.mounting, calibration), info.kind == "quad"),
                                 processor_for(info, self.level, self.mounting, calibration), calibration)
            state.cycles = self._cycles(info, calibration)
            state.stored_zero = self._stored_zero(info, calibration.id)
            state.judge_tare = self._first_judge.pop(info.id, True)
            zero = self._preset.pop(info.id, None)
            if zero is not None and len(zero["baseline_pF"]) == info.channels:
                state.baseline.preset(_array(zero["baseline_pF"]), _array(zero["std_pF"]))
                state.tare_judged = True  # judged live, before the recording
                if zero.get("loaded"):
                    state.loaded = np.isin(np.arange(info.channels), zero["loaded"])
                if zero.get("stale_runs") is not None and len(zero["stale_runs"]) == info.channels:
                    state.processor.restore_stale_runs(_array(zero["stale_last_pF"]), zero["stale_runs"])
                if zero.get("cycles") is not None and state.cycles is not None:
                    state.cycles.resume(zero)
                if zero.get("drift") is not None and isinstance(state.processor, QuadProcessor):
                    resume(state.processor, state.baseline, zero["drift"])
            self._sensors[info.id] = state
        return state

    def baselines(self) -> list[dict]:
        """Each tared sensor's zero: {sensor, baseline_pF, std_pF, loaded,
        where its stale-channel count stands: stale_last_pF, stale_runs, its
        load-cycle count: cycles, cycles_seen, cycles_armed, and a quad's
        drift tracker: drift} (NaN as None), what a recording begun now
        stores for its replay."""
        out = []
        for sid, state in sorted(self._sensors.items()):
            if state.baseline.ready:
                zero = {"sensor": sid, "baseline_pF": _listed(state.baseline.value), "std_pF": _listed(state.baseline.std),
                        "loaded": [] if state.loaded is None else np.flatnonzero(state.loaded).tolist()}
                runs = state.processor.stale_runs
                if runs is not None:
                    zero |= {"stale_last_pF": _listed(runs[0]), "stale_runs": runs[1].tolist()}
                if state.cycles is not None:
                    zero |= state.cycles.where()
                drift = where(state.processor, state.baseline.value) if isinstance(state.processor, QuadProcessor) else None
                if drift is not None:
                    zero["drift"] = drift
                out.append(zero)
        return out

    def preset_baselines(self, zeros: list[dict]) -> None:
        """Zeros a recording stored (``baselines``) for the sensors it will
        show: each starts tared with its own when first seen, as it ran live,
        not with a tare on whatever load the recording begins with."""
        for zero in zeros:
            self._preset[int(zero["sensor"])] = zero

    def judge_first_tare(self, sensor_id: int, judge: bool) -> None:
        """How the tare of a sensor not seen yet is to be judged (a recorded
        forced tare a replay meets before the sensor's first frame): it
        tares at its first frame, not from a zero the recording began with."""
        self._first_judge[sensor_id] = judge
        self._preset.pop(sensor_id, None)

    def _cycles(self, info: SensorInfo, calibration: SensorCalibration) -> CycleCounter:
        """The sensor's counter, from the counts kept for its calibration (none kept, or unreadable: 0); one
        back at its address after another sensor was there goes on with its own (identity.py)."""
        n = 1 if info.kind == "quad" else info.channels
        moved = self._live_elsewhere(info)
        if moved is not None and moved.calibration.id == calibration.id and moved.cycles is not None \
                and moved.cycles.counts.shape == (n,):
            return moved.cycles  # moved from another address (sensors swapped): its count goes on, one counter
        back = self.replacements.returning(info, calibration.id)
        if back is not None and back.counts.shape == (n,):
            return back
        try:
            counts = self.load_cycles(info, calibration.id) if self.load_cycles is not None else None
            counter = CycleCounter(n, counts)
        except Exception as exc:  # noqa: BLE001 — lost counts are a warning, never lost data
            log.warning("sensor %d: its load-cycle counts cannot be read (%s); counting from 0", info.id, exc)
            counter = CycleCounter(n)
        counter.at_start = counter.counts.tolist()  # what a recording stores, so its replay starts from the same
        return counter

    def _live_elsewhere(self, info: SensorInfo) -> SensorState | None:
        """The state of the same sensor (a serial's identity) at another address, if any."""
        key = identity(info)
        return next((state for sid, state in self._sensors.items() if sid != info.id and identity(state.info) == key),
                    None)

    def cycle_counts(self) -> dict[int, tuple[SensorInfo, str, list[int]]]:
        """{sensor: (info, calibration id, counts)} to keep (the registry)."""
        return {sid: (state.info, state.calibration.id, state.cycles.counts.tolist())
                for sid, state in list(self._sensors.items()) if state.cycles is not None}

    def replaced(self, sensor_id: int) -> dict | None:
        """How often another sensor took this address's place, the last time from which to which (identity.py)."""
        return self.replacements.changes.get(sensor_id)

    def cycles_at_start(self, sensor_id: int) -> list[int] | None:
        state = self._sensors.get(sensor_id)
        return None if state is None or state.cycles is None else state.cycles.at_start

    def fatigue(self, sensor_id: int) -> dict | None:
        """Load cycles (max and total over taxels) and the sensitivity factor in use."""
        state = self._sensors.get(sensor_id)
        if state is None or state.cycles is None:
            return None
        model = state.calibration.fatigue
        counts = state.cycles.counts
        factor = None if model is None else float(np.min(model.factor(counts)))
        return {"cycles_max": int(counts.max()), "cycles_total": int(counts.sum()), "sensitivity_factor": factor,
                "model": None if model is None else {"drop": model.drop, "tau_cycles": model.tau_cycles}}

    def tare(self, sensor_id: int | None = None, judge: bool = True) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared.
        ``judge`` False: the load present is the zero (a forced tare)."""
        ids = sorted(self._sensors) if sensor_id is None else [sensor_id]
        for sid in ids:
            if sid not in self._sensors:
                raise KeyError(sid)
            state = self._sensors[sid]
            state.baseline.tare()
            self._window_begun(state, judge)
        return ids

    @staticmethod
    def _window_begun(state: SensorState, judge: bool) -> None:
        """A tare window began: the last one's judgement and loaded taxels, and the drift tracked on its zero, go."""
        state.tare_judged, state.judge_tare, state.loaded, state.below_c0 = False, judge, None, []
        if isinstance(state.processor, GridProcessor):
            state.processor.reset()

    def loaded_now(self, sensor_id: int, capacitance_pF: np.ndarray) -> list[int]:
        """Taxels that a reading (n,) pF shows loaded against the calibration's
        C0 (loaded_tare.py; one reading, so its own noise): what a tare now
        would make its zero. Empty where C0 was not measured."""
        state = self._sensors.get(sensor_id)
        calibration = None if state is None else state.calibration
        if calibration is None or calibration.measured is None or not calibration.measured.any():
            return []
        std = state.baseline.std if state.baseline.ready else np.full(state.info.channels, np.nan)
        return np.flatnonzero(loaded_taxels(calibration.tare_c0_pF, calibration.measured, capacitance_pF, std, 1)).tolist()

    def below_c0(self, sensor_id: int) -> list[int]:
        """Taxels that read below the calibration's C0 at the last tare, enough of them to say it is not this
        sensor's C0 (loaded_tare.py); empty otherwise."""
        state = self._sensors.get(sensor_id)
        return [] if state is None else state.below_c0

    def loaded_at_tare(self, sensor_id: int) -> list[int]:
        """Taxels whose zero is the calibration's C0 since the last tare."""
        state = self._sensors.get(sensor_id)
        return [] if state is None or state.loaded is None else np.flatnonzero(state.loaded).tolist()

    def _judge_tare(self, state: SensorState) -> None:
        """Once a tare is complete: loaded channels get the stored zero (the first after the service
        started), else a grid's the calibration's C0."""
        state.tare_judged = state.judged_once = True
        state.tared_at = time.time()
        state.below_c0 = []
        stored, state.stored_zero = state.stored_zero, None
        if not state.judge_tare or (stored is not None and self._judge_stored(state, stored)):
            return
        calibration = state.calibration
        if calibration.measured is None or not calibration.measured.any():
            return
        baseline = state.baseline
        loaded, mismatch, c0 = judge(calibration.tare_c0_pF, calibration.measured, baseline.value, baseline.std,
                                     baseline.frames)
        state.below_c0 = np.flatnonzero(mismatch).tolist()
        if state.below_c0:
            log.warning("sensor %d: taxels %s read below the calibration's C0 at the tare: its C0 is not this "
                        "sensor's as it is now, so no taxel is judged loaded", state.info.id, state.below_c0)
        if loaded.any():
            baseline.substitute(loaded, c0)
            state.loaded = loaded
            log.warning("sensor %d: taxels %s were loaded at tare; their zero is the calibration's C0",
                        state.info.id, np.flatnonzero(loaded).tolist())

    def baseline(self, sensor_id: int) -> np.ndarray | None:
        state = self._sensors.get(sensor_id)
        return None if state is None or not state.baseline.ready else state.baseline.value

    def crosstalk_report(self, sensor_id: int) -> dict | None:
        state = self._sensors.get(sensor_id)
        if state is None or not isinstance(state.processor, GridProcessor) or state.processor.crosstalk is None:
            return None
        processor = state.processor
        return {
            "mechanical_coupling_in_use": processor.crosstalk.mechanical,
            "electrical_leakage_in_use": processor.crosstalk.electrical,
            "isolated_loads_adopted": processor.adopted_events,
            "pending_estimates": processor.estimator.report(),
            "common_mode_drift": processor.drift.drift,
        }


def _listed(values: np.ndarray) -> list[float | None]:
    return [None if v != v else v for v in values.tolist()]


def _array(values: list) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)

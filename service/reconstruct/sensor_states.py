"""Each sensor's state as the reconstruction keeps it: its calibration, tare and load cycles.

``SensorStates`` (the Reconstructor's base) makes a sensor's state when the
sensor is first seen: its calibration (set through ``set_calibration``,
else ``resolve``'s — the registry, a recording, ``--calibration`` chosen
above this layer — else the built-in one), the processor built on it
(calibration_upload.py), its tare window and its load-cycle counter with the
counts kept for that calibration (fatigue.py). A finished tare is judged
against the sensor's zero stored before the service started, the first
after it (stored_zero.py), else against the C0 its calibration measured
(loaded_tare.py: a grid's taxels, a quad's four electrodes together); a
quad's first against that C0's pattern, which may set the calibration
aside as another quad's (calibration_choice.py).
Another sensor described at
its address (identity.py) is made anew the same way, as first seen; one
back there after another was is judged against the zero it left with.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..readings import SensorInfo
from .baseline import Baseline
from .calibration_upload import expected_c0, own_level, processor_for, tare_window
from .fatigue import CycleCounter
from .grid import GridProcessor
from .identity import Replacements, identity, named
from .loaded_tare import judge, judge_quad, kept_zero_sigma
from .quad import QuadProcessor
from .quad_drift import resume, where
from .sensor_calibration import SensorCalibration
from .sigma import zero_sigma_for
from .calibration_choice import CalibrationChoice
from .cycle_counters import CycleCounters
from .stored_zero import MAX_AGE_S, StoredZero, StoredZeros, row_problem

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
    stored_zero: StoredZero | None = None  # the zero kept before the service started, or it left with, for its first tare
    zero_kept: dict | None = None  # what that tare made of it (stored_zero.py)
    judged_once: bool = False  # a tare of it was judged: the stored zero's turn is over
    tared_at: float = 0.0  # Unix time the last tare was judged: an untracked zero's age (stored_zero.py)
    tared_t_host: float = float("nan")  # t_host (s) of the reading that completed the last tare: the same, as it left
    last_t_host: float = float("nan")  # t_host (s) of its last reading: when the zero it left with was last tracked
    # (its own calibration, why): set aside for the built-in at a tare, not this quad's (calibration_choice.py)
    set_aside: tuple[SensorCalibration, str] | None = None


class SensorStates(StoredZeros, CalibrationChoice, CycleCounters):
    """The per-sensor half of the Reconstructor (module docstring)."""

    def __init__(self, level: str, mounting: str, tare_frames: int, resolve: Resolver | None) -> None:
        self.level = level
        self.mounting = mounting
        self.tare_frames = tare_frames
        self._sensors: dict[int, SensorState] = {}
        self.resolve = resolve
        self.load_cycles: Callable[[SensorInfo, str], list | None] | None = None  # counts kept for (sensor, calibration)
        self._chosen: dict[tuple, SensorCalibration] = {}  # by identity: set through set_calibration, over ``resolve``
        # Other sensors described at an address, and the counts and zeros of those that left.
        self.replacements = Replacements(max_zero_age_s=MAX_AGE_S)
        self.calibration_problems: dict[int, str] = {}  # sensor → why its own calibration could not be used
        self._first_judge: dict[int, bool] = {}  # a forced tare recorded before the sensor's first frame (replay)
        self._preset: dict[int, dict] = {}  # zeros a recording began with, for sensors not seen yet (replay)

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

    def outside_expected(self, sensor_id: int, capacitance_pF: np.ndarray) -> dict | None:
        """Channels without a zero whose reading (n,) pF lies outside the
        window a tare takes around the C0 its calibration expects
        (calibration_upload.tare_window), when they are most of those that
        read: the sensor's C0 is not the calibration's (a lone one is a
        faulty channel, left to ``unzeroed``). {channels, read_pF: [min, max],
        window_pF: [low, high], c0_pF: [min, max] over them, calibration: id,
        measured: whether that C0 was measured on the sensor}; None otherwise."""
        state = self._sensors.get(sensor_id)
        if state is None or not state.baseline.ready:
            return None
        low, high = tare_window(state.info, self.mounting, state.calibration)
        reads = capacitance_pF == capacitance_pF
        outside = np.isnan(state.baseline.value) & reads & ((capacitance_pF < low) | (capacitance_pF > high))
        if 2 * np.count_nonzero(outside) <= np.count_nonzero(reads):
            return None
        c0 = expected_c0(state.info, state.calibration)[outside]
        return {"channels": np.flatnonzero(outside).tolist(),
                "read_pF": [float(capacitance_pF[outside].min()), float(capacitance_pF[outside].max())],
                "window_pF": [float(low[outside].min()), float(high[outside].max())],
                "c0_pF": [float(c0.min()), float(c0.max())], "calibration": state.calibration.id,
                "measured": state.calibration.measured_c0_pF is not None}

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

    def _state(self, info: SensorInfo, restart: bool = False) -> SensorState:
        """The sensor's state, made anew for another sensor described at its
        address; ``restart``: its reading is a board's first after a power-up (_same_sensor)."""
        state = self._sensors.get(info.id)
        if state is not None and state.info is not info and _same_sensor(state.info, info, restart):
            known_as = (identity(state.info), state.calibration.id)
            self._described_again(state, info)
            # The INFO may name it only now (or its calibration): its stored zero is known by that. An INFO that
            # changes neither (a reply to INFO?) keeps the one found: the zero it left with was handed over then.
            if not state.judged_once and known_as != (identity(info), state.calibration.id):
                state.stored_zero = self._stored_zero(info, state.calibration.id)
        if state is None or state.info is not info:
            # A sensor that left for another address (a swap) takes its counter along, and tares there: neither
            # its counter nor its zero is kept as one that left.
            gone = state is not None and self._live_elsewhere(state.info) is None
            change = None if state is None else self.replacements.replaced(
                state.info, info, state.calibration.id, state.cycles if gone else None,
                self._zero_left(state) if gone else None)
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
            if zero is not None and zero.get("taring") is not None:
                self._resume_taring(state, zero)
            elif zero is not None and len(zero["baseline_pF"]) == info.channels:
                state.baseline.preset(_array(zero["baseline_pF"]), _array(zero["std_pF"]))
                state.tare_judged = True  # judged live, before the recording
                state.tared_t_host = _array([zero.get("tared_t_host")])[0]  # None in older recordings: unknown
                # A forced zero stays the zero when a calibration set later has it judged again, as it did live.
                state.judge_tare = zero.get("judge") is not False
                if zero.get("loaded"):
                    state.loaded = np.isin(np.arange(info.channels), zero["loaded"])
                    self._resume_zero_sigma(state, zero.get("zero_sigma"))
                self._resume_counts(state, zero)
                if zero.get("drift") is not None and isinstance(state.processor, QuadProcessor):
                    resume(state.processor, state.baseline, zero["drift"])
            self._sensors[info.id] = state
        return state

    @staticmethod
    def _resume_zero_sigma(state: SensorState, sigma) -> None:
        """The σ (ΔC/C0 per channel) of the zero a recording began with, kept at a loaded tare, as it was live;
        one that is no list of as many non-negative numbers as channels (absent in older recordings) is skipped."""
        if sigma is None:
            return
        if not (isinstance(sigma, list) and len(sigma) == state.info.channels and
                all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v < math.inf for v in sigma)):
            log.warning("sensor %d: its recorded zero_sigma %.60r is not %d numbers ≥ 0; its zero's σ is left out",
                        state.info.id, sigma, state.info.channels)
            return
        state.processor.kept_zero = (state.baseline.value, np.array(sigma, dtype=float))

    def _resume_taring(self, state: SensorState, zero: dict) -> None:
        """A recording begun while the sensor tared: its window goes on from
        the readings it had (judged at its end as live: forced or not); one
        that does not fit the sensor is said and the sensor tares afresh."""
        try:
            state.baseline.resume_window(zero["taring"])
        except (ValueError, KeyError, TypeError) as exc:
            log.warning("sensor %d: the tare window the recording began in cannot be gone on with (%s): tared "
                        "afresh", state.info.id, exc)
            return
        state.judge_tare = zero.get("judge") is not False
        self._resume_counts(state, zero)

    @staticmethod
    def _resume_counts(state: SensorState, zero: dict) -> None:
        """Where a recorded sensor's stale-channel and load-cycle counts stood (``baselines``)."""
        if zero.get("stale_runs") is not None and len(zero["stale_runs"]) == state.info.channels:
            state.processor.restore_stale_runs(_array(zero["stale_last_pF"]), zero["stale_runs"])
        if zero.get("cycles") is not None and state.cycles is not None:
            state.cycles.resume(zero)

    def baselines(self) -> list[dict]:
        """Each tared sensor's zero: {sensor, baseline_pF, std_pF, loaded,
        judge (False: a forced tare's, the load present is the zero),
        tared_t_host (its tare's last reading's host time, where known), where
        its stale-channel count stands: stale_last_pF, stale_runs, its
        load-cycle count: cycles, cycles_seen, cycles_armed, and a quad's
        drift tracker: drift} (NaN as None); a sensor taring, its window so
        far instead of a zero: {sensor, taring (Baseline.window_so_far),
        judge, and those counts}. What a recording begun now stores for its
        replay."""
        out = []
        for sid, state in sorted(self._sensors.items()):
            if not state.baseline.ready:
                out.append({"sensor": sid, "taring": state.baseline.window_so_far(), "judge": state.judge_tare,
                            **self._counts(state)})
                continue
            zero = {"sensor": sid, "baseline_pF": _listed(state.baseline.value), "std_pF": _listed(state.baseline.std),
                    "loaded": [] if state.loaded is None else np.flatnonzero(state.loaded).tolist(),
                    "judge": state.judge_tare, **self._counts(state)}
            kept = zero_sigma_for(state.processor.kept_zero, state.baseline.value)
            if kept is not None:
                zero["zero_sigma"] = _listed(kept)
            if state.tared_t_host == state.tared_t_host:
                zero["tared_t_host"] = state.tared_t_host
            drift = where(state.processor, state.baseline.value) if isinstance(state.processor, QuadProcessor) else None
            if drift is not None:
                zero["drift"] = drift
            out.append(zero)
        return out

    def preset_left_zeros(self, left: list[dict]) -> None:
        """The zeros of sensors that had left their address when a recording began (Replacements.left_zeros):
        one back in it is judged against its own, as it was live. A recording is any file: an entry that is not
        {identity, calibration, zero} as kept is said and skipped, not the replay."""
        for kept in left:
            problem = _left_problem(kept)
            if problem is not None:
                log.warning("a zero of a sensor that had left its address, recorded as %.120r, is skipped: %s", kept,
                            problem)
                continue
            self.replacements.keep_zero(tuple(kept["identity"]), kept["calibration"], kept["zero"])

    @staticmethod
    def _counts(state: SensorState) -> dict:
        """Where the sensor's stale-channel and load-cycle counts stand, as ``baselines`` gives them."""
        counts = {}
        runs = state.processor.stale_runs
        if runs is not None:
            counts |= {"stale_last_pF": _listed(runs[0]), "stale_runs": runs[1].tolist()}
        if state.cycles is not None:
            counts |= state.cycles.where()
        return counts

    def preset_baselines(self, zeros: list[dict]) -> None:
        """Zeros a recording stored (``baselines``) for the sensors it will
        show: each starts tared with its own when first seen, as it ran live,
        not with a tare on whatever load the recording begins with (one then
        taring goes on with its window so far)."""
        for zero in zeros:
            self._preset[int(zero["sensor"])] = zero

    def judge_first_tare(self, sensor_id: int, judge: bool) -> None:
        """How the tare of a sensor not seen yet is to be judged (a recorded
        forced tare a replay meets before the sensor's first frame): it
        tares at its first frame, not from a zero the recording began with."""
        self._first_judge[sensor_id] = judge
        self._preset.pop(sensor_id, None)

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
        """Taxels (a quad's electrodes) that a reading (n,) pF shows loaded
        against the calibration's C0 (``against_c0``; one reading, so its own
        noise): what a tare now would make its zero. Empty where C0 was not measured."""
        state = self._sensors.get(sensor_id)
        if state is None:
            return []
        std = state.baseline.std if state.baseline.ready else np.full(state.info.channels, np.nan)
        judged = against_c0(state.calibration, capacitance_pF, std, 1)
        return [] if judged is None else np.flatnonzero(judged[0]).tolist()

    def below_c0(self, sensor_id: int) -> list[int]:
        """Taxels that read below the calibration's C0 at the last tare, enough of them to say it is not this
        sensor's C0 (loaded_tare.py); empty otherwise."""
        state = self._sensors.get(sensor_id)
        return [] if state is None else state.below_c0

    def loaded_at_tare(self, sensor_id: int) -> list[int]:
        """Taxels whose zero is the calibration's C0 since the last tare."""
        state = self._sensors.get(sensor_id)
        return [] if state is None or state.loaded is None else np.flatnonzero(state.loaded).tolist()

    def _judge_tare(self, state: SensorState, t_host: float) -> None:
        """Once a tare is complete (its last reading received at ``t_host``): loaded channels get the
        stored zero (the first after the service started, or back at its address), else a grid's the
        calibration's C0. Judged only once they have: the zeros' saver (another thread,
        stored_zero.py) takes a judged zero, never the loaded means before it."""
        try:
            self._judge_loaded(state, t_host)
        finally:
            state.tare_judged = state.judged_once = True

    def _judge_loaded(self, state: SensorState, t_host: float) -> None:
        state.tared_at, state.tared_t_host = time.time(), t_host
        state.below_c0 = []
        stored, state.stored_zero = state.stored_zero, None
        if not state.judge_tare or self._not_its_calibration(state) or \
                (stored is not None and self._judge_stored(state, stored, t_host)):
            return
        baseline = state.baseline
        judged = against_c0(state.calibration, baseline.value, baseline.std, baseline.frames)
        if judged is None:
            return
        loaded, mismatch, c0 = judged
        channels = "electrodes" if state.info.kind == "quad" else "taxels"
        state.below_c0 = np.flatnonzero(mismatch).tolist()
        if state.below_c0:
            log.warning("sensor %d: %s %s read below the calibration's C0 at the tare: its C0 is not this "
                        "sensor's as it is now, so none is judged loaded", state.info.id, channels, state.below_c0)
        if loaded.any():
            calibration = state.calibration
            reference = calibration.tare_c0_pF if calibration.quad_c0_pF is None else calibration.quad_c0_pF
            self._keep_zero(state, loaded, c0, kept_zero_sigma(loaded, reference, c0))
            log.warning("sensor %d: %s %s were loaded at tare; their zero is the calibration's C0",
                        state.info.id, channels, np.flatnonzero(loaded).tolist())

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


def against_c0(calibration: SensorCalibration, mean_pF: np.ndarray, std_pF: np.ndarray,
               frames: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """(loaded, mismatch, C0), each (n,), of means of ``frames`` readings
    (n,) pF, spread ``std_pF`` (n,), against the C0 measured on the sensor:
    a grid's measured taxels (loaded_tare.judge), a quad's four electrodes
    together (judge_quad); None when its calibration measured none."""
    if calibration.quad_c0_pF is not None:
        return judge_quad(calibration.quad_c0_pF, mean_pF, std_pF, frames)
    if calibration.measured is None or not calibration.measured.any():
        return None
    return judge(calibration.tare_c0_pF, calibration.measured, mean_pF, std_pF, frames)


def _same_sensor(before: SensorInfo, info: SensorInfo, restart: bool) -> bool:
    """Whether ``info`` describes the sensor ``before`` did: equal, or
    ``before`` was known only from its data frames and the board's first INFO
    gives it the kind and shape inferred from them, an INFO not sent at a
    power-up (a reply to INFO?: its reading is no ``restart``). That INFO
    names the board (its address and identity change, not the sensor:
    identity.named), so the sensor keeps its zero; re-tared there, it took
    the load it held as 0 N. An INFO at a power-up may be another board's
    plugged into the port: its sensors tare afresh (on the first's zero, a
    quad 2-6 % above it read 2.2 N unloaded)."""
    if before == info:
        return True
    return not restart and not named(before) and \
        (before.kind, before.rows, before.cols) == (info.kind, info.rows, info.cols)


def _left_problem(kept) -> str | None:
    """What makes a recorded ``left`` entry no {identity (a list of strings, integers or null), calibration (its
    id), zero (stored_zero.row_problem)}; None when it is one."""
    if not isinstance(kept, dict):
        return "not an object"
    key = kept.get("identity")
    if not isinstance(key, list) or not key or \
            not all(v is None or isinstance(v, (str, int)) and not isinstance(v, bool) for v in key):
        return f"its identity is not a list of strings, integers or null: {key!r:.60}"
    if not isinstance(kept.get("calibration"), str):
        return f"its calibration is not an id: {kept.get('calibration')!r:.60}"
    return row_problem(kept.get("zero"))


def _listed(values: np.ndarray) -> list[float | None]:
    return [None if v != v else v for v in values.tolist()]


def _array(values: list) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)

"""The Reconstructor: readings (capacitance) → ForceFrames (forces, σ, flags), per sensor.

Sensors are batched (grids of a level in one call, quads sharing a model in
one call), a failing sensor isolated from the others (isolation.py). Each
sensor's SensorCalibration comes from ``calibrations`` (the registry, a
recording's own, ``--calibration``: chosen above this layer) or is the
built-in one; calibration_upload.py builds its processor and tare window,
loaded_tare.py judges its tare against the calibration's C0.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..physics.mountings import MOUNTINGS
from ..readings import Reading, SensorInfo
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .calibration_upload import processor_for, tare_window, upload_document
from .force_frame import ForceFrame
from .grid import LOADED_AT_TARE, NO_READING, GridProcessor, flag_names
from .grid_full import GridJob, process_full
from .isolation import Isolation
from .levels import DEFAULT_LEVEL, LEVELS, SceneConfig, choose_level
from .loaded_tare import loaded_taxels
from .quad import QuadProcessor
from .sensor_calibration import SensorCalibration, builtin, from_document

Resolver = Callable[[SensorInfo], "SensorCalibration | None"]

log = logging.getLogger(__name__)


@dataclass
class _SensorState:
    info: SensorInfo
    baseline: Baseline
    processor: GridProcessor | QuadProcessor
    calibration: SensorCalibration
    tare_judged: bool = False  # the finished tare was compared with the calibration's C0
    judge_tare: bool = True  # False after a forced tare: the user says the load is the zero
    loaded: np.ndarray | None = None  # (n,) taxels loaded at tare (their zero is the calibration's C0)


class Reconstructor:
    """Per-sensor tare and force reconstruction at a fidelity level.

    Live use returns each frame at once; until a sensor's baseline is ready
    its forces are null and flagged ``taring``. With ``hold_until_tared``
    (offline replay) readings are held until their sensor's baseline is ready
    and then released with forces, in arrival order, so no frame of a log
    lacks a value and the export keeps the order of the stream.
    """

    def __init__(self, tare_frames: int = DEFAULT_TARE_FRAMES, hold_until_tared: bool = False,
                 level: str = DEFAULT_LEVEL, mounting: str = "flat", scene: SceneConfig | None = None,
                 clock: Callable[[], float] = time.monotonic, calibrations: Resolver | None = None) -> None:
        """``level="auto"`` takes the cheapest level that meets ``scene``'s
        error budget (see levels.py). ``clock`` (seconds) times the errors
        and paces their log lines. ``calibrations`` gives a sensor's
        calibration when it is first seen (None: the built-in one)."""
        if level not in LEVELS:
            raise ValueError(f"unknown fidelity level {level!r}; known: {', '.join(LEVELS)}")
        if mounting not in MOUNTINGS:
            raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
        self.level_reason = "as configured"
        if level == "auto":
            scene = scene or SceneConfig(mounting=mounting)
            level, self.level_reason = choose_level(scene)
            mounting = scene.mounting
        self.level = level
        self.mounting = mounting
        self.tare_frames = tare_frames
        self.hold_until_tared = hold_until_tared
        self._sensors: dict[int, _SensorState] = {}
        self._held: deque[tuple[_SensorState, Reading]] = deque()
        self.resolve = calibrations
        self._chosen: dict[int, SensorCalibration] = {}  # set through set_calibration, over ``resolve``
        self.calibration_problems: dict[int, str] = {}  # sensor → why its own calibration could not be used
        self._isolation = Isolation(self._null_frames, clock, log)

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
        self._chosen[info.id] = calibration
        state = self._sensors.get(info.id)
        if state is not None:
            state.processor, state.calibration = processor, calibration
            state.tare_judged = False  # judged again against the new C0
            self._isolation.failing.discard(info.id)
        return document

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
        chosen = self._chosen.get(info.id)
        if chosen is not None and chosen.kind == info.kind:
            return chosen
        self.calibration_problems.pop(info.id, None)
        try:
            found = self.resolve(info) if self.resolve is not None else None
        except Exception as exc:  # noqa: BLE001 — a registry or document problem: the built-in one, said so
            self.calibration_problems[info.id] = f"{type(exc).__name__}: {exc}"
            log.warning("sensor %d: its calibration cannot be used (%s); the built-in one is", info.id, exc)
            found = None
        return found if found is not None else builtin(info, self.mounting)

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or (state.info is not info and state.info != info):
            calibration = self._calibration_for(info)
            window = tare_window(info, self.mounting, calibration)
            state = _SensorState(info, Baseline(info.channels, self.tare_frames, window),
                                 processor_for(info, self.level, self.mounting, calibration), calibration)
            self._sensors[info.id] = state
        return state

    def tare(self, sensor_id: int | None = None, judge: bool = True) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared.
        ``judge`` False: the load present is the zero (a forced tare)."""
        ids = sorted(self._sensors) if sensor_id is None else [sensor_id]
        for sid in ids:
            if sid not in self._sensors:
                raise KeyError(sid)
            state = self._sensors[sid]
            state.baseline.tare()
            state.tare_judged, state.judge_tare, state.loaded = False, judge, None
            if isinstance(state.processor, GridProcessor):
                state.processor.reset()
        return ids

    def loaded_now(self, sensor_id: int, capacitance_pF: np.ndarray) -> list[int]:
        """Taxels that a reading (n,) pF shows loaded against the calibration's
        C0 (loaded_tare.py; one reading, so its own noise): what a tare now
        would make its zero. Empty where C0 was not measured."""
        state = self._sensors.get(sensor_id)
        calibration = None if state is None else state.calibration
        if calibration is None or calibration.measured is None or not calibration.measured.any():
            return []
        std = state.baseline.std if state.baseline.ready else np.full(state.info.channels, np.nan)
        return np.flatnonzero(loaded_taxels(calibration.grid.c0_pF, calibration.measured, capacitance_pF, std, 1)).tolist()

    def loaded_at_tare(self, sensor_id: int) -> list[int]:
        """Taxels whose zero is the calibration's C0 since the last tare."""
        state = self._sensors.get(sensor_id)
        return [] if state is None or state.loaded is None else np.flatnonzero(state.loaded).tolist()

    def _judge_tare(self, state: _SensorState) -> None:
        """Once a grid's tare is complete: loaded taxels get the calibration's C0."""
        state.tare_judged = True
        calibration = state.calibration
        if not state.judge_tare or calibration.measured is None or not calibration.measured.any():
            return
        baseline = state.baseline
        loaded = loaded_taxels(calibration.grid.c0_pF, calibration.measured, baseline.value, baseline.std, baseline.frames)
        if loaded.any():
            baseline.substitute(loaded, calibration.grid.c0_pF)
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

    def errors(self) -> dict[int, dict]:
        """Per sensor that ever failed, its last error, how often and when (Isolation.errors)."""
        return self._isolation.errors()

    def process(self, reading: Reading) -> list[ForceFrame]:
        return self.process_many([reading])

    def process_many(self, readings: list[Reading]) -> list[ForceFrame]:
        """Reconstruct a batch of readings (e.g. one read from the port), each
        sensor's frames together; returns ForceFrames in arrival order."""
        pending: list[tuple[_SensorState | Exception, Reading]] = []
        for reading in readings:
            try:
                state = self._state(reading.sensor)
                if state.baseline.update(reading.capacitance_pF) and not state.tare_judged:
                    self._judge_tare(state)
            except Exception as exc:  # noqa: BLE001 — isolated: this reading goes out null and flagged
                state = exc
            pending.append((state, reading))
        if not self.hold_until_tared:
            return self._reconstruct(pending)
        self._held.extend(pending)
        release = []
        while self._held and (isinstance(self._held[0][0], Exception) or self._held[0][0].baseline.ready):
            release.append(self._held.popleft())
        return self._reconstruct(release)

    def flush(self) -> list[ForceFrame]:
        """Release every held reading; those of sensors that never completed a
        tare (a log shorter than the tare window) come out null and flagged."""
        frames = self._reconstruct(list(self._held))
        self._held.clear()
        return frames

    def _reconstruct(self, items: list[tuple[_SensorState | Exception, Reading]]) -> list[ForceFrame]:
        groups: dict[int, tuple[_SensorState, list[int]]] = {}
        out: list[ForceFrame | None] = [None] * len(items)
        for index, (state, reading) in enumerate(items):
            if isinstance(state, Exception):  # its baseline or state failed already
                out[index] = self._isolation.error_frames(reading.sensor, [reading], state)[0]
            else:
                groups.setdefault(id(state), (state, []))[1].append(index)

        def place(indices, frames):
            for i, frame in zip(indices, frames):
                out[i] = frame

        # Tared sensors of a kind go through one call per step, all sensors'
        # frames together: at 1 kHz the per-call cost, not the per-frame
        # arithmetic, dominates. Quads are batched by model, grids by level;
        # a sensor that failed last time runs alone until it succeeds.
        quads: dict[tuple, list[tuple[_SensorState, list[int]]]] = {}
        grids: list[tuple[_SensorState, list[int]]] = []
        for state, indices in groups.values():
            if not state.baseline.ready:
                place(indices, self._null_frames(state.info, [items[i][1] for i in indices], "taring"))
            elif state.info.kind == "quad":
                key = state.processor.batch_key if state.info.id not in self._isolation.failing else ("alone", state.info.id)
                quads.setdefault(key, []).append((state, indices))
            else:
                grids.append((state, indices))
        if grids:
            members = [(state, [items[i][1] for i in indices]) for state, indices in grids]
            for (_, indices), frames in zip(grids, self._isolated_grids(members)):
                place(indices, frames)
        for batch in quads.values():
            members = [(state, [items[i][1] for i in indices]) for state, indices in batch]
            place((i for _, indices in batch for i in indices), self._isolation.without_state(members, self._reconstruct_quads))
        return out

    def _isolated_grids(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[list[ForceFrame]]:
        """Tared grids' frames per sensor. At ``full`` they go through one
        call, with rollback (Isolation.with_rollback). Below ``full`` each
        sensor is its own call anyway, isolated where it is made."""
        if self.level != "full":
            return self._reconstruct_grids(members, isolated=True)
        return self._isolation.with_rollback(members, self._reconstruct_grids)

    def _null_frames(self, info: SensorInfo, readings: list[Reading], flag: str) -> list[ForceFrame]:
        """Frames without forces, flagged ``flag`` (taring, reconstruction_error)."""
        forces = np.full((len(readings), 3 if info.kind == "quad" else info.channels), np.nan)
        state = self._sensors.get(info.id)
        calibration = state.calibration.id if state is not None else ""
        return self._frames(readings, forces, [r.frame_flags() + [flag] for r in readings], None, calibration, None)

    def _reconstruct_grids(self, members: list[tuple[_SensorState, list[Reading]]],
                           isolated: bool = False) -> list[list[ForceFrame]]:
        """Tared grids, each with its readings; frames per sensor. Below
        ``full`` each sensor is processed on its own; ``isolated`` then turns
        a sensor's exception into its null, flagged frames."""
        if self.level == "full":
            jobs = [self._job(state, rs) for state, rs in members]
            return [self._grid_frames(state, rs, result) for (state, rs), result in zip(members, process_full(jobs))]
        out = []
        for state, rs in members:
            if not isolated:
                out.append(self._grid_frames(state, rs, self._process_grid(state, rs)))
                continue
            try:
                frames = self._grid_frames(state, rs, self._process_grid(state, rs))
            except Exception as exc:  # noqa: BLE001 — isolated: null frames, counted, logged at most once a minute
                frames = self._isolation.error_frames(state.info, rs, exc)
            else:
                if self._isolation.failing:
                    self._isolation.failing.discard(state.info.id)
            out.append(frames)
        return out

    @staticmethod
    def _job(state: _SensorState, readings: list[Reading]) -> GridJob:
        return GridJob(state.processor, np.stack([r.capacitance_pF for r in readings]), state.baseline.value,
                       state.baseline.std, np.array([r.t_us * 1e-6 for r in readings]))

    def _process_grid(self, state: _SensorState, readings: list[Reading]):
        job = self._job(state, readings)
        return job.processor.process(job.capacitance, job.baseline, job.baseline_std, job.t_s)

    def _grid_frames(self, state: _SensorState, readings: list[Reading], result) -> list[ForceFrame]:
        taxel_flags = result.taxel_flags
        if state.loaded is not None:
            np.bitwise_or(taxel_flags, LOADED_AT_TARE, out=taxel_flags, where=state.loaded)
        flags = [r.frame_flags() for r in readings]
        union = np.bitwise_or.reduce(taxel_flags, axis=1) & ~np.uint8(NO_READING)
        if np.count_nonzero(union):
            for f, bits in zip(flags, union.tolist()):
                f.extend(flag_names(bits))
        return self._frames(readings, result.forces_N, flags, taxel_flags, state.calibration.id, result.sigma_N)

    def _reconstruct_quads(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[ForceFrame]:
        """Tared quads sharing one model, each with its readings; their
        frames in member order."""
        counts = [len(rs) for _, rs in members]
        readings = [r for _, rs in members for r in rs] if len(members) > 1 else members[0][1]
        capacitance = np.stack([r.capacitance_pF for r in readings])
        baseline = np.repeat(np.stack([state.baseline.value for state, _ in members]), counts, axis=0)
        noise = np.repeat([state.processor.noise(state.baseline.value, state.baseline.std) for state, _ in members], counts)
        processor = members[0][0].processor
        forces, quad_flags = processor.process(capacitance, baseline, noise)
        sigma = processor.sigma(forces, noise)
        flags = [r.frame_flags() + extra for r, extra in zip(readings, quad_flags)]
        if len(members) == 1:
            return self._frames(readings, forces, flags, None, members[0][0].calibration.id, sigma)
        ids = [state.calibration.id for state, rs in members for _ in rs]
        return [frame for i, cid in enumerate(ids)
                for frame in self._frames(readings[i:i + 1], forces[i:i + 1], flags[i:i + 1], None, cid, sigma[i:i + 1])]

    def _frames(self, readings: list[Reading], forces: np.ndarray, flags: list[list[str]], taxel_flags: np.ndarray | None,
                calibration: str, sigma: np.ndarray | None) -> list[ForceFrame]:
        level = self.level
        if sigma is None:
            sigma = [None] * len(readings)
        if taxel_flags is None:
            return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, level, None, calibration, sg)
                    for r, f, fl, sg in zip(readings, forces, flags, sigma)]
        return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, level, tf, calibration, sg)
                for r, f, fl, tf, sg in zip(readings, forces, flags, taxel_flags, sigma)]

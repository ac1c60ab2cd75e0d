"""The Reconstructor: readings (capacitance) → ForceFrames (forces + flags), per sensor.

Sensors are batched (grids of a level in one call, quads sharing a model in
one call), a failing sensor isolated from the others (isolation.py);
calibration.py gives each sensor's calibration, its processor and its tare
window.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..physics.mountings import MOUNTINGS
from ..physics.paper_data import GridCalibration
from ..physics.quad_model import QuadModel
from ..readings import Reading, SensorInfo
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .calibration_upload import processor_for, tare_window, validated_upload
from .force_frame import ForceFrame
from .grid import NO_READING, GridProcessor, flag_names
from .grid_full import GridJob, process_full
from .isolation import Isolation
from .levels import DEFAULT_LEVEL, LEVELS, SceneConfig, choose_level
from .quad import QuadProcessor

log = logging.getLogger(__name__)


@dataclass
class _SensorState:
    info: SensorInfo
    baseline: Baseline
    processor: GridProcessor | QuadProcessor


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
                 clock: Callable[[], float] = time.monotonic) -> None:
        """``level="auto"`` takes the cheapest level that meets ``scene``'s
        error budget (see levels.py). ``clock`` (seconds) times the errors
        and paces their log lines."""
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
        self._uploaded: dict[int, GridCalibration | QuadModel] = {}
        self._isolation = Isolation(self._null_frames, clock, log)

    def _processor(self, info: SensorInfo) -> GridProcessor | QuadProcessor:
        return processor_for(info, self.level, self.mounting, self._uploaded.get(info.id))

    def set_calibration(self, info: SensorInfo, upload: dict) -> dict:
        """Replace a sensor's calibration; ValueError names the bad field and
        why (the API answers 422; calibration_upload.validated_upload lists
        the checks). The baseline is kept. Returns what is applied."""
        return self.apply_calibration(info, self.prepare_calibration(info, upload))

    def prepare_calibration(self, info: SensorInfo, upload: dict) -> tuple:
        """The slow half of ``set_calibration`` (validation, the new
        processor), which touches no state: it may run while frames are
        being reconstructed."""
        uploaded, applied = validated_upload(info, upload, self.mounting)
        return uploaded, processor_for(info, self.level, self.mounting, uploaded), applied

    def apply_calibration(self, info: SensorInfo, prepared: tuple) -> dict:
        """The quick half: swap the calibration and the sensor's processor in."""
        uploaded, processor, applied = prepared
        self._uploaded[info.id] = uploaded
        state = self._sensors.get(info.id)
        if state is not None:
            state.processor = processor
            self._isolation.failing.discard(info.id)
        return applied

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or (state.info is not info and state.info != info):
            window = tare_window(info, self.mounting, self._uploaded.get(info.id))
            state = _SensorState(info, Baseline(info.channels, self.tare_frames, window), self._processor(info))
            self._sensors[info.id] = state
        return state

    def tare(self, sensor_id: int | None = None) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared."""
        ids = sorted(self._sensors) if sensor_id is None else [sensor_id]
        for sid in ids:
            if sid not in self._sensors:
                raise KeyError(sid)
            self._sensors[sid].baseline.tare()
            if isinstance(self._sensors[sid].processor, GridProcessor):
                self._sensors[sid].processor.reset()
        return ids

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
                state.baseline.update(reading.capacitance_pF)
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
        return self._frames(readings, forces, [r.frame_flags() + [flag] for r in readings], None)

    def _reconstruct_grids(self, members: list[tuple[_SensorState, list[Reading]]],
                           isolated: bool = False) -> list[list[ForceFrame]]:
        """Tared grids, each with its readings; frames per sensor. Below
        ``full`` each sensor is processed on its own; ``isolated`` then turns
        a sensor's exception into its null, flagged frames."""
        if self.level == "full":
            jobs = [self._job(state, rs) for state, rs in members]
            return [self._grid_frames(rs, result) for (_, rs), result in zip(members, process_full(jobs))]
        out = []
        for state, rs in members:
            if not isolated:
                out.append(self._grid_frames(rs, self._process_grid(state, rs)))
                continue
            try:
                frames = self._grid_frames(rs, self._process_grid(state, rs))
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

    def _grid_frames(self, readings: list[Reading], result) -> list[ForceFrame]:
        flags = [r.frame_flags() for r in readings]
        union = np.bitwise_or.reduce(result.taxel_flags, axis=1) & ~np.uint8(NO_READING)
        if np.count_nonzero(union):
            for f, bits in zip(flags, union.tolist()):
                f.extend(flag_names(bits))
        return self._frames(readings, result.forces_N, flags, result.taxel_flags)

    def _reconstruct_quads(self, members: list[tuple[_SensorState, list[Reading]]]) -> list[ForceFrame]:
        """Tared quads sharing one model, each with its readings; their
        frames in member order."""
        counts = [len(rs) for _, rs in members]
        readings = [r for _, rs in members for r in rs] if len(members) > 1 else members[0][1]
        capacitance = np.stack([r.capacitance_pF for r in readings])
        baseline = np.repeat(np.stack([state.baseline.value for state, _ in members]), counts, axis=0)
        noise = np.repeat([state.processor.noise(state.baseline.value, state.baseline.std) for state, _ in members], counts)
        forces, quad_flags = members[0][0].processor.process(capacitance, baseline, noise)
        flags = [r.frame_flags() + extra for r, extra in zip(readings, quad_flags)]
        return self._frames(readings, forces, flags, None)

    def _frames(self, readings: list[Reading], forces: np.ndarray, flags: list[list[str]], taxel_flags: np.ndarray | None) -> list[ForceFrame]:
        if taxel_flags is None:
            return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level)
                    for r, f, fl in zip(readings, forces, flags)]
        return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level, tf)
                for r, f, fl, tf in zip(readings, forces, flags, taxel_flags)]

"""The Reconstructor: readings (capacitance) → ForceFrames (forces + flags), per sensor."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..physics.paper_data import GridCalibration, grid_calibration
from ..physics.quad_model import QuadModel
from ..physics.mountings import MOUNTINGS
from ..physics.taxel_response import taxel_response
from ..readings import Reading, SensorInfo
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .force_frame import ForceFrame
from .grid import NO_READING, GridJob, GridProcessor, flag_names, process_full
from .levels import DEFAULT_LEVEL, LEVELS, SceneConfig, choose_level
from .quad import QuadProcessor


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
                 level: str = DEFAULT_LEVEL, mounting: str = "flat", scene: SceneConfig | None = None) -> None:
        """``level="auto"`` takes the cheapest level that meets ``scene``'s
        error budget (see levels.py)."""
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

    def _processor(self, info: SensorInfo) -> GridProcessor | QuadProcessor:
        uploaded = self._uploaded.get(info.id)
        if info.kind == "quad":
            return QuadProcessor(self.level, uploaded) if isinstance(uploaded, QuadModel) else QuadProcessor(self.level)
        calibration = uploaded if isinstance(uploaded, GridCalibration) else grid_calibration(info.rows, info.cols)
        response = None if self.level == "level0" else taxel_response(calibration, self.mounting)
        return GridProcessor(self.level, calibration, response)

    def set_calibration(self, info: SensorInfo, upload: dict) -> dict:
        """Replace a sensor's calibration; ValueError names the bad field.

        Grid: ``sensitivity_pct_per_N`` per taxel. Quad: ``normal_fit``
        [c2, c1] and ``shear_fit`` [a, b]. The baseline is kept."""
        if info.kind == "grid":
            values = np.asarray(upload.get("sensitivity_pct_per_N", []), dtype=float)
            if values.shape != (info.channels,):
                raise ValueError(f"sensitivity_pct_per_N: expected {info.channels} values (rows*cols), got {values.size}")
            bad = np.flatnonzero(~((values > 0.1) & (values < 10.0)))
            if bad.size:
                raise ValueError(f"sensitivity_pct_per_N[{bad[0]}] = {values[bad[0]]} is outside (0.1, 10) %/N")
            base = grid_calibration(info.rows, info.cols)
            self._uploaded[info.id] = GridCalibration(info.rows, info.cols, base.c0_pF, values / 100.0)
            applied = {"sensitivity_pct_per_N": values.tolist()}
        else:
            if "normal_fit" not in upload or "shear_fit" not in upload:
                raise ValueError("a quad calibration needs normal_fit [c2, c1] and shear_fit [a, b]")
            c2, c1 = upload["normal_fit"]
            a, b = upload["shear_fit"]
            if not (c1 > 0 and c2 <= 0):
                raise ValueError(f"normal_fit: need c2 ≤ 0 < c1, got c2={c2}, c1={c1}")
            if not (a > 0 and b >= 0):
                raise ValueError(f"shear_fit: need a > 0 and b ≥ 0, got a={a}, b={b}")
            usable_normal = 0.9 * c1 / (-2 * c2) if c2 < 0 else 50.0
            usable_shear = 0.9 * a / (2 * b) if b > 0 else 50.0
            self._uploaded[info.id] = QuadModel((c2, c1, 0.0), a, b, usable_normal, usable_shear)
            applied = {"normal_fit": [c2, c1], "shear_fit": [a, b], "normal_usable_N": usable_normal, "shear_usable_N": usable_shear}
        state = self._sensors.get(info.id)
        if state is not None:
            state.processor = self._processor(info)
        return applied

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or (state.info is not info and state.info != info):
            state = _SensorState(info, Baseline(info.channels, self.tare_frames), self._processor(info))
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

    def process(self, reading: Reading) -> list[ForceFrame]:
        return self.process_many([reading])

    def process_many(self, readings: list[Reading]) -> list[ForceFrame]:
        """Reconstruct a batch of readings (e.g. one read from the port), each
        sensor's frames together; returns ForceFrames in arrival order."""
        pending = []
        for reading in readings:
            state = self._state(reading.sensor)
            state.baseline.update(reading.capacitance_pF)
            pending.append((state, reading))
        if not self.hold_until_tared:
            return self._reconstruct(pending)
        self._held.extend(pending)
        release = []
        while self._held and self._held[0][0].baseline.ready:
            release.append(self._held.popleft())
        return self._reconstruct(release)

    def flush(self) -> list[ForceFrame]:
        """Release every held reading; those of sensors that never completed a
        tare (a log shorter than the tare window) come out null and flagged."""
        frames = self._reconstruct(list(self._held))
        self._held.clear()
        return frames

    def _reconstruct(self, items: list[tuple[_SensorState, Reading]]) -> list[ForceFrame]:
        groups: dict[int, tuple[_SensorState, list[int]]] = {}
        for index, (state, _) in enumerate(items):
            groups.setdefault(id(state), (state, []))[1].append(index)
        out: list[ForceFrame | None] = [None] * len(items)

        def place(indices, frames):
            for i, frame in zip(indices, frames):
                out[i] = frame

        # Tared sensors of a kind go through one call per step, all sensors'
        # frames together: at 1 kHz the per-call cost, not the per-frame
        # arithmetic, dominates. Quads are batched by model, grids by level.
        quads: dict[tuple, list[tuple[_SensorState, list[int]]]] = {}
        grids: list[tuple[_SensorState, list[int]]] = []
        for state, indices in groups.values():
            if not state.baseline.ready:
                place(indices, self._taring_frames(state, [items[i][1] for i in indices]))
            elif state.info.kind == "quad":
                quads.setdefault(state.processor.batch_key, []).append((state, indices))
            else:
                grids.append((state, indices))
        if grids:
            readings = [[items[i][1] for i in indices] for _, indices in grids]
            for (_, indices), frames in zip(grids, self._reconstruct_grids([state for state, _ in grids], readings)):
                place(indices, frames)
        for batch in quads.values():
            readings = [items[i][1] for _, indices in batch for i in indices]
            frames = self._reconstruct_quads([(state, len(indices)) for state, indices in batch], readings)
            place((i for _, indices in batch for i in indices), frames)
        return out

    def _taring_frames(self, state: _SensorState, readings: list[Reading]) -> list[ForceFrame]:
        forces = np.full((len(readings), 3 if state.info.kind == "quad" else state.info.channels), np.nan)
        return self._frames(readings, forces, [r.frame_flags() + ["taring"] for r in readings], None)

    def _reconstruct_grids(self, states: list[_SensorState], readings: list[list[Reading]]) -> list[list[ForceFrame]]:
        """Tared grids, each with its readings; frames per sensor."""
        jobs = [GridJob(state.processor, np.stack([r.capacitance_pF for r in rs]), state.baseline.value, state.baseline.std,
                        np.array([r.t_us * 1e-6 for r in rs])) for state, rs in zip(states, readings)]
        if self.level == "full":
            results = process_full(jobs)
        else:
            results = [job.processor.process(job.capacitance, job.baseline, job.baseline_std, job.t_s) for job in jobs]
        out = []
        for rs, result in zip(readings, results):
            flags = [r.frame_flags() for r in rs]
            union = np.bitwise_or.reduce(result.taxel_flags, axis=1) & ~np.uint8(NO_READING)
            if np.count_nonzero(union):
                for f, bits in zip(flags, union.tolist()):
                    f.extend(flag_names(bits))
            out.append(self._frames(rs, result.forces_N, flags, result.taxel_flags))
        return out

    def _reconstruct_quads(self, sensors: list[tuple[_SensorState, int]], readings: list[Reading]) -> list[ForceFrame]:
        """Tared quads sharing one model; ``sensors`` gives each sensor's
        state and how many of ``readings`` (in order) are its."""
        counts = [count for _, count in sensors]
        capacitance = np.stack([r.capacitance_pF for r in readings])
        baseline = np.repeat(np.stack([state.baseline.value for state, _ in sensors]), counts, axis=0)
        noise = np.repeat([state.processor.noise(state.baseline.value, state.baseline.std) for state, _ in sensors], counts)
        forces, quad_flags = sensors[0][0].processor.process(capacitance, baseline, noise)
        flags = [r.frame_flags() + extra for r, extra in zip(readings, quad_flags)]
        return self._frames(readings, forces, flags, None)

    def _frames(self, readings: list[Reading], forces: np.ndarray, flags: list[list[str]], taxel_flags: np.ndarray | None) -> list[ForceFrame]:
        if taxel_flags is None:
            return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level)
                    for r, f, fl in zip(readings, forces, flags)]
        return [ForceFrame(r.sensor, r.seq, r.t_us, r.t_host, f, r.capacitance_pF, fl, self.level, tf)
                for r, f, fl, tf in zip(readings, forces, flags, taxel_flags)]

"""Reconstruction: readings (capacitance) → ForceFrames (forces + flags)."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ..calibration import GridCalibration, grid_calibration
from ..readings import Reading, SensorInfo
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .contact import summarise
from .frame import ForceFrame
from .grid import GRID_LEVELS, NO_READING, GridProcessor, flag_names
from .quad import QuadProcessor
from .select import SceneConfig, choose_level
from .taxel import TaxelResponse

__all__ = ["DEFAULT_LEVEL", "ForceFrame", "LEVELS", "MOUNTINGS", "Reconstructor", "taxel_response"]

LEVELS = GRID_LEVELS + ("auto",)
MOUNTINGS = {"flat": "uniform", "curved": "uneven"}
DEFAULT_LEVEL = "full"


@lru_cache(maxsize=8)
def _table(shape: str):
    from ..physics.tables import TableSpec, load

    return load(TableSpec(shape))


def taxel_response(calibration: GridCalibration, mounting: str = "flat") -> TaxelResponse:
    """The per-taxel response of a grid from the shipped model table."""
    if mounting not in MOUNTINGS:
        raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
    table = _table(MOUNTINGS[mounting])
    return TaxelResponse.from_table(table.force_N, table.relative_change, calibration.sensitivity_per_N)


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
        error budget (see select.py)."""
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

    def _processor(self, info: SensorInfo) -> GridProcessor | QuadProcessor:
        if info.kind == "quad":
            return QuadProcessor(self.level)
        calibration = grid_calibration(info.rows, info.cols)
        response = None if self.level == "level0" else taxel_response(calibration, self.mounting)
        return GridProcessor(self.level, calibration, response)

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or state.info != info:
            state = _SensorState(info, Baseline(info.channels, self.tare_frames), self._processor(info))
            self._sensors[info.id] = state
        return state

    def tare(self, sensor_id: int | None = None) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared."""
        ids = list(self._sensors) if sensor_id is None else [sensor_id]
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
        groups: dict[int, list[int]] = {}
        for index, (state, _) in enumerate(items):
            groups.setdefault(id(state), []).append(index)
        out: list[ForceFrame | None] = [None] * len(items)
        for indices in groups.values():
            state = items[indices[0]][0]
            readings = [items[i][1] for i in indices]
            for i, frame in zip(indices, self._reconstruct_sensor(state, readings)):
                out[i] = frame
        return out

    def _reconstruct_sensor(self, state: _SensorState, readings: list[Reading]) -> list[ForceFrame]:
        info = state.info
        flags = [r.frame_flags() for r in readings]
        taxel_flags = contacts = None
        if not state.baseline.ready:
            forces = np.full((len(readings), 3 if info.kind == "quad" else info.channels), np.nan)
            for f in flags:
                f.append("taring")
        else:
            capacitance = np.stack([r.capacitance_pF for r in readings])
            if info.kind == "grid":
                t_s = np.array([r.t_us * 1e-6 for r in readings])
                result = state.processor.process(capacitance, state.baseline.value, state.baseline.std, t_s)
                forces, taxel_flags = result.forces_N, result.taxel_flags
                union = np.bitwise_or.reduce(taxel_flags & ~np.uint8(NO_READING), axis=1)
                for f, bits in zip(flags, union.tolist()):
                    f.extend(flag_names(bits))
                summary = summarise(forces, info.rows, info.cols)
                contacts = [dict(zip(summary, values)) for values in zip(*(v.tolist() for v in summary.values()))]
            else:
                forces, quad_flags = state.processor.process(capacitance, state.baseline.value, state.baseline.std)
                for f, extra in zip(flags, quad_flags):
                    f.extend(extra)
        return [
            ForceFrame(info, r.seq, r.t_us, r.t_host, forces[k], r.capacitance_pF, flags[k], self.level,
                       None if taxel_flags is None else taxel_flags[k], None if contacts is None else contacts[k])
            for k, r in enumerate(readings)
        ]

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
from .grid import GRID_LEVELS, GridProcessor, flag_names
from .quad import QuadProcessor
from .taxel import TaxelResponse

__all__ = ["DEFAULT_LEVEL", "ForceFrame", "LEVELS", "MOUNTINGS", "Reconstructor", "taxel_response"]

LEVELS = GRID_LEVELS
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
                 level: str = DEFAULT_LEVEL, mounting: str = "flat") -> None:
        if level not in LEVELS:
            raise ValueError(f"unknown fidelity level {level!r}; known: {', '.join(LEVELS)}")
        if mounting not in MOUNTINGS:
            raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
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
            "common_mode_drift": processor.drift.drift,
            "detected": processor.estimator.report(),
        }

    def process(self, reading: Reading) -> list[ForceFrame]:
        state = self._state(reading.sensor)
        state.baseline.update(reading.capacitance_pF)
        if not self.hold_until_tared:
            return [self._reconstruct(state, reading)]
        self._held.append((state, reading))
        frames = []
        while self._held and self._held[0][0].baseline.ready:
            frames.append(self._reconstruct(*self._held.popleft()))
        return frames

    def flush(self) -> list[ForceFrame]:
        """Release every held reading; those of sensors that never completed a
        tare (a log shorter than the tare window) come out null and flagged."""
        frames = [self._reconstruct(state, reading) for state, reading in self._held]
        self._held.clear()
        return frames

    def _reconstruct(self, state: _SensorState, reading: Reading) -> ForceFrame:
        flags = reading.frame_flags()
        info = state.info
        taxel_flags = contact = None
        if not state.baseline.ready:
            flags.append("taring")
            forces = np.full(3 if info.kind == "quad" else info.channels, np.nan)
        elif info.kind == "grid":
            result = state.processor.process(reading.capacitance_pF, state.baseline.value, state.baseline.std, reading.t_us * 1e-6)
            forces, taxel_flags = result.forces_N, result.taxel_flags
            flags.extend(result.frame_flags)
            flags.extend(name for name in flag_names(int(np.bitwise_or.reduce(taxel_flags)))
                         if name not in flags and name != "no_reading")
            contact = {k: v.item() for k, v in summarise(forces, info.rows, info.cols).items()}
        else:
            forces, quad_flags = state.processor.process(reading.capacitance_pF, state.baseline.value, state.baseline.std)
            flags.extend(quad_flags)
        return ForceFrame(info, reading.seq, reading.t_us, reading.t_host, forces, reading.capacitance_pF, flags,
                          self.level, taxel_flags, contact)

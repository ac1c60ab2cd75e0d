"""Reconstruction: readings (capacitance) → ForceFrames (forces + flags)."""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ..calibration import GridCalibration, grid_calibration
from ..readings import Reading, SensorInfo
from . import level0
from .baseline import DEFAULT_TARE_FRAMES, Baseline
from .frame import ForceFrame

__all__ = ["ForceFrame", "Reconstructor"]

LEVELS = ("level0",)


@dataclass
class _SensorState:
    info: SensorInfo
    baseline: Baseline
    calibration: GridCalibration | None


class Reconstructor:
    """Per-sensor tare and force reconstruction at a fidelity level.

    Live use returns each frame at once; until a sensor's baseline is ready
    its forces are null and flagged ``taring``. With ``hold_until_tared``
    (offline replay) readings are held until their sensor's baseline is ready
    and then released with forces, in arrival order, so no frame of a log
    lacks a value and the export keeps the order of the stream.
    """

    def __init__(self, tare_frames: int = DEFAULT_TARE_FRAMES, hold_until_tared: bool = False, level: str = "level0") -> None:
        if level not in LEVELS:
            raise ValueError(f"unknown fidelity level {level!r}; known: {', '.join(LEVELS)}")
        self.level = level
        self.tare_frames = tare_frames
        self.hold_until_tared = hold_until_tared
        self._sensors: dict[int, _SensorState] = {}
        self._held: deque[tuple[_SensorState, Reading]] = deque()

    def _state(self, info: SensorInfo) -> _SensorState:
        state = self._sensors.get(info.id)
        if state is None or state.info != info:
            calibration = grid_calibration(info.rows, info.cols) if info.kind == "grid" else None
            state = _SensorState(info, Baseline(info.channels, self.tare_frames), calibration)
            self._sensors[info.id] = state
        return state

    def tare(self, sensor_id: int | None = None) -> list[int]:
        """Restart the baseline of one sensor (or all); return the ids tared."""
        ids = list(self._sensors) if sensor_id is None else [sensor_id]
        for sid in ids:
            if sid not in self._sensors:
                raise KeyError(sid)
            self._sensors[sid].baseline.tare()
        return ids

    def baseline(self, sensor_id: int) -> np.ndarray | None:
        state = self._sensors.get(sensor_id)
        return None if state is None or not state.baseline.ready else state.baseline.value

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
        if not state.baseline.ready:
            flags.append("taring")
            n = 3 if state.info.kind == "quad" else state.info.channels
            forces = np.full(n, np.nan)
        elif state.info.kind == "grid":
            forces = level0.grid_forces(reading.capacitance_pF, state.baseline.value, state.calibration)
        else:
            forces = level0.quad_forces(reading.capacitance_pF, state.baseline.value)
        return ForceFrame(reading.sensor, reading.seq, reading.t_us, reading.t_host, forces, reading.capacitance_pF, flags, self.level)

"""Each sensor's load-cycle counter (fatigue.py), across calibrations and addresses.

A counter counts under one calibration (a new one starts from the counts
kept for it); a sensor back at its address after another was there goes on
with its own, and one moved to another address (sensors swapped) takes its
counter along (identity.py). A mixin of SensorStates (sensor_states.py).
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ..readings import SensorInfo
from .fatigue import CycleCounter
from .identity import identity
from .sensor_calibration import SensorCalibration

if TYPE_CHECKING:
    from .sensor_states import SensorState

log = logging.getLogger("service.reconstruct.sensor_states")  # its messages as they always read


class CycleCounters:
    """Load-cycle counters of SensorStates (module docstring)."""

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

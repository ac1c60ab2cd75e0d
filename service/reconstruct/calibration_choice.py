"""Which calibration each sensor is reconstructed with, and swapping one in.

A sensor's calibration is the one set through ``set_calibration`` (an
upload, by the sensor's identity: identity.py), else ``resolve``'s (the
registry, a recording, ``--calibration``, chosen above this layer), else
the built-in one; one that does not fit the sensor is set aside with its
reason, never a reason to stop its data. Swapping keeps the sensor's zero
and judges its tare again against the new C0; the window of readings a tare
takes is the new C0's from then on (a sensor that had no zero tares at its
first reading inside it).

A quad's calibration whose measured C0 its tared means show is another
quad's (loaded_tare.not_its_quad: a pattern no load or temperature makes)
is set aside at the tare's judgement as one that cannot be resolved is:
the built-in in its place, the tared means its zero, the reason in
``calibration_problems`` (/health). It stays aside through a forced tare
(which judges nothing) and a lookup again (an INFO naming the board);
a tare judged later that fits it (the calibrated quad plugged back) brings
it back, and a calibration set through ``set_calibration`` replaces it.
A mixin of SensorStates
(sensor_states.py), whose state it reads and changes.
"""
from __future__ import annotations

import logging
from typing import TYPE_CHECKING

import numpy as np

from ..readings import SensorInfo
from .calibration_upload import own_level, processor_for, tare_window, upload_document
from .identity import identity, named
from .loaded_tare import not_its_quad
from .sensor_calibration import SensorCalibration, builtin, from_document

if TYPE_CHECKING:
    from .sensor_states import SensorState

log = logging.getLogger("service.reconstruct.sensor_states")  # its messages as they always read


class CalibrationChoice:
    """Calibration lookups and swaps of SensorStates (module docstring)."""

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
        """The quick half: swap the calibration and the sensor's processor in;
        why its own could not be used, if it could not, goes with the built-in."""
        calibration, processor, document = prepared
        self._chosen[identity(info)] = calibration
        state = self._sensors.get(info.id)
        if state is not None and identity(state.info) == identity(info):  # not one still reconstructed as another
            self._swap(state, calibration, processor)
            self.calibration_problems.pop(info.id, None)
        return document

    def _described_again(self, state: SensorState, info: SensorInfo) -> None:
        """A new INFO describes the sensor as before (``info`` the same
        sensor, sensor_states._same_sensor; not the same object): later
        readings carry ``info``, so it is kept (they skip the comparison);
        and the INFO may name the board, which a board already streaming
        when the service connected had not before the sensor's first frames:
        its calibration is looked up again and one that differs is swapped
        in, the zero kept (one set through ``set_calibration`` stays). At
        the first reading after the INFO, live or in a replay however its
        reads are joined."""
        before, state.info = identity(state.info), info
        if before in self._chosen:  # the INFO only named the board: the sensor is the same
            self._chosen[identity(info)] = self._chosen.pop(before)
            return
        if self.resolve is None:
            return
        calibration = self._calibration_for(info)
        if state.set_aside is not None and calibration.id == state.set_aside[0].id:  # still not this quad's
            self.calibration_problems[info.id] = state.set_aside[1]
            return
        if calibration.id != state.calibration.id:
            self._swap(state, calibration, processor_for(info, self.level, self.mounting, calibration))
            log.info("sensor %d: calibration %s now that its board's INFO named it", info.id, calibration.id)

    def _swap(self, state: SensorState, calibration: SensorCalibration, processor) -> None:
        """``calibration`` and its ``processor`` in place of the sensor's, its zero kept."""
        runs = state.processor.stale_runs
        if runs is not None:  # a converter stuck before the new calibration is still stuck
            processor.restore_stale_runs(*runs)
        processor.kept_zero = state.processor.kept_zero  # a zero kept at a loaded tare stays, and its σ with it
        state.processor, state.calibration = processor, calibration
        state.baseline.own_level = own_level(state.info, self.mounting, calibration)  # its C0 pattern from now on
        state.baseline.rewindow(tare_window(state.info, self.mounting, calibration))  # a tare expects its C0 now
        state.cycles = self._cycles(state.info, calibration)  # counts belong to a calibration: a new one starts anew
        state.tare_judged, state.below_c0 = False, []  # judged again against the new C0
        if state.set_aside is not None:  # another calibration, or the one set aside back: its reason goes
            self.calibration_problems.pop(state.info.id, None)
            state.set_aside = None
        self._calibration_applied(state.info.id)

    def _not_its_calibration(self, state: SensorState) -> bool:
        """At a judged tare of a quad whose calibration (or the one set aside
        for it) measured its C0: whether the tared means say that C0 is
        another quad's (module docstring). Set aside then, the built-in in
        its place; one set aside that fits them again is back in use."""
        own = state.set_aside[0] if state.set_aside is not None else state.calibration
        if own.quad_c0_pF is None:
            return False
        baseline = state.baseline
        found = not_its_quad(own.quad_c0_pF, baseline.value, baseline.std, baseline.frames)
        if found is None:
            if state.set_aside is not None and np.isfinite(baseline.value).all():  # fits it, not merely untold
                self._swap(state, own, processor_for(state.info, self.level, self.mounting, own))
                log.info("sensor %d: its tare fits calibration %s's C0 again: back in use", state.info.id, own.id)
            return False
        if state.set_aside is None:
            self._set_aside(state, found)
        return True

    def _set_aside(self, state: SensorState, found: dict) -> None:
        """The built-in calibration in place of the sensor's, whose C0 is
        another quad's (``found``: loaded_tare.not_its_quad's), said why."""
        own = state.calibration
        off = "/".join(f"{100 * x:+.1f}" for x in found["off"])
        why = (f"calibration {own.id}'s measured C0 is not this sensor's: its electrodes tared {off} % off it, "
               f"a pattern no load or temperature makes (R = {100 * found['R']:.2f} % of C0, beyond "
               f"{100 * found['limit']:.2f} %); calibrate this sensor (tactile calibrate), or check which sensor "
               "is plugged in, then tare it unloaded (not forced) to have it judged again")
        fallback = builtin(state.info, self.mounting)
        self._swap(state, fallback, processor_for(state.info, self.level, self.mounting, fallback))
        state.set_aside = (own, why)
        self.calibration_problems[state.info.id] = why
        log.warning("sensor %d: %s; the built-in calibration is used", state.info.id, why)

    def calibration(self, sensor_id: int) -> SensorCalibration | None:
        """The calibration sensor ``sensor_id`` is reconstructed with (None: not seen yet)."""
        state = self._sensors.get(sensor_id)
        return None if state is None else state.calibration

    def in_force(self) -> list[tuple[SensorInfo, str]]:
        """(the sensor as its calibration was chosen for it, the calibration's
        id) of each sensor seen, by id: what its frames are reconstructed with now."""
        return [(state.info, state.calibration.id) for _, state in sorted(self._sensors.items())]

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

"""Changes to the sensors' reconstruction while a stream runs: tares (one
refused while its sensor reads loaded), calibrations set, and either one
recorded made again where a replay reaches it (with the link's recorded
events: pipeline.py); each under the pipeline's lock, from any thread
(pipeline.py feeds)."""
from __future__ import annotations

import logging
from typing import Callable

from .readings import SensorInfo

TareListener = Callable[[dict[int, int], bool], None]
CalibrationListener = Callable[[int, int, dict], None]  # (before read, sensor id, document)

log = logging.getLogger("service.pipeline")  # the pipeline's, as before these moved here: its warnings keep their name


class LoadedAtTare(RuntimeError):
    """A tare refused: ``taxels`` {sensor id: [row-major taxels]} read loaded
    against their calibration's C0."""

    def __init__(self, taxels: dict[int, list[int]]) -> None:
        self.taxels = taxels
        super().__init__("loaded now, so a tare would make the load their zero: " + "; ".join(
            f"sensor {sid} taxels {t}" for sid, t in sorted(taxels.items())) + " (tare with force=true to accept)")


class SensorChanges:
    """``Pipeline``'s changes to its sensors (its ``_lock``, ``reconstructor``,
    ``interpreter``, ``latest``, ``tare_listeners``, ``calibration_listeners``,
    ``_reconstructed`` and ``relink``)."""

    def tare(self, sensor_id: int | None = None, force: bool = False) -> list[int]:
        """Restart the baseline of one sensor (or all). Unless ``force``,
        LoadedAtTare names the taxels whose latest reading stands above the
        calibration's C0 (that load would become the zero); with ``force``
        the load present is the zero."""
        with self._lock:
            if not force:
                loaded = self._loaded(sensor_id)
                if loaded:
                    raise LoadedAtTare(loaded)
            tared = self.reconstructor.tare(sensor_id, judge=not force)
            if self.tare_listeners:
                # Each sensor's tare applies from the first read whose frames of its kind were not
                # reconstructed yet (a grid's may wait in _deferred).
                done = self._reconstructed
                before_read = {sid: done["grid" if self.reconstructor.kind(sid) == "grid" else "other"] for sid in tared}
                for listener in self.tare_listeners:
                    listener(before_read, not force)
            return tared

    def redo(self, sensor_id: int | None, change: bool | dict | str) -> None:
        """A change recorded while recording, made again (replay.py): a tare
        (``change`` its ``judge``), a calibration set (``change`` its document)
        or the link's event (``change`` its name, no sensor: Pipeline.relink)."""
        if isinstance(change, str):
            self.relink(change)
        elif isinstance(change, dict):
            self.recalibrate(sensor_id, change)
        else:
            self.retare(sensor_id, change)

    def retare(self, sensor_id: int, judge: bool) -> None:
        """A recorded tare made again (replay.py): the sensor's baseline
        restarted, without the loaded check the live tare passed; a sensor
        not seen yet (a recording begun while it streamed) tares at its first
        frame anyway, judged as the recorded tare was."""
        with self._lock:
            kind = self.reconstructor.kind(sensor_id)
            if kind is not None:
                self.reconstructor.tare(sensor_id, judge=judge)
            else:
                self.reconstructor.judge_first_tare(sensor_id, judge)
            if self.tare_listeners:  # a recording of this replay records it too
                done = self._reconstructed
                before_read = {sensor_id: done["grid" if kind == "grid" else "other"] if kind else min(done.values())}
                for listener in self.tare_listeners:
                    listener(before_read, judge)

    def loaded(self, sensor_id: int | None = None) -> dict[int, list[int]]:
        """{sensor id: taxels} whose latest reading stands above the
        calibration's C0, of one sensor (or all): what a tare would refuse."""
        with self._lock:
            return self._loaded(sensor_id)

    def _loaded(self, sensor_id: int | None) -> dict[int, list[int]]:
        ids = self.reconstructor.sensor_ids() if sensor_id is None else [sensor_id]
        loaded = {sid: self.reconstructor.loaded_now(sid, self.latest[sid].capacitance_pF)
                  for sid in ids if sid in self.latest}
        return {sid: taxels for sid, taxels in loaded.items() if taxels}

    def set_calibration(self, info, upload: dict, sensor: dict | None = None,
                        store: Callable[[dict], object] | None = None) -> dict:
        """Validate ``upload`` (ValueError naming the field), ``store`` its
        document (the registry), then swap it in; returns the document."""
        prepared = self.reconstructor.prepare_calibration(info, upload, sensor)  # tens of ms, not under the lock
        if store is not None:
            store(prepared[2])
        with self._lock:
            document = self.reconstructor.apply_calibration(info, prepared)
            self._calibration_set(info, document)
            return document

    def calibrations_in_force(self) -> list[tuple[SensorInfo, str]]:
        """(the sensor as its calibration was chosen for it, that calibration's
        id) of each sensor seen, read under the lock from any thread."""
        with self._lock:
            return self.reconstructor.in_force()

    def recalibrate(self, sensor_id: int, document: dict) -> None:
        """A calibration set while recording, set again (replay.py) for the
        sensor described at ``sensor_id`` now; one that no longer fits it
        (the recording's bytes describe it otherwise, or it was edited) is
        said and skipped, whatever it raises: a recording is any file, and
        an error here ended the replay (its export cut short)."""
        info = self.interpreter.sensors.get(sensor_id)
        try:
            if info is None:
                raise ValueError("no such sensor described yet")
            prepared = self.reconstructor.prepare_calibration(info, document)
        except Exception as exc:  # noqa: BLE001 — one recorded document is skipped, never the replay
            log.warning("sensor %d: the calibration %s set while recording cannot be set again (%s); kept the one "
                        "in use", sensor_id, document.get("id"),
                        exc if isinstance(exc, ValueError) else f"{type(exc).__name__}: {exc}")
            return
        with self._lock:
            self._calibration_set(info, self.reconstructor.apply_calibration(info, prepared))

    def _calibration_set(self, info: SensorInfo, document: dict) -> None:
        """Tell the calibration listeners (a recording) where it applies from:
        the first read whose frames of the sensor's kind were not reconstructed yet."""
        if self.calibration_listeners:
            before_read = self._reconstructed["grid" if info.kind == "grid" else "other"]
            for listener in self.calibration_listeners:
                listener(before_read, info.id, document)

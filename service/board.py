"""One board's data path in the live service: its source, readout and pipeline.

A service reads one or several boards (``--source NAME=URL``, robot.toml).
Each ``Board`` has its own readout (its own thread or descriptor), its own
pipeline (decoder, interpreter, clock map, reconstruction, history, rates)
and its own link state, so a board that vanishes, stalls or floods touches
no other board's state; what they share is the event loop, the fan-out hub,
the recorder and the calibration book.
"""
from __future__ import annotations

import asyncio
import logging
import re
import time
from dataclasses import dataclass
from datetime import datetime
from functools import partial

from .calibration.registry import sensor_identity
from .handover import LoopHandover
from .history import Histories
from .pipeline import Pipeline
from .readout import DEFAULT_SILENCE_S, INFO_REPLY_S, Readout
from .reconstruct import DEFAULT_LEVEL, Reconstructor
from .sources.protocol_replay import recorded_baselines, recorded_changes, recorded_identification

log = logging.getLogger(__name__)

BOARD_NAME = re.compile(r"[A-Za-z][A-Za-z0-9_-]{0,31}")


def check_board_name(name: str) -> str:
    """``name`` if it can name a board in addresses (board/sensor), URLs and
    Zenoh keys: a letter, then letters, digits, '_' or '-', at most 32;
    ValueError naming it otherwise."""
    if not isinstance(name, str) or not BOARD_NAME.fullmatch(name):
        raise ValueError(f"board name {name!r} must start with a letter and hold only letters, digits, '_' "
                         f"and '-' (at most 32)")
    return name


class RemoteBoardError(RuntimeError):
    """A change asked of a board that another host's service reads (a gateway's board)."""


@dataclass(frozen=True)
class BoardSpec:
    """What a board is, as the command line or robot.toml says: ``name``
    None names it from its INFO (a bare ``--source URL``); ``calibration``:
    registry ids or files pinned for this board's sensors."""

    source: str
    name: str | None = None
    level: str = DEFAULT_LEVEL
    mounting: str = "flat"
    calibration: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.name is not None:
            check_board_name(self.name)


def _age_s(created: str | None, now: float) -> float | None:
    if not created:
        return None
    try:
        return round(now - datetime.fromisoformat(created).timestamp(), 1)
    except ValueError:
        return None


def calibration_state(pipeline, sid: int, now: float, book=None) -> dict | None:
    """Which calibration sensor ``sid`` uses: its id, whether it is a
    built-in (the papers', not measured on this sensor), when it was made
    and its age, when it was activated in the registry, why the sensor's own
    could not be used, the one activated in the registry that could not be
    (``not_applied``: {id, reason, kept}), the taxels loaded at the last tare, and what the
    first tare made of the zero stored before the service started."""
    reconstructor = pipeline.reconstructor
    calibration = reconstructor.calibration(sid)
    if calibration is None:
        return None
    info = pipeline.interpreter.sensors.get(sid)
    document = calibration.document or {}
    return {
        "id": calibration.id,
        "builtin": calibration.builtin,
        "note": document.get("note") or ("the papers' calibration, not measured on this sensor" if calibration.builtin else None),
        "created": calibration.created,
        "age_s": _age_s(calibration.created, now),
        "activated": None if book is None or info is None else book.activated_at(pipeline.interpreter.board, info,
                                                                                            calibration.id),
        "problem": reconstructor.calibration_problems.get(sid),
        "not_applied": pipeline.not_applied.get(sid),
        "loaded_at_tare": reconstructor.loaded_at_tare(sid),
        "stored_zero": reconstructor.zero_kept(sid),
        "below_c0": reconstructor.below_c0(sid),
    }


class Board:
    """One board of the service. ``name`` is its given name, or the one its
    first INFO settled (``board``, or ``board-2`` … beside other unnamed boards, until then)."""

    def __init__(self, spec: BoardSpec, calibrations, histories: Histories, name_board=None,
                 silence_s: float = DEFAULT_SILENCE_S, grid_batch_s: float = 0.0) -> None:
        self.spec = spec
        self.source = spec.source
        self.silence_s = silence_s
        self.calibrations = calibrations
        self.pipeline = Pipeline(Reconstructor(level=spec.level, mounting=spec.mounting), histories=histories,
                                 calibrations=calibrations, board_name=spec.name, name_board=name_board,
                                 grid_batch_s=grid_batch_s)
        self.handover: LoopHandover | None = None
        self.readout: Readout | None = None
        # Load-cycle counts are a physical sensor's wear: a simulated one is new every run (the counts of the
        # runs before made the demo quad read ever higher), a replayed one's are the recording's, not news.
        self.keeps_cycles = not self.source.startswith(("sim://", "replay://"))
        if self.source.startswith("sim://"):
            self.pipeline.reconstructor.load_cycles = None
        load_zero = getattr(calibrations, "load_zero", None)
        if self.keeps_cycles and load_zero is not None:  # a replay's zeros are its recording's (reconstruct/stored_zero.py)
            def board_of(info):
                return self.pipeline.interpreter.board if info.board_info is None else info.board_info

            self.pipeline.reconstructor.load_zero = lambda info, cid: load_zero(board_of(info), info, cid)
        if self.source.startswith("replay://"):
            self._schedule_recorded_changes()
            self._hold_as_recorded()
        # A replay's calibrations are its recording's (or fixed for its run), never today's registry's.
        # None (built-in calibrations, as the pipeline takes it) follows nothing.
        follows = getattr(calibrations, "follows_registry", False)
        self.follows_registry = follows and not self.source.startswith("replay://")
        self._tried: dict[str, str] = {}  # sensor key → the active calibration id last tried for it
        self._registry_error: str | None = None  # the last registry error logged (said once, until it changes)

    def _hold_as_recorded(self) -> None:
        """A recording served through the live path holds the frames its
        live link held for the board's INFO, where they were held (its link's
        events are among its recorded changes)."""
        try:
            identify = recorded_identification(self.source)
            if identify is not None:
                self.pipeline.identify_as_recorded(identify)
        except (ValueError, OSError) as exc:
            log.warning("%s: its frames are served as they came, none held for the board's INFO (%s)",
                        self.source, exc)

    def _schedule_recorded_changes(self) -> None:
        """A recording served through the live path starts from the zeros it
        began with and makes its recorded tares and calibrations set again
        where they were made (else every force after one differs from what
        was recorded)."""
        try:
            changes, began = recorded_changes(self.source), recorded_baselines(self.source)
        except (ValueError, OSError) as exc:
            log.warning("%s: its recorded tares and calibrations cannot be read (%s); replayed without them",
                        self.source, exc)
            return
        self.pipeline.schedule_recorded(changes)
        if "after_reads" in began:
            log.warning("%s: its first reads are lost (a damaged chunk), and with them its INFO and zeros: served "
                        "from read %d, where the recording holds those then in force", self.source, began["after_reads"])
        self.pipeline.preset_began(began)
        if began and self.spec.name is None:  # begun mid-stream, no INFO in it: the name the board had then
            self.pipeline.interpreter.board_name = began["board"]

    @property
    def name(self) -> str:
        return self.pipeline.interpreter.name

    @property
    def sensors(self) -> dict:
        return self.pipeline.interpreter.sensors

    def start(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start reading; the pipeline's listeners are wired by the service."""
        self.handover = LoopHandover(self.pipeline.feed_reads, self.pipeline.link_lost, loop)
        self.readout = Readout(self.source, self.handover, silence_s=self.silence_s)
        if not self.source.startswith("replay://"):  # a link a board may be swapped on, not a recording's bytes
            self.pipeline.identify_on_link(INFO_REPLY_S, self.readout.ask_info, loop.call_later,
                                           partial(self.readout.ask_info, restart=True))
        self.readout.start(loop)

    def stop(self) -> None:
        if self.readout is not None:
            self.readout.stop()
        self.save_cycles()
        self.save_zeros()

    def save_cycles(self) -> None:
        """Keep every sensor's load-cycle counts in the registry (a failure is logged, never raised)."""
        if not self.keeps_cycles:
            return
        # Only the sensors the board describes now: another board on the link left its own sensors' states behind.
        current = self.pipeline.interpreter.sensors
        reconstructor = self.pipeline.reconstructor
        counts = [entry for sid, entry in reconstructor.cycle_counts().items() if current.get(sid) == entry[0]]
        counts += reconstructor.replacements.left_counts()  # sensors another took the place of: their counts
        try:
            self.calibrations.save_cycles(self.pipeline.interpreter.board, counts)
        except Exception as exc:  # noqa: BLE001 — counts are kept again at the next period
            log.warning("load-cycle counts of board %s not kept: %s", self.name, exc)

    def save_zeros(self) -> None:
        """Keep every sensor's zero in force in the registry, its first tare's
        judge after a restart (stored_zero.py; a failure is logged, never raised)."""
        if not self.keeps_cycles:
            return
        current = self.pipeline.interpreter.sensors  # as save_cycles: the sensors the board describes now
        zeros = [entry for sid, entry in self.pipeline.reconstructor.zeros_to_keep().items()
                 if current.get(sid) == entry[0]]
        try:
            self.calibrations.save_zeros(self.pipeline.interpreter.board, zeros)
        except Exception as exc:  # noqa: BLE001 — kept again at the next period
            log.warning("zeros of board %s not kept: %s", self.name, exc)

    def follow_registry(self) -> None:
        """Apply each sensor's calibration activated in the registry since its
        own was chosen (``tactile calibrations activate``, ``tactile calibrate``
        from another process) as an upload is applied: validated, swapped in
        under the pipeline's lock from the next frame, told to a recording.
        One the sensor cannot use is not applied, tried once, and said
        (/health); the one in use stays. Called every few seconds off the event
        loop (live_service.py): one registry query; a registry that cannot be
        read is logged once and asked again next time."""
        if not self.follows_registry:
            return
        in_force = self.pipeline.calibrations_in_force()
        try:
            active = self.calibrations.registry_active(self.pipeline.interpreter.board, [info for info, _ in in_force])
            for info, in_use in in_force:
                sensor, wanted = active.get(info.id, (None, None))
                refused = self.pipeline.not_applied.get(info.id)
                if refused is not None and (refused["id"], refused["kept"]) != (wanted, in_use):
                    del self.pipeline.not_applied[info.id]  # another activated since, or the one in use changed
                if wanted == in_use:  # the registry agrees: one refused before and activated again is tried again
                    self._tried.pop(sensor["key"], None)
                elif wanted is not None and self._tried.get(sensor["key"]) != wanted:
                    self._switch(info, sensor, in_use, wanted)
        except Exception as exc:  # noqa: BLE001 — the data goes on with the calibrations in use
            if str(exc) != self._registry_error:
                log.warning("board %s: the calibration registry cannot be read to follow its activations (%s: %s); "
                            "asked again in a few seconds", self.name, type(exc).__name__, exc)
            self._registry_error = str(exc)
            return
        self._registry_error = None

    def _switch(self, info, sensor: dict, in_use: str, wanted: str) -> None:
        """Calibration ``wanted`` (the registry's active one) in place of ``in_use`` for sensor ``info``."""
        document = self.calibrations.document(wanted)
        self._tried[sensor["key"]] = wanted
        try:
            self.pipeline.set_calibration(info, document, sensor)
        except Exception as exc:  # noqa: BLE001 — whatever the document lacks, this sensor cannot use it
            reason = f"calibration {wanted}, activated in the registry: {exc}"
            log.warning("sensor %s: %s; not applied, it keeps calibration %s", info.address, reason, in_use)
            if in_use.startswith("builtin"):  # /health's line of a sensor whose own could not be used says it
                self.pipeline.reconstructor.calibration_problems[info.id] = f"{type(exc).__name__}: {reason}"
            else:
                self.pipeline.not_applied[info.id] = {"id": wanted, "reason": str(exc), "kept": in_use}
            return
        self.calibrations.forget_activation_times()
        log.info("sensor %s: calibration %s in place of %s, activated in the registry", info.address, wanted, in_use)

    def set_calibration(self, info, upload: dict) -> dict:
        """Validate an upload (ValueError naming the field), store it in the
        registry and make it the sensor's active calibration there, then
        reconstruct with it from the next frame; returns the document."""
        sensor = sensor_identity(self.pipeline.interpreter.board, info)
        store = self.calibrations.store if self.calibrations.use_registry else None
        return self.pipeline.set_calibration(info, upload, sensor, store)

    # What the API asks of a board (a gateway's remote boards answer the same).

    @property
    def info(self) -> dict:
        """The board's INFO (top-level fields)."""
        return self.pipeline.interpreter.board

    @property
    def latest(self) -> dict:
        return self.pipeline.latest

    @property
    def history(self):
        return self.pipeline.history

    def tared(self, sensor_id: int) -> bool:
        return self.pipeline.reconstructor.baseline(sensor_id) is not None

    def loaded(self, sensor_id: int | None = None) -> dict[int, list[int]]:
        return self.pipeline.loaded(sensor_id)

    def tare(self, sensor_id: int | None = None, force: bool = False) -> tuple[list[int], int]:
        """(sensors tared, frames a tare takes); pipeline.tare's errors."""
        return self.pipeline.tare(sensor_id, force=force), self.pipeline.reconstructor.tare_frames

    def calibration(self, sensor_id: int) -> dict | None:
        """The sensor's calibration as /health shows it, with its document (None before its first frame)."""
        state = calibration_state(self.pipeline, sensor_id, time.time(), self.calibrations)
        if state is None:
            return None
        return {**state, "document": self.pipeline.reconstructor.calibration(sensor_id).document}

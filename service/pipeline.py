"""The data path in one line: bytes → frames → readings → forces → listeners.

One ``Pipeline`` serves everyone — the live service, replay, ``record``,
the bench and the tests — and owns the order of work: decode, interpret,
reconstruct, keep history and rates, publish. Byte listeners (the
recorder's raw channel) see every chunk as received, before decoding it,
under the pipeline's lock;
frame listeners (the fan-out hub, the recorder) see each batch of
ForceFrames. Tares and calibrations: pipeline_changes.py. On a live link,
frames wait for the board's INFO after each (re)open and after a restart
whose INFO was lost (identify.py: ``identify_on_link``); link listeners (the
recorder) hear where the link dropped and where a wait passed, so that a
replay holds the same frames (``identify_as_recorded``).
"""
from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections import deque
from functools import partial
from typing import Callable, Protocol

from .clock_map import ClockMap
from .history import Histories
from .protocol_bulk import BulkDecoder
from .board_info import name_from_info
from .identify import Held, Identification
from .interpreter import Interpreter
from .protocol import Frame
from .pipeline_changes import CalibrationListener, SensorChanges, TareListener
from .readings import Reading, SensorInfo
from .recent import RecentCorruption, RecentIdentification
from .reconstruct import ForceFrame, Reconstructor
from .reconstruct.sensor_calibration import SensorCalibration

Listener = Callable[[list[ForceFrame]], None]
ByteListener = Callable[[bytes, float], None]
LinkListener = Callable[[str, int], None]  # (LINK_EVENTS' event, before read)
Defer = Callable[[Callable[[], None]], object]
Later = Callable[[float, Callable[[], None]], object]

log = logging.getLogger(__name__)

RATE_WINDOW_S = 1.0
# What the link did between two reads, as a recording keeps it: "lost" (link_lost: the link dropped), "expired"
# (frames held for the board's INFO went on without it: its wait passed).
LINK_EVENTS = ("lost", "expired")


class CalibrationSource(Protocol):
    """Where sensors' calibrations and load cycles come from (calibration/book.py)."""

    def for_sensor(self, board: dict, info: SensorInfo, mounting: str) -> SensorCalibration | None: ...

    def load_cycles(self, board: dict, info: SensorInfo, calibration_id: str) -> list[int] | None: ...


class RateMeter:
    """Frames per second over the last completed window of ~1 s."""

    def __init__(self) -> None:
        self.count = 0
        self._window_start: float | None = None
        self._window_count = 0
        self.rate_hz = 0.0

    def tick(self, now: float, n: int = 1) -> None:
        self.count += n
        if self._window_start is None:
            self._window_start, self._window_count = now, self.count
        elif now - self._window_start >= RATE_WINDOW_S:
            self.rate_hz = (self.count - self._window_count) / (now - self._window_start)
            self._window_start, self._window_count = now, self.count


class Pipeline(SensorChanges):
    """Decodes and reconstructs everything fed to it and hands each batch of
    ForceFrames to the listeners. Feeding is done from one thread at a time
    (the readout's, the event loop's or a replay's); ``tare`` and
    ``set_calibration`` may come from any other."""

    def __init__(self, reconstructor: Reconstructor | None = None, clock: Callable[[], float] = time.time,
                 histories: Histories | None = None, keep_history: bool = True,
                 calibrations: CalibrationSource | None = None, map_clock: bool = True,
                 board_name: str | None = None, name_board: Callable[[dict], str] | None = None,
                 grid_batch_s: float = 0.0) -> None:
        """``keep_history=False`` (offline export) keeps no latest frame,
        history or rates: each batch only goes to the listeners.
        ``calibrations`` (calibration/book.py's CalibrationBook): a sensor's
        calibration and load cycles when it is first seen, with the board's
        INFO to identify it. ``map_clock``: estimate each scan's host time
        from the receive times (False for a stream without them, a raw
        capture). ``board_name``: the board's name in every sensor's address
        (board/id); without it ``name_board`` (board_info.name_from_info by
        default) names the board from its first INFO. ``grid_batch_s``: live,
        grids wait up to this long to be reconstructed together with the
        reads that come meanwhile (CPU for latency: docs/performance.md)."""
        self.clock = ClockMap() if map_clock else None
        self.grid_batch_s = grid_batch_s
        self.keep_history = keep_history
        self.decoder = BulkDecoder()
        self.corruption = RecentCorruption()  # the decoder's CRC errors over the last seconds (/health)
        self.info_waits = RecentIdentification()  # restarts without INFO, waits for it unanswered, lately (/health)
        self.interpreter = Interpreter(clock, board_name=board_name, name_board=name_board or name_from_info)
        self.reconstructor = reconstructor or Reconstructor()
        if calibrations is not None:
            # As of the sensor's readings: the INFO its description was made under (reconstruction may come later).
            def board_of(info: SensorInfo) -> dict:
                return self.interpreter.board if info.board_info is None else info.board_info

            self.reconstructor.resolve = lambda info: calibrations.for_sensor(board_of(info), info,
                                                                              self.reconstructor.mounting)
            self.reconstructor.load_cycles = lambda info, cid: calibrations.load_cycles(board_of(info), info, cid)
        self.latest: dict[int, ForceFrame] = {}
        self.history = histories if histories is not None else Histories()
        self.rates: dict[int, RateMeter] = {}
        self.listeners: list[Listener] = []
        self.byte_listeners: list[ByteListener] = []
        # Tares, with each sensor's number of the first read they apply to
        # (the recorder writes them there, and a replay makes them there again).
        self.tare_listeners: list[TareListener] = []
        self.calibration_listeners: list[CalibrationListener] = []  # calibrations set, placed as tares are
        # A calibration activated in the registry that the sensor cannot use, by sensor: {id, reason, kept} (board.py).
        self.not_applied: dict[int, dict] = {}
        self.link_listeners: list[LinkListener] = []  # LINK_EVENTS, each with the pipeline's number of the next read
        self.reads = 0  # reads decoded so far
        self._reconstructed = {"grid": 0, "other": 0}  # reads whose grids / other sensors are reconstructed
        self._lock = threading.Lock()
        self._deferred: deque[tuple[list[Reading], float, int]] = deque()  # (grids, t_host, reads)
        self.bytes_fed = 0  # bytes of every read so far
        self._recorded: list[tuple[int, int, bool | dict]] = []  # (byte offset, sensor, change), in order
        self.identification: Identification | None = None  # a live link's frames waiting for INFO (identify_on_link)
        self._ask_info: Callable[[], object] | None = None
        self._ask_restart: Callable[[], object] | None = None  # a restart's INFO? (identify_on_link), else _ask_info's
        self._later: Later | None = None
        self._hold_began = "opened"  # why the last hold began (Identification.take): "opened" (the first), "restarted"

    def identify_on_link(self, wait_s: float, ask_info: Callable[[], object], later: Later,
                         ask_restart: Callable[[], object] | None = None) -> None:
        """A live link's frames wait for its board's INFO, from its first
        connect, after each ``link_lost`` and after a restart whose INFO was
        lost, at most ``wait_s`` (identify.py). ``ask_info`` asks the board
        INFO? (the readout's, at most one a second; it asked on connect): at
        such a restart, and when a data frame does not fit the description in
        force (a restart not found whose INFO was lost); ``ask_restart``, when
        given, at a restart instead (the readout's asks each restart, the
        limit being for repeats). ``later(delay, fn)``:
        ``fn`` on the feeding thread after ``delay`` s (the loop's call_later)."""
        self.identification = Identification(wait_s)
        self._ask_info, self._later, self._ask_restart = ask_info, later, ask_restart

    def identify_as_recorded(self, state: dict) -> None:
        """A recording's frames held as they were live, from ``state`` (the
        wait's when it began: Identification.state); each hold ends at its
        INFO or where the recording's events say (``redo``), not by a clock:
        nothing is asked of a recording, and its waits are never timed here."""
        self.identification = Identification.as_recorded(state)
        self._ask_info, self._later = (lambda: None), (lambda delay, fn: None)

    def schedule_recorded(self, changes: list[tuple[int, int | None, bool | dict | str]]) -> None:
        """Recorded changes (byte offset in the stream, sensor id, change:
        see ``redo``; the link's events too) to make again where the stream reaches each offset: a
        recording served through the live path (replay:// gives the offsets:
        its reads are not cut as they were recorded, its bytes are the same)."""
        self._recorded = sorted(changes, key=lambda change: change[0])

    def preset_began(self, began: dict) -> None:
        """What a recording begun mid-stream began with (mcap_reader.read_baselines, one board's): the INFO
        then in force, its sensors' zeros and those of sensors that had left their address, taken before its
        first frame (a replay, a replay:// board)."""
        if began.get("info"):
            self.interpreter.preset_info(began["info"])
        self.reconstructor.preset_baselines(began.get("sensors", []))
        self.reconstructor.preset_left_zeros(began.get("left", []))

    def feed(self, data: bytes, t_host: float) -> list[ForceFrame]:
        """One read: decoded, reconstructed and published as one batch, in arrival order."""
        return self._reconstruct(self._decode([(data, t_host)]), t_host, {"grid": 1, "other": 1})

    def feed_many(self, chunks: list[tuple[bytes, float]]) -> list[ForceFrame]:
        """Reads fed together (an offline replay joining recorded reads): each
        decoded with its own receive time, all reconstructed in one batch and
        published in arrival order — the frames each read alone gives, bit
        for bit (a frame's forces do not depend on its batch), for one call
        per step instead of one per read. Frames held for the board's INFO
        (identify_as_recorded) stay held across calls, as they were live
        across reads; a replay splits its joins where the link's events
        were recorded, as at its tares."""
        if not chunks:
            return []
        return self._reconstruct(self._decode(chunks), chunks[-1][1], {"grid": len(chunks), "other": len(chunks)})

    def feed_reads(self, chunks: list[tuple[bytes, float]], defer: Defer) -> None:
        """Reads that waited together, each with its receive time. Sensors
        that are cheap to reconstruct (all but grids) are published at once;
        grids wait for ``defer`` (the event loop's ``call_soon``), so that a
        controller on a quad waits neither for the grids of its own read nor
        for those of earlier reads still queued, which all go through
        together. Each sensor's frames stay in order."""
        if not chunks:
            return
        if self._recorded and self._recorded[0][0] < self.bytes_fed + sum(len(data) for data, _ in chunks):
            self._feed_with_recorded(chunks, defer)
            return
        t_host = chunks[-1][1]
        cheap, grids = [], []
        for reading in self._decode(chunks):
            (grids if reading.sensor.kind == "grid" else cheap).append(reading)
        self._reconstruct(cheap, t_host, {"other": len(chunks)})
        if grids or self._deferred:  # reads without grids still count behind those waiting
            self._deferred.append((grids, t_host, len(chunks)))
            if len(self._deferred) == 1:
                defer(self._reconstruct_deferred if self.grid_batch_s <= 0 else self._reconstruct_after_window)
        else:
            with self._lock:
                self._reconstructed["grid"] += len(chunks)

    def _feed_with_recorded(self, chunks: list[tuple[bytes, float]], defer: Defer) -> None:
        """Reads that reach a scheduled change's offset: the bytes before it
        decoded and reconstructed (grids waiting included), the change made,
        then the rest."""
        offset = self._recorded[0][0]
        before, after, position = [], [], self.bytes_fed
        for data, t_host in chunks:
            cut = min(max(offset - position, 0), len(data))
            if cut:
                before.append((data[:cut], t_host))
            if cut < len(data):  # a read cut in two counts as two, here and for every byte listener alike
                after.append((data[cut:], t_host))
            position += len(data)
        self.feed_reads(before, defer)
        self._reconstruct_deferred()
        while self._recorded and self._recorded[0][0] <= self.bytes_fed:
            _, sensor_id, change = self._recorded.pop(0)
            self.redo(sensor_id, change)
        self.feed_reads(after, defer)

    def finish(self, t_host: float) -> list[ForceFrame]:
        """End of a finite stream: decode what is left, release held frames
        (those waiting for an INFO too: the recording ended first)."""
        with self._lock:
            readings = self.interpreter.interpret_many(self.decoder.finish(), t_host)
            if self.identification is not None and self.identification.holding:
                readings = self._unidentified(self.identification.lost(), "the stream ended first") + readings
            frames = (self.reconstructor.process_many(readings) if readings else []) + self.reconstructor.flush()
        self._publish(frames, t_host)
        return frames

    def link_lost(self) -> None:
        """The partial frame is dropped and counted; sequence state is kept,
        so the scans lost while away show up as a gap. Frames still waiting
        for the board's INFO go on without it; the next link's wait for its own."""
        with self._lock:
            self.decoder.reset()
            self._link_event("lost")
            if self.identification is None:
                return
            readings = self._unidentified(self.identification.lost(), "the link dropped first")
        self._flush(readings)

    def relink(self, event: str) -> None:
        """A recorded LINK_EVENTS' event made again where it was (``redo``)."""
        if event == "lost":
            self.link_lost()
        elif event == "expired":
            if self.identification is not None:
                self._hold_expired(self.identification.holds)
        else:  # a recording is any file: an event it should not hold is said and skipped, never the replay
            log.warning("board %s: the link event %r recorded is none of %s: skipped", self.interpreter.name, event,
                        ", ".join(LINK_EVENTS))

    def _link_event(self, event: str) -> None:
        """Tell the link listeners (a recording), under the lock, before which read ``event`` happened."""
        for listener in self.link_listeners:
            listener(event, self.reads)

    def diagnostics(self) -> dict:
        """The decoder's counters and the interpreter's rejections (a recording's /diagnostics)."""
        return {"counters": self.decoder.counters.as_dict(), "rejected": dict(self.interpreter.rejected)}

    def _decode(self, chunks: list[tuple[bytes, float]]) -> list[Reading]:
        readings, restarted = [], False
        for data, t_host in chunks:
            # The byte listeners under the lock with the read's decoding: a recorder stopping (recorder.py)
            # takes the lock, so it never has a read whose counts are not in the decoder's counters yet.
            with self._lock:
                for listener in self.byte_listeners:
                    listener(data, t_host)
                self.reads += 1
                self.bytes_fed += len(data)
                # Each reading's scan time on the host clock: the board's clock mapped by the frames' arrival times.
                frames = self.decoder.feed(data)
                self.corruption.note(t_host, self.decoder.counters)
                if self.identification is None or not self.identification.wants(self.decoder.restarts_without_info):
                    readings += self.interpreter.interpret_many(frames, t_host, self.clock)
                else:
                    held, began = self._identify(frames, t_host)
                    readings += held
                    restarted = restarted or began == "restarted"
                if self.identification is not None:
                    self.info_waits.note(t_host, self.identification.unanswered)
        if self._ask_info is not None:
            self._ask_if_unknown(restarted)
        return readings

    def _identify(self, frames: list[Frame], t_host: float) -> tuple[list[Reading], str | None]:
        """A read's frames through the identification: (those it lets go, read; why a hold began, if one did:
        "restarted" is a restart, whose INFO? the caller asks). A hold that begins times itself out."""
        identification = self.identification
        unanswered = identification.unanswered
        now, released, began = identification.take(frames, t_host, self.decoder.restarts_without_info)
        if began:
            self._hold_began = began
            self._later(identification.wait_s, partial(self._hold_expired, identification.holds))
        if began == "restarted":
            self.info_waits.restarts.add(t_host)
        if identification.unanswered != unanswered:
            self._link_event("expired")
            return self._read(now) + self._unidentified(released, f"none within {identification.wait_s:.2f} s"), began
        return self._read(now) + self._answered(released), began

    def _hold_expired(self, hold: int) -> None:
        """``wait_s`` after hold number ``hold`` began: its frames, if no INFO
        came meanwhile, read under the description in force and published."""
        with self._lock:
            unanswered = self.identification.unanswered
            held = self.identification.expire(hold)
            if self.identification.unanswered != unanswered:
                self._link_event("expired")
            readings = self._unidentified(held, f"none within {self.identification.wait_s:.2f} s")
        self._flush(readings)

    def _unidentified(self, held: Held, why: str) -> list[Reading]:
        """Frames released without the board's INFO, read (and said, when
        there are any): they and those after them are flagged
        ``unidentified`` until its INFO comes (Interpreter.unidentified)."""
        count = sum(len(frames) for frames, _ in held)
        if count:
            log.warning("board %s: %d frames held for its INFO after its link opened or it restarted (%s) are read "
                        "under the description in force, flagged unidentified", self.interpreter.name, count, why)
            self.interpreter.unidentified = self._hold_began
        return self._read(held)

    def _answered(self, released: Held) -> list[Reading]:
        """Frames a hold's INFO released, its INFO first (Identification.take),
        read: flagged ``unidentified`` unless one of those INFO is taken — one
        refused as invalid says no more of the board than no INFO would."""
        if not released:
            return []
        self.interpreter.unidentified = self._hold_began
        readings = self._read(released[:1])  # the INFO: a valid one clears the flag (Interpreter._on_info)
        if self.interpreter.unidentified is not None:
            log.warning("board %s: the INFO its %d held frames waited for was refused (%s): they are read under the "
                        "description in force, flagged unidentified", self.interpreter.name,
                        sum(len(frames) for frames, _ in released[1:]), self.interpreter.info_refused)
        return readings + self._read(released[1:])

    def _read(self, held: Held) -> list[Reading]:
        """Readings of frames grouped by read, each group with its receive time, in order."""
        return [reading for frames, t_host in held if frames
                for reading in self.interpreter.interpret_many(frames, t_host, self.clock)]

    def _flush(self, readings: list[Reading]) -> None:
        """Readings released outside a read, reconstructed and published now,
        after the grids still deferred (each sensor's frames stay in order)."""
        if readings:
            self._reconstruct_deferred()
            self._reconstruct(readings, readings[-1].t_host, {})

    def _ask_if_unknown(self, restarted: bool) -> None:
        """Ask the board INFO?, with the lock free (nothing waits on the
        readout under it), at a restart whose INFO was lost, and when a
        sensor's data frames first did not fit the description in force
        (another shape, or none known): its INFO may have been lost. Once per
        sensor and INFO in force (the same answer again re-describes every
        sensor for nothing), never for one the INFO leaves undescribed on
        purpose (Interpreter.newly_unreadable)."""
        unreadable = self.interpreter.newly_unreadable()
        if restarted:
            (self._ask_restart or self._ask_info)()
        elif unreadable:
            self._ask_info()

    def _reconstruct(self, readings: list[Reading], t_host: float, reads: dict[str, int]) -> list[ForceFrame]:
        """``reads``: how many more reads are reconstructed, by kind ("grid",
        "other"), counted with the reconstruction (what a tare's position is)."""
        with self._lock:
            frames = self.reconstructor.process_many(readings) if readings else []
            for kind, count in reads.items():
                self._reconstructed[kind] += count
        self._publish(frames, t_host)
        return frames

    def _reconstruct_after_window(self) -> None:
        """On the loop: the grids deferred from now on go through together
        after ``grid_batch_s`` (fewer, larger batches: less per-read cost)."""
        asyncio.get_running_loop().call_later(self.grid_batch_s, self._reconstruct_deferred)

    def _reconstruct_deferred(self) -> None:
        """All grids deferred so far in one batch: reads that piled up while
        the loop was busy cost one call per step, not one per read."""
        batches, self._deferred = self._deferred, deque()
        if batches:
            self._reconstruct([r for readings, _, _ in batches for r in readings], batches[-1][1],
                              {"grid": sum(reads for _, _, reads in batches)})

    def _publish(self, frames: list[ForceFrame], t_host: float) -> None:
        if not frames:
            return
        if self.keep_history:
            self._keep(frames, t_host)
        for listener in self.listeners:
            listener(frames)

    def _keep(self, frames: list[ForceFrame], t_host: float) -> None:
        keep(frames, self.latest, self.history, self.rates, t_host)


def keep(frames: list[ForceFrame], latest: dict, histories: Histories, rates: dict, now: float) -> None:
    """Latest frame, history and rate of each sensor in ``frames`` (one
    board's): the rate meters ticked once per sensor and batch, with its
    frame count."""
    counts: dict[int, int] = {}
    for frame in frames:
        sid = frame.sensor.id
        history = histories.get(sid)
        if history is None or history.info is not frame.sensor:
            history = histories.for_frame(frame)
        history.append(frame)
        latest[sid] = frame
        counts[sid] = counts.get(sid, 0) + 1
    for sid, count in counts.items():
        meter = rates.get(sid)
        if meter is None:
            meter = rates[sid] = RateMeter()
        meter.tick(now, count)

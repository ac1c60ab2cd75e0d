"""The recorder: a listener of the pipeline that writes off the hot path.

``attach(pipeline)`` makes it listen to the pipeline's bytes and frames,
``detach()`` stops that. The pipeline's thread only puts references on a
queue (bytes, frame batches, a diagnostics snapshot per second of reads
and one at the stop); a writer thread serialises and writes them. Nothing
is dropped: the queue is unbounded and its depth is reported. A write
error (disk full, permission, a vanished directory) stops the recording,
is kept in ``error`` and logged, never swallowed.
"""
from __future__ import annotations

import logging
import math
import os
import queue
import threading
import time
from pathlib import Path

from ..reconstruct import ForceFrame
from .mcap_writer import McapLog

log = logging.getLogger(__name__)

DIAGNOSTICS_PERIOD_S = 1.0
FLUSH_PERIOD_S = 0.5
FSYNC_PERIOD_S = 5.0  # a power cut loses at most this much of a recording
_STOP = object()


class Recorder:
    """Records to ``out`` (.mcap) and optionally the raw bytes to ``raw_out``.

    Files are opened at construction so that a bad path fails at once, in
    the caller's thread."""

    def __init__(self, out: str | Path, raw_out: str | Path | None = None, exclusive: bool = False) -> None:
        """``exclusive``: refuse (FileExistsError) rather than overwrite an existing file."""
        self.path = Path(out)
        if self.path.suffix != ".mcap":
            raise ValueError(f"recording file {str(out)!r} must end in .mcap")
        self.raw_path = Path(raw_out) if raw_out else None
        mode = "xb" if exclusive else "wb"
        if exclusive and self.raw_path is not None and self.raw_path.exists():
            raise FileExistsError(f"{self.raw_path} exists")
        self._stream = open(self.path, mode)
        try:
            self._raw = open(self.raw_path, mode) if self.raw_path else None
        except OSError:
            self._stream.close()
            if exclusive:  # we made it: leave no empty .mcap behind
                self.path.unlink(missing_ok=True)
            raise
        self._log = McapLog(self._stream)
        self._pipelines: list[_Listeners] = []
        self._several = False  # boards' topics under /{board}: decided by what was attached, kept after detach
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self.error: str | None = None
        self.messages = 0
        self.bytes_in = 0
        self.fsyncs = 0
        self.fsync_s = 0.0  # time spent in fsync, on the writer thread
        self.started_at = time.time()
        self.stopped_at: float | None = None
        self._thread = threading.Thread(target=self._run, name="tactile-recorder", daemon=True)
        self._thread.start()

    def attach(self, pipeline) -> None:
        """Listen to ``pipeline``'s bytes and frames, with its diagnostics
        (``pipeline.diagnostics()``) as the first read arrives, then once
        per second of reads (frames or not: a board whose every frame is
        corrupt has its counters recorded too), and at ``detach``; a
        service with several boards attaches each board's pipeline."""
        listeners = _Listeners(self, pipeline)
        self._pipelines.append(listeners)
        self._several = self._several or len(self._pipelines) > 1
        # New lists, not appends: the pipeline may be iterating the old ones on another thread.
        pipeline.byte_listeners = [*pipeline.byte_listeners, listeners.on_bytes]
        pipeline.listeners = [*pipeline.listeners, listeners.on_frames]
        pipeline.tare_listeners = [*pipeline.tare_listeners, listeners.on_tare]
        pipeline.calibration_listeners = [*pipeline.calibration_listeners, listeners.on_calibration]
        pipeline.link_listeners = [*pipeline.link_listeners, listeners.on_link]

    def detach(self) -> None:
        """Stop listening, each pipeline's diagnostics written as they stand
        then: the counts of every byte recorded (the periodic snapshots lag
        the last reads by up to a second)."""
        attached, self._pipelines = self._pipelines, []
        for listeners in attached:
            pipeline = listeners.pipeline
            # Between two reads (byte listeners are called under the lock, with the read's decoding): the
            # last read recorded is counted, and no later one is recorded.
            with pipeline._lock:
                pipeline.byte_listeners = [f for f in pipeline.byte_listeners if f != listeners.on_bytes]
                pipeline.listeners = [f for f in pipeline.listeners if f != listeners.on_frames]
                pipeline.tare_listeners = [f for f in pipeline.tare_listeners if f != listeners.on_tare]
                pipeline.calibration_listeners = [f for f in pipeline.calibration_listeners
                                                  if f != listeners.on_calibration]
                pipeline.link_listeners = [f for f in pipeline.link_listeners if f != listeners.on_link]
                if self.active:
                    self._queue.put(("diag", (pipeline, pipeline.diagnostics()), time.time()))

    @property
    def active(self) -> bool:
        return self.stopped_at is None and self.error is None

    def stop(self, timeout: float = 10.0) -> dict:
        """Detach, write what is queued, finish the file, return the status."""
        self.detach()
        if self.stopped_at is None:
            self.stopped_at = time.time()
            self._queue.put((_STOP, None, None))
            self._thread.join(timeout)
        return self.status()

    def status(self) -> dict:
        return {
            "path": str(self.path),
            "raw_path": str(self.raw_path) if self.raw_path else None,
            "active": self.active,
            "messages": self.messages,
            "bytes_in": self.bytes_in,
            "queued": self._queue.qsize(),
            "started_at": self.started_at,
            "stopped_at": self.stopped_at,
            "fsyncs": self.fsyncs,
            "fsync_s": round(self.fsync_s, 4),
            "error": self.error,
        }

    def _run(self) -> None:
        last_flush = last_sync = time.monotonic()
        try:
            while True:
                kind, item, t_host = self._queue.get()
                if kind is _STOP:
                    break
                self._write(kind, item, t_host)
                now = time.monotonic()
                if now - last_flush >= FLUSH_PERIOD_S:
                    sync = now - last_sync >= FSYNC_PERIOD_S
                    self._flush(sync)
                    last_flush = now
                    if sync:
                        last_sync = now
            self._log.close()
            self._flush(sync=True)
        except Exception as exc:  # the thread's last word: a recording that stops says why, never hangs "active"
            self.error = f"recording to {self.path} failed: {type(exc).__name__}: {exc}"
            log.error(self.error)
        finally:
            for stream in (self._stream, self._raw):
                if stream is not None:
                    try:
                        stream.close()
                    except OSError as exc:
                        self.error = self.error or f"closing {stream.name} failed: {exc}"

    def _prefix(self, pipeline) -> str:
        """Topics of a one-board recording are as they always were (/raw,
        /sensor/{id}/…; the board is named in the messages); with several
        boards each board's topics are under /{board}."""
        return f"/{pipeline.interpreter.name}" if self._several else ""

    def _write(self, kind: str, item, t_host: float | None) -> None:
        pipeline, payload = item
        prefix = self._prefix(pipeline)
        if kind == "raw":
            self._log.raw(payload, t_host, prefix)
            if self._raw is not None:
                self._raw.write(payload)
            self.bytes_in += len(payload)
            self.messages += 1
        elif kind == "frames":
            for frame in payload:
                self.messages += self._log.frame(frame, prefix)
        elif kind == "calibrations":
            for sensor, calibration_id, document, cycles in payload:
                self._log.calibration(sensor, calibration_id, document, cycles, t_host)
                self.messages += 1
        elif kind == "tare":
            after_reads, judge = payload
            self._log.tare(pipeline.interpreter.name, after_reads, judge, t_host, prefix)
            self.messages += 1
        elif kind == "calibration_set":
            self._log.calibration_set(pipeline.interpreter.name, *payload, t_host, prefix)
            self.messages += 1
        elif kind == "link":
            self._log.link(pipeline.interpreter.name, *payload, t_host, prefix)
            self.messages += 1
        elif kind == "settings":
            self._log.settings(pipeline.interpreter.name, *payload, t_host, prefix)
            self.messages += 1
        elif kind == "resume":
            self._log.resume(pipeline.interpreter.name, *payload, t_host, prefix)
            self.messages += 1
        elif kind == "baselines":
            zeros, info, left = payload
            self._log.baselines(pipeline.interpreter.name, zeros, info, t_host, prefix, left)
            self.messages += 1
        else:
            self._log.diagnostics(t_host, payload, prefix)
            self.messages += 1

    def _flush(self, sync: bool = False) -> None:
        """Hand what is written to the OS; with ``sync``, to the disk."""
        streams = [self._stream] + ([self._raw] if self._raw is not None else [])
        for stream in streams:
            stream.flush()
        if sync:
            started = time.monotonic()
            for stream in streams:
                os.fsync(stream.fileno())
            self.fsync_s += time.monotonic() - started
            self.fsyncs += 1


class _Listeners:
    """A recorder's listeners on one pipeline: they only queue references
    (with the pipeline, which names the board when it is written)."""

    def __init__(self, recorder: Recorder, pipeline) -> None:
        self.recorder = recorder
        self.pipeline = pipeline
        self._last_diag = -math.inf  # the first read's snapshot: the counters the recording began with
        self._calibrations_written: set[tuple] = set()  # (sensor id, serial, board identity, calibration id)
        self._first_read: int | None = None  # the pipeline's number of the first read recorded

    def on_bytes(self, data: bytes, t_host: float) -> None:
        """On the feeding thread, under the pipeline's lock (a tare from the
        API's thread cannot reset a zero meanwhile), before the read is decoded."""
        if not self.recorder.active:
            return
        put = self.recorder._queue.put
        if self._first_read is None:  # this read's number
            self._first_read = self.pipeline.reads
            reconstructor = self.pipeline.reconstructor
            put(("settings", (self.pipeline, (reconstructor.level, reconstructor.mounting, self._identify())), t_host))
            zeros = self.pipeline.reconstructor.baselines()
            info = self.pipeline.interpreter.info_document()
            left = reconstructor.replacements.left_zeros()  # a sensor back later is judged against its own
            if zeros or info or left:  # a recording begun on a running service: the INFO and zeros its replay begins on
                put(("baselines", (self.pipeline, (zeros, info, left)), t_host))
            # The start of a frame this read completes, which the decoder already holds: recorded with the read,
            # so the replay decodes that frame as live did (without it, the frame live recorded had no bytes).
            data = self.pipeline.decoder.held() + data
        # Driven by reads, not frames: bytes that make no frame (all corrupt) are counted too. The counters of
        # every read before this one.
        if t_host - self._last_diag >= DIAGNOSTICS_PERIOD_S:
            self._last_diag = t_host
            put(("diag", (self.pipeline, self.pipeline.diagnostics()), t_host))
            after_reads = self.pipeline.reads - self._first_read
            if after_reads:  # where a replay whose start was lost (a damaged chunk) can begin: the first read has it
                interpreter, reconstructor = self.pipeline.interpreter, self.pipeline.reconstructor
                put(("resume", (self.pipeline, (after_reads, reconstructor.baselines(), interpreter.info_document(),
                                                sorted(interpreter.sensors), reconstructor.in_force(),
                                                reconstructor.replacements.left_zeros(), self._identify())), t_host))
        put(("raw", (self.pipeline, data), t_host))

    def on_tare(self, before_read: dict[int, int], judge: bool) -> None:
        """A tare: {sensor id: the pipeline's number of the first read it
        applies to}, counted here from the recording's first read."""
        if self.recorder.active:
            first = self._first_read if self._first_read is not None else self.pipeline.reads
            after_reads = {sid: max(0, n - first) for sid, n in before_read.items()}
            self.recorder._queue.put(("tare", (self.pipeline, (after_reads, judge)), time.time()))

    def on_link(self, event: str, before_read: int) -> None:
        """The link's event (pipeline.LINK_EVENTS) before the pipeline's read
        ``before_read``; under the pipeline's lock, so in order with its tares."""
        if self.recorder.active:
            first = self._first_read if self._first_read is not None else self.pipeline.reads
            self.recorder._queue.put(("link", (self.pipeline, (event, max(0, before_read - first))), time.time()))

    def _identify(self) -> dict | None:
        """The wait for the board's INFO as it stands (identify.py; None: no
        wait on this pipeline, a recording's or a replay's bytes)."""
        identification = self.pipeline.identification
        return None if identification is None else identification.state()

    def on_calibration(self, before_read: int, sensor_id: int, document: dict) -> None:
        """A calibration set (an upload), from the pipeline's read ``before_read`` on."""
        if self.recorder.active:
            first = self._first_read if self._first_read is not None else self.pipeline.reads
            self.recorder._queue.put(("calibration_set", (self.pipeline, (sensor_id, max(0, before_read - first),
                                                                          document)), time.time()))

    def on_frames(self, frames: list[ForceFrame]) -> None:
        recorder = self.recorder
        if not recorder.active:
            return
        calibrations = self._new_calibrations(frames)
        if calibrations:
            recorder._queue.put(("calibrations", (self.pipeline, calibrations), frames[0].t_host))
        recorder._queue.put(("frames", (self.pipeline, frames), None))

    def _new_calibrations(self, frames: list[ForceFrame]) -> list[tuple]:
        """(sensor, id, document, load cycles it started with) of calibrations
        these frames are the first to use, for the sensor they come from."""
        new = []
        reconstructor = self.pipeline.reconstructor
        for frame in frames:
            sensor = frame.sensor  # another sensor at the address (its serial, its board): its own entry
            key = (sensor.id, sensor.serial, sensor.board_identity, frame.calibration)
            if key not in self._calibrations_written:
                self._calibrations_written.add(key)
                calibration = reconstructor.calibration(frame.sensor.id)
                same = calibration is not None and calibration.id == frame.calibration
                new.append((frame.sensor, frame.calibration, calibration.document if same else None,
                            reconstructor.cycles_at_start(frame.sensor.id) if same else None))
        return new

"""The running service: source → pipeline → API hub, wired once.

A source with a descriptor (device, pty, ``socket://``) is read by the event
loop itself the moment bytes arrive; others (``sim://``, ``replay://``) by
the readout thread, which only reads: each chunk goes into an inbox with its
receive time and the loop drains it. Either way the loop decodes,
reconstructs and publishes, so a frame is sent as soon as its batch is
reconstructed; with the pipeline in the reading thread, every socket send of
the loop (which releases the GIL) handed the GIL back to the reconstruction
for up to a switch interval (5 ms), and latency piled up. Reads that arrive
while the loop is busy go through together, so the batches grow under load
instead of the backlog; sensors that are cheap to reconstruct go out before
any grid waiting to be reconstructed.
"""
from __future__ import annotations

import asyncio
import gc
import threading
import time
from collections import deque

from .fanout.hub import Hub
from .latency import LatencyMeter
from .pipeline import Pipeline
from .readout import Readout
from .record.recorder import Recorder
from .reconstruct import DEFAULT_LEVEL, Reconstructor
from .sched import SliceRequest, current_slice_us, request_slice
from .sources import DEFAULT_SOURCE

INBOX_LIMIT_BYTES = 1 << 22  # ~3 s of 8 sensors at 1 kHz read but not yet decoded


class TactileService:
    """Owns the data path for one source. ``start`` must be called from the
    event loop that serves the API, since the hub lives on it."""

    def __init__(self, source: str = DEFAULT_SOURCE, level: str = DEFAULT_LEVEL, mounting: str = "flat",
                 sched_slice_us: int | None = None) -> None:
        self.sched_slice_us = sched_slice_us
        self.scheduling = SliceRequest(None, current_slice_us())
        self.pipeline = Pipeline(Reconstructor(level=level, mounting=mounting))
        self.hub = Hub()
        self.published_latency = LatencyMeter()  # receive stamp → decoded, reconstructed, handed to listeners
        self.readout = Readout(source, self._received, self._link_lost)
        self.started_at = time.time()
        self.recorder: Recorder | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: int | None = None
        self._inbox: list[tuple[bytes, float] | None] = []  # None marks a lost link
        self._inbox_lock = threading.Lock()
        self._inbox_bytes = 0
        self._drained = threading.Event()
        self._drain_scheduled = False
        self._deferred: deque[tuple[list, float]] = deque()

    def start(self) -> None:
        # What exists now (modules, the app) lives as long as the process:
        # keep it out of the collector's full passes, which would otherwise
        # stall the loop for tens of ms every few seconds at 8 kHz of frames.
        gc.freeze()
        if self.sched_slice_us:  # on the loop's thread; the readout thread, started below, inherits it
            self.scheduling = request_slice(self.sched_slice_us)
        self._loop = self.readout.loop = asyncio.get_running_loop()
        self._loop_thread = threading.get_ident()
        self.pipeline.listeners += [self._measure_published, self.hub.publish]
        self.readout.start()

    def start_recording(self, path: str, raw_path: str | None = None) -> dict:
        """Start recording the live stream; OSError/ValueError name the bad path."""
        if self.recorder is not None and self.recorder.active:
            raise RuntimeError(f"already recording to {self.recorder.path}")
        self.recorder = Recorder(path, raw_path, diagnostics=self.pipeline.decoder.counters.as_dict)
        self.pipeline.byte_listeners.append(self.recorder.on_bytes)
        self.pipeline.listeners.append(self.recorder.on_frames)
        return self.recorder.status()

    def stop_recording(self) -> dict | None:
        recorder = self.recorder
        if recorder is None:
            return None
        if recorder.on_bytes in self.pipeline.byte_listeners:
            self.pipeline.byte_listeners.remove(recorder.on_bytes)
        if recorder.on_frames in self.pipeline.listeners:
            self.pipeline.listeners.remove(recorder.on_frames)
        return recorder.stop()

    def stop(self) -> None:
        self.stop_recording()
        self.readout.stop()
        for listener in (self._measure_published, self.hub.publish):
            if listener in self.pipeline.listeners:
                self.pipeline.listeners.remove(listener)

    def _measure_published(self, frames: list) -> None:
        self.published_latency.add(time.time() - frames[0].t_host)  # frames come in arrival order

    def _received(self, data: bytes, t_host: float) -> None:
        """A chunk read: read by the loop itself (a source with a descriptor),
        it is fed at once, after anything still queued; read by the readout
        thread, it is queued and the loop woken unless already due to drain."""
        if threading.get_ident() == self._loop_thread:
            if self._inbox:
                self._drain()
            self._feed([(data, t_host)])
        else:
            self._post((data, t_host))

    def _link_lost(self) -> None:
        self._post(None)

    def _post(self, item: tuple[bytes, float] | None) -> None:
        with self._inbox_lock:
            self._inbox.append(item)
            self._inbox_bytes += 0 if item is None else len(item[0])
            full = self._inbox_bytes > INBOX_LIMIT_BYTES
            if full:
                self._drained.clear()
            wake = not self._drain_scheduled
            self._drain_scheduled = True
        loop = self._loop
        if wake and loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._drain)
        if full:
            # A host that cannot keep up must not buffer without end: the reader
            # waits, the port's buffer fills and the board reports OVERRUN.
            self._drained.wait(1.0)

    async def let_urgent_go_first(self) -> None:
        """Called by a batched client's sender before each send. Twenty
        batched clients flush in the same turn of the loop; a read that
        arrives meanwhile would wait behind all their sends, and so would the
        unbatched clients' frames of it. Instead a read waiting for the loop
        is drained now, and the sender steps back one turn while an unbatched
        client has a message to send."""
        if self._inbox:
            self._drain()
        if self.hub.unbatched_due():
            await asyncio.sleep(0)

    def _drain(self) -> None:
        """Event loop: feed everything queued, in order, as few batches as possible."""
        with self._inbox_lock:
            items, self._inbox, self._inbox_bytes = self._inbox, [], 0
            self._drain_scheduled = False
            self._drained.set()
        chunks: list[tuple[bytes, float]] = []
        for item in items:
            if item is not None:
                chunks.append(item)
                continue
            self._feed(chunks)
            chunks = []
            self.pipeline.link_lost()
        self._feed(chunks)

    def _feed(self, chunks: list[tuple[bytes, float]]) -> None:
        """Sensors that are cheap to reconstruct (all but grids) are published
        at once; grids are queued and reconstructed in a later turn of the
        loop, after the sends of what was published: a controller on a quad
        waits neither for the grids of its own read nor for those of earlier
        reads still queued. Each sensor's frames stay in order."""
        if not chunks:
            return
        t_host = chunks[-1][1]
        cheap, grids = [], []
        for reading in self.pipeline.decode_chunks(chunks):
            (grids if reading.sensor.kind == "grid" else cheap).append(reading)
        if cheap:
            self.pipeline.reconstruct(cheap, t_host)
        if grids:
            self._deferred.append((grids, t_host))
            if len(self._deferred) == 1:
                self._loop.call_soon(self._finish_deferred)

    def _finish_deferred(self) -> None:
        """The grids queued by ``_feed``, all in one batch (reads that piled up
        while the loop was busy cost one call per step, not one per read)."""
        if not self._deferred:
            return
        batches, self._deferred = self._deferred, deque()
        self.pipeline.reconstruct([r for readings, _ in batches for r in readings], batches[-1][1])

    def health(self) -> dict:
        now = time.time()
        pipeline = self.pipeline
        counters = pipeline.decoder.counters.as_dict()
        sensors = {}
        for sid, info in sorted(pipeline.interpreter.sensors.items()):
            meter = pipeline.rates.get(sid)
            latest = pipeline.latest.get(sid)
            sensors[str(sid)] = {
                "kind": info.kind,
                "rate_hz": round(meter.rate_hz, 1) if meter else 0.0,
                "last_frame_age_s": None if latest is None else round(now - latest.t_host, 3),
                **counters["sensors"].get(str(sid), {}),
            }
        stream = {k: v for k, v in counters.items() if k != "sensors"}
        return {
            "status": "ok" if self.readout.link.up else "degraded",
            "uptime_s": round(now - self.started_at, 1),
            "link": self.readout.link.as_dict(now),
            "level": pipeline.reconstructor.level,
            "stream": stream,
            "rejected": dict(pipeline.interpreter.rejected),
            "board_errors": [{"t_host": t, "text": text} for t, text in pipeline.interpreter.board_errors],
            "sensors": sensors,
            "websocket_clients": len(self.hub.subscribers),
            "latency": {
                "published": self.published_latency.summary(),
                **{f"sent_{kind}": meter.summary() for kind, meter in self.hub.sent_latency.items()},
            },
            "scheduling": self.scheduling.as_dict(),
            "frames_published": self.hub.frames_published,
            "replay": self.readout.link.url.startswith("replay://"),
            "recording": None if self.recorder is None else self.recorder.status(),
            "reconstruction": {
                "level": pipeline.reconstructor.level,
                "level_reason": pipeline.reconstructor.level_reason,
                "mounting": pipeline.reconstructor.mounting,
                "crosstalk": {str(sid): pipeline.reconstructor.crosstalk_report(sid)
                              for sid, info in pipeline.interpreter.sensors.items() if info.kind == "grid"},
            },
        }

"""The live service: source → readout → pipeline → fan-out hub, wired once.

``start`` runs on the event loop that serves the API: the readout hands its
bytes to the loop (handover.py), the pipeline reconstructs them there and
publishes to the hub and the recorder. /health is assembled in health.py.
"""
from __future__ import annotations

import asyncio
import time
from pathlib import Path

from .fanout.hub import Hub
from .handover import LoopHandover
from .health import health_report
from .latency import LatencyMeter
from .pipeline import Pipeline
from .readout import Readout
from .reconstruct import DEFAULT_LEVEL, Reconstructor
from .record.recorder import Recorder
from .sched import SliceRequest, current_slice_us, tune_for_latency
from .sources import DEFAULT_SOURCE


class TactileService:
    """Owns the data path for one source."""

    def __init__(self, source: str = DEFAULT_SOURCE, level: str = DEFAULT_LEVEL, mounting: str = "flat",
                 sched_slice_us: int | None = None) -> None:
        self.source = source
        self.sched_slice_us = sched_slice_us
        self.scheduling = SliceRequest(None, current_slice_us())
        self.pipeline = Pipeline(Reconstructor(level=level, mounting=mounting))
        self.hub = Hub()
        self.published_latency = LatencyMeter()  # receive stamp → decoded, reconstructed, handed to listeners
        self.handover: LoopHandover | None = None
        self.readout: Readout | None = None
        self.started_at = time.time()
        self.recorder: Recorder | None = None

    def start(self) -> None:
        """On the event loop: tune, wire the listeners, start reading."""
        loop = asyncio.get_running_loop()
        self.scheduling = tune_for_latency(self.sched_slice_us)
        self.handover = LoopHandover(self.pipeline.feed_reads, self.pipeline.link_lost, loop)
        self.pipeline.listeners += [self._measure_published, self.hub.publish]
        self.readout = Readout(self.source, self.handover)
        self.readout.start(loop)

    def stop(self) -> None:
        self.stop_recording()
        if self.readout is not None:
            self.readout.stop()
        for listener in (self._measure_published, self.hub.publish):
            if listener in self.pipeline.listeners:
                self.pipeline.listeners.remove(listener)

    def start_recording(self, path: str | Path, raw_path: str | Path | None = None) -> dict:
        """Start recording the live stream; OSError/ValueError name the bad path."""
        if self.recorder is not None and self.recorder.active:
            raise RuntimeError(f"already recording to {self.recorder.path}")
        self.recorder = Recorder(path, raw_path)
        self.recorder.attach(self.pipeline)
        return self.recorder.status()

    def stop_recording(self) -> dict | None:
        return None if self.recorder is None else self.recorder.stop()

    async def let_urgent_go_first(self) -> None:
        """Called by a batched client's sender before each send. Twenty
        batched clients flush in the same turn of the loop; a read that
        arrives meanwhile would wait behind all their sends, and so would the
        unbatched clients' frames of it. Instead a read waiting for the loop
        is drained now, and the sender steps back one turn while an unbatched
        client has a message to send."""
        if self.handover is not None and self.handover.pending:
            self.handover.drain()
        if self.hub.unbatched_due():
            await asyncio.sleep(0)

    def health(self) -> dict:
        return health_report(self)

    def _measure_published(self, frames: list) -> None:
        self.published_latency.add(time.time() - frames[0].t_host)  # frames come in arrival order

"""The live service: source → readout → pipeline → fan-out hub, wired once.

``start`` runs on the event loop that serves the API: the readout hands its
bytes to the loop (handover.py), the pipeline reconstructs them there and
publishes to the hub and the recorder. /health is assembled in health.py.
"""
from __future__ import annotations

import asyncio
import logging
import re
import threading
import time
from pathlib import Path

from .calibration.book import CalibrationBook
from .calibration.registry import sensor_identity
from .fanout.hub import Hub
from .handover import LoopHandover
from .health import health_report
from .latency import LatencyMeter
from .pipeline import Pipeline
from .readout import DEFAULT_SILENCE_S, Readout
from .reconstruct import DEFAULT_LEVEL, Reconstructor
from .record.recorder import Recorder
from .sched import SliceRequest, current_slice_us, tune_for_latency
from .sources import DEFAULT_SOURCE


log = logging.getLogger(__name__)

CYCLES_SAVE_S = 10.0  # a crash loses at most this much of the load-cycle counts
RECORDING_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,122}\.mcap")


def recording_name(name: str | None) -> str:
    """A bare file name ending in .mcap — letters, digits, '.', '_', '-', at
    most 128 characters, not starting with a dot: nothing a file system could
    read as a directory, a device or a stream — or a timestamped default;
    ValueError naming what is wrong."""
    if name is None:
        return time.strftime("recording-%Y%m%d-%H%M%S.mcap")
    if not RECORDING_NAME.fullmatch(name):
        raise ValueError(f"{name[:130]!r} must be a bare file name ending in .mcap: letters, digits, '.', '_', '-' "
                         f"(not first), at most 128 characters")
    return name


class TactileService:
    """Owns the data path for one source."""

    def __init__(self, source: str = DEFAULT_SOURCE, level: str = DEFAULT_LEVEL, mounting: str = "flat",
                 sched_slice_us: int | None = None, recordings_dir: str | Path = "recordings",
                 silence_s: float = DEFAULT_SILENCE_S, calibrations: CalibrationBook | None = None) -> None:
        """``calibrations``: where sensors' calibrations come from and uploads
        go (default: the registry at its default place, calibration/book.py)."""
        self.source = source
        self.recordings_dir = Path(recordings_dir).resolve()
        self.silence_s = silence_s
        self.sched_slice_us = sched_slice_us
        self.scheduling = SliceRequest(None, current_slice_us())
        self.calibrations = calibrations if calibrations is not None else CalibrationBook(mounting=mounting)
        self.pipeline = Pipeline(Reconstructor(level=level, mounting=mounting), calibrations=self.calibrations)
        self.hub = Hub()
        self.published_latency = LatencyMeter()  # receive stamp → decoded, reconstructed, handed to listeners
        self.handover: LoopHandover | None = None
        self.readout: Readout | None = None
        self.started_at = time.time()
        self.recorder: Recorder | None = None
        self.zenoh = None  # a net.zenoh_publisher.ZenohPublisher to attach at start (tactile serve --zenoh)
        self._recording_lock = threading.Lock()  # start and stop come from the API's worker threads
        self._cycles_stop = threading.Event()

    def start(self) -> None:
        """On the event loop: tune, wire the listeners, start reading."""
        loop = asyncio.get_running_loop()
        self.scheduling = tune_for_latency(self.sched_slice_us)
        self.handover = LoopHandover(self.pipeline.feed_reads, self.pipeline.link_lost, loop)
        self.pipeline.listeners += [self._measure_published, self.hub.publish]
        self.readout = Readout(self.source, self.handover, silence_s=self.silence_s)
        self.readout.start(loop)
        self._cycles_stop.clear()
        threading.Thread(target=self._keep_cycles, name="tactile-cycles", daemon=True).start()
        if self.zenoh is not None:
            self.zenoh.attach(self)

    def stop(self) -> None:
        self.stop_recording()
        if self.zenoh is not None:
            self.zenoh.close()
        if self.readout is not None:
            self.readout.stop()
        self._cycles_stop.set()
        self.save_cycles()
        for listener in (self._measure_published, self.hub.publish):
            if listener in self.pipeline.listeners:
                self.pipeline.listeners.remove(listener)

    def start_recording(self, name: str | None = None) -> dict:
        """Record the live stream to ``name`` (a bare .mcap file name) in the
        recordings directory, the raw bytes beside it (.bin). ValueError for a
        name that is not a bare .mcap name, FileExistsError for one taken,
        RuntimeError while recording."""
        path = self.recordings_dir / recording_name(name)
        with self._recording_lock:
            if self.recorder is not None and self.recorder.active:
                raise RuntimeError(f"already recording to {self.recorder.path}")
            self.recordings_dir.mkdir(parents=True, exist_ok=True)
            self.recorder = Recorder(path, path.with_suffix(".bin"), exclusive=True)
            self.recorder.attach(self.pipeline)
            return self.recorder.status()

    def save_cycles(self) -> None:
        """Keep every sensor's load-cycle counts in the registry (a failure is logged, never raised)."""
        try:
            self.calibrations.save_cycles(self.pipeline.interpreter.board, self.pipeline.reconstructor.cycle_counts())
        except Exception as exc:  # noqa: BLE001 — counts are kept again at the next period
            log.warning("load-cycle counts not kept: %s", exc)

    def _keep_cycles(self) -> None:
        """Every CYCLES_SAVE_S, off the event loop (a registry write takes milliseconds)."""
        while not self._cycles_stop.wait(CYCLES_SAVE_S):
            self.save_cycles()

    def set_calibration(self, info, upload: dict) -> dict:
        """Validate an upload (ValueError naming the field), store it in the
        registry and make it the sensor's active calibration there, then
        reconstruct with it from the next frame; returns the document."""
        sensor = sensor_identity(self.pipeline.interpreter.board, info)
        store = self.calibrations.store if self.calibrations.use_registry else None
        return self.pipeline.set_calibration(info, upload, sensor, store)

    def stop_recording(self) -> dict | None:
        with self._recording_lock:
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

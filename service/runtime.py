"""The running service: readout thread → pipeline → API hub, wired once."""
from __future__ import annotations

import asyncio
import time

from .api.stream import Hub
from .pipeline import Pipeline
from .readout import Readout
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor
from .sources import DEFAULT_SOURCE


class TactileService:
    """Owns the data path for one source. ``start`` must be called from the
    event loop that serves the API, since the hub lives on it."""

    def __init__(self, source: str = DEFAULT_SOURCE, level: str = DEFAULT_LEVEL, mounting: str = "flat") -> None:
        self.pipeline = Pipeline(Reconstructor(level=level, mounting=mounting))
        self.hub = Hub()
        self.readout = Readout(source, self.pipeline.feed, self.pipeline.link_lost)
        self.started_at = time.time()
        self._loop: asyncio.AbstractEventLoop | None = None

    def start(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.pipeline.listeners.append(self._to_loop)
        self.readout.start()

    def stop(self) -> None:
        self.readout.stop()
        if self._to_loop in self.pipeline.listeners:
            self.pipeline.listeners.remove(self._to_loop)

    def _to_loop(self, frames: list[ForceFrame]) -> None:
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self.hub.publish, frames)

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
        }

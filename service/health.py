"""``GET /health``: the live service's state in one document."""
from __future__ import annotations

import time

from .readout import LinkState


def _sensors(pipeline, now: float, counters: dict) -> dict:
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
    return sensors


def _reconstruction(pipeline) -> dict:
    reconstructor = pipeline.reconstructor
    return {
        "level": reconstructor.level,
        "level_reason": reconstructor.level_reason,
        "mounting": reconstructor.mounting,
        "crosstalk": {str(sid): reconstructor.crosstalk_report(sid)
                      for sid, info in pipeline.interpreter.sensors.items() if info.kind == "grid"},
    }


def health_report(service) -> dict:
    """``service``: a live_service.TactileService."""
    now = time.time()
    pipeline = service.pipeline
    counters = pipeline.decoder.counters.as_dict()
    link = service.readout.link if service.readout is not None else LinkState(service.source)
    return {
        "status": "ok" if link.up else "degraded",
        "uptime_s": round(now - service.started_at, 1),
        "link": link.as_dict(now),
        "level": pipeline.reconstructor.level,
        "stream": {k: v for k, v in counters.items() if k != "sensors"},
        "rejected": dict(pipeline.interpreter.rejected),
        "board_errors": [{"t_host": t, "text": text} for t, text in pipeline.interpreter.board_errors],
        "sensors": _sensors(pipeline, now, counters),
        "websocket_clients": len(service.hub.subscribers),
        "latency": {
            "published": service.published_latency.summary(),
            **{f"sent_{kind}": meter.summary() for kind, meter in service.hub.sent_latency.items()},
        },
        "scheduling": service.scheduling.as_dict(),
        "frames_published": service.hub.frames_published,
        "replay": service.source.startswith("replay://"),
        "recording": None if service.recorder is None else service.recorder.status(),
        "reconstruction": _reconstruction(pipeline),
    }

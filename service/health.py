"""``GET /health``: the live service's state in one document."""
from __future__ import annotations

import time

from .readout import MIN_STALE_S, LinkState

STALE_SCAN_PERIODS = 20


def stale_after_s(board: dict) -> float:
    """Silence that makes the link or a sensor stale: max(0.5 s, 20 scan
    periods at the rate the board announced in INFO)."""
    rate = board.get("rate_hz")
    if isinstance(rate, (int, float)) and not isinstance(rate, bool) and rate > 0:
        return max(MIN_STALE_S, STALE_SCAN_PERIODS / rate)
    return MIN_STALE_S


def _sensors(pipeline, now: float, counters: dict, stale_after: float) -> dict:
    sensors = {}
    for sid, info in sorted(pipeline.interpreter.sensors.items()):
        meter = pipeline.rates.get(sid)
        latest = pipeline.latest.get(sid)
        age = None if latest is None else now - latest.t_host
        stale = age is None or age > stale_after
        sensors[str(sid)] = {
            "kind": info.kind,
            "rate_hz": 0.0 if stale or meter is None else round(meter.rate_hz, 1),
            "stale": stale,
            "last_frame_age_s": None if age is None else round(age, 3),
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
        "errors": {str(sid): error for sid, error in reconstructor.errors().items()},
    }


def _problems(link: dict, sensors: dict, errors: dict) -> list[str]:
    """Why the status is degraded, one line each (empty when ok)."""
    problems = []
    if link["state"] != "up":
        problems.append(f"link {link['state']}" + (f": {link['last_error']}" if link["last_error"] else ""))
    problems += [f"sensor {sid} stale" for sid, sensor in sensors.items() if sensor["stale"]]
    problems += [f"sensor {sid} reconstruction fails: {error['error']} ({error['count']} times)"
                 for sid, error in errors.items() if error["active"]]
    return problems


def health_report(service) -> dict:
    """``service``: a live_service.TactileService."""
    now = time.time()
    pipeline = service.pipeline
    counters = pipeline.decoder.counters.as_dict()
    link = service.readout.link if service.readout is not None else LinkState(service.source)
    stale_after = stale_after_s(pipeline.interpreter.board)
    link_state = link.as_dict(now, stale_after)
    sensors = _sensors(pipeline, now, counters, stale_after)
    reconstruction = _reconstruction(pipeline)
    failing = [sid for sid, error in reconstruction["errors"].items() if error["active"]]
    healthy = link_state["state"] == "up" and not any(s["stale"] for s in sensors.values()) and not failing
    return {
        "status": "ok" if healthy else "degraded",
        "problems": _problems(link_state, sensors, reconstruction["errors"]),
        "uptime_s": round(now - service.started_at, 1),
        "link": link_state,
        "level": pipeline.reconstructor.level,
        "stream": {k: v for k, v in counters.items() if k != "sensors"},
        "rejected": dict(pipeline.interpreter.rejected),
        "board_errors": [{"t_host": t, "text": text} for t, text in pipeline.interpreter.board_errors],
        "sensors": sensors,
        "websocket_clients": len(service.hub.subscribers),
        "latency": {
            "published": service.published_latency.summary(),
            **{f"sent_{kind}": meter.summary() for kind, meter in service.hub.sent_latency.items()},
        },
        "scheduling": service.scheduling.as_dict(),
        "frames_published": service.hub.frames_published,
        "replay": service.source.startswith("replay://"),
        "recording": None if service.recorder is None else service.recorder.status(),
        "reconstruction": reconstruction,
    }

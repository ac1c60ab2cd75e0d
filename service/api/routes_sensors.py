"""Read-only views of the sensors: what the board announced, each sensor's
latest frame, contact summary and recent history, and the stream clients."""
from __future__ import annotations

from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends, HTTPException, Query

from ..fanout.encoding import FIELDS, to_json_dict
from .deps import ALL_FIELDS, JSONResponse, get_service, known_sensor, latest_frame, parse_fields
from .schemas import Contact, FrameMessage

if TYPE_CHECKING:
    from ..reconstruct import ForceFrame
    from ..live_service import TactileService

router = APIRouter()


@router.get("/clients")
def clients(service: TactileService = Depends(get_service)) -> JSONResponse:
    """Each WebSocket client's subscription, queue, losses and latency
    (receive stamp → handed to its socket): a controller finds its own
    stream here. Apart from /health, which is polled often, since it
    costs a percentile per client."""
    return JSONResponse({"clients": [subscriber.describe() for subscriber in list(service.hub.subscribers)]})


@router.get("/sensors")
def sensors(service: TactileService = Depends(get_service)) -> JSONResponse:
    interpreter = service.pipeline.interpreter
    baseline = service.pipeline.reconstructor.baseline
    return JSONResponse(
        {
            "board": interpreter.board,
            "sensors": [
                {**info.as_dict(), "name": f"{info.kind}{sid}", "tared": baseline(sid) is not None}
                for sid, info in sorted(interpreter.sensors.items())
            ],
        }
    )


@router.get("/sensors/{sensor_id}/latest", responses={200: {"model": FrameMessage}})
def latest(frame: ForceFrame = Depends(latest_frame)) -> JSONResponse:
    return JSONResponse(to_json_dict(frame, ALL_FIELDS))


@router.get("/sensors/{sensor_id}/contact", responses={200: {"model": Contact}})
def contact(sensor_id: int, frame: ForceFrame = Depends(latest_frame)) -> JSONResponse:
    if frame.sensor.kind != "grid":
        raise HTTPException(400, f"sensor {sensor_id} is a {frame.sensor.kind}; contact summaries are for grids")
    if frame.contact is None:
        raise HTTPException(404, f"sensor {sensor_id} is still taring")
    return JSONResponse(frame.contact)


@router.get("/sensors/{sensor_id}/history", responses={200: {"model": list[FrameMessage]}})
def history(
    sensor_id: int,
    seconds: float = Query(2.0, gt=0, le=5, description="window length back from the latest frame (5 s kept at 1 kHz)"),
    max_points: int = Query(200, ge=1, le=5000, description="decimate to at most this many frames"),
    fields: str = Query("force,contact,flags", description=f"comma-separated: {', '.join(FIELDS)}"),
    service: TactileService = Depends(get_service),
) -> JSONResponse:
    known_sensor(sensor_id, service)  # after the query is validated: a bad query is 422 for any sensor
    try:
        wanted = parse_fields(fields)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    history = service.pipeline.history.get(sensor_id)
    frames = [] if history is None else history.window(seconds, max_points)
    return JSONResponse([to_json_dict(frame, wanted) for frame in frames])

"""What the routes share: the response class, the service and the token from
the app's state, authorisation, sensor look-ups and the stream/history
parameter parsers.

The service is taken from ``app.state.service`` (set by ``create_app``), so
the routes are module-level and the API never imports the runtime to run.
"""
from __future__ import annotations

import hmac
from typing import TYPE_CHECKING

import orjson
from fastapi import Depends, Header, HTTPException
from fastapi.requests import HTTPConnection
from fastapi.responses import Response

from ..fanout.encoding import DEFAULT_FIELDS, FIELDS

if TYPE_CHECKING:
    from ..live_service import TactileService
    from ..readings import SensorInfo
    from ..reconstruct import ForceFrame

ALL_FIELDS = frozenset(FIELDS)


class JSONResponse(Response):
    """orjson with numpy support: NaN (no value) becomes null."""

    media_type = "application/json"

    def render(self, content) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)


async def get_service(connection: HTTPConnection) -> TactileService:
    """The service this app serves (HTTP requests and WebSockets alike).
    Async, so that FastAPI resolves it on the event loop instead of handing
    every request to a worker thread for it."""
    return connection.app.state.service


def authorised(
    connection: HTTPConnection,
    authorization: str | None = Header(default=None, description="Bearer token, when the service requires one"),
):
    token = connection.app.state.token
    if token is None:
        return
    expected = f"Bearer {token}".encode()
    given = (authorization or "").encode("utf-8", "surrogateescape")  # any header, even not ASCII, is a 401
    if not hmac.compare_digest(given, expected):
        raise HTTPException(401, "this endpoint needs 'Authorization: Bearer <token>' (printed by tactile serve)")


def known_sensor(sensor_id: int, service: TactileService = Depends(get_service)) -> SensorInfo:
    sensors = service.pipeline.interpreter.sensors
    if sensor_id not in sensors:
        known = ", ".join(str(s) for s in sorted(sensors)) or "none yet"
        raise HTTPException(404, f"unknown sensor id {sensor_id}; known: {known}")
    return sensors[sensor_id]


def latest_frame(sensor_id: int, service: TactileService = Depends(get_service)) -> ForceFrame:
    known_sensor(sensor_id, service)
    frame = service.pipeline.latest.get(sensor_id)
    if frame is None:
        raise HTTPException(404, f"sensor {sensor_id} has not delivered a frame yet")
    return frame


def parse_sensors(text: str | None) -> frozenset[int] | None:
    if text is None or text == "":
        return None
    try:
        return frozenset(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"sensors={text!r} must be a comma-separated list of integer ids") from None


def parse_fields(text: str | None) -> frozenset[str]:
    if text is None or text == "":
        return DEFAULT_FIELDS
    fields = frozenset(part.strip() for part in text.split(","))
    unknown = fields - ALL_FIELDS
    if unknown:
        raise ValueError(f"fields={text!r}: unknown {sorted(unknown)}; known: {', '.join(FIELDS)}")
    return fields


def parse_positive(name: str, text: str | None, upper: float) -> float | None:
    if text is None or text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name}={text!r} is not a number") from None
    if not 0 < value <= upper:
        raise ValueError(f"{name}={text!r} must be in (0, {upper:g}]")
    return value

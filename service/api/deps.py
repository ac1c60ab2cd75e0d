"""What the routes share: the response class, the service and the token from
the app's state, authorisation, sensor look-ups and the stream/history
parameter parsers.

The service is taken from ``app.state.service`` (set by ``create_app``), so
the routes are module-level and the API never imports the runtime to run.
"""
from __future__ import annotations

import hmac
import re
from dataclasses import dataclass
from typing import TYPE_CHECKING

import orjson
from fastapi import Depends, Header, HTTPException, Request
from fastapi.requests import HTTPConnection
from fastapi.responses import Response

from ..fanout.encoding import DEFAULT_FIELDS, FIELDS
from ..readings import MAX_SENSOR_ID

if TYPE_CHECKING:
    from ..board import Board
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


@dataclass(frozen=True)
class Addressed:
    """A sensor found by its address: the board it is on and its description."""

    board: Board
    info: SensorInfo


def _known_on(board: Board) -> str:
    return ", ".join(f"{board.name}/{s}" for s in sorted(board.sensors)) or f"none yet on {board.name}"


def find_sensor(service: TactileService, sensor_id: int, board: str | None = None) -> Addressed:
    """The sensor at ``board``/``sensor_id``; without a board, the sensor
    with that id on the only board that has one (404 or 409 naming the
    boards otherwise)."""
    boards = service.all_boards
    if board is not None:
        found = service.board(board)
        if found is None:
            raise HTTPException(404, f"unknown board {board!r}; boards: {', '.join(b.name for b in boards)}")
        if sensor_id not in found.sensors:
            raise HTTPException(404, f"unknown sensor {board}/{sensor_id}; known: {_known_on(found)}")
        return Addressed(found, found.sensors[sensor_id])
    if len(boards) == 1:
        sensors = boards[0].sensors
        if sensor_id not in sensors:
            known = ", ".join(str(s) for s in sorted(sensors)) or "none yet"
            raise HTTPException(404, f"unknown sensor id {sensor_id}; known: {known}")
        return Addressed(boards[0], sensors[sensor_id])
    having = [b for b in boards if sensor_id in b.sensors]
    if len(having) == 1:
        return Addressed(having[0], having[0].sensors[sensor_id])
    if having:
        raise HTTPException(409, f"sensor id {sensor_id} is on boards {', '.join(b.name for b in having)}: "
                                 f"address it as /sensors/{{board}}/{sensor_id}")
    raise HTTPException(404, f"unknown sensor id {sensor_id}; known: {'; '.join(_known_on(b) for b in boards)}")


def known_sensor(sensor_id: int, board: str | None = None,
                 service: TactileService = Depends(get_service)) -> Addressed:
    """The route's sensor: ``/sensors/{sensor_id}/…`` or ``/sensors/{board}/{sensor_id}/…``."""
    return find_sensor(service, sensor_id, board)


def latest_frame(found: Addressed = Depends(known_sensor)) -> ForceFrame:
    frame = found.board.latest.get(found.info.id)
    if frame is None:
        raise HTTPException(404, f"sensor {found.info.address} has not delivered a frame yet")
    return frame


def known_query(request: Request) -> None:
    """422 naming a query parameter the endpoint does not take, or one given
    twice: FastAPI ignores the first and takes the last, so a typo
    (``max_point=10``) silently got the default."""
    dependant = getattr(request.scope.get("route"), "dependant", None)
    if dependant is None:
        return
    known, pending = set(), [dependant]
    while pending:  # the endpoint's query parameters and its dependencies'
        current = pending.pop()
        known.update(param.alias for param in current.query_params)
        pending += current.dependencies
    for name in request.query_params:
        if name not in known:
            raise HTTPException(422, f"unknown parameter {name!r}; known: {', '.join(sorted(known)) or 'none'}")
        if len(request.query_params.getlist(name)) > 1:
            raise HTTPException(422, f"{name} given {len(request.query_params.getlist(name))} times: give it once")


def parse_sensors(text: str | None) -> frozenset | None:
    """``0,1,left/2``: a bare id is that sensor on any board, ``board/id`` one board's."""
    if text is None or text == "":
        return None
    wanted = set()
    for part in text.split(","):
        board, _, sid = part.strip().rpartition("/")
        if re.fullmatch(r"-?[0-9]+", sid.strip()) is None:  # int() also takes "1_0" and other scripts' digits
            raise ValueError(f"sensors={text!r} must be a comma-separated list of ids or board/id addresses")
        number = int(sid)
        if not 0 <= number <= MAX_SENSOR_ID:
            raise ValueError(f"sensors={text!r}: {number} is no sensor id (ids are 0..{MAX_SENSOR_ID})")
        wanted.add((board, number) if board else number)
    return frozenset(wanted)


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

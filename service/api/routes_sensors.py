"""Read-only views of the sensors: what the board announced, each sensor's
latest frame, contact summary and recent history, and the stream clients."""
from __future__ import annotations

import asyncio
import threading
import time
from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response
from fastapi.responses import StreamingResponse

from ..fanout.encoding import FIELDS, to_json_dict
from ..fanout.history_json import RecentRings
from ..health import frame_stale
from .deps import (
    ALL_FIELDS,
    Addressed,
    JSONResponse,
    find_sensor,
    get_service,
    known_sensor,
    latest_frame,
    parse_fields,
)
from .schemas import ContactReply, FrameMessage

if TYPE_CHECKING:
    from ..live_service import TactileService
    from ..reconstruct import ForceFrame

AGE_HEADER = "X-Frame-Age-S"
STALE_FLAG = "sensor_stale"  # a latest frame whose sensor /health calls stale; not "stale", a stuck channel's flag
router = APIRouter()

MAX_HEAVY_READS = 2
SEND_PIECE_BYTES = 1 << 16
MAX_SENDING_BYTES = 64 << 20  # history answers held until their clients take them, all together
HISTORY_STEP_BYTES = 1 << 13  # JSON encoded between two turns of the event loop (7 frames of an 8x8 grid, ~0.2 ms)
JOIN_IN_THREAD_BYTES = 1 << 20  # CPython's bytes.join releases the GIL from this size on
RECENT_RING_BYTES = 64 << 20  # frames' JSON kept for the (sensor, fields) read last, about this much


@router.get("/clients")
def clients(service: TactileService = Depends(get_service)) -> JSONResponse:
    """Each WebSocket client's subscription, queue, losses and latency
    (receive stamp → handed to its socket): a controller finds its own
    stream here. Apart from /health, which is polled often, since it
    costs a percentile per client."""
    return JSONResponse({"clients": [subscriber.describe() for subscriber in list(service.hub.subscribers)]})


@router.get("/sensors")
def sensors(service: TactileService = Depends(get_service)) -> JSONResponse:
    """Every board (its name, source and INFO) and every sensor, each with
    its board and address (board/id). ``board`` is the INFO of a one-board
    service's board, as before boards were named."""
    boards = service.all_boards
    listed = [{**info.as_dict(), "serial": info.serial, "board": board.name, "address": f"{board.name}/{sid}", "name": f"{info.kind}{sid}",
               "tared": board.tared(sid)}
              for board in boards for sid, info in sorted(board.sensors.items())]
    return JSONResponse({
        "board": boards[0].info if len(boards) == 1 else None,
        "boards": [{"name": b.name, "source": b.source, "info": b.info} for b in boards],
        "sensors": listed,
    })


@router.get("/sensors/{sensor_id}/latest", responses={200: {"model": FrameMessage}})
@router.get("/sensors/{board}/{sensor_id}/latest", responses={200: {"model": FrameMessage}})
def latest(found: Addressed = Depends(known_sensor)) -> JSONResponse:
    # A board gone quiet still has a latest frame: its age beside it, and in its flags that it is no longer current
    # (a controller polling saw a 6 s old frame's forces, flags [], as if read now).
    frame, now = latest_frame(found), time.time()
    message = to_json_dict(frame, ALL_FIELDS)
    if frame_stale(found.board, frame, now):
        message["flags"] = [*frame.flags, STALE_FLAG]  # a new list: the frame's own is the live stream's
    return JSONResponse(message, headers={AGE_HEADER: _age(frame, now)})


@router.get("/sensors/{sensor_id}/contact", responses={200: {"model": ContactReply}})
@router.get("/sensors/{board}/{sensor_id}/contact", responses={200: {"model": ContactReply}})
def contact(found: Addressed = Depends(known_sensor)) -> JSONResponse:
    frame, now = latest_frame(found), time.time()
    if frame.sensor.kind != "grid":
        raise HTTPException(400, f"sensor {frame.sensor.address} is a {frame.sensor.kind}; contact summaries are for grids")
    if frame.contact is None:
        raise HTTPException(404, f"sensor {frame.sensor.address} is still taring")
    return JSONResponse({**frame.contact, "stale": frame_stale(found.board, frame, now)},
                        headers={AGE_HEADER: _age(frame, now)})


def _age(frame: ForceFrame, now: float) -> str:
    """Seconds from the frame's read being received to ``now``, for AGE_HEADER."""
    return f"{max(0.0, now - frame.t_host):.3f}"


@router.get("/sensors/{sensor_id}/history", responses={200: {"model": list[FrameMessage]}, 429: {}})
@router.get("/sensors/{board}/{sensor_id}/history", responses={200: {"model": list[FrameMessage]}, 429: {}})
async def history(
    request: Request,
    sensor_id: int,
    board: str | None = None,
    seconds: float = Query(2.0, gt=0, le=5, description="window length back from the latest frame (5 s kept at 1 kHz)"),
    max_points: int = Query(200, ge=1, le=5000, description="decimate to at most this many frames"),
    fields: str = Query("force,contact,flags", description=f"comma-separated: {', '.join(FIELDS)}"),
    service: TactileService = Depends(get_service),
) -> Response:
    """A heavy read, bounded three ways so that it never holds up the 1 kHz
    path for long: admitted at a bounded rate (admission.py), at most
    ``MAX_HEAVY_READS`` encoded at once and ``MAX_SENDING_BYTES`` waiting
    for their clients (429 beyond), and encoded on
    the event loop about ``HISTORY_STEP_BYTES`` at a time (frames encoded
    by a recent read are reused) and sent in pieces, so that the live
    stream's callbacks run between two steps (encoding in a worker thread
    was worse: the thread held the interpreter for milliseconds at a time
    whatever the switch interval). The same read asked again within
    ``RecentReads.max_age_s`` (dashboards polling) is not encoded again."""
    found = find_sensor(service, sensor_id, board)  # after the query is validated: a bad query is 422 for any sensor
    try:
        wanted = parse_fields(fields)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    gate = request.app.state.heavy_reads
    if not gate.acquire(blocking=False):
        raise HTTPException(429, f"{MAX_HEAVY_READS} history reads are running; retry shortly",
                            headers={"Retry-After": "1"})
    try:
        body = await encoded_history(request.app.state, found, seconds, max_points, wanted)
    finally:
        # The slot bounds the encoding the loop does; sending is the socket's: two clients that never
        # read their answers held both slots, and every other history read was refused, for as long.
        gate.release()
    state = request.app.state
    if state.history_sending and state.history_sending + len(body) > MAX_SENDING_BYTES:  # clients not reading theirs
        raise HTTPException(429, f"{state.history_sending >> 20} MB of history answers are still being sent; retry "
                                 f"shortly", headers={"Retry-After": "1"})
    state.history_sending += len(body)
    return StreamingResponse(pieces(body, state), media_type="application/json",
                             headers={"Content-Length": str(len(body))})


async def encoded_history(state, found, seconds: float, max_points: int, wanted: frozenset[str]) -> bytes:
    """``state``: the app's, with its RecentReads and RecentRings."""
    key = (found.info.address, seconds, max_points, wanted)
    body = state.recent_reads.get(key)
    if body is None:
        history = found.board.history.get(found.info.id)
        body = b"[]" if history is None else await encode_history(history, seconds, max_points, wanted,
                                                                   state.recent_rings)
        state.recent_reads.put(key, body)
    return body


async def pieces(body: bytes, state):
    """An answer in 64 KiB pieces: the event loop sends one, serves the live
    stream, then sends the next (a send does not give the loop up by itself).
    Its bytes count in ``state.history_sending`` until it is sent or its
    client gone."""
    try:
        for start in range(0, len(body), SEND_PIECE_BYTES):
            yield body[start:start + SEND_PIECE_BYTES]
            await asyncio.sleep(0)
    finally:
        state.history_sending -= len(body)


async def encode_history(history, seconds: float, max_points: int, wanted: frozenset[str],
                         recent_rings: RecentRings) -> bytes:
    """A JSON list of frames. Frames a recent read encoded are taken as
    they were (``recent_rings``); the others are encoded on the event loop
    about ``HISTORY_STEP_BYTES`` of JSON at a time, so it runs whatever else
    is due between two steps; a large answer's bytes are joined in a worker
    thread, since copying megabytes into fresh memory takes milliseconds
    (~1 ms per MB here, page faults included) and ``bytes.join`` lets go of
    the interpreter while it copies from ``JOIN_IN_THREAD_BYTES`` on."""
    slots = history.window_slots(seconds, max_points)
    if not len(slots):
        return b"[]"
    capacity = history.capacity
    ring = recent_rings.get(history, wanted)
    texts, missing = ring.kept(slots)
    step, done = 8, 0
    while done < len(missing):
        await asyncio.sleep(0)  # first after the framework's own work on the request, then between two steps
        if history.capacity != capacity:  # a new sensor shrank the ring meanwhile: the slots mean other frames
            raise HTTPException(503, "the history was resized while it was read (a sensor appeared); retry",
                                headers={"Retry-After": "1"})
        chunk = missing[done:done + step]
        encoded = ring.encode(slots[chunk])
        for i, text in zip(chunk.tolist(), encoded):
            texts[i] = text
        done += len(chunk)
        step = max(1, HISTORY_STEP_BYTES * len(chunk) // sum(map(len, encoded)))  # frames of this size per step
    texts[0] = b"[" + texts[0]
    texts[-1] += b"]"
    if len(texts) * len(texts[-1]) < JOIN_IN_THREAD_BYTES:  # frames of one sensor are of about one size
        return b",".join(texts)
    return await asyncio.to_thread(b",".join, texts)


class RecentReads:
    """Answers of heavy reads kept ``max_age_s``, so that many clients
    polling the same window share one encoding (thread-safe)."""

    def __init__(self, max_age_s: float = 0.2, clock=time.monotonic) -> None:
        self.max_age_s = max_age_s
        self._clock = clock
        self._answers: dict[tuple, tuple[float, bytes]] = {}
        self._lock = threading.Lock()

    def get(self, key: tuple) -> bytes | None:
        with self._lock:
            kept = self._answers.get(key)
        return kept[1] if kept is not None and self._clock() - kept[0] <= self.max_age_s else None

    def put(self, key: tuple, body: bytes) -> None:
        now = self._clock()
        with self._lock:
            self._answers = {k: v for k, v in self._answers.items() if now - v[0] <= self.max_age_s}
            self._answers[key] = (now, body)

"""The /ws stream: one ``StreamSession`` per WebSocket client.

A session subscribes its client to the service's hub, then runs two loops
until either ends: the sender takes the client's next message from its
queue and sends it; the receiver waits for the client to leave (noticed even
when nothing is being sent to it, a subscription that matches no frame).
Whichever ends first cancels the other, and the subscription is removed from
the hub whatever happened.

At most MAX_STREAM_CLIENTS stream at once. Reads need no token, so on a
service reachable from the LAN anyone could hold every place and lock out a
controller that reconnects: when the service has a token, a client that
presents it (``Authorization: Bearer``, as the Python client sends it) is
let in past the cap by closing the anonymous client that came last (1013,
try again later), so a place is always there for those with the token.
"""
from __future__ import annotations

import hmac
import time
from typing import TYPE_CHECKING

import anyio
import orjson
from fastapi import APIRouter, WebSocket, WebSocketDisconnect

from ..fanout.hub import Subscriber
from .deps import get_service, parse_fields, parse_positive, parse_sensors

if TYPE_CHECKING:
    from collections.abc import Awaitable, Callable

    from anyio.abc import TaskGroup
    from starlette.datastructures import QueryParams

    from ..live_service import TactileService

MAX_WS_RATE_HZ = 5000.0
MAX_BATCH_MS = 1000.0
# Every client costs the loop its encodings and sends: past this many (the load test runs 26), one more is
# refused rather than slowing every controller's stream (a page could open sockets without end).
MAX_STREAM_CLIENTS = 64

router = APIRouter()


STREAM_PARAMS = ("sensors", "fields", "encoding", "max_rate", "batch_ms")


def subscription(params: QueryParams) -> Subscriber:
    """The client's subscription from its query; ValueError names a bad
    parameter: an unknown one (a typo, ``max_rte=100``, gave the full rate),
    one given twice (the last was taken) or empty (the default was)."""
    unknown = sorted(set(params) - set(STREAM_PARAMS))
    if unknown:
        raise ValueError(f"unknown parameter {unknown[0]!r}; known: {', '.join(STREAM_PARAMS)}")
    for name in STREAM_PARAMS:
        given = params.getlist(name)
        if len(given) > 1:
            raise ValueError(f"{name} given {len(given)} times: give it once"
                             + (" (sensors=0,1 lists several)" if name == "sensors" else ""))
        if given == [""]:
            raise ValueError(f"{name}= is empty: leave it out for its default")
    encoding = params.get("encoding", "json")
    if encoding not in ("json", "binary"):
        raise ValueError(f"encoding={encoding!r} must be 'json' or 'binary'")
    return Subscriber(
        sensors=parse_sensors(params.get("sensors")),
        fields=parse_fields(params.get("fields")),
        binary=encoding == "binary",
        max_rate_hz=parse_positive("max_rate", params.get("max_rate"), MAX_WS_RATE_HZ),
        batch_ms=parse_positive("batch_ms", params.get("batch_ms"), MAX_BATCH_MS),
    )


class StreamSession:
    """One WebSocket client, from accept to the removal of its subscription."""

    def __init__(self, websocket: WebSocket, service: TactileService) -> None:
        self.websocket = websocket
        self.service = service
        self.subscriber: Subscriber | None = None
        self.ended_by: str | None = None  # "sender" or "receiver": the loop that ended first, or "evicted"
        self.holds_token = _holds_token(websocket)
        self._group: TaskGroup | None = None

    async def run(self) -> None:
        await self.websocket.accept()
        sessions: list[StreamSession] = self.websocket.app.state.stream_sessions
        if len(self.service.hub.subscribers) >= MAX_STREAM_CLIENTS and not self._make_room(sessions):
            await self.reject(f"too many stream clients ({MAX_STREAM_CLIENTS}): try again when one has left"
                              + (" (a client with the service's token is always let in)"
                                 if self.websocket.app.state.token is not None else ""), code=1013)
            return
        try:
            self.subscriber = subscription(self.websocket.query_params)
        except ValueError as exc:
            await self.reject(str(exc))
            return
        await self.tell_unknown_sensors()
        self.service.hub.add(self.subscriber)
        sessions.append(self)
        try:
            async with anyio.create_task_group() as group:
                self._group = group
                group.start_soon(self._until_either_ends, group, "sender", self.send_forever)
                group.start_soon(self._until_either_ends, group, "receiver", self.receive_until_disconnected)
        finally:
            sessions.remove(self)
            self.service.hub.remove(self.subscriber)
        if self.ended_by == "evicted":
            with anyio.move_on_after(1.0):
                try:
                    await self.reject("closed to make room for a client with the service's token: try again later",
                                      code=1013)
                except (WebSocketDisconnect, RuntimeError):  # it had gone already
                    pass

    def _make_room(self, sessions: list[StreamSession]) -> bool:
        """For a client with the token, close the anonymous one that came
        last (its place is free once it has left the hub); whether one was."""
        if not self.holds_token:
            return False
        anonymous = [s for s in sessions if not s.holds_token and s.ended_by is None and s._group is not None]
        if not anonymous:
            return False
        last = anonymous[-1]
        last.ended_by = "evicted"
        last._group.cancel_scope.cancel()
        self.service.hub.remove(last.subscriber)
        return True

    async def tell_unknown_sensors(self) -> None:
        """Sensors asked for that the board has not announced: a notice, not a
        refusal (a board that connects later may announce them)."""
        boards = self.service.all_boards
        ids = {sid for board in boards for sid in board.sensors}
        addresses = {(board.name, sid) for board in boards for sid in board.sensors}
        unknown = sorted((f"{s[0]}/{s[1]}" if isinstance(s, tuple) else str(s))
                         for s in self.subscriber.sensors or () if s not in ids and s not in addresses)
        if unknown:
            known = sorted(str(sid) for sid in ids) if len(boards) == 1 else sorted(f"{b}/{s}" for b, s in addresses)
            detail = f"sensors {', '.join(unknown)} are not known (yet); known: {', '.join(known) or 'none yet'}"
            await self.websocket.send_text(orjson.dumps({"type": "notice", "detail": detail}).decode())

    async def reject(self, detail: str, code: int = 1008) -> None:
        await self.websocket.send_text(orjson.dumps({"type": "error", "detail": detail}).decode())
        await self.websocket.close(code=code, reason=detail[:120])

    async def send_forever(self) -> None:
        subscriber, websocket, service = self.subscriber, self.websocket, self.service
        while True:
            message, notice, oldest_stamp = await subscriber.next_message()
            if subscriber.batch_ms is not None:
                await service.let_urgent_go_first()
            if notice is not None:
                await websocket.send_text(notice.decode())
            if subscriber.binary:
                await websocket.send_bytes(message)
            else:
                await websocket.send_text(message.decode())
            service.hub.sent(subscriber, time.time(), oldest_stamp)

    async def receive_until_disconnected(self) -> None:
        # The client's leaving is noticed here even when nothing is being sent
        # to it (a subscription that matches no frame); what it sends is ignored.
        while (await self.websocket.receive())["type"] != "websocket.disconnect":
            pass

    async def _until_either_ends(self, group: TaskGroup, name: str, run: Callable[[], Awaitable[None]]) -> None:
        try:
            await run()
        except (WebSocketDisconnect, RuntimeError):  # the client went away mid-send
            pass
        if self.ended_by is None:
            self.ended_by = name
        group.cancel_scope.cancel()


def _holds_token(websocket: WebSocket) -> bool:
    """Whether the client presented the service's token (none set: no one does)."""
    token = websocket.app.state.token
    given = (websocket.headers.get("authorization") or "").encode("utf-8", "surrogateescape")
    return token is not None and hmac.compare_digest(given, f"Bearer {token}".encode())


@router.websocket("/ws")
async def stream(websocket: WebSocket) -> None:
    """Query: sensors=0,1 or left/0,right/1 · fields=force,raw,contact,flags · max_rate=Hz ·
    batch_ms=ms · encoding=json|binary."""
    await StreamSession(websocket, await get_service(websocket)).run()

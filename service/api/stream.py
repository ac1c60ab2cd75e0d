"""WebSocket fan-out: encode each frame once, bounded queue per client.

The readout thread hands batches to the event loop with
``call_soon_threadsafe``; ``Hub.publish`` then runs on the loop. Each frame is
serialised once per batch however many clients take it; a client's message
is those bytes joined. A client whose queue is full loses its own oldest
message (never blocking the pipeline or other clients) and the next message
it receives says how many frames it lost.
"""
from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import orjson

from ..reconstruct import ForceFrame

QUEUE_MESSAGES = 64
_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


@dataclass(eq=False)
class Subscriber:
    """One WebSocket client. ``sensors`` None means all; ``max_rate_hz`` None
    means every frame."""

    sensors: frozenset[int] | None = None
    max_rate_hz: float | None = None
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(QUEUE_MESSAGES))
    dropped_frames: int = 0
    _next_due: dict[int, float] = field(default_factory=dict)
    _queued_counts: list[int] = field(default_factory=list)

    def wants(self, frame: ForceFrame) -> bool:
        sid = frame.sensor.id
        if self.sensors is not None and sid not in self.sensors:
            return False
        if self.max_rate_hz is None:
            return True
        due = self._next_due.get(sid, 0.0)
        if frame.t_host < due:
            return False
        period = 1.0 / self.max_rate_hz
        # Keep the phase while on time; restart it after a pause.
        self._next_due[sid] = due + period if frame.t_host < due + period else frame.t_host + period
        return True

    def offer(self, message: bytes, frame_count: int) -> None:
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped_frames += self._queued_counts.pop(0)
        self.queue.put_nowait(message)
        self._queued_counts.append(frame_count)

    async def next_message(self) -> bytes:
        message = await self.queue.get()
        self._queued_counts.pop(0)
        if self.dropped_frames:
            dropped, self.dropped_frames = self.dropped_frames, 0
            message = message[:-1] + b',"dropped":' + str(dropped).encode() + b"}"
        return message


class Hub:
    def __init__(self) -> None:
        self.subscribers: set[Subscriber] = set()
        self.frames_published = 0

    def publish(self, frames: list[ForceFrame]) -> None:
        self.frames_published += len(frames)
        if not self.subscribers:
            return
        encoded: dict[int, bytes] = {}
        for subscriber in self.subscribers:
            parts = []
            for i, frame in enumerate(frames):
                if subscriber.wants(frame):
                    part = encoded.get(i)
                    if part is None:
                        part = encoded[i] = orjson.dumps(frame.stream_dict(), option=_JSON_OPTIONS)
                    parts.append(part)
            if parts:
                subscriber.offer(b'{"type":"frames","frames":[' + b",".join(parts) + b"]}", len(parts))

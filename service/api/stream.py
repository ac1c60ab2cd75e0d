"""WebSocket fan-out: encode each frame once, bounded queue per client.

The readout thread hands batches to the event loop with
``call_soon_threadsafe``; ``Hub.publish`` then runs on the loop. A frame is
serialised once per (fields, encoding) however many clients take it; a
client's message is those parts joined. A client may decimate
(``max_rate_hz`` per sensor) or batch (``batch_ms``: frames are held and sent
together once the interval has passed). A client whose queue is full loses
its own oldest message — never blocking the pipeline or other clients — and
is told how many frames it lost.
"""
from __future__ import annotations

import asyncio
import struct
from dataclasses import dataclass, field

import orjson

from ..reconstruct import ForceFrame
from .messages import DEFAULT_FIELDS, to_binary, to_json_dict

QUEUE_MESSAGES = 64
_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


@dataclass(eq=False)
class Subscriber:
    """One WebSocket client. ``sensors`` None means all."""

    sensors: frozenset[int] | None = None
    fields: frozenset[str] = DEFAULT_FIELDS
    binary: bool = False
    max_rate_hz: float | None = None
    batch_ms: float | None = None
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(QUEUE_MESSAGES))
    dropped_frames: int = 0
    _next_due: dict[int, float] = field(default_factory=dict)
    _queued_counts: list[int] = field(default_factory=list)
    _batch: list[bytes] = field(default_factory=list)
    _batch_started: float | None = None

    @property
    def key(self) -> tuple[frozenset[str], bool]:
        return self.fields, self.binary

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

    def take(self, parts: list[bytes], now: float) -> None:
        """Queue ``parts`` (encoded frames), now or, when batching, once the
        batch interval has passed."""
        if self.batch_ms is None:
            self._offer(parts)
            return
        if self._batch_started is None:
            self._batch_started = now
        self._batch.extend(parts)
        if (now - self._batch_started) * 1000.0 >= self.batch_ms:
            self._offer(self._batch)
            self._batch, self._batch_started = [], None

    def _offer(self, parts: list[bytes]) -> None:
        if not parts:
            return
        if self.binary:
            message = struct.pack("<H", len(parts)) + b"".join(parts)
        else:
            message = b'{"type":"frames","frames":[' + b",".join(parts) + b"]}"
        if self.queue.full():
            self.queue.get_nowait()
            self.dropped_frames += self._queued_counts.pop(0)
        self.queue.put_nowait(message)
        self._queued_counts.append(len(parts))

    async def next_message(self) -> tuple[bytes, bytes | None]:
        """The next message, and a JSON notice of frames lost before it (or None)."""
        message = await self.queue.get()
        self._queued_counts.pop(0)
        notice = None
        if self.dropped_frames:
            notice = orjson.dumps({"type": "dropped", "frames": self.dropped_frames})
            self.dropped_frames = 0
        return message, notice


class Hub:
    def __init__(self) -> None:
        self.subscribers: set[Subscriber] = set()
        self.frames_published = 0

    def publish(self, frames: list[ForceFrame]) -> None:
        self.frames_published += len(frames)
        if not self.subscribers:
            return
        encoded: dict[tuple, bytes] = {}
        now = frames[-1].t_host
        for subscriber in self.subscribers:
            parts = []
            everything = subscriber.sensors is None and subscriber.max_rate_hz is None
            for i, frame in enumerate(frames):
                if everything or subscriber.wants(frame):
                    key = (i, subscriber.key)
                    part = encoded.get(key)
                    if part is None:
                        if subscriber.binary:
                            part = to_binary(frame, subscriber.fields)
                        else:
                            part = orjson.dumps(to_json_dict(frame, subscriber.fields), option=_JSON_OPTIONS)
                        encoded[key] = part
                    parts.append(part)
            subscriber.take(parts, now)

"""Fan-out to stream clients: bounded queue per client, each frame encoded once.

``Hub.publish`` runs on the event loop with each reconstructed batch, wraps
each frame once in an ``Outgoing`` and queues references to those each
client wants. A frame is serialised when a client's message is sent — once
per (fields, encoding), cached on its ``Outgoing``, however many clients take
it — so frames a stalled client drops cost nothing. A client may decimate (``max_rate_hz`` per sensor: the
flags of the frames it skips come with the next frame it is sent) or batch
(``batch_ms``: frames are held and sent together, at most that long after the
oldest of them was received). A client whose queue is full loses its own
oldest message — never blocking the pipeline or other clients — and is told
how many frames it lost; a client that fell behind gets what is queued for it
in one message.
"""
from __future__ import annotations

import asyncio
import dataclasses
import struct
import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import orjson

from ..latency import LatencyMeter
from ..reconstruct import ForceFrame
from .encoding import DEFAULT_FIELDS, to_binary, to_json_dict

QUEUE_MESSAGES = 64
# At most this many frames in a merged message: the frames of a message are
# encoded in one go on the loop (~40 µs for an 8x8 grid in JSON), so a larger
# merge would hold up the other clients' frames (256 gave 18 ms spikes).
MERGE_FRAMES = 32
CLIENT_WINDOW_SAMPLES = 2_000  # 2 s of an unbatched 1 kHz client, 10 s of 5 ms batches
_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY
_UNSET = object()


class Outgoing:
    """A published frame as every client's queue holds it, with its
    serialised forms by (fields, binary), filled on first send."""

    __slots__ = ("frame", "parts", "_flag_key")

    def __init__(self, frame: ForceFrame) -> None:
        self.frame = frame
        self.parts: dict[tuple[frozenset[str], bool], bytes] | None = None
        self._flag_key: tuple[tuple[str, ...], bytes] | None | object = _UNSET

    def flag_key(self) -> tuple[tuple[str, ...], bytes] | None:
        """(frame flags, per-taxel bits as bytes), or None when the frame has
        no flag: found once, however many decimating clients skip the frame."""
        key = self._flag_key
        if key is _UNSET:
            frame = self.frame
            bits = frame.taxel_flags
            taxel = bits.tobytes() if bits is not None and np.count_nonzero(bits) else b""
            key = self._flag_key = (tuple(frame.flags), taxel) if frame.flags or taxel else None
        return key

    def encoded(self, fields: frozenset[str], binary: bool) -> bytes:
        parts = self.parts
        if parts is None:
            parts = self.parts = {}
        key = (fields, binary)
        part = parts.get(key)
        if part is None:
            if binary:
                part = to_binary(self.frame, fields)
            else:
                part = orjson.dumps(to_json_dict(self.frame, fields), option=_JSON_OPTIONS)
            parts[key] = part
        return part


class CarriedFlags:
    """The quality flags of frames of one sensor a decimating client skipped,
    for the next frame it is sent: a 10 ms saturation or one lost frame
    between two frames of a 30 Hz stream is otherwise never seen.
    ``flags``: frame flags, in the order first seen; ``taxel_flags``: (n,)
    uint8 per-taxel bits OR-ed, None while no skipped frame had one."""

    __slots__ = ("flags", "taxel_flags", "_last")

    def __init__(self) -> None:
        self.flags: dict[str, None] = {}
        self.taxel_flags: np.ndarray | None = None
        self._last: tuple | None = None

    def add(self, item: Outgoing, key: tuple[tuple[str, ...], bytes]) -> None:
        """Join ``item``'s flags (``key``: its ``flag_key()``)."""
        if key == self._last:  # a flag held frame after frame: joined already
            return
        self._last = key
        frame = item.frame
        self.flags.update(dict.fromkeys(frame.flags))
        bits = frame.taxel_flags
        if not key[1]:
            return
        if self.taxel_flags is None or self.taxel_flags.shape != bits.shape:
            self.taxel_flags = bits.copy()  # a sensor that changed shape: the old indices name no taxel now
        else:
            self.taxel_flags |= bits

    def onto(self, item: Outgoing) -> Outgoing:
        """``item``, or — when these flags add to its own — a copy of its
        frame with them joined (forces, σ and all else its own), encoded
        for this client alone. Taxel bits of another shape are left out."""
        frame = item.frame
        extra = [name for name in self.flags if name not in frame.flags]
        own, carried = frame.taxel_flags, self.taxel_flags
        if carried is not None and carried.shape != frame.forces_N.shape:
            carried = None
        if carried is not None and own is not None:
            carried = None if not np.count_nonzero(carried & ~own) else carried | own
        if not extra and carried is None:
            return item
        joined = dataclasses.replace(frame, flags=frame.flags + extra, taxel_flags=own if carried is None else carried)
        joined.keep_contact(frame.contact)  # the same forces: the same summary
        return Outgoing(joined)


@dataclass(eq=False)
class Subscriber:
    """One WebSocket client. ``sensors``: ids (that sensor on any board) and
    (board, id) addresses; None means all."""

    sensors: frozenset | None = None
    fields: frozenset[str] = DEFAULT_FIELDS
    binary: bool = False
    max_rate_hz: float | None = None
    batch_ms: float | None = None
    pending: deque[list[Outgoing]] = field(default_factory=deque)  # messages not yet taken, oldest first
    dropped_frames: int = 0  # since the last notice
    dropped_total: int = 0
    # Receive stamp → handed to this client's socket, per message (its oldest frame).
    latency: LatencyMeter = field(default_factory=lambda: LatencyMeter(CLIENT_WINDOW_SAMPLES))
    _next_due: dict[tuple[str, int], float] = field(default_factory=dict)
    _carried: dict[tuple[str, int], CarriedFlags] = field(default_factory=dict)  # per (board, sensor id)
    _batch: list[Outgoing] = field(default_factory=list)
    _flush_timer: asyncio.TimerHandle | None = None
    _wakeup: asyncio.Future | None = None  # set while its sender waits for a message

    @property
    def woken(self) -> bool:
        """A message came while its sender waited, and the sender has not run yet."""
        return self._wakeup is not None and self._wakeup.done()

    def chosen(self, item: Outgoing) -> Outgoing | None:
        """``item`` as this client is sent it, or None: another sensor's, or
        skipped by ``max_rate_hz`` — its flags then come with the next frame
        of its sensor this client is sent (``CarriedFlags``)."""
        frame = item.frame
        info = frame.sensor
        sid = info.id
        if self.sensors is not None and sid not in self.sensors and (info.board, sid) not in self.sensors:
            return None
        if self.max_rate_hz is None:
            return item
        sid = (info.board, sid)
        due = self._next_due.get(sid, 0.0)
        if frame.t_host < due:
            key = item.flag_key()
            if key is not None:
                carried = self._carried.get(sid)
                if carried is None:
                    carried = self._carried[sid] = CarriedFlags()
                carried.add(item, key)
            return None
        period = 1.0 / self.max_rate_hz
        # Keep the phase while on time; restart it after a pause.
        self._next_due[sid] = due + period if frame.t_host < due + period else frame.t_host + period
        carried = self._carried.pop(sid, None)
        return item if carried is None else carried.onto(item)

    def take(self, frames: list[Outgoing]) -> None:
        """Queue ``frames``, now or, when batching, in the batch that is sent
        ``batch_ms`` after its oldest frame was received: a batched frame
        waits at most ``batch_ms``, whenever the next frames come."""
        if self.batch_ms is None:
            self._offer(frames)
            return
        if not frames:
            return
        if not self._batch:
            delay = frames[0].frame.t_host + self.batch_ms / 1000.0 - time.time()
            self._flush_timer = asyncio.get_running_loop().call_later(max(delay, 0.0), self._flush)
        self._batch.extend(frames)

    def describe(self) -> dict:
        """What this client asked for and how it is served (GET /clients)."""
        return {
            "sensors": None if self.sensors is None else sorted(
                (f"{s[0]}/{s[1]}" if isinstance(s, tuple) else s for s in self.sensors), key=str),
            "fields": sorted(self.fields),
            "encoding": "binary" if self.binary else "json",
            "max_rate_hz": self.max_rate_hz,
            "batch_ms": self.batch_ms,
            "queued_messages": len(self.pending),
            "dropped_frames": self.dropped_total,
            "latency": self.latency.summary(),
        }

    def close(self) -> None:
        if self._flush_timer is not None:
            self._flush_timer.cancel()

    def _flush(self) -> None:
        """The batch, as messages of at most ``MERGE_FRAMES`` frames: a
        message is encoded in one go on the loop."""
        batch, self._batch, self._flush_timer = self._batch, [], None
        for start in range(0, len(batch), MERGE_FRAMES):
            self._offer(batch[start:start + MERGE_FRAMES])

    def _offer(self, frames: list[Outgoing]) -> None:
        if not frames:
            return
        if len(self.pending) >= QUEUE_MESSAGES:
            lost = len(self.pending.popleft())
            self.dropped_frames += lost
            self.dropped_total += lost
        self.pending.append(frames)
        if self._wakeup is not None and not self._wakeup.done():
            self._wakeup.set_result(None)

    async def next_message(self) -> tuple[bytes, bytes | None, float]:
        """The next message, a JSON notice of frames lost before it (or None),
        and the receive stamp of its oldest frame. A client that fell behind
        gets what is queued for it in one message (up to ``MERGE_FRAMES``):
        those frames wait already, and one send costs less than several, so
        it catches up sooner and the loop has more time for everyone else."""
        if not self.pending:
            self._wakeup = asyncio.get_running_loop().create_future()
            try:
                await self._wakeup
            finally:
                self._wakeup = None
        frames = self.pending.popleft()
        if self.pending and len(frames) + len(self.pending[0]) <= MERGE_FRAMES:
            frames = list(frames)  # the hub offers one list to every client that takes all frames
            while self.pending and len(frames) + len(self.pending[0]) <= MERGE_FRAMES:
                frames.extend(self.pending.popleft())
        notice = None
        if self.dropped_frames:
            notice = orjson.dumps({"type": "dropped", "frames": self.dropped_frames})
            self.dropped_frames = 0
        fields, binary = self.fields, self.binary
        parts = [item.encoded(fields, binary) for item in frames]
        oldest = frames[0].frame.t_host
        if self.binary:
            return struct.pack("<H", len(parts)) + b"".join(parts), notice, oldest
        return b'{"type":"frames","frames":[' + b",".join(parts) + b"]}", notice, oldest


class Hub:
    def __init__(self) -> None:
        self.subscribers: list[Subscriber] = []
        self.frames_published = 0
        # Receive stamp → handed to the client's socket, per kind of client
        # (a batched frame also waits for its batch, by request).
        self.sent_latency = {"unbatched": LatencyMeter(), "batched": LatencyMeter()}

    def sent(self, subscriber: Subscriber, now: float, oldest_stamp: float) -> None:
        latency = now - oldest_stamp
        self.sent_latency["unbatched" if subscriber.batch_ms is None else "batched"].add(latency)
        subscriber.latency.add(latency)

    def add(self, subscriber: Subscriber) -> None:
        # Unbatched clients first: their senders wake first after each batch,
        # so a latency-critical client does not wait behind batched ones.
        self.subscribers.append(subscriber)
        self.subscribers.sort(key=lambda s: s.batch_ms is not None)

    def unbatched_due(self) -> bool:
        """Whether an unbatched client has a message its sender has not yet
        taken: batched senders let it go first."""
        for subscriber in self.subscribers:
            if subscriber.batch_ms is not None:
                return False  # unbatched clients come first in the list
            if subscriber.woken:
                return True
        return False

    def remove(self, subscriber: Subscriber) -> None:
        subscriber.close()
        if subscriber in self.subscribers:
            self.subscribers.remove(subscriber)

    def publish(self, frames: list[ForceFrame]) -> None:
        self.frames_published += len(frames)
        if not frames or not self.subscribers:
            return
        items = list(map(Outgoing, frames))  # one list, shared by every client that takes all
        for subscriber in self.subscribers:
            if subscriber.sensors is None and subscriber.max_rate_hz is None:
                subscriber.take(items)
            else:
                subscriber.take([taken for item in items if (taken := subscriber.chosen(item)) is not None])

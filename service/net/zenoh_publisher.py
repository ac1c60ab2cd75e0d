"""The service on Zenoh: a pipeline listener that publishes every frame, the
health document once per second, and answers queries for the latest frames.

``ZenohPublisher(config)`` opens the session (a listen port in use fails
here, before the service starts); ``attach(service)`` makes it listen to
the service's pipeline; ``close()`` detaches and closes the session.

A put costs ~20 µs (p99 ~100 µs) on loopback, too much for the pipeline's
thread at 2 000 frames/s: that thread only appends the frames to a bounded
queue (the oldest are dropped and counted when it is full) and a sender
thread encodes and puts them. The sender puts a sensor's frames that are
queued together in one sample (up to ``MAX_RECORDS`` records), so nothing
waits for a batch, and a late sender catches up with fewer puts. QoS and
keys: docs/scale.md.
"""
from __future__ import annotations

import logging
import struct
import threading
import time
from collections import deque

import orjson
import zenoh

from ..fanout.encoding import DEFAULT_FIELDS, to_binary
from ..latency import LatencyMeter
from .zenoh_config import board_key, frame_key, health_key, latest_key, open_session, sensors_key

log = logging.getLogger(__name__)

QUEUE_FRAMES = 2048  # ~1 s of a grid and a quad at 1 kHz
MAX_RECORDS = 32  # per sample, as a WebSocket client's catch-up message
HEALTH_PERIOD_S = 1.0


def encode(frames) -> bytes:
    """One sample: the u16 record count and the frames' binary records, as
    a WebSocket binary message (docs/api.md)."""
    return struct.pack("<H", len(frames)) + b"".join(to_binary(frame, DEFAULT_FIELDS) for frame in frames)


class FrameQueue:
    """Frames from the pipeline's thread to the sender: ``push`` never
    blocks; beyond ``capacity`` the oldest frames are dropped and counted."""

    def __init__(self, capacity: int = QUEUE_FRAMES) -> None:
        self.capacity = capacity
        self.dropped = 0
        self._frames: deque = deque()
        self._lock = threading.Lock()
        self._ready = threading.Event()

    def push(self, frames) -> None:
        with self._lock:
            self._frames.extend(frames)
            excess = len(self._frames) - self.capacity
            for _ in range(excess):
                self._frames.popleft()
            if excess > 0:
                self.dropped += excess
        self._ready.set()

    def wake(self) -> None:
        self._ready.set()

    def take(self, timeout: float | None = None) -> list:
        """Everything queued, oldest first (waiting up to ``timeout`` for it)."""
        self._ready.wait(timeout)
        self._ready.clear()
        with self._lock:
            frames, self._frames = self._frames, deque()
        return list(frames)

    def __len__(self) -> int:
        return len(self._frames)


class ZenohPublisher:
    """Publishes one service's frames and health; answers its latest frames.

    ``board_name`` (``--board-name``) fixes the board's key; without it the
    key follows the board's INFO (board_key)."""

    def __init__(self, config: zenoh.Config, board_name: str | None = None, queue_frames: int = QUEUE_FRAMES,
                 health_period_s: float = HEALTH_PERIOD_S) -> None:
        self.session = open_session(config)
        self.board_name = board_name
        self.health_period_s = health_period_s
        self.queue = FrameQueue(queue_frames)
        self.sent_latency = LatencyMeter()  # receive stamp → put on the session, per sample (its oldest frame)
        self.frames_published = 0
        self.samples_published = 0
        self.health_published = 0
        self.put_errors = 0
        self.board: str | None = None  # the board's key chunk in use
        self._service = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._queryables: list = []
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []

    def attach(self, service) -> "ZenohPublisher":
        """Listen to ``service``'s pipeline (a live_service.TactileService)
        and start the sender and health threads."""
        self._service = service
        pipeline = service.pipeline
        # A new list, not an append: the pipeline may be iterating the old one.
        pipeline.listeners = [*pipeline.listeners, self.on_frames]
        self._use_board(self._board_key())
        self._threads = [threading.Thread(target=self._send_loop, name="tactile-zenoh-send", daemon=True),
                         threading.Thread(target=self._health_loop, name="tactile-zenoh-health", daemon=True)]
        for thread in self._threads:
            thread.start()
        return self

    def on_frames(self, frames: list) -> None:
        """The pipeline's listener: queue the frames, never block."""
        self.queue.push(frames)

    def close(self, timeout: float = 2.0) -> None:
        """Detach, stop the threads, send what is queued, close the session."""
        service, self._service = self._service, None
        if service is not None:
            service.pipeline.listeners = [f for f in service.pipeline.listeners if f != self.on_frames]
        self._closing.set()
        self.queue.wake()
        for thread in self._threads:
            thread.join(timeout)
        self.session.close()

    def status(self) -> dict:
        """What /health shows under "zenoh"."""
        info = self.session.info
        return {
            "board": self.board,
            "zid": str(info.zid()),
            "peers": len(info.peers_zid()),
            "routers": len(info.routers_zid()),
            "frames_published": self.frames_published,
            "frames_dropped": self.queue.dropped,
            "samples_published": self.samples_published,
            "queued_frames": len(self.queue),
            "put_errors": self.put_errors,
            "health_published": self.health_published,
            "latency": self.sent_latency.summary(),
        }

    def _board_key(self) -> str:
        service = self._service
        return board_key(service.pipeline.interpreter.board if service is not None else {}, self.board_name)

    def _use_board(self, board: str) -> None:
        """Answer queries under ``board``'s keys (again, if INFO renamed it)."""
        if board == self.board:
            return
        for entity in [*self._queryables, *self._publishers.values()]:
            entity.undeclare()
        self._publishers.clear()
        self.board = board
        self._queryables = [self.session.declare_queryable(latest_key(board, "*"), self._answer_latest),
                            self.session.declare_queryable(sensors_key(board), self._answer_sensors)]

    def _publisher(self, sensor: int) -> zenoh.Publisher:
        key = frame_key(self.board, sensor)
        publisher = self._publishers.get(key)
        if publisher is None:
            publisher = self._publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.DROP, priority=zenoh.Priority.REAL_TIME,
                express=False, reliability=zenoh.Reliability.BEST_EFFORT)
        return publisher

    def _send_loop(self) -> None:
        """Until closed and nothing is left to send."""
        while True:
            frames = self.queue.take()
            if frames:
                self._use_board(self._board_key())
                self._send(frames)
            if self._closing.is_set() and not len(self.queue):
                return

    def _send(self, frames: list) -> None:
        by_sensor: dict[int, list] = {}
        for frame in frames:
            by_sensor.setdefault(frame.sensor.id, []).append(frame)
        for sensor, group in by_sensor.items():
            for start in range(0, len(group), MAX_RECORDS):
                sample = group[start:start + MAX_RECORDS]
                try:
                    self._publisher(sensor).put(encode(sample))
                except zenoh.ZError as exc:
                    self.put_errors += 1
                    if self.put_errors == 1:
                        log.warning("zenoh put of sensor %d's frames failed: %s", sensor, exc)
                    continue
                self.sent_latency.add(time.time() - sample[0].t_host)
                self.frames_published += len(sample)
                self.samples_published += 1

    def _health_loop(self) -> None:
        """Now, then every period until closed."""
        publisher, key = None, None
        while not self._closing.is_set():
            service = self._service
            if service is None:
                return
            if health_key(self.board) != key:
                if publisher is not None:
                    publisher.undeclare()
                key = health_key(self.board)
                publisher = self.session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                                           priority=zenoh.Priority.DATA,
                                                           reliability=zenoh.Reliability.RELIABLE)
            publisher.put(orjson.dumps(service.health(), option=orjson.OPT_SERIALIZE_NUMPY))
            self.health_published += 1
            self._closing.wait(self.health_period_s)

    def _answer_latest(self, query: zenoh.Query) -> None:
        service, board = self._service, self.board
        if service is None or board is None:
            return
        for sensor, frame in list(service.pipeline.latest.items()):
            key = latest_key(board, sensor)
            if query.key_expr.intersects(key):
                query.reply(key, encode([frame]))

    def _answer_sensors(self, query: zenoh.Query) -> None:
        service, board = self._service, self.board
        if service is None or board is None:
            return
        interpreter = service.pipeline.interpreter
        document = {"board": board, "info": {k: v for k, v in interpreter.board.items() if k != "sensors"},
                    "sensors": [{"id": s.id, "kind": s.kind, "rows": s.rows, "cols": s.cols}
                                for s in sorted(interpreter.sensors.values(), key=lambda s: s.id)]}
        query.reply(sensors_key(board), orjson.dumps(document))

"""The service on Zenoh: a pipeline listener that publishes every frame, the
health document once per second, and answers queries for the latest frames.

``ZenohPublisher(config)`` opens the session (a listen port in use fails
here, before the service starts); ``attach(service)`` makes it listen to
every board's pipeline; ``close()`` detaches and closes the session.

A put costs ~20 µs (p99 ~100 µs) on loopback, too much for the pipeline's
thread at 2 000 frames/s: that thread only appends the frames to a bounded
queue (the oldest are dropped and counted when it is full) and a sender
thread encodes and puts them. The sender puts a sensor's frames that are
queued together in one sample (up to ``MAX_RECORDS`` records), so nothing
waits for a batch, and a late sender catches up with fewer puts. Every
sample's attachment is the process's instance id (zenoh_config.instance_id),
which its liveliness tokens and sensors documents name too. QoS and keys:
docs/scale.md.
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
from .zenoh_config import (PREFIX, alive_key, frame_key, health_key, instance_id, latest_key, open_session,
                           sensors_key)

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
    """Publishes a service's frames and health, per board under
    ``tactile/<board>/``; answers each board's latest frames and sensors;
    holds a liveliness token per board while the session lives."""

    def __init__(self, config: zenoh.Config, queue_frames: int = QUEUE_FRAMES,
                 health_period_s: float = HEALTH_PERIOD_S) -> None:
        self.session = open_session(config)
        self.instance = instance_id()
        self._attachment = zenoh.ZBytes(self.instance.encode())
        self.health_period_s = health_period_s
        self.queue = FrameQueue(queue_frames)
        self.sent_latency = LatencyMeter()  # receive stamp → put on the session, per sample (its oldest frame)
        self.frames_published = 0
        self.samples_published = 0
        self.health_published = 0
        self.put_errors = 0
        self._service = None
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._queryables: dict[str, list] = {}  # board name → its queryables
        self._declared: dict[str, object] = {}  # board name → the board declared under it (whose name may change)
        self._declare_lock = threading.Lock()  # the sender and the health thread both declare
        self._closing = threading.Event()
        self._threads: list[threading.Thread] = []

    @property
    def boards(self) -> list[str]:
        """The boards' key chunks in use."""
        return sorted(self._queryables)

    def attach(self, service) -> "ZenohPublisher":
        """Listen to every board's pipeline of ``service`` (a
        live_service.TactileService) and start the sender and health threads."""
        self._service = service
        for board in service.all_boards:
            # A new list, not an append: the pipeline may be iterating the old one.
            board.pipeline.listeners = [*board.pipeline.listeners, self.on_frames]
        self._declare_boards()
        self._threads = [threading.Thread(target=self._send_loop, name="tactile-zenoh-send", daemon=True),
                         threading.Thread(target=self._health_loop, name="tactile-zenoh-health", daemon=True)]
        for thread in self._threads:
            thread.start()
        return self

    def on_frames(self, frames: list) -> None:
        """A pipeline's listener: queue the frames, never block."""
        self.queue.push(frames)

    def close(self, timeout: float = 2.0) -> None:
        """Detach, stop the threads, send what is queued, close the session."""
        service, self._service = self._service, None
        for board in service.all_boards if service is not None else ():
            board.pipeline.listeners = [f for f in board.pipeline.listeners if f != self.on_frames]
        self._closing.set()
        self.queue.wake()
        for thread in self._threads:
            thread.join(timeout)
        self.session.close()

    def status(self) -> dict:
        """What /health shows under "zenoh"."""
        info = self.session.info
        return {
            "boards": self.boards,
            "instance": self.instance,
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

    def _declare_boards(self) -> None:
        """Queryables under each board's name (again when a board's first
        INFO named it: the provisional name's are undeclared, after a sample
        ``{"renamed_to": NAME}`` under its health key says so — a gateway then
        forgets it at once, where a withdrawn token alone reads as a service lost)."""
        service = self._service
        if service is None:
            return
        names = {board.name: board for board in service.all_boards}
        with self._declare_lock:
            for gone in set(self._queryables) - set(names):
                self._tell_renamed(gone, self._declared.pop(gone).name)
                for entity in self._queryables.pop(gone):
                    entity.undeclare()
                for key in [k for k in list(self._publishers) if k.startswith(f"{PREFIX}/{gone}/")]:
                    self._publishers.pop(key).undeclare()
            for name in set(names) - set(self._queryables):
                board = names[name]
                # The token vanishes for its subscribers the moment this session ends (a crash
                # closes its sockets): a gateway says the board is lost without waiting for health.
                self._declared[name] = board
                self._queryables[name] = [
                    self.session.declare_queryable(latest_key(name, "*"), lambda q, b=board: self._answer_latest(b, q)),
                    self.session.declare_queryable(sensors_key(name), lambda q, b=board: self._answer_sensors(b, q)),
                    self.session.liveliness().declare_token(alive_key(name, self.instance))]

    def _tell_renamed(self, old: str, new: str) -> None:
        document = {"board": old, "renamed_to": new, "instance": self.instance}
        try:
            self.session.put(health_key(old), orjson.dumps(document), attachment=self._attachment,
                             congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA)
        except zenoh.ZError as exc:  # the gateway then reports the old name lost, and forgets it a minute later
            self.put_errors += 1
            log.warning("zenoh: telling that board %s is now %s failed: %s", old, new, exc)

    def _publisher(self, board: str, sensor: int) -> zenoh.Publisher:
        key = frame_key(board, sensor)
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
                if any(frame.sensor.board not in self._queryables for frame in frames):
                    self._declare_boards()
                self._send(frames)
            if self._closing.is_set() and not len(self.queue):
                return

    def _send(self, frames: list) -> None:
        by_sensor: dict[tuple[str, int], list] = {}
        for frame in frames:
            by_sensor.setdefault((frame.sensor.board, frame.sensor.id), []).append(frame)
        for (board, sensor), group in by_sensor.items():
            for start in range(0, len(group), MAX_RECORDS):
                sample = group[start:start + MAX_RECORDS]
                try:
                    self._publisher(board, sensor).put(encode(sample), attachment=self._attachment)
                except zenoh.ZError as exc:
                    self.put_errors += 1
                    if self.put_errors == 1:
                        log.warning("zenoh put of sensor %s/%d's frames failed: %s", board, sensor, exc)
                    continue
                self.sent_latency.add(time.time() - sample[0].t_host)
                self.frames_published += len(sample)
                self.samples_published += 1

    def _health_loop(self) -> None:
        """Each board's health document now, then every period until closed."""
        publishers: dict[str, zenoh.Publisher] = {}
        while not self._closing.is_set():
            service = self._service
            if service is None:
                return
            self._declare_boards()
            report = service.health()
            for name in list(report["boards"]):
                publisher = publishers.get(name)
                if publisher is None:
                    publisher = publishers[name] = self.session.declare_publisher(
                        health_key(name), congestion_control=zenoh.CongestionControl.BLOCK,
                        priority=zenoh.Priority.DATA, reliability=zenoh.Reliability.RELIABLE)
                publisher.put(orjson.dumps(board_document(report, name), option=orjson.OPT_SERIALIZE_NUMPY),
                              attachment=self._attachment)
                self.health_published += 1
            for gone in set(publishers) - set(report["boards"]):
                publishers.pop(gone).undeclare()
            self._closing.wait(self.health_period_s)

    def _answer_latest(self, board, query: zenoh.Query) -> None:
        for sensor, frame in list(board.pipeline.latest.items()):
            key = latest_key(board.name, sensor)
            if query.key_expr.intersects(key):
                query.reply(key, encode([frame]), attachment=self._attachment)

    def _answer_sensors(self, board, query: zenoh.Query) -> None:
        interpreter = board.pipeline.interpreter
        document = {"board": board.name, "instance": self.instance,
                    "info": {k: v for k, v in interpreter.board.items() if k != "sensors"},
                    "sensors": [{"id": s.id, "kind": s.kind, "rows": s.rows, "cols": s.cols}
                                for s in sorted(interpreter.sensors.values(), key=lambda s: s.id)]}
        query.reply(sensors_key(board.name), orjson.dumps(document))


def board_document(report: dict, name: str) -> dict:
    """The service's /health ``report`` as one board's health: that board's
    part (status, problems, link, sensors by id, …) with what the service
    shares (latency, recording, zenoh)."""
    shared = {k: v for k, v in report.items() if k not in ("boards", "sensors", "status", "problems")}
    zenoh_status = {**(report.get("zenoh") or {}), "board": name}
    return {**shared, **report["boards"][name], "board": name, "zenoh": zenoh_status}

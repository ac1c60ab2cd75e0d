"""The Python client on Zenoh: frames of every board of every host, straight
from the services (``tactile serve --zenoh``), no gateway.

    from service.client_zenoh import ZenohClient

    with ZenohClient(["tcp/lab-pc:7447", "tcp/arm-pc:7447"]) as client:
        for frame in client.subscribe(board="*", sensors=[1]):
            board = frame["header"]["board"]
            fx, fy, fz = frame["force_N"]
            age = client.last_health_age_s(board)  # None: no health heard yet
            if age is None or age > 2.0:           # that service is gone
                ...

Frames have the shape ``TactileClient.subscribe(binary=True)`` gives
(service/client.py: header, rows/cols for grids, force_N and a quad's wrench,
sigma, flags; numpy float32 with NaN), plus ``header["board"]``, the board's
key, and ``header["instance"]``, the service that published it. A grid's
rows and cols are not in the binary records: the client asks the board's
``tactile/<board>/sensors`` queryable once per board and service (and
again for a sensor it does not know yet). Keys and QoS: docs/scale.md.

A consumer slower than the stream loses the oldest waiting frames, never
the service's time or memory: ``dropped`` counts them. Every failure — no
frame within ``timeout``, no answer to a query, a sample that does not
decode — is a ``TactileError`` saying what.

Two services may publish one board name (docs/scale.md "One name, two
services"). The client follows one per name, as a gateway serves one
(service/net/following.py): the other's frames and health are dropped,
counted in ``refused`` and ``clashes()``, and a warning names both; when
the followed one goes, the other is followed, with a warning saying so.
"""
from __future__ import annotations

import struct
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator

import orjson
import zenoh

from .client import TactileClient, TactileError
from .fanout.encoding import DEFAULT_FIELDS, decode_binary
from .net.following import Following, named
from .net.zenoh_config import (PREFIX, frame_key, instance_of_alive, instance_of_sample, latest_key, open_session,
                               sensors_key, session_config)

INBOX_SAMPLES = 4096  # ~2 s of a grid and a quad at 1 kHz


def _board_of(key: zenoh.KeyExpr | str) -> str:
    return str(key).split("/")[1]


def _records(payload: bytes) -> int:
    return int.from_bytes(payload[:2], "little")  # a sample's u16 record count


class _BoardFrames(TactileClient):
    """The WebSocket client's conversion of binary records into the frame
    shape, with the sensors' shapes asked over Zenoh instead of GET /sensors."""

    def __init__(self, shapes) -> None:
        super().__init__()
        self._shapes = shapes

    def _sensor(self, board: str, sensor_id: int) -> dict:
        return self._shapes(board, sensor_id)


class _Inbox:
    """Samples from Zenoh's threads to the consumer: at most ``capacity``;
    a consumer that falls behind loses the oldest (their frames counted)."""

    def __init__(self, capacity: int) -> None:
        self.dropped = 0
        self._samples: deque[tuple[str, bytes, str]] = deque(maxlen=capacity)
        self._ready = threading.Event()
        self._lock = threading.Lock()  # several subscribers may deliver at once

    def put(self, sample: zenoh.Sample, instance: str) -> None:
        with self._lock:
            if len(self._samples) == self._samples.maxlen:
                self.dropped += _records(self._samples[0][1])
            self._samples.append((str(sample.key_expr), sample.payload.to_bytes(), instance))
        self._ready.set()

    def get(self, timeout: float) -> tuple[str, bytes, str] | None:
        deadline = time.monotonic() + timeout
        while True:
            self._ready.clear()  # before looking: a sample put after the look sets it again
            if self._samples:
                return self._samples.popleft()
            if not self._ready.wait(deadline - time.monotonic()):
                return None


class ZenohClient:
    """A Zenoh session to the services: ``endpoints`` to connect to (then
    multicast scouting is off), or a whole ``config`` (service.net.zenoh_config.
    session_config), or Zenoh's defaults (peers found by multicast scouting).
    Health samples and liveliness tokens of every board are followed from
    the start. ``one_service_per_board=False`` takes every service's frames
    and health of a name, as they come."""

    def __init__(self, endpoints: Iterable[str] = (), config: zenoh.Config | None = None, timeout: float = 5.0,
                 one_service_per_board: bool = True) -> None:
        endpoints = list(endpoints)
        if config is None:
            config = session_config(connect=endpoints, multicast=False if endpoints else None)
        self.timeout = timeout
        self.dropped = 0  # frames lost because the consumer of subscribe fell behind
        self.refused = 0  # frames subscribed to, dropped: another service's than the one followed under that name
        self.following = Following() if one_service_per_board else None
        self.session = open_session(config)
        self._health: dict[str, tuple[float, dict]] = {}
        self._shapes: dict[tuple[str, str], dict[int, dict]] = {}  # by (board, instance)
        self._converters: dict[tuple[str, str], _BoardFrames] = {}
        self._lock = threading.Lock()
        self._alive_subscriber = self.session.liveliness().declare_subscriber(
            f"{PREFIX}/*/alive/**", self._on_alive, history=True)  # the tokens there already, then each change
        self._health_subscriber = self.session.declare_subscriber(f"{PREFIX}/*/health", self._on_health)

    def __enter__(self) -> "ZenohClient":
        return self

    def __exit__(self, *_exc) -> None:
        self.close()

    def close(self) -> None:
        self.session.close()

    def _admit(self, board: str, instance: str, alive: bool | None = None) -> bool:
        return self.following is None or self.following.admit(board, instance, alive)

    def _on_alive(self, sample: zenoh.Sample) -> None:
        self._admit(_board_of(sample.key_expr), instance_of_alive(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

    def followed(self, board: str) -> str | None:
        """The instance (host:pid:random) whose frames and health of ``board``
        the client takes, None if none was heard (or every service's are taken)."""
        return None if self.following is None else self.following.followed(board)

    def clashes(self) -> dict[str, dict]:
        """Boards published by another service besides the one followed (live,
        or gone within the last minute): board → ``publisher`` (the instance
        followed), ``publishers`` (each: ``instance``, ``served``, ``alive``,
        ``samples_refused`` — its samples dropped), ``problems`` (naming both)."""
        return {} if self.following is None else self.following.clashes()

    def _on_health(self, sample: zenoh.Sample) -> None:
        """A board's health document; ``{"renamed_to": NAME}`` is its service
        saying the name is gone (a bare board's provisional one, at its first
        INFO: zenoh_publisher.py), which drops it."""
        board = _board_of(sample.key_expr)
        if not self._admit(board, instance_of_sample(sample)):
            return
        try:
            document = orjson.loads(sample.payload.to_bytes())
        except orjson.JSONDecodeError:
            return  # not a health document: nothing to learn from it
        with self._lock:
            if isinstance(document, dict) and isinstance(document.get("renamed_to"), str):
                self._health.pop(board, None)
            else:
                self._health[board] = (time.monotonic(), document)

    def boards(self) -> list[str]:
        """Boards whose health was heard since the client started."""
        with self._lock:
            return sorted(self._health)

    def health(self, board: str) -> dict | None:
        """The board's last health document (its /health), None if none came."""
        with self._lock:
            entry = self._health.get(board)
        return None if entry is None else entry[1]

    def last_health_age_s(self, board: str) -> float | None:
        """Seconds since the board's last health sample (one a second while its
        service runs), None if none came: a service that is gone grows old."""
        with self._lock:
            entry = self._health.get(board)
        return None if entry is None else time.monotonic() - entry[0]

    def _get(self, key: str, instance: str | None, instance_of) -> zenoh.Sample:
        """The answer of ``instance`` (None: the first) among every service's
        (one name may be answered by two services, the one followed not first)."""
        replies = [reply.ok for reply in self.session.get(key, target=zenoh.QueryTarget.ALL,
                                                          consolidation=zenoh.ConsolidationMode.NONE,
                                                          timeout=self.timeout) if reply.ok is not None]
        if not replies:
            raise TactileError(f"zenoh query {key}: no answer within {self.timeout} s (is that board's service running?)")
        answers = [r for r in replies if instance is None or instance_of(r) == instance]
        if not answers:
            raise TactileError(f"zenoh query {key}: no answer from {named(instance)}, the service followed, within "
                               f"{self.timeout} s (answered by {', '.join(sorted(map(instance_of, replies)))})")
        return answers[0]

    def sensors(self, board: str, instance: str | None = None) -> list[dict]:
        """The board's sensors (id, kind, rows, cols), as the service followed
        under that name (or ``instance``) knows them."""
        instance = self.followed(board) if instance is None else instance
        sample = self._get(sensors_key(board), instance, lambda r: orjson.loads(r.payload.to_bytes()).get("instance", ""))
        document = orjson.loads(sample.payload.to_bytes())
        with self._lock:
            self._shapes[(board, document.get("instance", ""))] = {s["id"]: s for s in document["sensors"]}
        return document["sensors"]

    def _shape(self, board: str, instance: str, sensor_id: int) -> dict:
        with self._lock:
            shape = self._shapes.get((board, instance), {}).get(sensor_id)
        if shape is None:
            self.sensors(board, instance)  # the board, its service, or this sensor, is new to us
            with self._lock:
                shape = self._shapes[(board, instance)].get(sensor_id)
        if shape is None:
            raise TactileError(f"a frame from board {board}'s sensor {sensor_id}, which its service {instance} "
                               "does not list")
        return shape

    def _frames(self, board: str, instance: str, payload: bytes, key: str) -> list[dict]:
        try:
            records = decode_binary(payload)
        except (ValueError, IndexError, UnicodeDecodeError, struct.error) as exc:
            raise TactileError(f"zenoh sample on {key} does not decode ({exc})") from None
        converter = self._converters.get((board, instance))
        if converter is None:
            if self.following is not None:  # a restarted or handed-over service's: its predecessor's are of no use
                with self._lock:
                    for old in [k for k in self._converters if k[0] == board]:
                        del self._converters[old]
                        self._shapes.pop(old, None)
            converter = self._converters[(board, instance)] = _BoardFrames(
                lambda _, sid: self._shape(board, instance, sid))
        frames = [converter._from_binary(record, DEFAULT_FIELDS) for record in records]
        for frame in frames:
            frame["header"]["instance"] = instance
        return frames

    def latest(self, board: str, sensor: int) -> dict:
        """The sensor's latest frame, asked from the service followed under that name."""
        key = latest_key(board, sensor)
        sample = self._get(key, self.followed(board), instance_of_sample)
        return self._frames(_board_of(sample.key_expr), instance_of_sample(sample), sample.payload.to_bytes(), key)[-1]

    def subscribe(self, board: str = "*", sensors: Iterable[int] | None = None, timeout: float | None = None,
                  queue_samples: int = INBOX_SAMPLES) -> Iterator[dict]:
        """Frames as they arrive, from ``board`` ("*": every board) and
        ``sensors`` (None: all). TactileError when none comes within
        ``timeout`` s (default: the client's). At most ``queue_samples``
        samples wait for the consumer: one that falls behind loses the
        oldest, counted in ``dropped``. Frames of a board name from another
        service than the one followed are dropped, counted in ``refused``."""
        timeout = self.timeout if timeout is None else timeout
        keys = [frame_key(board, "*")] if sensors is None else [frame_key(board, sid) for sid in sensors]
        inbox, dropped_before = _Inbox(queue_samples), self.dropped

        def take(sample: zenoh.Sample) -> None:
            instance = instance_of_sample(sample)
            if self._admit(_board_of(sample.key_expr), instance):
                inbox.put(sample, instance)
            else:
                with self._lock:
                    self.refused += _records(sample.payload.to_bytes())

        subscribers = [self.session.declare_subscriber(key, take) for key in keys]
        try:
            while True:
                received = inbox.get(timeout)
                self.dropped = dropped_before + inbox.dropped
                if received is None:
                    raise TactileError(f"no frame on {', '.join(keys)} within {timeout} s")
                key, payload, instance = received
                yield from self._frames(_board_of(key), instance, payload, key)
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()


def subscribe_zenoh(board: str = "*", sensors: Iterable[int] | None = None, endpoints: Iterable[str] = (),
                    config: zenoh.Config | None = None, timeout: float = 5.0) -> Iterator[dict]:
    """Frames of ``board``'s ``sensors`` over Zenoh, in a session of their own
    (ZenohClient.subscribe; a ZenohClient also gives health and latest)."""
    with ZenohClient(endpoints, config, timeout) as client:
        yield from client.subscribe(board, sensors)

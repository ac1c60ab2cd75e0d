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
again, at most once a second, for a sensor it does not know yet or whose
records its known shape does not fit: a board's INFO may announce another
shape mid-stream), over Zenoh, never over HTTP. Until its shape is known
and fits, such a sensor's frames are skipped, counted in ``unshaped`` and
told once in ``notices``; the other sensors' frames go on.

A consumer slower than the stream loses the oldest waiting frames, never
the service's time or memory: ``dropped`` counts them. A subscribed sample
that does not decode (bytes that are no records, a record cut short, another
version's) is dropped, counted in ``undecodable`` and per board in
``undecodable_by_board``, and told once per board in ``notices``; the other
samples' frames go on. So is a sample larger than the gateway's bound
(``MAX_SAMPLE_BYTES``, 1 MiB: 32 frames of a 256-channel grid are ~70 KiB),
before it is queued or decoded: nothing from a peer (unauthenticated) is
parsed at any size (an answer to a query that large is an error, a health
document that large is ignored). What is kept per board or sensor (counts,
converters, shapes, why a sensor is skipped) is kept for the ``KEPT_BOARDS``
boards (``KEPT_SENSORS`` sensors) used last, and ``notices`` holds the last
``KEPT_NOTICES`` lines: a peer publishing under any number of made-up names
leaves memory flat, and the boards in use keep theirs. Every failure — no
frame within ``timeout``, no answer to a query, a queried frame that does
not decode — is a ``TactileError`` saying what.

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

from .client import TactileClient, TactileError, _skipping_said, _unshaped_notice
from .fanout.encoding import DEFAULT_FIELDS, decode_binary
from .net.following import Following, named
from .net.zenoh_config import (PREFIX, frame_key, instance_of_alive, instance_of_sample, latest_key, open_session,
                               sensors_key, session_config)
from .net.zenoh_feed import MAX_SAMPLE_BYTES, announced_shapes
from .recent import MostRecent

INBOX_SAMPLES = 4096  # ~2 s of a grid and a quad at 1 kHz
KEPT_BOARDS = 64  # boards whose state is kept, the most recently used (a gateway serves 64: gateway.MAX_BOARDS)
KEPT_SENSORS = 4 * KEPT_BOARDS  # sensors told as skipped (a board has a few)
KEPT_NOTICES = 64  # the last notices; older ones are dropped


def _board_of(key: zenoh.KeyExpr | str) -> str:
    return str(key).split("/")[1]


def _records(payload: bytes) -> int:
    return int.from_bytes(payload[:2], "little")  # a sample's u16 record count


def _oversized(key: str, size: int) -> str | None:
    """Why a sample of ``size`` bytes on ``key`` is not parsed, None if it may be."""
    if size <= MAX_SAMPLE_BYTES:
        return None
    return f"a zenoh sample on {key} of {size} bytes is over the {MAX_SAMPLE_BYTES}-byte bound, not decoded"


def _decoded(payload: bytes, key: str) -> list[dict]:
    """The binary records of a frame sample on ``key``; TactileError naming why
    if it does not decode or is over the bound (then it is not decoded)."""
    too_large = _oversized(key, len(payload))
    if too_large is not None:
        raise TactileError(too_large)
    try:
        return decode_binary(payload)
    except (ValueError, IndexError, UnicodeDecodeError, struct.error) as exc:
        raise TactileError(f"a zenoh sample on {key} does not decode ({exc})") from None


def _undecodable_said(undecodable: int, last: str) -> str:
    """What a stream that gave no frame says of the ``undecodable`` samples
    dropped since its last frame, ``last`` the latest one's notice-like line."""
    return f" ({undecodable} samples did not decode; the last: {last})" if undecodable else ""


def _document(sample: zenoh.Sample) -> dict | None:
    """A JSON object answered (a sensors document), None if the answer is none
    (or over the bound: not parsed)."""
    if len(sample.payload) > MAX_SAMPLE_BYTES:
        return None
    try:
        document = orjson.loads(sample.payload.to_bytes())
    except orjson.JSONDecodeError:
        return None
    return document if isinstance(document, dict) else None


def _document_instance(sample: zenoh.Sample) -> str:
    """The service instance a sensors document names ("" if none)."""
    return str((_document(sample) or {}).get("instance", ""))


class _BoardFrames(TactileClient):
    """The WebSocket client's conversion of binary records into the frame
    shape for one board of one service, ``instance``: the sensors' shapes
    asked over Zenoh instead of GET /sensors (the client's base URL is no
    address of that service), skipped records told to ``owner``."""

    def __init__(self, owner: "ZenohClient", board: str, instance: str) -> None:
        super().__init__()
        self._owner, self._board, self._instance = owner, board, instance
        self._skipping = owner._skipping  # one told per sensor, whichever service's converter skipped it

    def _known_shape(self, _board: str, sensor_id: int) -> dict | None:
        return self._owner._known_shape(self._board, self._instance, sensor_id)

    def _ask_shapes(self, _board: str) -> None:
        self._owner.sensors(self._board, self._instance)

    def _skip_unshaped(self, address: str, why: str) -> None:
        self._owner._skip_unshaped(address, why)


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
        self.unshaped = 0  # frames subscribed to, skipped: their sensor's shape unknown or not fitting them
        self.undecodable = 0  # samples subscribed to, dropped: they do not decode
        # board (its key's) → its samples in ``undecodable``, the KEPT_BOARDS boards with one lately
        self.undecodable_by_board: dict[str, int] = MostRecent(KEPT_BOARDS)
        self.notices: list[str] = []  # a line when a sensor's frames begin to be skipped or a board's sample
        # first does not decode, saying why; the last KEPT_NOTICES
        self._undecodable_last = ""  # "board B: why" of the latest sample that did not decode
        # "board/id" → why its frames are skipped, until one fits again
        self._skipping: dict[str, str] = MostRecent(KEPT_SENSORS)
        self.following = Following() if one_service_per_board else None
        self.session = open_session(config)
        self._health: dict[str, tuple[float, dict]] = {}
        self._shapes: dict[tuple[str, str], dict[int, dict]] = MostRecent(KEPT_BOARDS)  # by (board, instance)
        self._converters: dict[tuple[str, str], _BoardFrames] = MostRecent(KEPT_BOARDS)
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
        if not self._admit(board, instance_of_sample(sample)) or len(sample.payload) > MAX_SAMPLE_BYTES:
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
        under that name (or ``instance``) knows them; TactileError if it does
        not answer, or answers no sensors document."""
        instance = self.followed(board) if instance is None else instance
        key = sensors_key(board)
        sample = self._get(key, instance, _document_instance)
        document = _document(sample)
        if document is None or not isinstance(document.get("sensors"), list):
            raise TactileError(f"zenoh query {key}: the answer is no sensors document (at most {MAX_SAMPLE_BYTES} "
                               f"bytes): {len(sample.payload)} bytes, {sample.payload.to_bytes()[:80]!r}")
        shapes, _ = announced_shapes(document, board)  # a shape no frame can have is left out: its frames are skipped
        with self._lock:
            self._shapes[(board, _document_instance(sample))] = {
                sid: {"id": sid, "kind": info.kind, "rows": info.rows, "cols": info.cols}
                for sid, info in shapes.items()}
        return document["sensors"]

    def _known_shape(self, board: str, instance: str, sensor_id: int) -> dict | None:
        """The sensor as ``instance``'s service last listed it, None if it did not."""
        with self._lock:
            return self._shapes.get((board, instance), {}).get(sensor_id)

    def _skip_unshaped(self, address: str, why: str) -> None:
        """Count a frame of sensor ``address`` ("board/id") skipped for ``why``;
        tell it in ``notices`` when that sensor's frames begin to be skipped."""
        self.unshaped += 1
        if address not in self._skipping:
            self._notice(_unshaped_notice(address, why))
        self._skipping[address] = why

    def _notice(self, line: str) -> None:
        """Tell ``line`` in ``notices``, the oldest dropped beyond KEPT_NOTICES."""
        self.notices.append(line)
        del self.notices[:-KEPT_NOTICES]

    def _drop_undecodable(self, board: str, why: str) -> None:
        """Count a subscribed sample of ``board`` that does not decode (``why``);
        tell it in ``notices`` at the board's first such sample (among those
        kept). From the consumer's thread or Zenoh's (a sample over the bound)."""
        with self._lock:
            self.undecodable += 1
            count = self.undecodable_by_board[board] = self.undecodable_by_board.get(board, 0) + 1
            self._undecodable_last = f"board {board}: {why}"
            if count == 1:
                self._notice(f"{self._undecodable_last}: such samples are dropped (counted in undecodable)")

    def _frames(self, board: str, instance: str, records: list[dict]) -> list[dict]:
        """The frames of a sample's decoded binary ``records``, from ``instance``'s ``board``."""
        with self._lock:  # a read moves it in _converters' order too
            converter = self._converters.get((board, instance))
            if converter is None:
                if self.following is not None:  # a restarted or handed-over service's: its predecessor's are of no use
                    for old in [k for k in self._converters if k[0] == board]:
                        del self._converters[old]
                        self._shapes.pop(old, None)
                converter = self._converters[(board, instance)] = _BoardFrames(self, board, instance)
        frames = converter._shaped_frames(records, DEFAULT_FIELDS)
        for frame in frames:
            frame["header"]["instance"] = instance
        return frames

    def latest(self, board: str, sensor: int) -> dict:
        """The sensor's latest frame, asked from the service followed under that name."""
        key = latest_key(board, sensor)
        sample = self._get(key, self.followed(board), instance_of_sample)
        unshaped = self.unshaped
        frames = self._frames(_board_of(sample.key_expr), instance_of_sample(sample),
                              _decoded(sample.payload.to_bytes(), key))
        if not frames:
            said = _skipping_said(self._skipping, self.unshaped > unshaped)
            raise TactileError(f"zenoh query {key}: the frame answered was skipped{said}")
        return frames[-1]

    def subscribe(self, board: str = "*", sensors: Iterable[int] | None = None, timeout: float | None = None,
                  queue_samples: int = INBOX_SAMPLES) -> Iterator[dict]:
        """Frames as they arrive, from ``board`` ("*": every board) and
        ``sensors`` (None: all). TactileError when none comes within
        ``timeout`` s (default: the client's). At most ``queue_samples``
        samples wait for the consumer: one that falls behind loses the
        oldest, counted in ``dropped``. Frames of a board name from another
        service than the one followed are dropped, counted in ``refused``;
        frames whose sensor's shape is unknown or does not fit them are
        skipped, counted in ``unshaped`` (samples of those alone are no
        frame within ``timeout`` either); samples that do not decode are
        dropped, counted in ``undecodable`` and ``undecodable_by_board``, and
        told once per board in ``notices``."""
        timeout = self.timeout if timeout is None else timeout
        keys = [frame_key(board, "*")] if sensors is None else [frame_key(board, sid) for sid in sensors]
        inbox, dropped_before = _Inbox(queue_samples), self.dropped

        def take(sample: zenoh.Sample) -> None:
            board, instance = _board_of(sample.key_expr), instance_of_sample(sample)
            too_large = _oversized(str(sample.key_expr), len(sample.payload))
            if not self._admit(board, instance):
                with self._lock:
                    self.refused += _records(sample.payload.to_bytes())
            elif too_large is not None:  # neither queued nor decoded
                self._drop_undecodable(board, too_large)
            else:
                inbox.put(sample, instance)

        subscribers = [self.session.declare_subscriber(key, take) for key in keys]
        # samples whose every record is skipped, or that do not decode, are no frame
        given_at, unshaped, undecodable = time.monotonic(), self.unshaped, self.undecodable
        try:
            while True:
                wait = given_at + timeout - time.monotonic()
                received = inbox.get(wait) if wait > 0 else None
                self.dropped = dropped_before + inbox.dropped
                if received is None:
                    said = _skipping_said(self._skipping, self.unshaped > unshaped) + \
                        _undecodable_said(self.undecodable - undecodable, self._undecodable_last)
                    raise TactileError(f"no frame on {', '.join(keys)} within {timeout} s{said}")
                key, payload, instance = received
                try:
                    records = _decoded(payload, key)
                except TactileError as exc:  # one bad sample never ends the stream of every board followed
                    self._drop_undecodable(_board_of(key), str(exc))
                    continue
                for frame in self._frames(_board_of(key), instance, records):
                    yield frame
                    given_at, unshaped, undecodable = time.monotonic(), self.unshaped, self.undecodable
        finally:
            for subscriber in subscribers:
                subscriber.undeclare()


def subscribe_zenoh(board: str = "*", sensors: Iterable[int] | None = None, endpoints: Iterable[str] = (),
                    config: zenoh.Config | None = None, timeout: float = 5.0) -> Iterator[dict]:
    """Frames of ``board``'s ``sensors`` over Zenoh, in a session of their own
    (ZenohClient.subscribe; a ZenohClient also gives health and latest)."""
    with ZenohClient(endpoints, config, timeout) as client:
        yield from client.subscribe(board, sensors)

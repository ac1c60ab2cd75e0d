"""A small client for robot controllers.

    from service.client import TactileClient, TactileError

    client = TactileClient("http://127.0.0.1:8000")
    print(client.latest(0)["contact"])                      # one grid frame, every field
    for frame in client.subscribe(sensors=[1], binary=True):
        fx, fy, fz = frame["force_N"]                      # quad, 1 kHz
        ...

REST over urllib, the stream over websockets (installed with uvicorn's
standard extra). Every failure — the service not running, an HTTP error
(with the service's detail), a reply that is no JSON, a connection refused,
closed or timed out, a stream silent for ``timeout`` — is a ``TactileError``
naming what failed.

One frame shape, whichever the encoding (``latest``, ``history`` and
``subscribe`` with ``binary`` False or True all give it):

    {"header": {"board", "sensor_id", "sensor_name", "kind", "seq", "board_time_us", "stamp",
                "scan_stamp", "calibration", "age_s"},  # age_s: latest() only (below)
     "rows", "cols",                          # grids
     "force_N",                               # grid: rows*cols taxels, row-major;
                                              # quad: [fx, fy, fz] (also as "wrench")
     "wrench": {"force": {"x", "y", "z"}},    # quads
     "raw": {"capacitance_pF": [...]},        # when fields include "raw"
     "contact": {...},                        # grids, JSON only (see below)
     "flags": [...],                          # when fields include "flags" (default)
     "taxel_flags": {"saturated": [27]}}      # grids, when fields include "flags"

Numbers: JSON gives lists with None for no value, binary numpy float32
arrays with NaN (``wrench`` has None either way). The binary encoding does
not carry the contact summary: a binary grid frame has no ``contact`` key —
subscribe in JSON (or ask ``contact(id)``) where it is needed. ``subscribe`` counts the frames the
server dropped for this client and those it skipped for a loop behind in
``dropped`` (the skipped also per sensor in ``dropped_by_sensor``) and keeps
its notices (e.g. a subscription to sensors not announced yet) in ``notices``.
A binary record whose sensor's shape GET /sensors does not give (a sensor
not listed yet, a grid whose rows and cols changed and are not listed yet)
is skipped, never given another shape: counted in ``unshaped`` (and in
``dropped`` and ``dropped_by_sensor``), told once in ``notices`` until that
sensor's records fit again; the other sensors' frames go on.

``latest`` (and ``contact``) give the sensor's last frame however old:
``age_s`` (the header's; ``contact``'s at its top level) is the seconds
from its read to the answer, and a frame of a sensor /health calls stale
(no frame for max(0.5 s, 20 scan periods)) has ``sensor_stale`` in its
``flags`` (``contact``: ``"stale": true``) — its forces are not current.
"""
from __future__ import annotations

import http.client
import itertools
import math
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from collections import deque
from collections.abc import Iterator

import orjson

from .fanout.encoding import DEFAULT_FIELDS, decode_binary

DEFAULT_MAX_LAG_S = 0.25  # subscribe: a loop further behind the newest arrived gets each sensor's newest
LAGGING_QUEUE = 1024  # messages read ahead when trimming by lag: up to ~10 MB of a loop that stalled
AGE_HEADER = "X-Frame-Age-S"  # as api/routes_sensors.py sends it (the client does not import the API's FastAPI)
SHAPES_RETRY_S = 1.0  # shapes asked again for records their sensor's known shape does not fit at most this often
QUAD_FORCES = 3  # Fx, Fy, Fz


class TactileError(RuntimeError):
    """Anything that went wrong talking to the service; the message says what
    (the request or stream, and the service's detail or the network's error)."""


def _sensor_path(sensor: int | str) -> str:
    """``/sensors/{id}`` or, for an address "board/id", ``/sensors/{board}/{id}``."""
    return f"/sensors/{urllib.parse.quote(str(sensor))}".replace("%2F", "/")


def _retry_after(error: urllib.error.HTTPError) -> float | None:
    """A 429's ``Retry-After`` in seconds (None: it gives none)."""
    try:
        return max(0.0, float(error.headers.get("Retry-After")))
    except (TypeError, ValueError):
        return None


def _lagging(pending: deque[dict], max_lag_s: float) -> bool:
    """Whether a frame of ``pending`` lies more than ``max_lag_s`` before the
    newest of its own board's (a stamp is its service's host clock: a
    gateway's boards come from hosts whose clocks may differ by more; a
    frame without one is never behind)."""
    newest: dict = {}
    for frame in pending:
        header = frame["header"]
        stamp, board = header.get("stamp"), header.get("board")
        if stamp is not None and stamp > newest.get(board, -math.inf):  # NaN compares False
            newest[board] = stamp
    return any(newest.get(h.get("board"), stamp) - stamp > max_lag_s
               for h in (frame["header"] for frame in pending) if (stamp := h.get("stamp")) is not None)


def _address(frame: dict) -> str:
    """A frame's sensor as ``"board/id"``."""
    header = frame["header"]
    return f"{header.get('board')}/{header.get('sensor_id')}"


def _keep_newest(pending: deque[dict]) -> dict[str, int]:
    """Keep only the last arrived frame of each sensor in ``pending``, in
    arrival order; how many of each sensor's (``"board/id"``) went."""
    last = {_address(frame): i for i, frame in enumerate(pending)}
    kept = sorted(last.values())
    skipped: dict[str, int] = {}
    for i, frame in enumerate(pending):
        if last[address := _address(frame)] != i:
            skipped[address] = skipped.get(address, 0) + 1
    if skipped:
        frames = list(pending)
        pending.clear()
        pending.extend(frames[i] for i in kept)
    return skipped


def _age_s(headers: dict) -> float | None:
    """Seconds from the latest frame's read to the answer (``X-Frame-Age-S``;
    None from a service that does not say)."""
    try:
        return float(headers[AGE_HEADER.lower()])
    except (KeyError, ValueError):
        return None


def _least_recently_served(pending: deque[dict], served: dict[str, int]) -> dict:
    """Take from ``pending`` the frame of the sensor handed out longest ago
    (``served``: address → when, by count; never: first), the earlier arrived
    on a tie: a loop behind gets each sensor's newest in turn."""
    index = min(range(len(pending)), key=lambda i: served.get(_address(pending[i]), -1))
    frame = pending[index]
    del pending[index]
    return frame


def _misfit(info: dict | None, record: dict) -> str | None:
    """Why a binary ``record`` cannot be a frame of the sensor ``info`` lists
    (None: it can): listed, of its kind, a grid's forces one per taxel of its
    rows x cols, a quad's three (a record without forces has none to count)."""
    kind, n = record["kind"], len(record["force_N"])
    if info is None:
        return "not listed by its service"
    if info.get("kind") != kind:
        return f"{kind} records of {n} forces where its service lists a {info.get('rows')}x{info.get('cols')} " \
               f"{info.get('kind')}"
    if kind == "grid" and n and info["rows"] * info["cols"] != n:
        return f"records of {n} forces where its service lists a {info['rows']}x{info['cols']} grid"
    if kind == "quad" and n not in (0, QUAD_FORCES):
        return f"quad records of {n} forces where a quad has {QUAD_FORCES}"
    return None


def _unshaped_notice(address: str, why: str) -> str:
    return f"sensor {address}: {why}: its frames are skipped (counted in unshaped) until its shape fits them"


def _skipping_said(skipping: dict[str, str], skipped: bool) -> str:
    """What a stream that gave no frame says of the sensors whose records are
    skipped, if it ``skipped`` any since its last frame."""
    if not (skipped and skipping):
        return ""
    return f" (records skipped: {'; '.join(f'sensor {a}: {why}' for a, why in skipping.items())})"


def _none_if_nan(value) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


def _normalized(frame: dict) -> dict:
    """A JSON frame message, with a quad's force (and σ) also as ``force_N``
    (``sigma_N``) [fx, fy, fz]."""
    for key, flat in (("wrench", "force_N"), ("wrench_sigma", "sigma_N")):
        wrench = frame.get(key)
        if wrench is not None and flat not in frame:
            force = wrench["force"]
            frame[flat] = [force["x"], force["y"], force["z"]]
    return frame


def _checked_base_url(base_url: str) -> str:
    """``base_url`` without its trailing slash; TactileError naming what is
    wrong with one no request could be made to (urllib's own ValueError
    came from the first request, not a TactileError)."""
    if not isinstance(base_url, str) or any(c.isspace() for c in base_url):
        raise TactileError(f"base URL {base_url!r}: no spaces, e.g. http://127.0.0.1:8000")
    try:
        parts = urllib.parse.urlsplit(base_url)
        parts.port  # noqa: B018 — urlsplit checks the port only when asked
    except ValueError as exc:
        raise TactileError(f"base URL {base_url!r}: {exc}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise TactileError(f"base URL {base_url!r}: expected http://HOST[:PORT], e.g. http://127.0.0.1:8000")
    return base_url.rstrip("/")


class TactileClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 5.0) -> None:
        self.base_url = _checked_base_url(base_url)
        self.token = token
        self.timeout = timeout
        self.dropped = 0
        self.dropped_by_sensor: dict[str, int] = {}  # "board/id" → frames subscribe skipped: a loop behind, unshaped
        self.notices: list[str] = []
        self.unshaped = 0  # binary records subscribe skipped: their sensor's shape unknown or not fitting them
        self._heard: list[str] = []  # the notices the service sent (the others are the client's own)
        self._skipping: dict[str, str] = {}  # "board/id" → why its records are skipped, until one fits again
        self._sensors: dict[int, dict] = {}
        self._shapes_asked = -SHAPES_RETRY_S  # when the shapes were last asked for records they did not fit

    def _request(self, method: str, path: str, body: dict | None = None, replied: dict | None = None):
        """The answer's JSON; ``replied``, if given, gets the answer's headers (names lower-cased)."""
        headers = {"Content-Type": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        data = orjson.dumps(body) if body is not None else None
        what = f"{method} {self.base_url}{path}"
        request = urllib.request.Request(self.base_url + path, data=data, method=method, headers=headers)
        deadline = time.monotonic() + self.timeout
        try:
            while True:
                try:
                    left = max(deadline - time.monotonic(), 0.001)  # a retry has what is left of the timeout
                    with urllib.request.urlopen(request, timeout=left) as response:
                        payload = response.read()
                        if replied is not None:
                            replied.update((name.lower(), value) for name, value in response.headers.items())
                    break
                except urllib.error.HTTPError as exc:
                    # The service admits history reads at a bounded rate (docs/api.md): a read refused for now
                    # is asked again when it says, within the timeout, as a program polling would have to.
                    wait = _retry_after(exc) if method == "GET" and exc.code == 429 else None
                    if wait is None or time.monotonic() + wait > deadline:
                        raise
                    exc.close()
                    time.sleep(wait)
        except urllib.error.HTTPError as exc:
            try:
                detail = orjson.loads(exc.read() or b"{}").get("detail") or exc.reason
            except (orjson.JSONDecodeError, AttributeError, OSError, http.client.HTTPException):
                detail = exc.reason
            raise TactileError(f"{what}: {exc.code} {detail}") from None
        except urllib.error.URLError as exc:
            reason = exc.reason
            if isinstance(reason, ConnectionRefusedError):
                raise TactileError(f"{what}: connection refused (is tactile serve running there?)") from None
            if isinstance(reason, (TimeoutError, socket.timeout)):
                raise TactileError(f"{what}: no answer within {self.timeout} s") from None
            raise TactileError(f"{what}: cannot reach the service: {reason}") from None
        except (TimeoutError, socket.timeout):
            raise TactileError(f"{what}: no answer within {self.timeout} s") from None
        except (http.client.HTTPException, ConnectionError) as exc:
            raise TactileError(f"{what}: connection closed before the answer ({type(exc).__name__}: {exc})") from None
        except OSError as exc:
            raise TactileError(f"{what}: {exc}") from None
        try:
            return orjson.loads(payload)
        except orjson.JSONDecodeError as exc:
            raise TactileError(f"{what}: the answer is no JSON ({exc}): {payload[:80]!r}") from None

    def health(self) -> dict:
        return self._request("GET", "/health")

    def clients(self) -> list[dict]:
        """Every WebSocket client's subscription and its latency to its socket."""
        return self._request("GET", "/clients")["clients"]

    def sensors(self) -> list[dict]:
        sensors = self._request("GET", "/sensors")["sensors"]
        self._sensors = {(s["board"], s["id"]): s for s in sensors}
        return sensors

    def latest(self, sensor: int | str) -> dict:
        """``sensor``: an id (on a one-board service, or the only board with
        it) or an address ``"board/id"``; likewise below."""
        replied: dict = {}
        frame = _normalized(self._request("GET", f"{_sensor_path(sensor)}/latest", replied=replied))
        frame["header"]["age_s"] = _age_s(replied)
        return frame

    def contact(self, sensor: int | str) -> dict:
        """The latest frame's contact summary, with ``stale`` and ``age_s`` as ``latest``'s."""
        replied: dict = {}
        summary = self._request("GET", f"{_sensor_path(sensor)}/contact", replied=replied)
        summary["age_s"] = _age_s(replied)
        return summary

    def history(self, sensor: int | str, seconds: float = 2.0, max_points: int = 200) -> list[dict]:
        frames = self._request("GET", f"{_sensor_path(sensor)}/history?seconds={seconds}&max_points={max_points}")
        return [_normalized(f) for f in frames]

    def tare(self, sensor: int | str | None = None) -> dict:
        return self._request("POST", "/tare" if sensor is None else f"{_sensor_path(sensor)}/tare")

    def _known_shape(self, board: str, sensor_id: int) -> dict | None:
        """The sensor as last listed (kind, rows, cols), None if it was not."""
        return self._sensors.get((board, sensor_id))

    def _ask_shapes(self, board: str) -> None:
        """Ask the sensors' shapes again; TactileError if that fails."""
        self.sensors()

    def _listed_shape(self, record: dict) -> tuple[dict | None, str | None]:
        """The listed shape of ``record``'s sensor if it fits the record, else
        None and why not. A sensor new or changed (a board's INFO may announce
        another shape mid-stream) has the shapes asked again, at most once a
        SHAPES_RETRY_S: a record that still does not fit waits for no answer."""
        board, sensor_id = record["board"], record["sensor_id"]
        info = self._known_shape(board, sensor_id)
        why = _misfit(info, record)
        if why is not None and time.monotonic() - self._shapes_asked >= SHAPES_RETRY_S:
            self._shapes_asked = time.monotonic()
            try:
                self._ask_shapes(board)
            except TactileError as exc:
                return None, f"{why}, and asking again failed: {exc}"
            info = self._known_shape(board, sensor_id)
            why = _misfit(info, record)
        return (info, None) if why is None else (None, why)

    def _shaped_frames(self, records: list[dict], fields: frozenset[str]) -> list[dict]:
        """The frames of decoded binary ``records`` whose sensor's shape is known
        and fits them; the others are skipped (``_skip_unshaped``)."""
        frames = []
        for record in records:
            address = f"{record['board']}/{record['sensor_id']}"
            info, why = self._listed_shape(record)
            if info is None:
                self._skip_unshaped(address, why)
            else:
                self._skipping.pop(address, None)
                frames.append(self._from_binary(record, info, fields))
        return frames

    def _skip_unshaped(self, address: str, why: str) -> None:
        """Count a record of sensor ``address`` skipped for ``why``; tell it in
        ``notices`` when that sensor's records begin to be skipped."""
        self.unshaped += 1
        self._count_skipped({address: 1})
        if address not in self._skipping:
            self.notices.append(_unshaped_notice(address, why))
        self._skipping[address] = why

    def _from_binary(self, record: dict, info: dict, fields: frozenset[str]) -> dict:
        """A decoded binary record in the JSON frame shape; ``info``: its
        sensor's listed shape, which fits it (a grid's rows and cols)."""
        kind = record["kind"]
        frame: dict = {"header": {"board": record["board"], "sensor_id": record["sensor_id"], "sensor_name": f"{kind}{record['sensor_id']}",
                                  "kind": kind, "seq": record["seq"], "board_time_us": record["board_time_us"],
                                  "stamp": record["stamp"], "scan_stamp": _none_if_nan(record["scan_stamp"]),
                                  "calibration": record["calibration"]}}
        if kind == "grid":
            frame["rows"], frame["cols"] = info["rows"], info["cols"]
        if "force" in fields:
            frame["force_N"] = record["force_N"]
            if kind == "quad":
                fx, fy, fz = (_none_if_nan(v) for v in record["force_N"])
                frame["wrench"] = {"force": {"x": fx, "y": fy, "z": fz}}
        if "sigma" in fields and "sigma_N" in record:
            frame["sigma_N"] = record["sigma_N"]
            if kind == "quad":
                sx, sy, sz = (_none_if_nan(v) for v in record["sigma_N"])
                frame["wrench_sigma"] = {"force": {"x": sx, "y": sy, "z": sz}}
        if "raw" in fields:
            frame["raw"] = {"capacitance_pF": record["capacitance_pF"]}
        if "flags" in fields:
            frame["flags"] = record["flags"]
            if kind == "grid":
                frame["taxel_flags"] = record.get("taxel_flags", {})
        return frame

    def subscribe(self, sensors: list[int | str] | None = None, fields: list[str] | None = None, max_rate: float | None = None,
                  batch_ms: float | None = None, binary: bool = False, timeout: float = 5.0,
                  max_lag_s: float | None = DEFAULT_MAX_LAG_S) -> Iterator[dict]:
        """Frames as they arrive, in the one frame shape (module docstring).
        A controller must not wait forever on a silent stream: TactileError
        when no message comes within ``timeout`` s, and when the stream ends
        (the service stopped, the network failed). ``sensors``: ids and
        "board/id" addresses. Frames come in order while the loop keeps
        within ``max_lag_s`` (by ``stamp``) of the newest that has arrived;
        once it falls further behind, each read keeps only the newest
        arrived frame of each sensor and hands out that of the sensor served
        longest ago, until the loop catches up (finds nothing waiting): a
        loop behind acts on every sensor's freshest data in turn. The
        skipped are counted in ``dropped`` (with the service's) and per
        sensor in ``dropped_by_sensor`` ("board/id" → frames). Taking the
        oldest frame within the window gave a 50 Hz loop on a grid and a
        quad at 1 kHz 276 quad and 6 grid frames in 6 s, each ~250 ms old.
        None: every frame, in order, for a logger (the service then drops
        for it once its own queue is full, counted in ``dropped`` only: its
        notice gives no sensor)."""
        from websockets.exceptions import ConnectionClosed, ConnectionClosedOK

        query = {"encoding": "binary" if binary else "json"}
        if sensors is not None:
            query["sensors"] = ",".join(map(str, sensors))
        if fields is not None:
            query["fields"] = ",".join(fields)
        if max_rate is not None:
            query["max_rate"] = str(max_rate)
        if batch_ms is not None:
            query["batch_ms"] = str(batch_ms)
        wanted = DEFAULT_FIELDS if fields is None else frozenset(fields)
        url = self.base_url.replace("http", "ws", 1) + "/ws?" + urllib.parse.urlencode(query)
        if binary:
            self.sensors()  # rows and cols, which binary records do not carry
        # Trimming by lag needs what has arrived read off the socket meanwhile (websockets' reader thread stops at
        # max_queue messages, and the socket's and the service's queues then hold seconds of frames behind them).
        ws = self._connect(url, max_queue=16 if max_lag_s is None else LAGGING_QUEUE)
        heard = len(self._heard)
        pending: deque[dict] = deque()

        def receive(wait: float) -> str | bytes | None:
            try:
                return ws.recv(timeout=wait)
            except TimeoutError:
                if wait == 0:
                    return None
                said = f" (the service said: {'; '.join(self._heard[heard:])})" if self._heard[heard:] else ""
                raise TactileError(f"no message from {url} within {timeout} s{said}") from None
            except ConnectionClosedOK as exc:
                raise TactileError(f"stream {url} closed by the service ({exc})") from None
            except ConnectionClosed as exc:
                raise TactileError(f"stream {url} lost: {exc}") from None

        behind = False  # the loop fell more than max_lag_s behind and has not caught up since
        served: dict[str, int] = {}  # address → the count of frames handed out when its last one was
        given_at, unshaped = time.monotonic(), self.unshaped  # messages whose every record is skipped are no frame
        with ws:
            for count in itertools.count():
                arrived = False
                while max_lag_s is not None and (message := receive(0)) is not None:  # what has come meanwhile
                    pending.extend(self._frames_in(message, url, wanted))
                    arrived = True
                if not pending:  # nothing waiting: the loop keeps up with the stream
                    behind = False
                    pending.extend(self._frames_in(receive(timeout), url, wanted))
                    arrived = True
                if max_lag_s is not None and arrived:
                    behind = behind or _lagging(pending, max_lag_s)
                    if behind:
                        self._count_skipped(_keep_newest(pending))
                if not pending:
                    if time.monotonic() - given_at > timeout:
                        said = _skipping_said(self._skipping, self.unshaped > unshaped)
                        raise TactileError(f"no frame from {url} within {timeout} s{said}")
                    continue
                frame = _least_recently_served(pending, served) if behind else pending.popleft()
                served[_address(frame)] = count
                yield frame
                given_at, unshaped = time.monotonic(), self.unshaped

    def _count_skipped(self, skipped: dict[str, int]) -> None:
        """Add the frames ``subscribe`` skipped (``"board/id"`` → how many) to
        ``dropped`` and ``dropped_by_sensor``."""
        for address, n in skipped.items():
            self.dropped += n
            self.dropped_by_sensor[address] = self.dropped_by_sensor.get(address, 0) + n

    def _connect(self, url: str, max_queue: int = 16):
        """The stream's WebSocket, open; TactileError naming why not."""
        from websockets.exceptions import InvalidHandshake, InvalidURI
        from websockets.sync.client import connect

        headers = {"Authorization": f"Bearer {self.token}"} if self.token else None
        try:
            return connect(url, max_size=None, open_timeout=self.timeout, additional_headers=headers, max_queue=max_queue)
        except ConnectionRefusedError:
            raise TactileError(f"stream {url}: connection refused (is tactile serve running there?)") from None
        except TimeoutError:
            raise TactileError(f"stream {url}: no answer within {self.timeout} s") from None
        except (InvalidHandshake, InvalidURI) as exc:
            raise TactileError(f"stream {url}: refused: {exc}") from None
        except OSError as exc:
            raise TactileError(f"stream {url}: cannot reach the service: {exc}") from None

    def _frames_in(self, message: str | bytes, url: str, wanted: frozenset[str]) -> Iterator[dict]:
        """The frames one stream message carries; counts ``dropped`` and keeps
        ``notices`` on the way."""
        if isinstance(message, bytes):
            try:
                records = decode_binary(message)
            except Exception as exc:
                raise TactileError(f"stream {url}: a binary message that does not decode ({exc})") from None
            yield from self._shaped_frames(records, wanted)
            return
        try:
            doc = orjson.loads(message)
            kind = doc["type"]
        except (orjson.JSONDecodeError, KeyError, TypeError) as exc:
            raise TactileError(f"stream {url}: a message that is no frame message ({exc}): "
                               f"{message[:80]!r}") from None
        if kind == "frames":
            for frame in doc["frames"]:
                yield _normalized(frame)
        elif kind == "dropped":
            self.dropped += doc["frames"]
        elif kind == "notice":
            self.notices.append(doc["detail"])
            self._heard.append(doc["detail"])
        else:
            raise TactileError(doc.get("detail", str(doc)))

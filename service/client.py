"""A small client for robot controllers.

    from service.client import TactileClient

    client = TactileClient("http://127.0.0.1:8000")
    print(client.latest(0)["force_N"])                      # one grid frame
    for frame in client.subscribe(sensors=[1], binary=True):
        fx, fy, fz = frame["force_N"]                      # quad, 1 kHz
        ...

REST over urllib, the stream over websockets (installed with uvicorn's
standard extra). ``subscribe`` yields one dict per frame — the JSON message
shape (docs/api.md), or the decoded binary record — and counts the frames
the server dropped for this client in ``dropped`` and its notices (e.g. a
subscription to sensors not announced yet) in ``notices``.
"""
from __future__ import annotations

import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator

import orjson

from .fanout.encoding import decode_binary


class TactileError(RuntimeError):
    """The service answered with an error; the message is its detail."""


class TactileClient:
    def __init__(self, base_url: str = "http://127.0.0.1:8000", token: str | None = None, timeout: float = 5.0) -> None:
        self.base_url = base_url.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.dropped = 0
        self.notices: list[str] = []

    def _request(self, method: str, path: str, body: dict | None = None):
        headers = {"Content-Type": "application/json"}
        if self.token:
            headers["Authorization"] = f"Bearer {self.token}"
        data = orjson.dumps(body) if body is not None else None
        request = urllib.request.Request(self.base_url + path, data=data, method=method, headers=headers)
        try:
            with urllib.request.urlopen(request, timeout=self.timeout) as response:
                return orjson.loads(response.read())
        except urllib.error.HTTPError as exc:
            detail = orjson.loads(exc.read() or b"{}").get("detail", exc.reason)
            raise TactileError(f"{method} {path}: {exc.code} {detail}") from None

    def health(self) -> dict:
        return self._request("GET", "/health")

    def clients(self) -> list[dict]:
        """Every WebSocket client's subscription and its latency to its socket."""
        return self._request("GET", "/clients")["clients"]

    def sensors(self) -> list[dict]:
        return self._request("GET", "/sensors")["sensors"]

    def latest(self, sensor_id: int) -> dict:
        return self._request("GET", f"/sensors/{sensor_id}/latest")

    def history(self, sensor_id: int, seconds: float = 2.0, max_points: int = 200) -> list[dict]:
        return self._request("GET", f"/sensors/{sensor_id}/history?seconds={seconds}&max_points={max_points}")

    def tare(self, sensor_id: int | None = None) -> dict:
        return self._request("POST", "/tare" if sensor_id is None else f"/sensors/{sensor_id}/tare")

    def subscribe(self, sensors: list[int] | None = None, fields: list[str] | None = None, max_rate: float | None = None,
                  batch_ms: float | None = None, binary: bool = False, timeout: float = 5.0) -> Iterator[dict]:
        """Frames as they arrive. A controller must not wait forever on a
        silent stream: TactileError when no message comes within ``timeout`` s."""
        from websockets.exceptions import ConnectionClosedOK
        from websockets.sync.client import connect

        query = {"encoding": "binary" if binary else "json"}
        if sensors is not None:
            query["sensors"] = ",".join(map(str, sensors))
        if fields is not None:
            query["fields"] = ",".join(fields)
        if max_rate is not None:
            query["max_rate"] = str(max_rate)
        if batch_ms is not None:
            query["batch_ms"] = str(batch_ms)
        url = self.base_url.replace("http", "ws", 1) + "/ws?" + urllib.parse.urlencode(query)
        with connect(url, max_size=None) as ws:
            while True:
                try:
                    message = ws.recv(timeout=timeout)
                except TimeoutError:
                    raise TactileError(f"no message from {url} within {timeout} s") from None
                except ConnectionClosedOK:
                    return
                if isinstance(message, bytes):
                    yield from decode_binary(message)
                    continue
                doc = orjson.loads(message)
                if doc["type"] == "frames":
                    yield from doc["frames"]
                elif doc["type"] == "dropped":
                    self.dropped += doc["frames"]
                elif doc["type"] == "notice":
                    self.notices.append(doc["detail"])
                else:
                    raise TactileError(doc.get("detail", str(doc)))

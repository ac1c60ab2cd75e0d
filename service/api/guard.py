"""What every request passes before the API sees it: a pure ASGI middleware.

Threats it answers (docs/security.md): a web page in the user's browser
posting to the service on localhost (cross-site requests, forms), DNS
rebinding (a hostile name resolving to 127.0.0.1), and unauthenticated
clients sending large bodies.

* ``Host`` must name the service: localhost, an IP address (a rebinding
  attack needs a name of its own), the ``--host`` it is bound to, or a
  name allowed with ``--allow-host`` (403 otherwise).
* State-changing requests (POST, PUT, PATCH, DELETE) and WebSocket
  handshakes with an ``Origin`` must come from the service's own origin
  (the page it served: Origin = http(s)://Host) or one allowed with
  ``--allow-origin`` (403 naming the origin); clients that send no Origin
  (curl, the Python client, controllers) are not browsers.
* With a token, a state-changing request must carry ``Authorization:
  Bearer <token>``, checked before its body is read (401, also for a
  malformed header).
* A state-changing request's body must be ``application/json``, at most
  ``max_body_bytes`` (413, enforced while reading), nested at most
  MAX_JSON_DEPTH deep (422 naming its depth: FastAPI's parser gives up
  within the stack somewhere under 1000 levels with a vague 400, and
  deeper documents reach recursive code behind it), and strict JSON: NaN
  and Infinity are not JSON (422).
* No page of another site may frame the service's (clickjacking: a hidden
  frame of the dashboard under a decoy, the user's click on "Tare all"
  sent by the dashboard itself, its own origin): every HTTP response says
  ``X-Frame-Options: DENY`` and ``Content-Security-Policy: frame-ancestors
  'none'``.

Headers are bounded before this runs: the server parses HTTP with h11 and a
header limit (server_options.py).
"""
from __future__ import annotations

import hmac
import ipaddress

import numpy as np
import orjson

UNSAFE_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})
LOCAL_HOSTS = ("localhost", "127.0.0.1", "::1")
DEFAULT_MAX_BODY_BYTES = 1 << 20
MAX_JSON_DEPTH = 64  # a calibration document, the deepest body the API takes, nests 5


def is_ip_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def host_name(value: str) -> str:
    """A Host header's name without its port, IPv6 brackets removed, lower case."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:value.find("]")] if "]" in value else value[1:]
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class RequestGuard:
    def __init__(self, app, bind_host: str = "127.0.0.1", token: str | None = None,
                 allow_hosts: tuple[str, ...] = (), allow_origins: tuple[str, ...] = (),
                 max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> None:
        self.app = app
        self.hosts = frozenset({*LOCAL_HOSTS, host_name(bind_host), *(host_name(h) for h in allow_hosts)})
        self.origins = frozenset(origin.rstrip("/").lower() for origin in allow_origins)
        self.expected = f"Bearer {token}".encode() if token else None
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] not in ("http", "websocket"):
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        refusal = self._refusal(scope, headers)
        if refusal is None and scope["type"] == "http" and scope["method"] in UNSAFE_METHODS:
            refusal, receive = await self._read_body(headers, receive)
        if refusal is None:
            await self.app(scope, receive, _unframeable(send) if scope["type"] == "http" else send)
        elif scope["type"] == "websocket":
            await send({"type": "websocket.close", "code": 1008, "reason": refusal[1][:120]})
        else:
            await _respond(send, *refusal)

    def _refusal(self, scope, headers: dict[str, str]) -> tuple[int, str] | None:
        host = headers.get("host", "")
        name = host_name(host)
        if name not in self.hosts and not is_ip_address(name):
            return 403, (f"host {host!r} is not this service (allowed: {', '.join(sorted(self.hosts))} and IP addresses; "
                         f"add names with --allow-host)")
        unsafe = scope["type"] == "websocket" or scope["method"] in UNSAFE_METHODS
        origin = headers.get("origin")
        if unsafe and origin is not None and not self._same_or_allowed(origin, host):
            return 403, f"origin {origin!r} may not change this service or stream from it (allow it with --allow-origin)"
        if scope["type"] == "http" and scope["method"] in UNSAFE_METHODS and self.expected is not None:
            given = headers.get("authorization", "").encode("latin-1")
            if not hmac.compare_digest(given, self.expected):
                return 401, "this endpoint needs 'Authorization: Bearer <token>' (printed by tactile serve)"
        return None

    def _same_or_allowed(self, origin: str, host: str) -> bool:
        origin = origin.rstrip("/").lower()
        return origin in self.origins or origin in (f"http://{host.lower()}", f"https://{host.lower()}")

    async def _read_body(self, headers: dict[str, str], receive):
        """Read a state-changing request's body up to the limit; (refusal, receive)."""
        declared = headers.get("content-length")
        if declared is not None and (not (declared.isascii() and declared.isdigit()) or int(declared) > self.max_body_bytes):
            return (413, f"a request body is at most {self.max_body_bytes} bytes (Content-Length: {declared})"), receive
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return (400, "the client went away"), receive
            size += len(message.get("body", b""))
            if size > self.max_body_bytes:
                return (413, f"a request body is at most {self.max_body_bytes} bytes"), receive
            chunks.append(message.get("body", b""))
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        media = headers.get("content-type", "").split(";")[0].strip().lower()
        if (body or media) and media != "application/json":  # a form's type is refused even with no body
            return (415, f"send the body as application/json, not {media or 'no type'!r}"), receive
        depth = json_depth(body)
        if depth > MAX_JSON_DEPTH:
            return (422, f"the body nests {depth} deep; at most {MAX_JSON_DEPTH} levels are taken"), receive
        if body:
            try:
                orjson.loads(body)
            except orjson.JSONDecodeError as exc:
                return (422, f"the body is not JSON (NaN and Infinity are not JSON numbers): {exc}"), receive
        replayed = False

        async def replay():
            nonlocal replayed
            if replayed:
                return await receive()
            replayed = True
            return {"type": "http.request", "body": body, "more_body": False}

        return None, replay


def json_depth(body: bytes) -> int:
    """How deep ``body``'s arrays and objects nest (0: none), brackets
    within strings not counted, without parsing it (what a parser would
    recurse into): escaped backslashes, then escaped quotes are dropped
    (left to right, as JSON reads escapes), so the quotes left delimit
    the strings; the brackets outside them are summed. A 1 MiB body in
    2-5 ms (the parse beside it: 1-70 ms), on the event loop."""
    data = np.frombuffer(body.replace(b"\\\\", b"").replace(b'\\"', b""), dtype=np.uint8)
    within = np.bitwise_xor.accumulate(data == ord('"'))  # odd quotes so far: within a string
    opening = ((data == ord("[")) | (data == ord("{"))) & ~within
    closing = ((data == ord("]")) | (data == ord("}"))) & ~within
    steps = opening.view(np.int8)[opening | closing] * 2 - 1  # +1, -1 in order
    return int(np.cumsum(steps, dtype=np.int32).max()) if steps.size else 0


NOT_FRAMEABLE = [(b"x-frame-options", b"DENY"), (b"content-security-policy", b"frame-ancestors 'none'")]


def _unframeable(send):
    """``send`` with NOT_FRAMEABLE added to the response's headers."""
    async def sending(message) -> None:
        if message["type"] == "http.response.start":
            message = {**message, "headers": [*message.get("headers", ()), *NOT_FRAMEABLE]}
        await send(message)
    return sending


async def _respond(send, status: int, detail: str) -> None:
    body = orjson.dumps({"detail": detail})
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *NOT_FRAMEABLE]})
    await send({"type": "http.response.body", "body": body})

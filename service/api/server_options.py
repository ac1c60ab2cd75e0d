"""How uvicorn serves the API: the options ``tactile serve``, the gateway and
the tests' live servers share (docs/security.md).

* HTTP is parsed by h11 with a bound on what it buffers before a request is
  complete (request line and headers): httptools, uvicorn's faster default,
  has none, and one unauthenticated request with 35 MB of headers took the
  service from 96 to 621 MB and stalled the 1 kHz stream for 2 s before the
  guard could answer 401. A request past the bound gets 400 at once. The
  REST API's request rate makes h11's cost per request immaterial; the
  streams are WebSockets, framed by the websockets library either way.
* A request must arrive within 5 s of the connection opening (or of the
  previous response), and connections are capped below the open-file
  limit, the oldest one still waiting for its request making way for a
  new one (connections.py): 1 100 slow-header connections held every
  descriptor of a 1024-file service, and with them /health, the board's
  reconnection and the registry.
* A WebSocket client's messages are read only to notice it leave: at most
  WS_MAX_MESSAGE bytes each (a client sending 16 MB messages slowed every
  stream).
* No per-message deflate: compressing every 1 kHz message costs more CPU
  than loopback or a LAN saves.
* A WebSocket handshake its parser refuses (headers past websockets'
  limits) gets 400 and is closed (ws_handshake.py); it held the connection
  open for ever.
"""
from __future__ import annotations

from .connections import BACKLOG, BoundedH11
from .ws_handshake import protocol

MAX_HEADER_BYTES = 8 << 10  # request line + headers still arriving; a browser's are a few KiB
WS_MAX_MESSAGE = 4 << 10

SERVER_OPTIONS = {
    "http": BoundedH11,
    "backlog": BACKLOG,
    "ws": protocol(),
    "h11_max_incomplete_event_size": MAX_HEADER_BYTES,
    "ws_max_size": WS_MAX_MESSAGE,
    "ws_per_message_deflate": False,
}

"""uvicorn's h11 protocol with the two bounds a slow or idle client must not outlast.

* A request must arrive whole (head, and body if any) within
  REQUEST_TIMEOUT_S of the connection opening or of the previous response,
  else the connection is closed. uvicorn has no such bound: its
  ``timeout_keep_alive`` starts only after a first response and any byte
  cancels it, so 1 100 connections each sending a header byte every 5 s
  stayed open for ever.
* At most ``max_connections`` connections (HTTP and WebSocket) are open at
  once, each with room for a file it is answered from, below the open-file
  limit by a reserve for the service's own files and for a burst of accepts
  (connection_cap). A connection past the cap
  closes the oldest one still waiting for its request (a client that has
  sent one is never waiting more than a round trip), else, when every
  connection is a WebSocket or a request being answered, itself: an
  established stream is never taken, and half-open connections cannot keep
  a controller that reconnects out. uvicorn's ``limit_concurrency`` answers
  503 only once a request has arrived whole, so it bounds neither.
* A WebSocket's kernel send buffer is WS_SEND_BUFFER: left to grow (Linux
  autotunes it to 4 MB), it held a minute of a slow client's frames, which
  then arrived in order, a minute old, while the hub's own bounded queue
  (fanout/hub.py) dropped for it without the client ever seeing a gap.
"""
from __future__ import annotations

import resource
import socket
import weakref

from uvicorn.protocols.http.h11_impl import H11Protocol

REQUEST_TIMEOUT_S = 5.0
BACKLOG = 128  # connections one accept burst takes before any is looked at (uvicorn's 2048 is twice the usual limit)
OWN_FILES = 128  # serial ports, registry, recordings, zenoh's sockets, the interpreter's: about 30 with one board
SELECT_LIMIT = 1024  # pyserial waits on a port with select(), which fails on a descriptor past 1023
MIN_CONNECTIONS = 16
# Its socket and the file a response streams from (the dashboard's and the API docs' static files: held
# while a slow reader takes 1.5 MB): 760 connections under a cap of one each held all 1024 descriptors.
DESCRIPTORS_PER_CONNECTION = 2
WS_SEND_BUFFER = 32 << 10  # bytes (the kernel doubles it): ~50 JSON grid frames, ~0.1 s of a quad's

# Per server (its uvicorn ServerState): its connections waiting for a request, oldest first.
_WAITING: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def connection_cap(soft_limit: int | None = None) -> int:
    """Connections to allow under the soft open-file limit (this process's
    by default): what leaves OWN_FILES + BACKLOG descriptors, all below
    SELECT_LIMIT, with DESCRIPTORS_PER_CONNECTION each; MIN_CONNECTIONS
    under a limit too low for that (macOS's default 256: raise it)."""
    if soft_limit is None:
        soft_limit = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    usable = SELECT_LIMIT if soft_limit == resource.RLIM_INFINITY else min(soft_limit, SELECT_LIMIT)
    return max(MIN_CONNECTIONS, (usable - OWN_FILES - BACKLOG) // DESCRIPTORS_PER_CONNECTION)


class BoundedH11(H11Protocol):
    max_connections = connection_cap()
    request_timeout_s = REQUEST_TIMEOUT_S

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._previous = None  # the cycle answered last: a request arrived when self.cycle is another, whole
        self._deadline = None
        self._waiting = _WAITING.setdefault(self.server_state, {})

    def connection_made(self, transport) -> None:
        super().connection_made(transport)
        self._await_request(None)
        if len(self.connections) > self.max_connections:
            victim = next(iter(self._waiting))  # the oldest waiting; self (the newest) when no other waits
            victim._close()
            self.connections.discard(victim)  # counted out now: its descriptor goes at the loop's next turn

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        self._check_arrived()

    def on_response_complete(self) -> None:
        answered = self.cycle
        super().on_response_complete()  # may start a pipelined request's cycle
        if not self.transport.is_closing():
            self._await_request(answered)
            self._check_arrived()

    def handle_websocket_upgrade(self, event) -> None:
        self._stop_waiting()  # the transport is the WebSocket's from now on
        sock = self.transport.get_extra_info("socket")
        if sock is not None:
            # uvloop's PseudoSocket ignores setsockopt: set it on a duplicate of its descriptor (the same socket).
            with socket.fromfd(sock.fileno(), sock.family, sock.type) as same:
                same.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, WS_SEND_BUFFER)
        super().handle_websocket_upgrade(event)

    def connection_lost(self, exc) -> None:
        self._stop_waiting()
        super().connection_lost(exc)

    def _await_request(self, previous) -> None:
        """Wait for the request after ``previous`` (a cycle, None for the first)."""
        self._stop_waiting()
        self._previous = previous
        self._waiting[self] = None
        self._deadline = self.loop.call_later(self.request_timeout_s, self._close)

    def _check_arrived(self) -> None:
        if self._deadline is not None and self.cycle is not self._previous and not self.cycle.more_body:
            self._stop_waiting()

    def _stop_waiting(self) -> None:
        if self._deadline is not None:
            self._deadline.cancel()
            self._deadline = None
        self._waiting.pop(self, None)

    def _close(self) -> None:
        self._stop_waiting()
        if not self.transport.is_closing():
            self.transport.close()

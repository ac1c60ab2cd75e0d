"""uvicorn's WebSocket protocol with a refused handshake answered and closed.

websockets' parser refuses a handshake request past its limits (a line over
8 KiB, more than 128 headers) and stops reading; uvicorn's sans-I/O
WebSocket protocol (its default since websockets' legacy one was
deprecated) then neither answered nor closed: every such request held a
connection open for ever. Here it gets 400 and the connection is closed, as
uvicorn's HTTP parser (server_options.py) and its legacy WebSocket protocol
do.
"""
from __future__ import annotations

try:
    from uvicorn.protocols.websockets.websockets_sansio_impl import WebSocketsSansIOProtocol
except ImportError:  # an older uvicorn: its default (legacy websockets) answers 400 itself
    WebSocketsSansIOProtocol = None

_BODY = b"WebSocket handshake refused (a header line past 8 KiB, or more than 128 headers)\n"
REFUSED = (b"HTTP/1.1 400 Bad Request\r\nContent-Type: text/plain\r\nConnection: close\r\n"
           b"Content-Length: %d\r\n\r\n" % len(_BODY)) + _BODY


def protocol() -> type | str:
    """What SERVER_OPTIONS["ws"] names: the class below, or "auto" where uvicorn has no sans-I/O protocol."""
    return BoundedHandshake if WebSocketsSansIOProtocol is not None else "auto"


if WebSocketsSansIOProtocol is not None:
    class BoundedHandshake(WebSocketsSansIOProtocol):
        """WebSocketsSansIOProtocol answering 400 to a handshake its parser refused."""

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if not self.handshake_initiated and self.conn.handshake_exc is not None and not self.transport.is_closing():
                self.transport.write(REFUSED)
                self.transport.close()

"""Source over pyserial: devices, ``socket://``, pty paths and ``sim://``."""
from __future__ import annotations

import io

import serial
from serial.urlhandler import protocol_socket

from . import Source, handlers


READ_BYTES = 1 << 16


class SerialSource(Source):
    def __init__(self, url: str, baudrate: int = 2_000_000) -> None:
        self.url = url
        handlers.register()
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=0, do_not_open=True)
        except ValueError as exc:  # pyserial's word for an unknown URL scheme
            raise OSError(f"cannot open {url!r}: {exc}") from None
        try:
            self._port.open()
        except (serial.SerialException, OSError) as exc:
            # pyserial's socket:// may fail after connecting (a peer that resets at once) and keep the socket.
            self.close()
            raise OSError(f"cannot open {url!r}: {exc}") from None

    def _read_internal(self, timeout: float) -> bytes:
        """Wait up to ``timeout`` for a first byte, then take everything
        already received without waiting. (``in_waiting`` cannot size the read:
        pyserial's socket:// answers 0 or 1 there, not a byte count.)"""
        try:
            self._set_timeout(timeout)
            if timeout == 0:  # the event loop saw the descriptor readable: one read takes it all
                return self._port.read(READ_BYTES)
            first = self._port.read(1)
            if not first:
                return b""
            self._set_timeout(0)
            return first + self._port.read(READ_BYTES)
        except serial.SerialException as exc:
            raise OSError(f"{self.url}: {exc}") from None

    def finished(self) -> bool:
        return bool(getattr(self._port, "finished", False))  # replay:// says so

    def read_time(self) -> float | None:
        return getattr(self._port, "read_time", None)  # replay:// knows it

    def _plain_socket(self):
        """The socket of pyserial's socket:// port (private there, without
        fileno()); None for any other port (rfc2217:// has a socket too, but
        its own reader thread drains it)."""
        if isinstance(self._port, protocol_socket.Serial):
            return self._port._socket
        return None

    def fileno(self) -> int | None:
        sock = self._plain_socket()
        if sock is not None:
            return sock.fileno()
        try:
            return self._port.fileno()  # device and pty paths
        except io.UnsupportedOperation:  # sim://, replay://: generated on read
            return None

    def _set_timeout(self, timeout: float) -> None:
        if self._port.timeout != timeout:  # on hardware, setting it reconfigures the port
            self._port.timeout = timeout

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except serial.SerialException as exc:
            raise OSError(f"{self.url}: {exc}") from None

    def close(self) -> None:
        sock = self._plain_socket()
        if sock is not None:
            # pyserial's socket:// close() leaks the socket when shutdown() fails
            # (a peer that reset) and then sleeps 0.3 s "for quick reconnects":
            # close it here and tell pyserial it is closed.
            sock.close()
            self._port._socket = None
            self._port.is_open = False
        self._port.close()

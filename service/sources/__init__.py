"""Byte sources: one small contract over every transport.

A source yields raw bytes with ``read(timeout)`` and takes host commands
with ``write``. ``open_source`` accepts anything pyserial does — a device
path (``/dev/ttyACM0``), ``socket://host:port``, ``loop://``, a pty path —
plus the simulator's ``sim://`` URL, so hardware and simulator share one
code path. Backends are imported when first used.
"""
from __future__ import annotations

import abc

DEFAULT_SOURCE = "sim://"


class Source(abc.ABC):
    """Contract: ``read`` returns the bytes received within ``timeout``
    seconds (possibly none) and raises ``OSError`` when the link is gone."""

    def read(self, timeout: float) -> bytes:
        if timeout < 0:
            raise ValueError(f"timeout must be >= 0, got {timeout}")
        return self._read_internal(timeout)

    @abc.abstractmethod
    def _read_internal(self, timeout: float) -> bytes: ...

    @abc.abstractmethod
    def write(self, data: bytes) -> None: ...

    def finished(self) -> bool:
        """Whether a finite source (a recording) has delivered everything it
        holds; a device or a socket never is."""
        return False

    def fileno(self) -> int | None:
        """A descriptor that selects readable when bytes arrive, so an event
        loop can read the source without a thread; None when there is none."""
        return None

    @abc.abstractmethod
    def close(self) -> None: ...

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def open_source(url: str, baudrate: int = 2_000_000) -> Source:
    """Open a source by URL or device path; raises OSError when it cannot."""
    from .serial_source import SerialSource

    return SerialSource(url, baudrate)


def check_source(url: str) -> None:
    """Raise ValueError, naming what is wrong, for a source that can never
    open: a scheme no handler knows, a URL its handler refuses (a bad
    sim:// option, a replay:// recording that is not there). A device or a
    socket:// peer that is missing now is no error: the readout waits for
    it to appear."""
    if "://" not in url:
        return
    from . import handlers

    scheme = url.split("://", 1)[0]
    if not scheme.isidentifier():
        raise ValueError(f"{url!r}: {scheme!r} is no URL scheme")
    module = handlers.handler_module(scheme)
    if module is None:
        raise ValueError(f"{url!r}: no handler for {scheme}:// (pyserial knows socket://, rfc2217://, loop://, "
                         f"spy://, hwgrep://, alt://; this service adds sim:// and replay://)")
    check = getattr(module, "check_url", None)
    if check is not None:
        check(url)

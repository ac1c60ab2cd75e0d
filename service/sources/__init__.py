"""Byte sources: one small contract over every transport.

A source yields raw bytes with ``read(timeout)`` and takes host commands
with ``write``. ``open_source`` accepts anything pyserial does — a device
path (``/dev/ttyACM0``), ``socket://host:port``, ``loop://``, a pty path —
plus the simulator's ``sim://`` URL, so hardware and simulator share one
code path. Backends are imported when first used.
"""
from __future__ import annotations

import abc
import urllib.parse

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

    def read_time(self) -> float | None:
        """The host time (s since the epoch) the last read's bytes stand for,
        when the source knows it better than their arrival does: a recording
        replayed on its own timeline, so that its host's pacing delays do not
        pass for the board's. None (a device, a socket): stamp them on arrival."""
        return None

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
    from . import handlers

    if "://" not in url:
        scheme = url.split(":/", 1)[0] if ":/" in url else ""
        if scheme.isidentifier() and handlers.handler_module(scheme) is not None:  # "sim:/?…": a device path never there
            raise ValueError(f"{url!r}: a {scheme} URL begins {scheme}:// (two slashes)")
        return
    scheme = url.split("://", 1)[0]
    if not scheme.isidentifier():
        raise ValueError(f"{url!r}: {scheme!r} is no URL scheme")
    module = handlers.handler_module(scheme)
    if module is None:
        raise ValueError(f"{url!r}: no handler for {scheme}:// (pyserial knows socket://, rfc2217://, loop://, "
                         f"spy://, hwgrep://, alt://; this service adds sim:// and replay://)")
    check = getattr(module, "check_url", None) or (check_host_port if scheme in ("socket", "rfc2217") else None)
    if check is not None:
        check(url)


def check_host_port(url: str) -> None:
    """ValueError naming what a socket:// or rfc2217:// URL lacks: pyserial
    would retry one without a port for ever, its reason a TypeError."""
    parts = urllib.parse.urlsplit(url)
    form = f"{parts.scheme}://HOST:PORT"
    if not parts.hostname:
        raise ValueError(f"{url!r}: no host ({form})")
    port = parts.netloc.rsplit(":", 1)[1] if ":" in parts.netloc.rsplit("]", 1)[-1] else None
    if port is None or not port.isdigit() or not 0 < int(port) < 65536:
        raise ValueError(f"{url!r}: " + ("no port" if port is None else f"port {port!r} is not 1-65535") + f" ({form})")

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

"""The readout thread: keeps a source open, reads bytes, survives unplugging.

Reading happens in one dedicated thread so that a blocking driver never
stalls the event loop. On any OSError the source is closed and reopened with
exponential backoff; the decoder's partial frame is dropped and counted, its
sequence state kept, so the scans lost while away show up as a gap.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Callable

from .sources import Source, open_source

log = logging.getLogger(__name__)

ON_CONNECT_COMMANDS = b"START\nINFO?\n"


class LinkState:
    def __init__(self, url: str) -> None:
        self.url = url
        self.up = False
        self.connects = 0
        self.last_error: str | None = None
        self.last_data_time: float | None = None

    def as_dict(self, now: float) -> dict:
        return {
            "source": self.url,
            "up": self.up,
            "connects": self.connects,
            "reconnects": max(self.connects - 1, 0),
            "last_error": self.last_error,
            "last_data_age_s": None if self.last_data_time is None else round(now - self.last_data_time, 3),
        }


class Readout(threading.Thread):
    """Reads ``url`` until stopped, handing each chunk to ``on_bytes(data, t)``
    and calling ``on_disconnect()`` whenever the link drops."""

    def __init__(
        self,
        url: str,
        on_bytes: Callable[[bytes, float], None],
        on_disconnect: Callable[[], None],
        opener: Callable[[str], Source] = open_source,
        backoff_s: tuple[float, float] = (0.05, 2.0),
        clock: Callable[[], float] = time.time,
    ) -> None:
        super().__init__(name="tactile-readout", daemon=True)
        self.link = LinkState(url)
        self._on_bytes = on_bytes
        self._on_disconnect = on_disconnect
        self._opener = opener
        self._backoff = backoff_s
        self._clock = clock
        self._stop_event = threading.Event()
        self._source: Source | None = None

    def stop(self, timeout: float = 2.0) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout)

    def run(self) -> None:
        delay = self._backoff[0]
        while not self._stop_event.is_set():
            try:
                self._source = self._opener(self.link.url)
            except OSError as exc:
                self.link.last_error = str(exc)
                self._stop_event.wait(delay)
                delay = min(delay * 2, self._backoff[1])
                continue
            self.link.up = True
            self.link.connects += 1
            delay = self._backoff[0]
            log.info("connected to %s", self.link.url)
            try:
                self._source.write(ON_CONNECT_COMMANDS)
                self._read_until_gone(self._source)
            except OSError as exc:
                self.link.last_error = str(exc)
                log.warning("link to %s lost: %s", self.link.url, exc)
            finally:
                self.link.up = False
                self._source.close()
                self._on_disconnect()
            self._stop_event.wait(delay)

    def _read_until_gone(self, source: Source) -> None:
        while not self._stop_event.is_set():
            data = source.read(0.05)
            if data:
                now = self._clock()
                self.link.last_data_time = now
                self._on_bytes(data, now)

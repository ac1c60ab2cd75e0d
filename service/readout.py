"""The readout thread: keeps a source open, reads bytes, survives unplugging.

The thread opens the source and, on any OSError, closes it and reopens it
with exponential backoff; the decoder's partial frame is dropped and counted,
its sequence state kept, so the scans lost while away show up as a gap.

Given an event loop, a source with a descriptor (a device, a pty,
``socket://``) is read by the loop itself as soon as bytes arrive, and the
thread only waits for the link to drop: a read handed from a thread to the
loop costs two wake-ups instead of one, and under load each wake-up can come
a couple of milliseconds late. Sources without one (``sim://``,
``replay://``) are read by the thread, which a blocking driver cannot stall.
While the loop is busy, a watched source's bytes wait in the kernel's and
the device's buffers (tens of KB: tens of ms at 8 sensors); a loop stalled
longer makes the board drop scans and report OVERRUN, as any host that falls
behind does — ``GET /health`` shows such stalls in its latency figures.
"""
from __future__ import annotations

import asyncio
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
    and calling ``on_disconnect()`` whenever the link drops. With ``loop``
    (given or set before ``start``), ``on_bytes`` is called on the loop's
    thread for sources it can watch."""

    def __init__(
        self,
        url: str,
        on_bytes: Callable[[bytes, float], None],
        on_disconnect: Callable[[], None],
        opener: Callable[[str], Source] = open_source,
        backoff_s: tuple[float, float] = (0.05, 2.0),
        clock: Callable[[], float] = time.time,
        loop: asyncio.AbstractEventLoop | None = None,
    ) -> None:
        super().__init__(name="tactile-readout", daemon=True)
        self.link = LinkState(url)
        self._on_bytes = on_bytes
        self._on_disconnect = on_disconnect
        self._opener = opener
        self._backoff = backoff_s
        self._clock = clock
        self.loop = loop
        self._watched_fd: int | None = None
        self._watch_lock = threading.Lock()
        self._stop_event = threading.Event()
        self._source: Source | None = None

    def stop(self, timeout: float = 2.0) -> None:
        self._unwatch()  # first: called on the loop's thread, the loop cannot serve a request while we join
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
        fd = source.fileno() if self.loop is not None else None
        if fd is not None:
            self._read_on_loop(source, fd)
            return
        while not self._stop_event.is_set():
            self._deliver(source.read(0.05))

    def _deliver(self, data: bytes) -> None:
        if data:
            now = self._clock()
            self.link.last_data_time = now
            self._on_bytes(data, now)

    def _read_on_loop(self, source: Source, fd: int) -> None:
        """The loop reads ``source`` whenever ``fd`` is readable; this thread
        waits until the link drops (raising its OSError) or the readout stops."""
        gone = threading.Event()
        failure: list[OSError] = []

        def readable() -> None:
            try:
                data = source.read(0)
            except OSError as exc:
                self._unwatch()
                failure.append(exc)
                gone.set()
                return
            self._deliver(data)

        def watch() -> None:
            if self._watched_fd == fd:  # not stopped meanwhile
                self.loop.add_reader(fd, readable)

        self._watched_fd = fd
        try:
            self.loop.call_soon_threadsafe(watch)
        except RuntimeError:  # the loop is closed: the service is going away
            self._watched_fd = None
            return
        while not gone.wait(0.05):
            if self._stop_event.is_set():
                self._unwatch()
                return
        raise failure[0]

    def _unwatch(self) -> None:
        """Make the loop stop reading before the source is closed: at once on
        the loop's own thread, else by asking it and waiting."""
        with self._watch_lock:
            fd, self._watched_fd = self._watched_fd, None
        loop = self.loop
        if fd is None or loop is None or loop.is_closed():
            return
        try:
            on_loop = asyncio.get_running_loop() is loop
        except RuntimeError:
            on_loop = False
        if on_loop:
            loop.remove_reader(fd)
            return
        done = threading.Event()
        try:
            loop.call_soon_threadsafe(lambda: (loop.remove_reader(fd), done.set()))
        except RuntimeError:  # closed meanwhile: nothing is watched any more
            return
        done.wait(1.0)

"""The readout: keeps a source open, reads bytes, survives unplugging.

Its thread opens the source and, on any OSError, closes it and reopens it
with exponential backoff (50 ms doubling to 0.5 s: a replugged device is
read again within a fraction of a second, at a few cheap attempts a second
while it is away), telling the sink ``link_lost()``. A link that goes
silent — a board that hangs, a socket whose peer stopped without closing —
is asked ``INFO?`` after ``silence_s`` and reopened if still silent half a
second later. A finite source (a recording) that has delivered everything
is ``finished``: it stays open and is not reopened. The pipeline may ask the
board ``INFO?`` too (``ask_info``: a board restarted without its INFO, or
sends frames its description cannot read), at most once per
``ASK_INFO_EVERY_S``, so that a board that never answers is not flooded;
each restart is asked, unless an INFO? asked less than INFO_REPLY_S before
may still be answered. Only the thread writes to the source: ``ask_info``
(on the event loop) hands it the INFO?, since a port that stops taking
bytes blocks a write for as long as it lasts (pyserial's has no timeout).

Where the bytes are read is decided once per connection, here
(``_read_until_gone``), as python-can's ``Notifier.add_bus`` does: given an
event loop, a source with a descriptor (a device, a pty, ``socket://``) is
read by the loop itself as soon as bytes arrive (``sink.on_loop``), and the
thread only waits for the link to drop: a read handed from a thread to the
loop costs two wake-ups instead of one, and under load each wake-up can come
a couple of milliseconds late. Sources without one (``sim://``,
``replay://``), or any source without a loop, are read by the thread
(``sink.from_thread``), which a blocking driver cannot stall.
Each read is stamped with its arrival, or with the time its source gives it
(``Source.read_time``: a replay:// read's recorded receive time on the
replay's timeline, so the clock map sees the recorded intervals, not the
replaying host's delays).
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
from typing import Callable, Protocol

from .sources import Source, open_source

log = logging.getLogger(__name__)

ON_CONNECT_COMMANDS = b"START\nINFO?\n"
DEFAULT_SILENCE_S = 2.0
REOPEN_AFTER_ASKING_S = 0.5
# A board answers INFO? with one INFO frame after the frames already in flight (protocol.md): an INFO of at
# most 1 040 bytes takes 5 ms at 2 Mbaud (200 kB/s), behind the tens of KB the device's and the kernel's
# buffers hold (0.1-0.2 s at that rate). Frames wait at most this long for it after a (re)open (identify.py).
INFO_REPLY_S = 0.25
ASK_INFO_EVERY_S = 1.0  # ask_info's: a board that never answers is asked once a second, not once per frame it sends
MIN_STALE_S = 0.5


class LinkState:
    def __init__(self, url: str) -> None:
        self.url = url
        self.up = False
        self.finished = False
        self.connects = 0
        self.connected_at: float | None = None
        self.last_error: str | None = None
        self.last_data_time: float | None = None

    def silent_s(self, now: float) -> float | None:
        """Seconds since the last byte, also one from before a reopen (a link
        reopened on a silent board has had no data since), or since the first
        connect before any byte; None while down."""
        if not self.up or self.connected_at is None:
            return None
        return now - (self.connected_at if self.last_data_time is None else self.last_data_time)

    def silent_since_open_s(self, now: float) -> float | None:
        """Seconds without a byte since this (re)open, None while down: a
        reopened link gets the full ``silence_s`` before it is asked INFO? again."""
        if not self.up or self.connected_at is None:
            return None
        return now - max(self.last_data_time or self.connected_at, self.connected_at)

    def state(self, now: float, stale_after_s: float = MIN_STALE_S) -> str:
        """up | stale (connected, no bytes for ``stale_after_s``, however
        often reopened) | down | finished (a recording's end)."""
        if self.finished:
            return "finished"
        silent = self.silent_s(now)  # once: the readout thread may drop the link meanwhile
        if silent is None:
            return "down"
        return "stale" if silent > stale_after_s else "up"

    def as_dict(self, now: float, stale_after_s: float = MIN_STALE_S) -> dict:
        silent = self.silent_s(now)
        return {
            "source": self.url,
            "state": self.state(now, stale_after_s),
            "up": self.up,
            "connects": self.connects,
            "reconnects": max(self.connects - 1, 0),
            "last_error": self.last_error,
            "last_data_age_s": None if self.last_data_time is None else round(now - self.last_data_time, 3),
            "silent_s": None if silent is None else round(silent, 3),
            "stale_after_s": stale_after_s,
        }


class ByteSink(Protocol):
    """Where the readout hands its bytes (handover.py has both kinds)."""

    def on_loop(self, data: bytes, t_host: float) -> None: ...

    def from_thread(self, data: bytes, t_host: float) -> None: ...

    def link_lost(self) -> None: ...


class Readout:
    """Reads ``url`` from ``start`` until ``stop``, handing each chunk with
    its receive time to ``sink`` and telling it whenever the link drops."""

    def __init__(
        self,
        url: str,
        sink: ByteSink,
        opener: Callable[[str], Source] = open_source,
        backoff_s: tuple[float, float] = (0.05, 0.5),
        clock: Callable[[], float] = time.time,
        silence_s: float = DEFAULT_SILENCE_S,
    ) -> None:
        if not silence_s > 0:
            raise ValueError(f"silence_s must be > 0, got {silence_s}")
        self.link = LinkState(url)
        self._silence_s = silence_s
        self._asked_at: float | None = None  # INFO? asked for the silence now
        self._info_asked_at: float | None = None  # INFO? last asked by ask_info
        self._ask_lock = threading.Lock()  # ask_info's, from any thread: held for no I/O
        self._info_wanted = False  # ask_info asked an INFO? this thread has not written yet
        self._wake = threading.Event()  # the thread has something to do now (ask_info, a failure on the loop)
        self._sink = sink
        self._opener = opener
        self._backoff = backoff_s
        self._clock = clock
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=self._run, name="tactile-readout", daemon=True)
        self._watched_fd: int | None = None
        self._watch_lock = threading.Lock()
        self._stop_event = threading.Event()
        self._source: Source | None = None

    def start(self, loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Start reading; with ``loop``, sources it can watch are read on it."""
        self._loop = loop
        self._thread.start()

    def is_alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout: float = 2.0) -> None:
        self._unwatch()  # first: called on the loop's thread, the loop cannot serve a request while we join
        self._stop_event.set()
        if self._thread.is_alive():
            self._thread.join(timeout)

    def _run(self) -> None:
        delay = self._backoff[0]
        while not self._stop_event.is_set():
            try:
                self._source = self._opener(self.link.url)
            except OSError as exc:
                self.link.last_error = str(exc)
                self._stop_event.wait(delay)
                delay = min(delay * 2, self._backoff[1])
                continue
            self.link.connects += 1
            self.link.connected_at = self._clock()
            self._asked_at, self._info_wanted = None, False  # the commands on connect ask INFO?
            delay = self._backoff[0]
            log.info("connected to %s", self.link.url)
            try:
                self.link.up = True
                self._source.write(ON_CONNECT_COMMANDS)
                self._read_until_gone(self._source)
            except OSError as exc:
                self.link.last_error = str(exc)
                log.warning("link to %s lost: %s", self.link.url, exc)
            except Exception as exc:  # a bug downstream must not end the readout for good: reopen and say why
                self.link.last_error = f"{type(exc).__name__}: {exc}"
                log.exception("reading %s failed; reopening", self.link.url)
            finally:
                self.link.up = False
                self._source.close()
                self._sink.link_lost()
            self._stop_event.wait(delay)

    def _read_until_gone(self, source: Source) -> None:
        """The one place that decides who reads: the loop, or this thread."""
        fd = source.fileno() if self._loop is not None else None
        if fd is not None:
            self._read_on_loop(source, fd)
            return
        while not self._stop_event.is_set():
            data = source.read(0.05)
            if data:
                self._sink.from_thread(data, self._received(source))
            elif source.finished():
                self.link.finished = True
                self._stop_event.wait()
            else:
                self._check_silence(source)
            self._write_asked(source)

    def _check_silence(self, source: Source) -> None:
        """Ask a silent board ``INFO?``; raise OSError (reopen) if that brings nothing."""
        now = self._clock()
        silent = self.link.silent_since_open_s(now)
        if silent is None or silent < self._silence_s:
            return
        if self._asked_at is None or self._asked_at < now - silent:  # not yet asked in this silence
            self._asked_at = now
            log.warning("no bytes from %s for %.1f s: asking INFO?", self.link.url, silent)
            source.write(b"INFO?\n")
        elif now - self._asked_at >= REOPEN_AFTER_ASKING_S:
            raise OSError(f"no bytes for {silent:.1f} s, not even after INFO?")

    def ask_info(self, restart: bool = False) -> bool:
        """Ask the board ``INFO?`` (from any thread, never waiting on the
        port: this readout's thread writes it), unless the link is down or
        this asked less than ASK_INFO_EVERY_S ago (the INFO? on connect and
        for a silence are the readout's own); True when asked. ``restart``:
        a restart whose power-up INFO was lost (the pipeline asks once per
        restart), held back only by an INFO? asked less than INFO_REPLY_S
        ago, whose answer may still come: the limit is for repeats, and a
        board restarting 0.9 s apart had every other restart not asked."""
        with self._ask_lock:
            now = self._clock()
            every = INFO_REPLY_S if restart else ASK_INFO_EVERY_S
            if not self.link.up or (self._info_asked_at is not None and now - self._info_asked_at < every):
                return False
            self._info_asked_at, self._info_wanted = now, True
        self._wake.set()
        return True

    def _write_asked(self, source: Source) -> None:
        """On this thread: the INFO? ``ask_info`` asked, if any (a failed write is the link gone, as any)."""
        if self._info_wanted:
            self._info_wanted = False
            source.write(b"INFO?\n")

    def _received(self, source: Source) -> float:
        """The stamp of a read just taken: its arrival, or the time the source
        gives it (``Source.read_time``). The link's last data is its arrival."""
        now = self._clock()
        self.link.last_data_time = now
        stamp = source.read_time()
        return now if stamp is None else stamp

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
                self._wake.set()
                return
            if data:
                self._sink.on_loop(data, self._received(source))

        def watch() -> None:
            if self._watched_fd == fd:  # not stopped meanwhile
                self._loop.add_reader(fd, readable)

        self._watched_fd = fd
        try:
            self._loop.call_soon_threadsafe(watch)
        except RuntimeError:  # the loop is closed: the service is going away
            self._watched_fd = None
            return
        while not gone.is_set():
            if self._stop_event.is_set():
                self._unwatch()
                return
            try:
                self._write_asked(source)
                self._check_silence(source)
            except OSError:
                self._unwatch()
                raise
            self._wake.wait(0.05)
            self._wake.clear()
        raise failure[0]

    def _unwatch(self) -> None:
        """Make the loop stop reading before the source is closed: at once on
        the loop's own thread, else by asking it and waiting."""
        with self._watch_lock:
            fd, self._watched_fd = self._watched_fd, None
        loop = self._loop
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

"""Bytes from the reading thread to the event loop, with backpressure.

A source the loop cannot watch (``sim://``, ``replay://``) is read by the
readout's thread, which only reads: each chunk goes into an inbox with its
receive time and the loop is woken to feed the pipeline. Reads that arrive
while the loop is busy go through together, so under load the batches grow
instead of the backlog. A source the loop watches hands its bytes over on
the loop itself (``on_loop``), after anything still queued.

The pipeline runs on the loop, not the reading thread: with the pipeline in
the reading thread, every socket send of the loop (which releases the GIL)
handed the GIL back to the reconstruction for up to a switch interval
(5 ms), and latency piled up.
"""
from __future__ import annotations

import asyncio
import threading
from typing import Callable

INBOX_LIMIT_BYTES = 1 << 22  # ~3 s of 8 sensors at 1 kHz read but not yet decoded

Feed = Callable[[list[tuple[bytes, float]], Callable], None]


class LoopHandover:
    """The readout's byte sink when an event loop runs the pipeline.

    ``feed(chunks, defer)`` is called on the loop with every chunk queued,
    in order, and the loop's ``call_soon`` to defer work to its next turn;
    ``link_lost()`` on the loop where the link dropped between chunks."""

    def __init__(self, feed: Feed, link_lost: Callable[[], None], loop: asyncio.AbstractEventLoop,
                 limit_bytes: int = INBOX_LIMIT_BYTES) -> None:
        self._feed = feed
        self._link_lost = link_lost
        self._loop = loop
        self._limit = limit_bytes
        self._inbox: list[tuple[bytes, float] | None] = []  # None marks a lost link
        self._lock = threading.Lock()
        self._bytes = 0
        self._drained = threading.Event()
        self._drain_scheduled = False

    @property
    def queued_bytes(self) -> int:
        return self._bytes

    @property
    def pending(self) -> bool:
        return bool(self._inbox)

    def on_loop(self, data: bytes, t_host: float) -> None:
        """A chunk read by the loop itself: fed at once, after anything queued."""
        if self._inbox:
            self.drain()
        self._feed([(data, t_host)], self._loop.call_soon)

    def from_thread(self, data: bytes, t_host: float) -> None:
        """A chunk read by the readout's thread: queued, the loop woken."""
        self._post((data, t_host))

    def link_lost(self) -> None:
        self._post(None)

    def drain(self) -> None:
        """On the loop: feed everything queued, in order, as few batches as possible."""
        with self._lock:
            items, self._inbox, self._bytes = self._inbox, [], 0
            self._drain_scheduled = False
            self._drained.set()
        chunks: list[tuple[bytes, float]] = []
        for item in items:
            if item is not None:
                chunks.append(item)
                continue
            self._feed(chunks, self._loop.call_soon)
            chunks = []
            self._link_lost()
        self._feed(chunks, self._loop.call_soon)

    def _post(self, item: tuple[bytes, float] | None) -> None:
        with self._lock:
            self._inbox.append(item)
            self._bytes += 0 if item is None else len(item[0])
            full = self._bytes > self._limit
            if full:
                self._drained.clear()
            wake = not self._drain_scheduled
            self._drain_scheduled = True
        if wake and not self._loop.is_closed():
            self._loop.call_soon_threadsafe(self.drain)
        if full:
            # A host that cannot keep up must not buffer without end: the reader
            # waits, the port's buffer fills and the board reports OVERRUN.
            self._drained.wait(1.0)


class ThreadSink:
    """The readout's byte sink without an event loop (``tactile record``,
    tests): the reading thread feeds the pipeline itself."""

    def __init__(self, feed: Callable[[bytes, float], object], link_lost: Callable[[], None]) -> None:
        self.from_thread = self.on_loop = feed
        self.link_lost = link_lost

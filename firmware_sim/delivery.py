"""Delivery jitter: a link that hands a board's bytes on late, never early.

A host does not see a frame when the board scanned it: the USB stack, the
driver and the reading thread add a delay that varies, and whatever piled
up meanwhile arrives in one read, every frame of it stamped with the read's
time. ``DelayedLink`` models that with one draw per chunk (the bytes one
``put`` hands it): the chunk comes out at ``now + U(0, jitter)``, never
before an earlier chunk (a serial link keeps its order). ``deliveries``
runs a board and such a link on a virtual clock, as fast as the CPU allows,
for studies of the board clock against the host's (service.clock_map).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from .board import Board, BoardConfig

_STREAM = 0x6A17  # the link's random stream, apart from the board's noise (same seed, other draws)
_EPSILON_S = 1e-9  # past a scan's time by more than the rounding of board time to true time and back


class DelayedLink:
    """Bytes in at ``put(data, now)``, out at ``take(now)`` once their chunk's delay has passed."""

    def __init__(self, jitter_ms: float, seed: int = 0) -> None:
        self._jitter_s = jitter_ms * 1e-3
        self._rng = np.random.default_rng([seed, _STREAM])
        self._chunks: deque[tuple[float, bytes]] = deque()
        self._last = -math.inf
        self.pending = 0  # bytes held

    def put(self, data: bytes, now: float) -> None:
        if data:
            self._last = max(self._last, now + self._rng.uniform(0.0, self._jitter_s))
            self._chunks.append((self._last, data))
            self.pending += len(data)

    def take(self, now: float) -> bytes:
        out = bytearray()
        while self._chunks and self._chunks[0][0] <= now:
            out += self._chunks.popleft()[1]
        self.pending -= len(out)
        return bytes(out)

    @property
    def next_release(self) -> float:
        """When the next chunk comes out (inf when none is held)."""
        return self._chunks[0][0] if self._chunks else math.inf


def deliveries(config: BoardConfig, seconds: float) -> list[tuple[float, bytes]]:
    """(receive time, bytes) of every read of a board for ``seconds`` of true time.

    The board hands each scan to the link as it completes it; the reader takes
    a chunk the moment it comes out (``config.jitter_ms`` later at most), so a
    read holds one scan or several that a late one held up.
    """
    board = Board(config)
    link = DelayedLink(config.jitter_ms, config.seed)
    link.put(board.power_up(), 0.0)
    reads: list[tuple[float, bytes]] = []
    while (now := board.next_scan_time + _EPSILON_S) <= seconds:
        while link.next_release <= now:
            release = link.next_release
            reads.append((release, link.take(release)))
        link.put(board.advance(now), now)
    return reads

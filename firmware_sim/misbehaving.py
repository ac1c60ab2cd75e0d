"""A TCP 'board' that misbehaves on demand, for tests and studies of a
service reading several boards (tests/test_boards.py, scripts/floodlatency.py).

It streams a real capture (an 8x8 grid and a quad at 1 kHz), and as its
``phase`` is set: goes ``silent``, ``flood``s (64 KiB of frames and 8 KiB of
junk every 5 ms, as fast as the socket takes them, ~50x a board's rate), or,
``stop`` set, disappears (connection and listening socket closed).
"""
from __future__ import annotations

import socket
import threading
import time

import numpy as np

from .board import BoardConfig, capture
from .sensors import SimGrid, SimQuad


class MisbehavingBoard:
    """Listens on 127.0.0.1 (``port``); the phase is set from outside:
    "stream" (the default), "silent", "flood"; ``stop.set()`` makes it go."""

    def __init__(self) -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.phase = "stream"  # then "silent", "flood", "gone"
        self.stop = threading.Event()
        data, _ = capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="press", seed=9), 20.0)
        self.data = data
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        """One connection at a time; the service reconnecting (after the
        silence) gets a new one, served in the phase of the moment."""
        self.server.settimeout(0.05)
        pos, started = 0, time.monotonic()
        conn = None
        try:
            while not self.stop.is_set():
                try:
                    new, _ = self.server.accept()
                    if conn is not None:
                        conn.close()
                    conn = new
                except TimeoutError:
                    pass
                if conn is None or self.phase == "silent":
                    continue
                try:
                    if self.phase == "stream":  # the capture at its own rate
                        due = int((time.monotonic() - started) * len(self.data) / 20.0)
                        conn.sendall(self.data[pos:due])
                        pos = due
                    else:  # flood: 64 KiB of frames and 8 KiB of junk every 5 ms, ~50x a board's rate
                        junk = np.random.default_rng(pos).integers(0, 256, 8192, np.uint8).tobytes()
                        conn.sendall(self.data[pos % 65536:pos % 65536 + 65536] + junk)
                        pos += 65536
                        time.sleep(0.005)
                except OSError:
                    conn.close()
                    conn = None
        finally:
            if conn is not None:
                conn.close()
            self.server.close()

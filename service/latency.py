"""How long frames take through the service, as the service sees it.

A controller that misses a deadline wants to know whether the time went in
the service or after it (network, its own process). The service stamps every
chunk when it is read (``t_host``); these meters keep, per stage, how long
after that stamp the last frames were published (decoded and reconstructed)
and handed to a WebSocket client's socket. ``GET /health`` reports them.
One sample per published batch or sent message, that of its oldest frame
(the worst of the batch): a float store, so measuring costs next to nothing
at 8 000 frames/s.
"""
from __future__ import annotations

import numpy as np

WINDOW_SAMPLES = 10_000  # ~5 s of 1 ms reads; 10 s of an unbatched 1 kHz client


class LatencyMeter:
    """Ring of the last ``capacity`` latencies (seconds) of one stage.

    Parameters
    ----------
    capacity : samples kept; percentiles are over these
    """

    def __init__(self, capacity: int = WINDOW_SAMPLES) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be at least 1, got {capacity}")
        self._samples = np.zeros(capacity)
        self._next = 0
        self.count = 0

    def add(self, seconds: float) -> None:
        self._samples[self._next] = seconds
        self._next = (self._next + 1) % self._samples.size
        self.count += 1

    def summary(self) -> dict:
        """Samples in all, and p50 / p99 / max in ms over the window (None
        while nothing was measured)."""
        count = self.count  # /health reads from a worker thread while the loop adds
        kept = self._samples[: min(count, self._samples.size)].copy()
        if kept.size == 0:
            return {"samples": 0, "window": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
        p50, p99 = np.percentile(kept, [50, 99]) * 1000.0
        return {"samples": count, "window": int(kept.size), "p50_ms": round(float(p50), 3),
                "p99_ms": round(float(p99), 3), "max_ms": round(float(kept.max()) * 1000.0, 3)}

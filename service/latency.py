"""How long frames take through the service, as the service sees it.

A controller that misses a deadline wants to know whether the time went in
the service or after it (network, its own process). The service stamps every
chunk when it is read (``t_host``); these meters keep, per stage, how long
after that stamp the last frames were published (decoded and reconstructed)
and handed to a WebSocket client's socket. ``GET /health`` reports them.
"""
from __future__ import annotations

import numpy as np

WINDOW_SAMPLES = 10_000  # ~1.25 s of 8 sensors at 1 kHz per stage


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

    def add(self, now: float, stamps: list[float]) -> None:
        """Record ``now - stamp`` for each receive stamp (frames of one batch
        or one message)."""
        n = len(stamps)
        if n == 0:
            return
        capacity = self._samples.size
        if n > capacity:
            stamps, n = stamps[-capacity:], capacity
        end = self._next + n
        values = now - np.asarray(stamps, dtype=float)
        if end <= capacity:
            self._samples[self._next:end] = values
        else:
            split = capacity - self._next
            self._samples[self._next:] = values[:split]
            self._samples[: n - split] = values[split:]
        self._next = end % capacity
        self.count += n

    def summary(self) -> dict:
        """Frames measured in all, and p50 / p99 / max in ms over the window
        (None while nothing was measured)."""
        kept = self._samples[: min(self.count, self._samples.size)]
        if kept.size == 0:
            return {"frames": 0, "window": 0, "p50_ms": None, "p99_ms": None, "max_ms": None}
        p50, p99 = np.percentile(kept, [50, 99]) * 1000.0
        return {"frames": self.count, "window": int(kept.size), "p50_ms": round(float(p50), 3),
                "p99_ms": round(float(p99), 3), "max_ms": round(float(kept.max()) * 1000.0, 3)}

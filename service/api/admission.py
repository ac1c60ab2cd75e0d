"""Heavy reads admitted at a bounded rate, before the framework sees them.

A history read costs the event loop (routing, validation, the answer's
bytes) far more than a frame of the live stream; twenty dashboards polling
at 5 Hz kept the loop busy often enough to push the 1 kHz path's p99 past
its 2 ms budget even with tiny answers. This middleware answers heavy
requests beyond ``rate_per_s`` (burst ``burst``) with 429 at the ASGI level,
which costs a few microseconds; the rest go on to the routes, which bound
their concurrency and share recent answers (routes_sensors.py).
"""
from __future__ import annotations

import time

import orjson


def is_heavy(scope) -> bool:
    return scope["type"] == "http" and scope["method"] == "GET" and scope["path"].endswith("/history")


class Admission:
    def __init__(self, app, rate_per_s: float = 4.0, burst: float = 4.0, clock=time.monotonic) -> None:
        self.app = app
        self.rate_per_s = rate_per_s
        self.burst = burst
        self._clock = clock
        self._tokens = burst
        self._last = clock()

    def admit(self) -> bool:
        """Take a token if there is one (the event loop's thread only: no lock)."""
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate_per_s)
        self._last = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True

    async def __call__(self, scope, receive, send) -> None:
        if not is_heavy(scope) or self.admit():
            await self.app(scope, receive, send)
            return
        body = orjson.dumps({"detail": f"history reads are admitted at {self.rate_per_s:g} per second; retry shortly"})
        await send({"type": "http.response.start", "status": 429,
                    "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                                (b"retry-after", b"1")]})
        await send({"type": "http.response.body", "body": body})

"""Counts over the last seconds: what /health names while it goes on and
forgets once it stops (a sensor's dropped frames, the board's ERROR frames,
corrupt frames, the waits for the board's INFO), where the counters since
start only grow."""
from __future__ import annotations

import math
from collections import deque

# Long enough that a problem recurring every few seconds stays named, short enough that one that stopped goes soon.
PROBLEM_WINDOW_S = 10


class RecentCount:
    """Events counted per whole second of host time (s since the epoch), the
    last ``window_s`` + 1 seconds kept; ``latest``: what the last one said.
    O(1) per event. An event stamped before the newest counts in its second
    (host time stepped back)."""

    __slots__ = ("window_s", "_seconds", "latest")

    def __init__(self, window_s: int = PROBLEM_WINDOW_S) -> None:
        self.window_s = window_s
        self._seconds: deque[list[int]] = deque(maxlen=window_s + 1)  # [second, count], oldest first
        self.latest: str | None = None

    def add(self, t: float, n: int = 1, latest: str | None = None) -> None:
        second = math.floor(t)
        seconds = self._seconds
        if seconds and second <= seconds[-1][0]:
            seconds[-1][1] += n
        else:
            seconds.append([second, n])
        if latest is not None:
            self.latest = latest

    def recent(self, now: float) -> int:
        """Events in the seconds that end within the last ``window_s`` before ``now``."""
        start = now - self.window_s
        return sum(n for second, n in self._seconds if second + 1 > start)


class RecentCorruption:
    """A decoder's frames and CRC errors over the last ``window_s``, the
    errors also by the sensor id their (unverified) headers claim: ``note``
    takes the decoder's counters after each read with its receive time."""

    def __init__(self, window_s: int = PROBLEM_WINDOW_S) -> None:
        self.window_s = window_s
        self.frames = RecentCount(window_s)
        self.corrupt = RecentCount(window_s)
        self.by_sensor: dict[int, RecentCount] = {}
        self._frames = self._corrupt = 0
        self._claimed: dict[int, int] = {}  # CRC errors so far by claimed sensor id

    def note(self, t: float, counters) -> None:
        """``counters``: protocol_decoder.StreamCounters, as after a read received at ``t``."""
        if counters.frames != self._frames:
            self.frames.add(t, counters.frames - self._frames)
            self._frames = counters.frames
        if counters.crc_errors == self._corrupt:  # the usual read: one compare
            return
        self.corrupt.add(t, counters.crc_errors - self._corrupt)
        self._corrupt = counters.crc_errors
        for sid, sensor in counters.sensors.items():
            new = sensor.crc_errors - self._claimed.get(sid, 0)
            if new:
                self.by_sensor.setdefault(sid, RecentCount(self.window_s)).add(t, new)
                self._claimed[sid] = sensor.crc_errors


class RecentIdentification:
    """A live link's waits for the board's INFO (identify.py) over the last
    ``window_s``: those begun at a restart whose power-up INFO was lost
    (``restarts``: one per restart of the board, where the decoder counts one
    per sensor), and those that ended without it (``unanswered``; ``note``
    takes the identification's count after each read with its receive time:
    a wait that its timer ended counts at the next read)."""

    def __init__(self, window_s: int = PROBLEM_WINDOW_S) -> None:
        self.window_s = window_s
        self.restarts = RecentCount(window_s)
        self.unanswered = RecentCount(window_s)
        self._unanswered = 0

    def note(self, t: float, unanswered: int) -> None:
        if unanswered != self._unanswered:
            self.unanswered.add(t, unanswered - self._unanswered)
            self._unanswered = unanswered

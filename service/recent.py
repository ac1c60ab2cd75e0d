"""Counts over the last seconds: what /health names while it goes on and
forgets once it stops (a sensor's dropped frames, the board's ERROR frames,
corrupt frames, the waits for the board's INFO), where the counters since
start only grow; and ``MostRecent``, state kept for the names used last."""
from __future__ import annotations

import math
from collections import deque

from .protocol import BOARD_SENSOR_ID

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
    """A decoder's data frames (GRID, QUAD: not the board's INFO and ERROR
    frames, which a board may send by the thousand) and their CRC errors
    (those whose unverified header claims a sensor, not the board's own id),
    the errors also by that sensor id, and the bytes received and skipped
    (no part of a good frame), over the last ``window_s``: ``note`` takes
    the decoder's counters after each read with its receive time."""

    def __init__(self, window_s: int = PROBLEM_WINDOW_S) -> None:
        self.window_s = window_s
        self.frames = RecentCount(window_s)
        self.corrupt = RecentCount(window_s)
        self.bytes_in = RecentCount(window_s)
        self.discarded = RecentCount(window_s)
        self.by_sensor: dict[int, RecentCount] = {}
        self._frames = self._corrupt = self._bytes_in = self._discarded = 0
        self._claimed: dict[int, int] = {}  # CRC errors so far by claimed sensor id

    def note(self, t: float, counters) -> None:
        """``counters``: protocol_decoder.StreamCounters, as after a read received at ``t``."""
        data = counters.frames - counters.control_frames
        if data != self._frames:
            self.frames.add(t, data - self._frames)
            self._frames = data
        if counters.bytes_in != self._bytes_in:
            self.bytes_in.add(t, counters.bytes_in - self._bytes_in)
            self._bytes_in = counters.bytes_in
        if counters.bytes_discarded != self._discarded:
            self.discarded.add(t, counters.bytes_discarded - self._discarded)
            self._discarded = counters.bytes_discarded
        if counters.crc_errors == self._corrupt:  # the usual read: one compare
            return
        self._corrupt = counters.crc_errors
        corrupt = 0
        for sid, sensor in counters.sensors.items():
            new = sensor.crc_errors - self._claimed.get(sid, 0)
            if new and sid != BOARD_SENSOR_ID:
                self.by_sensor.setdefault(sid, RecentCount(self.window_s)).add(t, new)
                self._claimed[sid] = sensor.crc_errors
                corrupt += new
        if corrupt:
            self.corrupt.add(t, corrupt)


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


class MostRecent(dict):
    """A dict of at most ``limit`` keys: setting or reading one (``[]``,
    ``get``) makes it the most recent, and beyond ``limit`` the least recent
    is forgotten. For state per name where the names come from the network
    (unauthenticated peers may make up any number): the names in use stay,
    a flood of others keeps memory flat. Not thread-safe: lock around it
    where several threads use it."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit = limit

    def __getitem__(self, key):
        value = super().pop(key)
        super().__setitem__(key, value)
        return value

    def get(self, key, default=None):
        return self[key] if key in self else default

    def __setitem__(self, key, value) -> None:
        super().pop(key, None)
        super().__setitem__(key, value)
        while len(self) > self.limit:
            del self[next(iter(self))]

    def __reduce__(self):
        return type(self), (self.limit,), None, None, iter(list(self.items()))  # copy, pickle: the limit first

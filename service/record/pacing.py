"""Playback pacing: recorded times released at a speed, on an injectable clock."""
from __future__ import annotations

import math
import time
from typing import Callable

# The slowest speed a replay takes: slower is a typing slip (a day's recording would take 27 years).
MIN_SPEED = 1e-4
MAX_SLEEP_S = 1e6  # one sleep at most (11.6 days): a longer wait is slept in pieces


def parse_speed(text: str) -> float:
    """'1', '2.5', … (at least MIN_SPEED) or 'max' (as fast as possible:
    math.inf); ValueError naming the text otherwise."""
    if text == "max":
        return math.inf
    try:
        speed = float(text)
    except ValueError:
        raise ValueError(f"speed {text!r} must be a number or 'max'") from None
    if not speed > 0:
        raise ValueError(f"speed {text!r} must be > 0")
    if speed < MIN_SPEED:
        raise ValueError(f"speed {text!r} must be at least {MIN_SPEED}")
    return speed


class Timeline:
    """Recorded times moved onto a replay's own timeline on the host's wall
    clock: the first is now, each later one ``(t − t_first)/speed`` after it
    (a replay's stamps then keep the recorded intervals, not the delays of
    the host that replays them). At ``math.inf`` there is none (``at``: None)."""

    def __init__(self, speed: float = 1.0, clock: Callable[[], float] = time.time) -> None:
        if not speed > 0:
            raise ValueError(f"replay speed must be > 0, got {speed}")
        self.speed = speed
        self._clock = clock
        self._anchor: tuple[float, float] | None = None

    def at(self, t_recorded: float) -> float | None:
        """Wall-clock seconds of recorded time ``t_recorded`` (s); None at speed max."""
        if math.isinf(self.speed):
            return None
        if self._anchor is None:
            self._anchor = (t_recorded, self._clock())
        return self._anchor[1] + (t_recorded - self._anchor[0]) / self.speed


class Pacer:
    """Releases recorded times at ``speed`` × real time (math.inf: no waiting).

    The first call anchors recorded time to the clock; ``clock`` and
    ``sleep`` are injectable so tests run on a virtual clock."""

    def __init__(self, speed: float = 1.0, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if not speed > 0:
            raise ValueError(f"replay speed must be > 0, got {speed}")
        self.speed = speed
        self._clock = clock
        self._sleep = sleep
        self._anchor: tuple[float, float] | None = None

    def wait(self, t_recorded: float, size: int = 0) -> None:
        """Until ``t_recorded`` (s) is due; ``size``: the bytes this wait
        releases, for a progress display (pacing goes by time alone)."""
        if math.isinf(self.speed):
            return
        if self._anchor is None:
            self._anchor = (t_recorded, self._clock())
            return
        due = self._anchor[1] + (t_recorded - self._anchor[0]) / self.speed
        delay = due - self._clock()
        while delay > 0:  # in pieces: time.sleep overflows past 2**63 ns (an 11-day recording at MIN_SPEED)
            self._sleep(min(delay, MAX_SLEEP_S))
            delay = due - self._clock()

"""Which physical sensor a SensorInfo describes, and what changes when another takes its place.

A sensor is the one its serial names (INFO's optional ``serial``,
protocol.md), else sensor ``id`` of the board its INFO names (serial, else
model) — the identity the calibration registry keys it by
(calibration/registry.py sensor_identity). When an INFO describes another
sensor at an address (a board restart with another sensor plugged in, or
only the serial changing), the reconstruction makes it a new state:
calibration looked up again for the new identity, a new tare, its own
load-cycle counts. ``Replacements`` keeps what a user is told of it
(/health) and the counters of the sensors that left, so that one plugged
back continues its own count (its wear), live and in a replay alike, and
the zeros they left with, so that one plugged back is judged against its
own (stored_zero.py): re-tared on the load it came back with, a quad back
under 2 N read 0.000 N unflagged. Those zeros are kept while they can be
used (MAX_AGE_S) and LEFT_ZEROS at most: a board flapping between many
identities does not grow them without limit.
"""
from __future__ import annotations

from ..readings import SensorInfo
from .fatigue import CycleCounter

LEFT_ZEROS = 64  # zeros of sensors that left kept at most, the oldest dropped first


def identity(info: SensorInfo) -> tuple:
    """What tells one physical sensor from another (module docstring)."""
    if info.serial:
        return ("serial", info.serial)
    board = info.board_info or {}
    return ("board", board.get("serial") or board.get("board") or info.board_identity, info.id)


def named(info: SensorInfo) -> bool:
    """Whether an INFO named the sensor (a serial, or a board): one known
    only from its data frames is named by its board's first INFO, not replaced."""
    return bool(info.serial or info.board_info or info.board_identity)


def described(info: SensorInfo) -> str:
    """The identity in words, for /health and the log."""
    if info.serial:
        return f"serial {info.serial!r}"
    board = identity(info)[1]
    return f"sensor {info.id} of board {board!r}" if board else f"sensor {info.id} of an unnamed board"


class Replacements:
    """Per address, how often another sensor took its place and the last
    change ({count, from, to}); the load-cycle counters and zeros of sensors
    that left. ``max_zero_age_s``: a zero older than that is of no use (dropped)."""

    def __init__(self, max_zero_age_s: float = float("inf")) -> None:
        self.changes: dict[int, dict] = {}
        self._left: dict[tuple, tuple[SensorInfo, CycleCounter]] = {}  # (identity, calibration id) → (its info, counter)
        self._zeros: dict[tuple, dict] = {}  # (identity, calibration id) → the zero it left with (stored_zero.row)
        self.max_zero_age_s = max_zero_age_s

    def replaced(self, old: SensorInfo, new: SensorInfo, calibration_id: str, cycles: CycleCounter | None,
                 zero: dict | None = None) -> dict | None:
        """``new`` describes the address ``old`` did: the change, counted, when it is another sensor (else None);
        ``old``'s counter and ``zero`` (stored_zero.row, ``saved`` on its readings' clock) are kept for its return."""
        if not named(old) or identity(old) == identity(new):
            return None
        if cycles is not None:
            self._left[(identity(old), calibration_id)] = (old, cycles)
        if zero is not None:
            self.keep_zero(identity(old), calibration_id, zero)
        count = self.changes.get(new.id, {}).get("count", 0) + 1
        change = self.changes[new.id] = {"count": count, "from": described(old), "to": described(new)}
        return change

    def returning(self, info: SensorInfo, calibration_id: str) -> CycleCounter | None:
        """The counter a sensor that left had under this calibration, now
        that it is back (None: it never left); its count goes on from there."""
        _, counter = self._left.pop((identity(info), calibration_id), (None, None))
        if counter is not None:
            counter.at_start = counter.counts.tolist()  # where a recording of its return starts it
        return counter

    def keep_zero(self, key: tuple, calibration_id: str, zero: dict) -> None:
        """Keep the zero sensor ``key`` (its identity) left with under this calibration, dropping those older than
        ``max_zero_age_s`` before it and the oldest past LEFT_ZEROS."""
        self._zeros.pop((key, calibration_id), None)
        self._zeros[(key, calibration_id)] = zero
        oldest = zero["saved"] - self.max_zero_age_s
        for stale in [k for k, kept in self._zeros.items() if kept["saved"] < oldest]:
            del self._zeros[stale]
        while len(self._zeros) > LEFT_ZEROS:
            del self._zeros[next(iter(self._zeros))]

    def returning_zero(self, info: SensorInfo, calibration_id: str) -> dict | None:
        """The zero a sensor that left had under this calibration, now that it is back (None: none kept)."""
        return self._zeros.pop((identity(info), calibration_id), None)

    def left_zeros(self) -> list[dict]:
        """The zeros kept, oldest first: {identity, calibration, zero}, what a recording begun now stores."""
        return [{"identity": list(key), "calibration": cid, "zero": zero} for (key, cid), zero in self._zeros.items()]

    def left_counts(self) -> list[tuple[SensorInfo, str, list[int]]]:
        """(info, calibration id, counts) of counters that left, to keep (the registry)."""
        return [(info, cid, counter.counts.tolist()) for (_, cid), (info, counter) in list(self._left.items())]

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
back continues its own count (its wear), live and in a replay alike.
"""
from __future__ import annotations

from ..readings import SensorInfo
from .fatigue import CycleCounter


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
    change ({count, from, to}); the load-cycle counters of sensors that left."""

    def __init__(self) -> None:
        self.changes: dict[int, dict] = {}
        self._left: dict[tuple, tuple[SensorInfo, CycleCounter]] = {}  # (identity, calibration id) → (its info, counter)

    def replaced(self, old: SensorInfo, new: SensorInfo, calibration_id: str, cycles: CycleCounter | None) -> dict | None:
        """``new`` describes the address ``old`` did: the change, counted, when it is another sensor (else None)."""
        if not named(old) or identity(old) == identity(new):
            return None
        if cycles is not None:
            self._left[(identity(old), calibration_id)] = (old, cycles)
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

    def left_counts(self) -> list[tuple[SensorInfo, str, list[int]]]:
        """(info, calibration id, counts) of counters that left, to keep (the registry)."""
        return [(info, cid, counter.counts.tolist()) for (_, cid), (info, counter) in list(self._left.items())]

"""Readings: one data frame in picofarads, and the sensor it came from.

GRID/QUAD payloads are u32 attofarad channels whose sentinels (0xFFFFFFFF
open, 0 shorted) become NaN, never a capacitance (interpreter.py makes
readings; board_info.py reads what INFO says about the sensors).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .protocol import FLAG_OVERRUN, FLAG_SATURATED

OPEN_SENTINEL = 0xFFFFFFFF
SHORT_SENTINEL = 0x00000000
AF_PER_PF = 1e6
MAX_SENSOR_ID = 254  # 255 is the board itself
MAX_CHANNELS = 256  # a payload holds at most 1024 bytes of u32 channels


@dataclass(frozen=True, slots=True)
class SensorInfo:
    id: int
    kind: str  # "grid" | "quad"
    rows: int
    cols: int
    serial: str | None = None  # the sensor's own identity, when INFO carries one
    board: str = ""  # the name of the board it is on: a sensor's address is board/id
    # Without a serial of its own, a sensor is known by its board's (protocol.md), else the board's model:
    # another board on the same link makes it another sensor (new tare, its own calibration). None until
    # the link's board changed (the first INFO, after data or not, names the board the sensors were on).
    board_identity: str | None = None
    # The board's INFO (top-level fields) in force when this description was made ({} before any): what
    # its calibration is looked up under, as of its readings (the reconstruction may run later, joined).
    board_info: dict | None = field(default=None, compare=False, hash=False, repr=False)

    @property
    def channels(self) -> int:
        return self.rows * self.cols

    @property
    def address(self) -> str:
        return f"{self.board}/{self.id}"

    def as_dict(self) -> dict:
        # Without the serial: this is the export format the replay goldens pin.
        return {"id": self.id, "kind": self.kind, "rows": self.rows, "cols": self.cols}


@dataclass(slots=True)
class Reading:
    """One data frame in physical units.

    ``capacitance_pF`` has shape (rows*cols,) for a grid (row-major) or (4,)
    for a quad in the order C11, C12, C21, C22; NaN where the channel sent a
    sentinel, which ``open_mask``/``short_mask`` tell apart.
    """

    sensor: SensorInfo
    seq: int
    t_us: int
    t_host: float
    board_flags: int
    gap: int
    capacitance_pF: np.ndarray
    open_channel: bool
    shorted_channel: bool
    board_restart: bool = False
    t_host_scan: float = math.nan  # the scan's time on the host clock (clock_map.py); NaN: not mapped
    clock_suspect: bool = False  # t_host_scan may be off by the read's lateness (ClockMap.suspect)
    # Read before the board said what it is since its link opened or it restarted (Interpreter.unidentified):
    # the description and zeros in force may be another board's.
    unidentified: bool = False

    def frame_flags(self) -> list[str]:
        if not (self.board_flags or self.gap or self.board_restart or self.open_channel or self.shorted_channel
                or self.clock_suspect or self.unidentified):
            return []  # the usual frame: once per frame at 1 kHz, so the common case is one test
        flags = []
        if self.board_flags & FLAG_SATURATED:
            flags.append("saturated")
        if self.board_flags & FLAG_OVERRUN:
            flags.append("overrun")
        if self.gap:
            flags.append("seq_gap")
        if self.board_restart:
            flags.append("board_restart")
        if self.open_channel:
            flags.append("open_channel")
        if self.shorted_channel:
            flags.append("shorted_channel")
        if self.clock_suspect:
            flags.append("clock_suspect")
        if self.unidentified:
            flags.append("unidentified")
        return flags

"""Frames → readings: what the board announced, and data frames in picofarads.

The decoder only checks the protocol envelope. This module knows what the
payloads mean: INFO describes the board's sensors (grid shape, kind), ERROR
carries board text, and GRID/QUAD payloads are u32 attofarad channels whose
sentinels (0xFFFFFFFF open, 0 shorted) become NaN, never a capacitance.
"""
from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass

import numpy as np
import orjson

from .protocol import FLAG_OVERRUN, FLAG_SATURATED, Frame, FrameType

log = logging.getLogger(__name__)

OPEN_SENTINEL = 0xFFFFFFFF
SHORT_SENTINEL = 0x00000000
AF_PER_PF = 1e6


@dataclass(frozen=True, slots=True)
class SensorInfo:
    id: int
    kind: str  # "grid" | "quad"
    rows: int
    cols: int

    @property
    def channels(self) -> int:
        return self.rows * self.cols

    def as_dict(self) -> dict:
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

    def frame_flags(self) -> list[str]:
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
        return flags


def default_sensor(sensor_id: int, frame: Frame) -> SensorInfo | None:
    """What a data frame means without INFO: a quad is always 4 channels and
    the protocol fixes a 256-byte grid as 8x8; any other grid is unknown."""
    if frame.type == FrameType.QUAD:
        return SensorInfo(sensor_id, "quad", 2, 2)
    if frame.type == FrameType.GRID and len(frame.payload) == 256:
        return SensorInfo(sensor_id, "grid", 8, 8)
    return None


def parse_info(payload: bytes) -> tuple[dict, dict[int, SensorInfo]]:
    """Parse an INFO payload; raise ValueError naming what is wrong. A sensor
    of a kind this service does not know is left out (logged), so one exotic
    sensor does not hide the shapes of the others."""
    try:
        doc = orjson.loads(payload)
    except orjson.JSONDecodeError as exc:
        raise ValueError(f"INFO payload is not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"INFO payload must be a JSON object, got {type(doc).__name__}")
    sensors: dict[int, SensorInfo] = {}
    for entry in doc.get("sensors", []):
        if not isinstance(entry, dict) or not isinstance(entry.get("id"), int):
            raise ValueError(f"INFO sensor entry without an integer id: {entry!r}")
        sid, kind = entry["id"], entry.get("kind")
        if kind == "quad":
            sensors[sid] = SensorInfo(sid, "quad", 2, 2)
        elif kind == "grid":
            rows, cols = entry.get("rows"), entry.get("cols")
            if not (isinstance(rows, int) and isinstance(cols, int) and rows > 0 and cols > 0 and rows * cols <= 256):
                raise ValueError(f"INFO grid sensor {sid} has invalid shape rows={rows!r} cols={cols!r}")
            sensors[sid] = SensorInfo(sid, "grid", rows, cols)
        else:
            log.warning("INFO: ignoring sensor %s of unknown kind %r", sid, kind)
    return doc, sensors


class Interpreter:
    """Keeps the board description and turns data frames into readings."""

    def __init__(self, clock=time.time) -> None:
        self.board: dict = {}
        self.sensors: dict[int, SensorInfo] = {}
        self.board_errors: deque[tuple[float, str]] = deque(maxlen=50)
        self.rejected = {"info_invalid": 0, "shape_mismatch": 0, "unknown_shape": 0}
        self._clock = clock

    def interpret(self, frame: Frame, t_host: float | None = None) -> Reading | None:
        """Return a reading for a data frame, or None for INFO/ERROR frames and
        for data frames whose payload does not fit the announced sensor."""
        t_host = self._clock() if t_host is None else t_host
        if frame.type == FrameType.INFO:
            self._on_info(frame.payload)
            return None
        if frame.type == FrameType.ERROR:
            text = frame.payload.decode("utf-8", errors="replace")
            log.warning("board error: %s", text)
            self.board_errors.append((t_host, text))
            return None
        info = self.sensors.get(frame.sensor)
        if info is None:
            info = default_sensor(frame.sensor, frame)
            if info is None:
                self.rejected["unknown_shape"] += 1
                return None
            self.sensors[frame.sensor] = info
        expected_kind = "grid" if frame.type == FrameType.GRID else "quad"
        if info.kind != expected_kind or len(frame.payload) != 4 * info.channels:
            self.rejected["shape_mismatch"] += 1
            return None
        raw = np.frombuffer(frame.payload, dtype="<u4")
        capacitance = raw / AF_PER_PF
        # The two sentinels are the ends of the u32 range: one wrapped compare finds both.
        sentinel = (raw - np.uint32(SHORT_SENTINEL + 1)) >= np.uint32(OPEN_SENTINEL - 1)
        opened = shorted = False
        if np.count_nonzero(sentinel):  # ndarray.any() costs 5x more at this size
            capacitance[sentinel] = np.nan
            opened = bool((raw == OPEN_SENTINEL).any())
            shorted = bool((raw == SHORT_SENTINEL).any())
        return Reading(info, frame.seq, frame.t_us, t_host, frame.flags, frame.gap, capacitance, opened, shorted,
                       frame.board_restart)

    def _on_info(self, payload: bytes) -> None:
        try:
            doc, sensors = parse_info(payload)
        except ValueError as exc:
            self.rejected["info_invalid"] += 1
            log.warning("ignoring INFO frame: %s", exc)
            return
        self.board = {k: v for k, v in doc.items() if k != "sensors"}
        self.sensors.update(sensors)

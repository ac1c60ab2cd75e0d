"""What a board's INFO says: its fields and its sensors' descriptions
(protocol.md), and what a data frame means without one."""
from __future__ import annotations

import logging
import re

import orjson

from .protocol import Frame, FrameType
from .readings import MAX_CHANNELS, MAX_SENSOR_ID, SensorInfo

log = logging.getLogger(__name__)


def default_sensor(sensor_id: int, frame: Frame) -> SensorInfo | None:
    """What a data frame means without INFO: a quad is always 4 channels and
    the protocol fixes a 256-byte grid as 8x8; any other grid is unknown."""
    if frame.type == FrameType.QUAD:
        return SensorInfo(sensor_id, "quad", 2, 2)
    if frame.type == FrameType.GRID and len(frame.payload) == 256:
        return SensorInfo(sensor_id, "grid", 8, 8)
    return None


# Top-level INFO fields and the JSON types they must have (bool is an int
# subclass in Python, so it is excluded explicitly where a number is meant).
_BOARD_FIELDS = {"board": str, "fw": str, "serial": str, "rate_hz": (int, float), "pong": bool, "sensors": list}


def _has_type(value, types) -> bool:
    return isinstance(value, types) and (types is bool or not isinstance(value, bool))


def _is_int(value) -> bool:
    return _has_type(value, int)


def _parse_sensor(entry) -> SensorInfo | None:
    """One ``sensors`` entry; None for a well-formed sensor of a kind this
    service does not know."""
    if not isinstance(entry, dict):
        raise ValueError(f"INFO sensor entry is not an object: {entry!r}")
    sid, kind, serial = entry.get("id"), entry.get("kind"), entry.get("serial")
    if not (_is_int(sid) and 0 <= sid <= MAX_SENSOR_ID):
        raise ValueError(f"INFO sensor entry without an integer id in 0..{MAX_SENSOR_ID}: {entry!r}")
    if not isinstance(kind, str):
        raise ValueError(f"INFO sensor {sid} has no kind string: {kind!r}")
    if "serial" in entry and not isinstance(serial, str):
        raise ValueError(f"INFO sensor {sid} has a serial that is not a string: {serial!r}")
    if kind == "quad":
        return SensorInfo(sid, "quad", 2, 2, serial)
    if kind == "grid":
        rows, cols = entry.get("rows"), entry.get("cols")
        if not (_is_int(rows) and _is_int(cols) and rows > 0 and cols > 0 and rows * cols <= MAX_CHANNELS):
            raise ValueError(f"INFO grid sensor {sid} has invalid shape rows={rows!r} cols={cols!r}")
        return SensorInfo(sid, "grid", rows, cols, serial)
    log.warning("INFO: ignoring sensor %s of unknown kind %r", sid, kind)
    return None


def parse_info(payload: bytes) -> tuple[dict, dict[int, SensorInfo], dict[int, str]]:
    """Parse an INFO payload into (its document, its sensors by id, why each
    sensor it names but leaves undescribed is so, by id); raise ValueError
    naming what is wrong. Any field of the wrong JSON type invalidates the
    whole INFO (the protocol's rule); unknown keys are ignored. A sensor of
    a kind this service does not know is left out (logged), so one exotic
    sensor does not hide the shapes of the others; so is one described
    twice in two ways (the same description twice counts once)."""
    try:
        doc = orjson.loads(payload)
    except orjson.JSONDecodeError as exc:
        raise ValueError(f"INFO payload is not JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"INFO payload must be a JSON object, got {type(doc).__name__}")
    for name, types in _BOARD_FIELDS.items():
        if name in doc and not _has_type(doc[name], types):
            raise ValueError(f"INFO field {name!r} has the wrong type: {doc[name]!r}")
    if doc.get("rate_hz", 1) <= 0:
        raise ValueError(f"INFO rate_hz {doc['rate_hz']!r} is not positive")
    sensors: dict[int, SensorInfo] = {}
    first: dict[int, SensorInfo | None] = {}
    conflicting: set[int] = set()
    for entry in doc.get("sensors", []):
        info = _parse_sensor(entry)
        sid = entry["id"]
        if sid in first:  # the same description again is harmless; two different ones say nothing sure
            if info != first[sid]:
                conflicting.add(sid)
            continue
        first[sid] = info
        if info is not None:
            sensors[sid] = info
    for sid in sorted(conflicting):
        sensors.pop(sid, None)
        log.warning("INFO describes sensor %s twice, differently: it is left undescribed (its data frames give "
                    "its shape), the board and its other sensors are taken", sid)
    undescribed = {sid: "gives it a kind this service does not know" for sid, info in first.items() if info is None}
    undescribed.update({sid: "describes it twice, differently" for sid in conflicting})
    return doc, sensors, undescribed


UNNAMED_BOARD = "board"


def name_from_info(board: dict) -> str:
    """A board's name from its INFO: its serial, else its model name, made
    address-safe (letters, digits, '_', '-'), else ``board``."""
    text = board.get("serial") or board.get("board") or ""
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)[:32] or UNNAMED_BOARD

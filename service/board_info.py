"""What a board's INFO says: its fields and its sensors' descriptions
(protocol.md), and what a data frame means without one."""
from __future__ import annotations

import logging
import math
import re

import orjson

from .protocol import MAX_PAYLOAD, Frame, FrameType
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


UNKNOWN_KIND = "gives it a kind this service does not know"  # a board's other sensors (a thermistor): no fault

# Top-level INFO fields and the JSON types they must have (bool is an int
# subclass in Python, so it is excluded explicitly where a number is meant).
_BOARD_FIELDS = {"board": str, "fw": str, "serial": str, "rate_hz": (int, float), "pong": bool, "sensors": list}


def _has_type(value, types) -> bool:
    return isinstance(value, types) and (types is bool or not isinstance(value, bool))


def _is_int(value) -> bool:
    return _has_type(value, int)


def _parse_sensor(entry) -> tuple[int, SensorInfo | None, str | None]:
    """One ``sensors`` entry: (its id, its SensorInfo, None), or (its id,
    None, why it is left undescribed: a kind this service does not know, a
    shape no grid can have, an id no sensor can have). ValueError for a field of the wrong JSON type, which makes the
    whole INFO invalid (protocol.md); a value out of range only sets that
    sensor aside, so one mis-described sensor does not stop the others'."""
    if not isinstance(entry, dict):
        raise ValueError(f"INFO sensor entry is not an object: {entry!r}")
    sid, kind, serial = entry.get("id"), entry.get("kind"), entry.get("serial")
    if not _is_int(sid):
        raise ValueError(f"INFO sensor entry without an integer id: {entry!r}")
    if not isinstance(kind, str):
        raise ValueError(f"INFO sensor {sid} has no kind string: {kind!r}")
    if "serial" in entry and not isinstance(serial, str):
        raise ValueError(f"INFO sensor {sid} has a serial that is not a string: {serial!r}")
    if not 0 <= sid <= MAX_SENSOR_ID:
        return sid, None, f"gives it an id no sensor can have (ids are 0..{MAX_SENSOR_ID})"
    if kind == "quad":
        return sid, SensorInfo(sid, "quad", 2, 2, serial), None
    if kind == "grid":
        rows, cols = entry.get("rows"), entry.get("cols")
        for name, value in (("rows", rows), ("cols", cols)):
            if value is not None and not _is_int(value):
                raise ValueError(f"INFO grid sensor {sid} has {name} that is not an integer: {value!r}")
        if rows is None or cols is None or rows <= 0 or cols <= 0 or rows * cols > MAX_CHANNELS:
            return sid, None, (f"gives it a shape no grid frame can have (rows={rows!r}, cols={cols!r}: each 1 or more, "
                          f"at most {MAX_CHANNELS} channels)")
        return sid, SensorInfo(sid, "grid", rows, cols, serial), None
    return sid, None, f"{UNKNOWN_KIND} ({kind!r})"


def parse_info(payload: bytes) -> tuple[dict, dict[int, SensorInfo], dict[int, str]]:
    """Parse an INFO payload into (its document, its sensors by id, why each
    sensor it names but leaves undescribed is so, by id); raise ValueError
    naming what is wrong. Any field of the wrong JSON type invalidates the
    whole INFO (the protocol's rule); unknown keys are ignored. A sensor of
    a kind this service does not know, or of a shape no grid can have, is
    left out (logged), so one mis-described sensor does not hide the shapes
    of the others; so is one described twice in two ways (the same
    description twice counts once)."""
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
    parsed = [_parse_sensor(entry) for entry in doc.get("sensors", [])]  # every entry's types first
    sensors: dict[int, SensorInfo] = {}
    first: dict[int, SensorInfo | None] = {}
    undescribed: dict[int, str] = {}
    conflicting: set[int] = set()
    for sid, info, why in parsed:
        if sid in first:  # the same description again is harmless; two different ones say nothing sure
            if info != first[sid]:
                conflicting.add(sid)
            continue
        first[sid] = info
        if info is not None:
            sensors[sid] = info
        else:
            undescribed[sid] = why
            log.warning("sensor %s: the INFO %s; it is left undescribed (its data frames give its shape where "
                        "they can), the board and its other sensors are taken", sid, why)
    for sid in sorted(conflicting):
        sensors.pop(sid, None)
        log.warning("INFO describes sensor %s twice, differently: it is left undescribed (its data frames give "
                    "its shape), the board and its other sensors are taken", sid)
    undescribed.update({sid: "describes it twice, differently" for sid in conflicting})
    return doc, sensors, undescribed


# A long sensor entry as a board spaces it (a grid with its shape and a serial).
INFO_ENTRY_MAX_BYTES = len(', {"id": 254, "kind": "grid", "rows": 16, "cols": 16, "serial": "A8-2291-0001"}')


def info_is_full(size: int, entries: int) -> bool:
    """Whether an INFO payload of ``size`` bytes listing ``entries`` sensors
    had no room under the protocol's MAX_PAYLOAD (1024 bytes) for another:
    less room left than the payload spends per sensor it lists (its own
    fields counted in: an entry as this board writes it, over-estimated;
    30 bytes a spaced quad entry among 33), or than a long entry takes
    (INFO_ENTRY_MAX_BYTES). A board of more sensors than fit lists what fits
    (protocol.md: ids 0..254), and the rest are read from their frames."""
    room = MAX_PAYLOAD - size
    return room < min(size / entries if entries else math.inf, INFO_ENTRY_MAX_BYTES)


UNNAMED_BOARD = "board"


def name_from_info(board: dict) -> str:
    """A board's name from its INFO: its serial, else its model name, made
    address-safe (letters, digits, '_', '-'), else ``board``."""
    text = board.get("serial") or board.get("board") or ""
    return re.sub(r"[^A-Za-z0-9_-]", "_", text)[:32] or UNNAMED_BOARD

"""Frame encodings: the message a robot controller receives, in JSON and in a
compact binary form, and the replay export's JSON line.

Shaped after ROS habits (std_msgs/Header, TactileState-like named arrays,
geometry_msgs/WrenchStamped for the quad):

    {"header": {"board": "left", "sensor_id": 0, "sensor_name": "grid0", "kind": "grid",
                "seq": 1250, "board_time_us": 1251000, "stamp": 1795342752.12,
                "scan_stamp": 1795342752.1187, "calibration": "3f2a…" | "builtin-table1",
                "instance": "arm-pc:4711:3b3e8d"},                  # a gateway's frames only
     "rows": 8, "cols": 8,
     "force_N": [64 numbers, row-major, null = no reading],      # grid, calibrated
     "sigma_N": [64 numbers: 1-σ of each force, null = none],    # grid, fields=sigma
     "wrench": {"force": {"x": …, "y": …, "z": …}},             # quad, calibrated
     "wrench_sigma": {"force": {"x": …, "y": …, "z": …}},       # quad, fields=sigma
     "raw": {"capacitance_pF": [...]},                          # fields=raw
     "contact": {"total_N", "cop_x_mm", "cop_y_mm", "area_mm2", "contacts"},
     "flags": [...], "taxel_flags": {"saturated": [27]}}

``board`` is the name of the board the sensor is on (a sensor's address is
board/sensor_id); ``stamp`` is the host time at which the bytes were received (s since the
epoch), ``board_time_us`` the board clock (wraps at 2^32), ``scan_stamp``
the scan's time on the host clock (the board clock mapped to it,
service/clock_map.py; null until mapped), ``calibration``
the id of the calibration the forces rest on (the registry's, or a
built-in: docs/calibration.md), ``instance`` (a gateway's frames) the
service that published the frame: seq and board_time_us begin again with
another instance, whose first frame of each sensor is flagged
board_restart. Numbers are numbers, never strings; null means no value.

Binary (``encoding=binary``), little-endian, one record per frame,
concatenated; a message starts with the u16 record count:

    u8 version (4) · u8 kind (0 grid, 1 quad) · u8 sensor id · u8 field bits
    (1 force, 2 raw, 4 sigma, 8 taxel flags) · u16 seq · u32 board_time_us · f64 stamp ·
    f64 scan_stamp (NaN: not mapped) · u32 frame-flag bits (FRAME_FLAG_BITS order) · u16 n · u8 m ·
    m bytes calibration id (ASCII) · u8 b · b bytes board name (ASCII) · f32[n] force · f32[n] sigma (if
    requested) · f32[n'] raw (if requested; n' = channels) · u8[n] taxel flags (a grid's, with the
    ``flags`` field; bits of reconstruct/taxel_flags.py's TAXEL_FLAG_NAMES) — NaN = no value. n is always
    the frame's force count (forces NaN when not asked for), so a record's size follows from its head.
Version 4 added the taxel flags: a binary client learns which taxels are
saturated, stale or corrected, as a JSON one does. ``decode_binary`` also
reads version 3 records (no taxel flags; n was 0 when neither force nor σ
was asked for), so a gateway or client upgraded first still reads a
service that was not.

The replay export (``tactile replay --export``, the recorder's ``forces``
topic) is flatter, one object per frame: see ``to_export_dict``.
The HTTP schema models documenting these shapes are in ``service.api.schemas``.
"""
from __future__ import annotations

import struct

import numpy as np

from ..reconstruct import ForceFrame
from ..reconstruct.force_frame import taxel_flag_lists

FIELDS = ("force", "sigma", "raw", "contact", "flags")
DEFAULT_FIELDS = frozenset({"force", "sigma", "contact", "flags"})
FRAME_FLAG_BITS = (
    "taring", "saturated", "overrun", "seq_gap", "open_channel", "shorted_channel", "out_of_range",
    "crosstalk_corrected", "drift_suspect", "stale", "normal_out_of_range", "shear_out_of_range", "electrode_fault",
    "board_restart", "reconstruction_error", "loaded_at_tare", "clock_suspect", "unidentified",
)
_FLAG_BIT = {name: 1 << i for i, name in enumerate(FRAME_FLAG_BITS)}
_RECORD = struct.Struct("<BBBBHIddIHB")
BINARY_VERSION = 4
READABLE_VERSIONS = (3, 4)  # 3: the same record without taxel flags


def sensor_name(frame: ForceFrame) -> str:
    return f"{frame.sensor.kind}{frame.sensor.id}"


def sigma_of(frame: ForceFrame) -> np.ndarray:
    """The frame's 1-σ of each force, shape of ``forces_N``: NaN (null) per force
    where it has none (the tare window), as docs/api.md's ``sigma_N`` says."""
    return frame.sigma_N if frame.sigma_N is not None else np.full(len(frame.forces_N), np.nan)


def to_json_dict(frame: ForceFrame, fields: frozenset[str] = DEFAULT_FIELDS) -> dict:
    info = frame.sensor
    out: dict = {
        "header": {
            "board": info.board,
            "sensor_id": info.id,
            "sensor_name": sensor_name(frame),
            "kind": info.kind,
            "seq": frame.seq,
            "board_time_us": frame.t_us,
            "stamp": frame.t_host,
            "scan_stamp": None if frame.t_host_scan != frame.t_host_scan else frame.t_host_scan,
            "calibration": frame.calibration,
        }
    }
    if frame.instance:
        out["header"]["instance"] = frame.instance
    sigma = sigma_of(frame)
    if info.kind == "grid":
        out["rows"], out["cols"] = info.rows, info.cols
        if "force" in fields:
            out["force_N"] = frame.forces_N
        if "sigma" in fields:
            out["sigma_N"] = sigma
        if "contact" in fields:
            out["contact"] = frame.contact
    else:
        if "force" in fields:
            out["wrench"] = _wrench(frame.forces_N)
        if "sigma" in fields:
            out["wrench_sigma"] = _wrench(sigma)
    if "raw" in fields:
        out["raw"] = {"capacitance_pF": frame.capacitance_pF}
    if "flags" in fields:
        out["flags"] = frame.flags
        if info.kind == "grid":
            out["taxel_flags"] = frame.taxel_flag_lists()
    return out


def _wrench(fxyz: np.ndarray) -> dict:
    fx, fy, fz = (None if np.isnan(v) else float(v) for v in fxyz)
    return {"force": {"x": fx, "y": fy, "z": fz}}


def to_export_dict(frame: ForceFrame) -> dict:
    """The replay export / recording shape (one JSON object per frame). Two
    literals, not one dict grown per kind: an offline export builds one per frame."""
    info = frame.sensor
    if info.kind == "grid":  # the shape, which the flat taxel list does not say (a 4×4 and a 2×8 grid both have 16)
        return {"board": info.board, "sensor": info.id, "seq": frame.seq, "t_us": frame.t_us, "kind": info.kind,
                "rows": info.rows, "cols": info.cols, "taxels_N": frame.forces_N, "sigma_N": sigma_of(frame),
                "calibration": frame.calibration, "flags": frame.flags,
                "taxel_flags": taxel_flag_lists(frame.taxel_flags), "contact": frame.contact}
    return {"board": info.board, "sensor": info.id, "seq": frame.seq, "t_us": frame.t_us, "kind": info.kind,
            "fxyz_N": frame.forces_N, "sigma_N": sigma_of(frame), "calibration": frame.calibration, "flags": frame.flags}


def to_binary(frame: ForceFrame, fields: frozenset[str] = DEFAULT_FIELDS) -> bytes:
    info = frame.sensor
    flag_bits = 0
    for name in frame.flags:
        flag_bits |= _FLAG_BIT.get(name, 0)
    with_sigma = "sigma" in fields
    with_taxel_flags = "flags" in fields and info.kind == "grid"
    field_bits = ((1 if "force" in fields else 0) | (2 if "raw" in fields else 0) | (4 if with_sigma else 0)
                  | (8 if with_taxel_flags else 0))
    forces = np.asarray(frame.forces_N, dtype="<f4")  # always n values (NaN unless asked for): n sizes the record
    calibration = frame.calibration.encode("ascii", "replace")[:255]
    board = info.board.encode("ascii", "replace")[:255]
    head = _RECORD.pack(BINARY_VERSION, 0 if info.kind == "grid" else 1, info.id, field_bits, frame.seq,
                        frame.t_us, frame.t_host, frame.t_host_scan, flag_bits, forces.size, len(calibration))
    sigma = b""
    if with_sigma:
        sigma = (np.full(forces.size, np.nan, "<f4") if frame.sigma_N is None else np.asarray(frame.sigma_N, "<f4")).tobytes()
    if "force" not in fields:
        forces = np.full(forces.size, np.nan, "<f4")
    raw = np.asarray(frame.capacitance_pF, dtype="<f4").tobytes() if "raw" in fields else b""
    taxel_flags = b""
    if with_taxel_flags:
        taxel_flags = bytes(forces.size) if frame.taxel_flags is None else np.asarray(frame.taxel_flags, np.uint8).tobytes()
    return head + calibration + bytes((len(board),)) + board + forces.tobytes() + sigma + raw + taxel_flags


def decode_binary(message: bytes) -> list[dict]:
    """Parse a binary message (for clients and tests). A grid has as many
    raw channels as forces, a quad 4: each record says its own size, also
    after a sensor changed shape."""
    (count,) = struct.unpack_from("<H", message, 0)
    pos, out = 2, []
    for _ in range(count):
        version, kind, sid, field_bits, seq, t_us, stamp, scan_stamp, flag_bits, n, m = _RECORD.unpack_from(message, pos)
        if version not in READABLE_VERSIONS:
            raise ValueError(f"binary record version {version}, this decoder reads {READABLE_VERSIONS}")
        pos += _RECORD.size
        calibration = message[pos:pos + m].decode("ascii")
        pos += m
        board = message[pos + 1:pos + 1 + message[pos]].decode("ascii")
        pos += 1 + message[pos]
        record = {"board": board, "sensor_id": sid, "kind": "grid" if kind == 0 else "quad", "seq": seq, "board_time_us": t_us,
                  "stamp": stamp, "scan_stamp": scan_stamp, "calibration": calibration,
                  "flags": [name for name, bit in _FLAG_BIT.items() if flag_bits & bit]}
        record["force_N"] = np.frombuffer(message, "<f4", n, pos)
        pos += 4 * n
        if field_bits & 4:
            record["sigma_N"] = np.frombuffer(message, "<f4", n, pos)
            pos += 4 * n
        if field_bits & 2:
            m = n if kind == 0 else 4
            if kind == 0 and n == 0:  # version 3 with raw alone: nothing in the record sizes it
                raise ValueError(f"a version {version} grid record with raw channels and no forces cannot be sized")
            record["capacitance_pF"] = np.frombuffer(message, "<f4", m, pos)
            pos += 4 * m
        if field_bits & 8:
            record["taxel_flag_bits"] = np.frombuffer(message, np.uint8, n, pos)
            record["taxel_flags"] = taxel_flag_lists(record["taxel_flag_bits"])
            pos += n
        out.append(record)
    return out

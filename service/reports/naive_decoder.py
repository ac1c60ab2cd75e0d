"""A naive reference decoder for the bench: protocol v1 read straight from
its text (docs/protocol.md), first-order forces, the replay's JSON lines.

Frame by frame: find the sync, check version, length and CRC, skip one
byte on any failure; GRID 8×8 and QUAD payloads become forces to first
order, F = (C/C0 − 1)/s per taxel with table 1's C0 and s, a quad's
electrodes r = C/C0 − 1 (nominal C0) combined as in level0.py (eqs 19, 30,
32, the small-force slopes); sentinels give null. Each frame is written as
``tactile replay --export`` writes it (the same keys; no per-taxel flags, a
contact summary of total force, centre of pressure and area).

    python -m service.reports.naive_decoder CAPTURE.bin OUT.jsonl
"""
from __future__ import annotations

import struct
import sys
from binascii import crc_hqx

import numpy as np
import orjson

from ..physics.paper_data import (PITCH_MM, QUAD_DIELECTRIC_MM, QUAD_ELECTRODE_AREA_MM2, QUAD_NORMAL_SLOPE_PER_N,
                                  QUAD_SHEAR_SLOPE_PER_N, table1, taxel_centres_mm)

HEADER = struct.Struct("<2sBBBBHIH")
QUAD_C0_PF = 8.854e-3 * 5.0 * QUAD_ELECTRODE_AREA_MM2 / QUAD_DIELECTRIC_MM  # ε0·εr·S/d, εr = 5


def frames(data: bytes):
    """(type, sensor, flags, seq, t_us, payload) of every frame that checks out."""
    pos = 0
    while (start := data.find(b"\xa5\x5a", pos)) >= 0 and start + 16 <= len(data):
        _, version, ftype, sensor, flags, seq, t_us, length = HEADER.unpack_from(data, start)
        end = start + 16 + length
        if version != 1 or length > 1024 or end > len(data) or \
                crc_hqx(data[start + 2 : end - 2], 0xFFFF) != int.from_bytes(data[end - 2 : end], "little"):
            pos = start + 1
            continue
        yield ftype, sensor, flags, seq, t_us, data[start + 14 : end - 2]
        pos = end


def export(data: bytes, out) -> int:
    cal = table1()
    x, y = taxel_centres_mm(8, 8)
    written = 0
    for ftype, sensor, flags, seq, t_us, payload in frames(data):
        if ftype not in (0x10, 0x11) or len(payload) not in (16, 256):
            continue
        counts = np.frombuffer(payload, "<u4")
        c = np.where((counts == 0) | (counts == 0xFFFFFFFF), np.nan, counts / 1e6)
        doc = {"sensor": sensor, "seq": seq, "t_us": t_us, "kind": "grid" if ftype == 0x10 else "quad"}
        if ftype == 0x10 and counts.size == 64:
            doc["rows"] = doc["cols"] = 8
            forces = (c / cal.c0_pF - 1.0) / cal.sensitivity_per_N
            loaded = np.nan_to_num(forces) > 0.05
            total = float(forces[loaded].sum())
            doc["taxels_N"] = forces
            doc["flags"] = ["saturated"] * (flags & 1) + ["overrun"] * (flags >> 1 & 1)
            doc["taxel_flags"] = {}
            doc["contact"] = {"total_N": total, "cop_x_mm": float(x[loaded] @ forces[loaded]) / total if total else None,
                              "cop_y_mm": float(y[loaded] @ forces[loaded]) / total if total else None,
                              "area_mm2": int(loaded.sum()) * PITCH_MM**2}
        elif ftype == 0x11 and counts.size == 4:
            r11, r12, r21, r22 = c / QUAD_C0_PF - 1.0
            doc["fxyz_N"] = np.array([(r12 + r22 - r11 - r21) / 4 / QUAD_SHEAR_SLOPE_PER_N,
                                      (r21 + r22 - r11 - r12) / 4 / QUAD_SHEAR_SLOPE_PER_N,
                                      (r11 + r12 + r21 + r22) / 4 / QUAD_NORMAL_SLOPE_PER_N])
            doc["flags"] = []
        else:
            continue
        out.write(orjson.dumps(doc, option=orjson.OPT_SERIALIZE_NUMPY) + b"\n")
        written += 1
    return written


if __name__ == "__main__":
    with open(sys.argv[1], "rb") as source, open(sys.argv[2], "wb") as sink:
        export(source.read(), sink)

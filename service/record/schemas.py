"""JSON schemas of the recorded MCAP channels.

Bytes travel base64-encoded (the JSON convention Foxglove reads). The 8x8
forces are also written as ``foxglove.Grid`` (one FLOAT32 cell per taxel,
4 mm cells) so a recording opens as a heat map in Foxglove.
"""
from __future__ import annotations

import orjson

RAW_BYTES = {
    "title": "tactile.RawBytes",
    "description": "Bytes exactly as the port delivered them, with the host receive time",
    "type": "object",
    "properties": {
        "t_host": {"type": "number", "description": "host receive time, s since the epoch"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}

RAW_FRAME = {
    "title": "tactile.RawFrame",
    "description": "One data frame's channels in picofarads (null for a sentinel)",
    "type": "object",
    "properties": {
        "sensor": {"type": "integer"},
        "seq": {"type": "integer"},
        "t_us": {"type": "integer", "description": "board clock, µs, wraps at 2^32"},
        "capacitance_pF": {"type": "array", "items": {"type": ["number", "null"]}},
    },
}

CALIBRATION = {
    "title": "tactile.Calibration",
    "description": "The calibration a sensor's forces rest on from here on (a registry document; a built-in one "
                   "is its id alone), written when the recording first uses it",
    "type": "object",
    "properties": {
        "board": {"type": "string", "description": "the board's name (recordings before boards were named: absent)"},
        "sensor": {"type": "integer"},
        "id": {"type": "string"},
        "key": {"type": "string", "description": "the sensor's identity (registry key) it was chosen under: a "
                                                 "board's INFO may name the board later, and the calibration then"},
        "document": {"type": ["object", "null"]},
        "cycles_at_start": {"type": ["array", "null"], "items": {"type": "integer"},
                            "description": "load cycles counted under this calibration when the recording began"},
    },
}

BASELINES = {
    "title": "tactile.Baselines",
    "description": "The zeros in force when a recording began on a running service (sensors tared before it): "
                   "a replay starts from them instead of taring afresh on whatever load the recording begins with; "
                   "a sensor then taring has its window so far instead (taring), which the replay goes on with",
    "type": "object",
    "properties": {
        "board": {"type": "string"},
        "info": {"type": "object", "description": "the board's INFO in force when the recording began (its bytes do "
                                                  "not hold it): the sensors' shapes, serials, rate"},
        "sensors": {"type": "array", "items": {"type": "object", "properties": {
            "sensor": {"type": "integer"},
            "baseline_pF": {"type": "array", "items": {"type": ["number", "null"]}},
            "std_pF": {"type": "array", "items": {"type": ["number", "null"]}},
            "loaded": {"type": "array", "items": {"type": "integer"},
                       "description": "taxels whose zero is the calibration's C0 (loaded at the tare)"},
            "zero_sigma": {"type": "array", "items": {"type": "number"},
                           "description": "per channel, the σ (ΔC/C0) of the zero kept at a loaded tare "
                                          "(reconstruct/loaded_tare.py kept_zero_sigma), 0 where tared"},
            "judge": {"type": "boolean", "description": "the zero is judged against a calibration set later (false: a "
                                                      "forced tare's, the load present is the zero; absent: true)"},
            "taring": {"type": ["object", "null"], "description": "a tare window in progress (no baseline_pF then): "
                                                                "readings seen, restarts, and per channel its valid "
                                                                "readings' count, sum_pF, sum_sq_pF2, samples_pF "
                                                                "(baseline.py window_so_far)"},
            "stale_last_pF": {"type": "array", "items": {"type": ["number", "null"]},
                              "description": "each channel's last reading, where its stale count stands"},
            "stale_runs": {"type": "array", "items": {"type": "integer"},
                           "description": "frames each channel had repeated that reading (stale at 50)"},
            "cycles": {"type": "array", "items": {"type": "integer"}, "description": "load cycles counted"},
            "cycles_seen": {"type": "integer", "description": "frames the cycle counter had seen (every 4th is judged)"},
            "cycles_armed": {"type": "array", "items": {"type": "boolean"},
                             "description": "outputs loaded above 1 N, a cycle pending"},
            "drift": {"type": "array", "items": {"type": ["number", "string", "boolean", "null", "array"]},
                      "description": "a quad's common-mode drift tracker where it stood (quad_drift.py; a "
                                     "non-finite number as its name)"},
            "tared_t_host": {"type": "number", "description": "host receive time (Unix s) of the reading that "
                                                             "completed its tare: an untracked zero's date, should "
                                                             "it leave its address (absent: unknown)"}}}},
        "left": {"type": "array", "description": "zeros of sensors another had taken the place of, each judged "
                                                 "against its own when it comes back (reconstruct/identity.py)",
                 "items": {"type": "object", "properties": {
                     "identity": {"type": "array", "items": {"type": ["string", "integer", "null"]},
                                  "description": "[\"serial\", its serial] or [\"board\", its board, its id]"},
                     "calibration": {"type": "string"},
                     "zero": {"type": "object", "description": "as the registry keeps it: zero_pF, std_pF, frames, "
                                                               "saved (host receive time, Unix s)"}}}},
    },
}

IDENTIFY = {
    "type": "object",
    "description": "the board's frames' wait for its INFO (identify.py) as it stood (absent: no wait, the bytes of a "
                   "recording or a replay, or a recording made before 2026-11-25: its replay holds nothing)",
    "properties": {
        "wait_s": {"type": "number", "description": "the longest a hold lasted live (INFO_REPLY_S)"},
        "expecting": {"type": ["string", "null"], "description": "\"opened\": the next frames wait (a link opened)"},
        "holding": {"type": "boolean", "description": "frames waited then (those before the recording are not in it)"},
    },
}

RESUME = {
    "title": "tactile.Resume",
    "description": "Once a second of reads, the zeros, INFO and calibrations in force before the board's read "
                   "after_reads: where a replay whose first reads were lost (a damaged chunk) begins, as the "
                   "recording ran from there",
    "type": "object",
    "properties": {**BASELINES["properties"],
                   "after_reads": {"type": "integer", "description": "the board's reads recorded before it"},
                   "described": {"type": "array", "items": {"type": "integer"},
                                 "description": "the sensors then described (by INFO or their frames), tared or not"},
                   "calibrations": {"type": "array", "description": "the calibration each sensor seen was then "
                                                                    "reconstructed with (absent in older recordings)",
                                    "items": {"type": "object", "properties": {
                                        "board": {"type": "string"}, "sensor": {"type": "integer"},
                                        "id": {"type": "string"},
                                        "key": {"type": "string", "description": "its identity, as /calibrations"}}}},
                   "identify": IDENTIFY},
}

TARE = {
    "title": "tactile.Tare",
    "description": "A tare made while recording (POST /tare): each sensor's baseline restarted before the board's "
                   "read after_reads (counted from the recording's first read of that board), where a replay "
                   "restarts it too",
    "type": "object",
    "properties": {
        "board": {"type": "string"},
        "judge": {"type": "boolean", "description": "loaded taxels judged against the calibration's C0 (false: a "
                                                    "forced tare, the load present is the zero)"},
        "sensors": {"type": "array", "items": {"type": "object", "properties": {
            "sensor": {"type": "integer"}, "after_reads": {"type": "integer"}}}},
    },
}

CALIBRATION_SET = {
    "title": "tactile.CalibrationSet",
    "description": "A calibration set while recording (PUT /sensors/.../calibration): the sensor reconstructed "
                   "with it from the board's read after_reads (counted from the recording's first read of that "
                   "board), where a replay sets it too",
    "type": "object",
    "properties": {
        "board": {"type": "string"},
        "sensor": {"type": "integer"},
        "after_reads": {"type": "integer"},
        "document": {"type": "object", "description": "the calibration document set (with its id)"},
    },
}

SETTINGS = {
    "title": "tactile.Settings",
    "description": "How a board's forces were reconstructed while recording: what its replay reconstructs with "
                   "unless told otherwise (its forces equal the recorded ones only so)",
    "type": "object",
    "properties": {
        "board": {"type": "string"},
        "level": {"type": "string", "description": "fidelity level in use (level0, table, full; auto's choice)"},
        "mounting": {"type": "string"},
        "identify": IDENTIFY,
    },
}

LINK = {
    "title": "tactile.Link",
    "description": "What the link did before the board's read after_reads (counted from the recording's first read "
                   "of that board), where a replay does it too: \"lost\" the link dropped (the partial frame dropped, "
                   "frames held for the INFO went on without it, the next link's wait for theirs), \"expired\" frames "
                   "held for the board's INFO went on without it (its wait passed: by the loop's timer, which no "
                   "recorded time gives, or at a read received after it)",
    "type": "object",
    "properties": {
        "board": {"type": "string"},
        "event": {"type": "string", "enum": ["lost", "expired"]},
        "after_reads": {"type": "integer"},
    },
}

FORCES = {
    "title": "tactile.Forces",
    "description": "Reconstructed forces of one frame (the replay export shape)",
    "type": "object",
    "properties": {
        "sensor": {"type": "integer"},
        "seq": {"type": "integer"},
        "t_us": {"type": "integer"},
        "kind": {"type": "string", "enum": ["grid", "quad"]},
        "rows": {"type": "integer", "description": "grids: taxel rows (taxels_N is row-major)"},
        "cols": {"type": "integer"},
        "taxels_N": {"type": "array", "items": {"type": ["number", "null"]}},
        "fxyz_N": {"type": "array", "items": {"type": ["number", "null"]}},
        "flags": {"type": "array", "items": {"type": "string"}},
        "taxel_flags": {"type": "object"},
        "contact": {"type": ["object", "null"]},
    },
}

DIAGNOSTICS = {
    "title": "tactile.Diagnostics",
    "description": "Link and decoder counters: at the first read, once per second of reads, and at the stop",
    "type": "object",
    "properties": {"counters": {"type": "object"}, "rejected": {"type": "object"}},
}

FOXGLOVE_GRID = {
    "title": "foxglove.Grid",
    "type": "object",
    "properties": {
        "timestamp": {"type": "object", "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}}},
        "frame_id": {"type": "string"},
        "pose": {
            "type": "object",
            "properties": {
                "position": {"type": "object", "properties": {k: {"type": "number"} for k in "xyz"}},
                "orientation": {"type": "object", "properties": {k: {"type": "number"} for k in "xyzw"}},
            },
        },
        "column_count": {"type": "integer"},
        "cell_size": {"type": "object", "properties": {"x": {"type": "number"}, "y": {"type": "number"}}},
        "row_stride": {"type": "integer"},
        "cell_stride": {"type": "integer"},
        "fields": {
            "type": "array",
            "items": {
                "type": "object",
                "properties": {"name": {"type": "string"}, "offset": {"type": "integer"}, "type": {"type": "integer"}},
            },
        },
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}

FOXGLOVE_FLOAT32 = 7  # foxglove NumericType


def encoded(schema: dict) -> bytes:
    return orjson.dumps(schema)

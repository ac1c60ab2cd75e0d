"""The replay export, a batch of ForceFrames at a time: JSON lines, or a
Parquet table (export_parquet.py).

``JsonLines`` writes, line for line, exactly ``orjson.dumps(to_export_dict(frame),
option=OPT_SERIALIZE_NUMPY)``, but column by column: the keys are those
``to_export_dict`` gives the batch's first frame of each sensor, each key's
values are encoded for all the sensor's frames at once (forces as one
orjson call on the stacked array, contact summaries by contact_batch) and
the lines assembled from a template. A key this module does not know, or
whose encoding differs from ``to_export_dict``'s on that first frame, is
taken from ``to_export_dict`` frame by frame: new keys are exported as
that function defines them, only slower.
"""
from __future__ import annotations

from typing import BinaryIO, Callable

import numpy as np
import orjson

from ..fanout.encoding import to_export_dict
from ..reconstruct import ForceFrame
from .contact_batch import summaries

JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY
Column = Callable[[list[ForceFrame]], list[bytes]]


def export_line(frame: ForceFrame) -> bytes:
    """One frame's line, the reference the batch encoder equals."""
    return orjson.dumps(to_export_dict(frame), option=JSON_OPTIONS) + b"\n"


def _dumps(value) -> bytes:
    return orjson.dumps(value, option=JSON_OPTIONS)


def _ints(read: Callable[[ForceFrame], int]) -> Column:
    return lambda frames: [b"%d" % read(f) for f in frames]


def _stacked(arrays: list[np.ndarray]) -> list[bytes]:
    """Each array's JSON from one orjson call on their stack (rows of one
    shape and dtype); one call each otherwise."""
    first = arrays[0]
    if first.ndim != 1 or not first.size or any(a.dtype != first.dtype or a.shape != first.shape for a in arrays):
        return [_dumps(a) for a in arrays]
    text = _dumps(np.stack(arrays))
    return [b"[" + row + b"]" for row in text[2:-2].split(b"],[")]


def _forces(frames: list[ForceFrame]) -> list[bytes]:
    return _stacked([f.forces_N for f in frames])


def _sigma(frames: list[ForceFrame]) -> list[bytes]:
    if any(f.sigma_N is None for f in frames):
        return [_dumps(f.sigma_N) for f in frames]
    return _stacked([f.sigma_N for f in frames])


def _flags(frames: list[ForceFrame]) -> list[bytes]:
    known: dict[tuple, bytes] = {}
    out = []
    for f in frames:
        key = tuple(f.flags)
        text = known.get(key)
        if text is None:
            text = known[key] = _dumps(f.flags)
        out.append(text)
    return out


def _taxel_flags(frames: list[ForceFrame]) -> list[bytes]:
    if any(f.taxel_flags is None for f in frames):
        return [_dumps(f.taxel_flag_lists()) for f in frames]
    flagged = np.stack([f.taxel_flags for f in frames]).any(axis=1).tolist()
    return [_dumps(f.taxel_flag_lists()) if hit else b"{}" for f, hit in zip(frames, flagged)]


def _contact(frames: list[ForceFrame]) -> list[bytes]:
    info = frames[0].sensor
    return [_dumps(c) for c in summaries(np.stack([f.forces_N for f in frames]), info.rows, info.cols)]


def _text(read: Callable[[ForceFrame], str]) -> Column:
    def column(frames: list[ForceFrame]) -> list[bytes]:
        known: dict[str, bytes] = {}
        return [known.get(v) or known.setdefault(v, _dumps(v)) for v in map(read, frames)]

    return column


COLUMNS: dict[str, Column] = {
    "board": _text(lambda f: f.sensor.board),
    "sensor": _ints(lambda f: f.sensor.id),
    "seq": _ints(lambda f: f.seq),
    "t_us": _ints(lambda f: f.t_us),
    "kind": _text(lambda f: f.sensor.kind),
    "taxels_N": _forces,
    "fxyz_N": _forces,
    "flags": _flags,
    "taxel_flags": _taxel_flags,
    "contact": _contact,
    "calibration": _text(lambda f: f.calibration),
    "sigma_N": _sigma,
}


def _sensor_lines(frames: list[ForceFrame]) -> list[bytes]:
    """The lines of one sensor's frames (one shape, one set of keys)."""
    sample = to_export_dict(frames[0])
    columns = []
    for key, value in sample.items():
        encode = COLUMNS.get(key)
        column = encode(frames) if encode is not None else None
        if column is None or column[0] != _dumps(value):
            column = [_dumps(to_export_dict(f)[key]) for f in frames]
        columns.append(column)
    template = b"{" + b",".join(_dumps(key).replace(b"%", b"%%") + b":%b" for key in sample) + b"}\n"
    return [template % values for values in zip(*columns)]


def encode_lines(frames: list[ForceFrame]) -> bytes:
    """The batch's JSON lines, in frame order."""
    by_sensor: dict[object, list[int]] = {}
    for i, f in enumerate(frames):
        by_sensor.setdefault(f.sensor, []).append(i)
    if len(by_sensor) == 1:
        return b"".join(_sensor_lines(frames))
    lines: list[bytes] = [b""] * len(frames)
    for indices in by_sensor.values():
        for i, line in zip(indices, _sensor_lines([frames[i] for i in indices])):
            lines[i] = line
    return b"".join(lines)


class JsonLines:
    """``write(frames)`` appends their lines to ``stream``."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream

    def write(self, frames: list[ForceFrame]) -> None:
        if frames:
            self._stream.write(encode_lines(frames))

    def close(self) -> None:
        """Nothing is held back; the stream is its owner's to close."""

"""The replay export, a batch of ForceFrames at a time: JSON lines, or a
Parquet table (export_parquet.py).

``JsonLines`` writes, line for line, exactly ``export_line(frame)``:
``orjson.dumps(to_export_dict(frame), option=OPT_SERIALIZE_NUMPY)``. The
grids' contact summaries, the costly part of a line after its floats, are
found for each sensor's frames at once (contact_batch) and kept on the
frames first; everything else is the per-frame reference itself, so a key
added to ``to_export_dict`` is exported as it defines it. (One orjson call
per frame, with the forces as numpy rows, is cheaper than encoding columns
and splitting them: measured in docs/performance.md.)
"""
from __future__ import annotations

from typing import BinaryIO

import numpy as np
import orjson

from ..fanout.encoding import to_export_dict
from ..readings import SensorInfo
from ..reconstruct import ForceFrame
from .contact_batch import sigmas, summaries

JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def export_line(frame: ForceFrame) -> bytes:
    """One frame's line, the reference the batch encoder equals."""
    return orjson.dumps(to_export_dict(frame), option=JSON_OPTIONS) + b"\n"


def keep_contacts(frames: list[ForceFrame]) -> None:
    """Each grid frame's contact summary, found per sensor for all its frames at once."""
    # Grouped by the SensorInfo's identity: its hash hashes all its fields, once per frame.
    by_sensor: dict[int, tuple[SensorInfo, list[ForceFrame]]] = {}
    for frame in frames:
        info = frame.sensor
        if info.kind == "grid":
            group = by_sensor.get(id(info))
            if group is None:
                group = by_sensor[id(info)] = (info, [])
            group[1].append(frame)
    for info, grid_frames in by_sensor.values():
        # One copy of the rows (np.stack costs 3× more for 64-value rows).
        forces = np.concatenate([f.forces_N for f in grid_frames]).reshape(len(grid_frames), info.rows * info.cols)
        sigma = sigmas(grid_frames, forces.shape)
        for frame, summary in zip(grid_frames, summaries(forces, info.rows, info.cols, sigma)):
            frame.keep_contact(summary)


def encode_lines(frames: list[ForceFrame]) -> bytes:
    """The batch's JSON lines, in frame order."""
    keep_contacts(frames)
    dumps, options = orjson.dumps, JSON_OPTIONS
    lines = [dumps(to_export_dict(frame), option=options) for frame in frames]
    lines.append(b"")
    return b"\n".join(lines)


# Frames gathered and encoded together: a recorded read holds one or two per sensor. Not more: glibc gives
# a freed heap top back to the kernel past a few MB, and 4 096 8×8 lines (10 MB, and as much joined) were
# faulted in again at every batch, 80 000 page faults for 60 000 frames (docs/performance.md).
LINES_PER_WRITE = 512


class JsonLines:
    """``write(frames)`` appends their lines to ``stream``; with ``gather``
    (an offline replay) batches are kept until LINES_PER_WRITE frames are
    waiting, since an MCAP replay writes each recorded read — a frame or two
    per sensor — and the per-call costs (the contact summaries' numpy calls
    per sensor) were most of the export. ``close()`` writes what waits."""

    def __init__(self, stream: BinaryIO, gather: bool = False) -> None:
        self._stream = stream
        self._gather = gather
        self._waiting: list[ForceFrame] = []

    def write(self, frames: list[ForceFrame]) -> None:
        if self._gather:
            self._waiting += frames
            if len(self._waiting) < LINES_PER_WRITE:
                return
            frames, self._waiting = self._waiting, []
        for start in range(0, len(frames), LINES_PER_WRITE):
            self._stream.write(encode_lines(frames[start:start + LINES_PER_WRITE]))

    def close(self) -> None:
        """Write what waits; the stream is its owner's to close."""
        frames, self._waiting, self._gather = self._waiting, [], False
        self.write(frames)

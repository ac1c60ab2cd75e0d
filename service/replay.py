"""Offline replay of recordings and raw captures through the live pipeline.

A recording is a sequence of timed byte chunks (record/readers.py); they go
through the same pipeline as live data, paced by a ``Pacer`` (injectable
clock, any speed, or as fast as possible).
A raw capture's readings are held until each sensor's auto-tare is
complete, so every exported frame has forces. A recording is replayed as it
ran live (the tare window null and flagged), so its forces come out bit for
bit as recorded.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import BinaryIO

import orjson

from .fanout.encoding import to_export_dict
from .pipeline import Pipeline
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor
from .record.pacing import Pacer
from .record.readers import is_timed_by_host, timed_chunks

_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def export_line(frame: ForceFrame) -> bytes:
    return orjson.dumps(to_export_dict(frame), option=_JSON_OPTIONS) + b"\n"


def replay(path: str | Path, export: BinaryIO | None = None, level: str = DEFAULT_LEVEL, mounting: str = "flat",
           pacer: Pacer | None = None, calibrations=None) -> Pipeline:
    """Replay a recording (.mcap) or raw capture (any other suffix); write
    one JSON line per data frame to ``export``. ``calibrations``: a
    calibration/book.py CalibrationBook (None: built-in calibrations).
    Returns the pipeline, whose counters tell what was dropped."""
    pacer = pacer or Pacer(math.inf)
    hold = not is_timed_by_host(path)
    pipeline = Pipeline(Reconstructor(hold_until_tared=hold, level=level, mounting=mounting), clock=lambda: 0.0,
                        calibrations=None if calibrations is None else calibrations.for_sensor)
    if export is not None:
        pipeline.listeners.append(lambda frames: export.writelines(export_line(f) for f in frames))
    t_last = 0.0
    for t_recorded, chunk in timed_chunks(path):
        pacer.wait(t_recorded)
        pipeline.feed(chunk, t_recorded)
        t_last = t_recorded
    pipeline.finish(t_last)
    return pipeline


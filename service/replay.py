"""Offline replay of recordings and raw captures through the live pipeline.

A recording is a sequence of timed byte chunks (record/readers.py); they go
through the same pipeline as live data, paced by a ``Pacer`` (injectable
clock, any speed, or as fast as possible). As fast as possible, the bytes
go in large chunks (a raw capture is not decoded just to time them) and the
pipeline keeps no history: an export needs neither, and the forces do not
depend on how the stream is cut.
A raw capture's readings are held until each sensor's auto-tare is
complete, so every exported frame has forces. A recording is replayed as it
ran live (the tare window null and flagged), so its forces come out bit for
bit as recorded.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import BinaryIO, Protocol

from .pipeline import Pipeline
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor
from .record.export import JsonLines, export_line
from .record.pacing import Pacer
from .record.readers import is_timed_by_host, timed_chunks

__all__ = ["Pacer", "Writer", "export_line", "replay"]


class Writer(Protocol):
    def write(self, frames: list[ForceFrame]) -> None: ...


def replay(path: str | Path, export: BinaryIO | None = None, level: str = DEFAULT_LEVEL, mounting: str = "flat",
           pacer: Pacer | None = None, writer: Writer | None = None, calibrations=None) -> Pipeline:
    """Replay a recording (.mcap) or raw capture (any other suffix); write
    one JSON line per data frame to ``export``, or each batch of frames to
    ``writer`` (record.export_parquet.Parquet, say). ``calibrations``: a
    calibration/book.py CalibrationBook (None: built-in calibrations).
    Returns the pipeline, whose counters tell what was dropped."""
    pacer = pacer or Pacer(math.inf)
    hold = not is_timed_by_host(path)
    pipeline = Pipeline(Reconstructor(hold_until_tared=hold, level=level, mounting=mounting), clock=lambda: 0.0,
                        keep_history=False, calibrations=calibrations, map_clock=not hold)
    writer = writer or (JsonLines(export) if export is not None else None)
    if writer is not None:
        pipeline.listeners.append(writer.write)
    t_last = 0.0
    for t_recorded, chunk in timed_chunks(path, paced=not math.isinf(pacer.speed)):
        pacer.wait(t_recorded)
        pipeline.feed(chunk, t_recorded)
        t_last = t_recorded
    pipeline.finish(t_last)
    return pipeline

"""Offline replay of raw captures: bytes from a file through the live pipeline.

A raw capture is exactly what a port delivered, corrupt bytes included. It
runs through the same decoder and reconstruction as live data, as fast as the
CPU allows; readings are held until each sensor's auto-tare is complete so
every exported frame has forces (live, the tare window is reported null).
"""
from __future__ import annotations

from pathlib import Path
from typing import BinaryIO

import orjson

from .pipeline import Pipeline
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor

CHUNK_BYTES = 1 << 16
_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def export_line(frame: ForceFrame) -> bytes:
    return orjson.dumps(frame.export_dict(), option=_JSON_OPTIONS) + b"\n"


def replay_raw(path: str | Path, export: BinaryIO | None = None, level: str = DEFAULT_LEVEL, mounting: str = "flat") -> Pipeline:
    """Replay a raw capture; write one JSON line per data frame to ``export``.

    Returns the pipeline, whose decoder and interpreter counters tell what
    was dropped. Raises FileNotFoundError / OSError for an unreadable file.
    """
    pipeline = Pipeline(Reconstructor(hold_until_tared=True, level=level, mounting=mounting), clock=lambda: 0.0)
    if export is not None:
        pipeline.listeners.append(lambda frames: export.writelines(export_line(f) for f in frames))
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            pipeline.feed(chunk, 0.0)
    pipeline.finish(0.0)
    return pipeline

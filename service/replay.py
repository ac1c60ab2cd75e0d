"""Replay of recordings and raw captures through the live pipeline.

A recording is a sequence of timed byte chunks: an MCAP log's ``/raw``
channel carries each read of the port with its receive time; a raw capture
(exactly what a port delivered, possibly corrupt) has no times, so each of
its 4 KiB chunks is timed by the board clock of the frames it completes.
The chunks go through the same decoder and reconstruction as live data,
paced by a ``Pacer`` (injectable clock, any speed, or as fast as possible).
A raw capture's readings are held until each sensor's auto-tare is
complete, so every exported frame has forces. A recording is replayed as it
ran live (the tare window null and flagged), so its forces come out bit for
bit as recorded.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterator
from pathlib import Path
from typing import BinaryIO, Callable

import orjson

from .fanout.encoding import to_export_dict
from .pipeline import Pipeline
from .protocol import T_US_MODULUS, Decoder
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor

CHUNK_BYTES = 4096
_JSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def export_line(frame: ForceFrame) -> bytes:
    return orjson.dumps(to_export_dict(frame), option=_JSON_OPTIONS) + b"\n"


class Pacer:
    """Releases recorded times at ``speed`` × real time (math.inf: no waiting).

    The first call anchors recorded time to the clock; ``clock`` and
    ``sleep`` are injectable so tests run on a virtual clock."""

    def __init__(self, speed: float = 1.0, clock: Callable[[], float] = time.monotonic,
                 sleep: Callable[[float], None] = time.sleep) -> None:
        if not speed > 0:
            raise ValueError(f"replay speed must be > 0, got {speed}")
        self.speed = speed
        self._clock = clock
        self._sleep = sleep
        self._anchor: tuple[float, float] | None = None

    def wait(self, t_recorded: float) -> None:
        if math.isinf(self.speed):
            return
        if self._anchor is None:
            self._anchor = (t_recorded, self._clock())
            return
        due = self._anchor[1] + (t_recorded - self._anchor[0]) / self.speed
        delay = due - self._clock()
        if delay > 0:
            self._sleep(delay)


def raw_chunks(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """4 KiB chunks of a raw capture, each timed (s) by the latest board
    time it completes (t_us unwrapped), or by the previous chunk's time."""
    decoder = Decoder()
    t, wraps, last_t_us = 0.0, 0, None
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            for frame in decoder.feed(chunk):
                if last_t_us is not None and frame.t_us < last_t_us - T_US_MODULUS // 2:
                    wraps += 1
                last_t_us = frame.t_us
                t = max(t, (wraps * T_US_MODULUS + frame.t_us) * 1e-6)
            yield t, chunk


def timed_chunks(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """Timed byte chunks of a recording, chosen by the file's suffix."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no such recording: {path}")
    if path.suffix == ".mcap":
        from .record.mcap_log import read_raw

        return read_raw(path)
    return raw_chunks(path)


def replay(path: str | Path, export: BinaryIO | None = None, level: str = DEFAULT_LEVEL, mounting: str = "flat",
           pacer: Pacer | None = None) -> Pipeline:
    """Replay a recording (.mcap) or raw capture (any other suffix); write
    one JSON line per data frame to ``export``. Returns the pipeline, whose
    counters tell what was dropped."""
    pacer = pacer or Pacer(math.inf)
    hold = Path(path).suffix != ".mcap"
    pipeline = Pipeline(Reconstructor(hold_until_tared=hold, level=level, mounting=mounting), clock=lambda: 0.0)
    if export is not None:
        pipeline.listeners.append(lambda frames: export.writelines(export_line(f) for f in frames))
    t_last = 0.0
    for t_recorded, chunk in timed_chunks(path):
        pacer.wait(t_recorded)
        pipeline.feed(chunk, t_recorded)
        t_last = t_recorded
    pipeline.finish(t_last)
    return pipeline


"""Recordings as timed byte chunks, a reader chosen by the file's suffix.

An MCAP recording's ``/raw`` channel carries each read of the port with its
receive time; a raw capture (exactly what a port delivered, possibly
corrupt) has no times, so each of its chunks is timed by the board clock of
the frames it completes. Either way the chunks replay through the same
decoder as live bytes.
"""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from ..protocol import T_US_MODULUS, Decoder
from .mcap_reader import read_raw

CHUNK_BYTES = 4096
BULK_BYTES = 1 << 20  # untimed reads: as fast as possible, few calls per stage


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


def bulk_chunks(path: str | Path, size: int = BULK_BYTES) -> Iterator[tuple[float, bytes]]:
    """(0.0, bytes) in ``size`` chunks: for a replay that waits for no clock
    (no decoding just to time the chunks)."""
    with open(path, "rb") as source:
        while chunk := source.read(size):
            yield 0.0, chunk


READERS = {".mcap": read_raw}  # by suffix; any other file is a raw capture


def timed_chunks(path: str | Path, paced: bool = True, board: str | None = None) -> Iterator[tuple[float, bytes]]:
    """(time s, bytes) of a recording; FileNotFoundError or ValueError (not
    the format its suffix says) at once, before the first chunk is asked for.
    ``paced=False`` (nothing waits for the times): a raw capture in large
    untimed chunks. A recording keeps its reads as they came: a live
    pipeline's frames depend on where a read ends (a tare completed within
    a read applies to the whole read), and its replay equals the live run."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    if path.suffix in READERS:
        return READERS[path.suffix](path, board)
    if board is not None:
        raise ValueError(f"{path} is a raw capture of one board: it has no board {board!r} to choose")
    return raw_chunks(path) if paced else bulk_chunks(path)


def is_timed_by_host(path: str | Path) -> bool:
    """Whether the recording carries receive times (and replays as it ran
    live) rather than board times only."""
    return Path(path).suffix in READERS

"""Recordings as timed byte chunks, a reader chosen by the file's suffix.

An MCAP recording's ``/raw`` channel carries each read of the port with its
receive time; a raw capture (exactly what a port delivered, possibly
corrupt) has no times, so each of its chunks is timed by the board clock of
the frames it completes. Either way the chunks replay through the same
decoder as live bytes.
"""
from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

from ..protocol import DATA_TYPES, T_US_MODULUS, Decoder, Frame
from .mcap_reader import read_raw

CHUNK_BYTES = 4096
BULK_BYTES = 1 << 20  # untimed reads: as fast as possible, few calls per stage


class BoardClock:
    """A board's time (s) from its data frames: ``t`` the newest, t_us
    unwrapped (0.0 before the first frame).

    A restart (protocol.md: INFO, then every sensor's seq and t_us from 0;
    the decoder flags each sensor's first frame after it) is no wrap, and
    says nothing of how long the board was off: the run after it continues
    from the newest time of the run before, without a wait (each sensor's
    flagged frame re-anchors the run; they are a scan apart at most). Only
    data frames count: an INFO is not flagged, and a power-up INFO's clock
    near 0 would pass for a wrap."""

    def __init__(self) -> None:
        self.t = 0.0
        self._offset, self._wraps, self._last_us = 0.0, 0, None

    def feed(self, frames: Iterable[Frame]) -> float:
        for frame in frames:
            if frame.type not in DATA_TYPES:
                continue
            if frame.board_restart:
                self._offset, self._wraps = self.t - frame.t_us * 1e-6, 0
            elif self._last_us is not None and frame.t_us < self._last_us - T_US_MODULUS // 2:
                self._wraps += 1
            self._last_us = frame.t_us
            self.t = max(self.t, self._offset + (self._wraps * T_US_MODULUS + frame.t_us) * 1e-6)
        return self.t


def raw_chunks(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """4 KiB chunks of a raw capture, each timed (s) by the latest board
    time it completes (``BoardClock``), or by the previous chunk's time."""
    decoder, clock = Decoder(), BoardClock()
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            yield clock.feed(decoder.feed(chunk)), chunk


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

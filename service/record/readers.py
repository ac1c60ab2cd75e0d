"""Recordings as timed byte chunks, a reader chosen by the file's suffix.

An MCAP recording's ``/raw`` channel carries each read of the port with its
receive time; a raw capture (exactly what a port delivered, possibly
corrupt) has no times, so each of its chunks is timed by the board clock of
the frames it completes. Either way the chunks replay through the same
decoder as live bytes.

Receive times are the host's wall clock (time.time(), as the live pipeline
stamps them), which an NTP step moves by any amount while recording: paced,
a recording is timed by them with such steps taken out (``HostTime``).
"""
from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from datetime import datetime, timezone
from pathlib import Path

from ..protocol import DATA_TYPES, SYNC, T_US_MODULUS, Frame
from ..protocol_decoder import Decoder
from .mcap_reader import read_raw

CHUNK_BYTES = 4096
PACE_S = 0.02  # board time one paced chunk of a raw capture spans at most: how late its first frames go out
BULK_BYTES = 1 << 20  # untimed reads: as fast as possible, few calls per stage
WRAP_S = T_US_MODULUS * 1e-6  # the board clock's range: 71.6 min
STEP_S = 1.0  # receive times apart from the board clock by more than this between two reads: the host clock stepped

log = logging.getLogger(__name__)


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

    @property
    def last_us(self) -> int | None:
        """The newest data frame's t_us as sent."""
        return self._last_us

    def resync(self, t: float) -> float:
        """Take ``t`` for the newest frame's time: after a silence whose
        length the frames alone cannot tell (more than half the clock's
        range, 36 min), measured by other means; the newest time."""
        self._offset, self._wraps = t - self._last_us * 1e-6, 0
        self.t = t
        return t


class _Board:
    """What HostTime keeps of one board: its bytes decoded, its clock, the
    (pacing time, board time) of its last read that completed data frames
    and the pacing time of its last read."""

    def __init__(self) -> None:
        self.decoder, self.clock = Decoder(), BoardClock()
        self.timed: tuple[float, float, int] | None = None  # (pacing time, board time, its t_us as sent)
        self.last: float | None = None


class HostTime:
    """Pacing times of a recording's reads: their receive times with the
    host clock's steps taken out (an NTP step of +1 h while recording
    stalled a paced replay for an hour; one of -1 h let the hour after it
    through unpaced).

    Between two reads of a board that complete data frames, receive time
    moves as the board clock does, to within the delivery's delay; where
    they part by more than STEP_S, the host clock was stepped, and the
    pacing follows the board clock across it (a log line says so). A pause
    in the recording (the board silent, STOP … START, a cable out) shows on
    both clocks and is kept, as is any time across a board restart (its
    clock cannot tell it). A read that completes no data frame has no board
    time to be checked by: it moves the pacing on by STEP_S at most, and
    the next read that does completes any wait. Called with each read, in
    file order: (board, receive time s, bytes) → pacing time s."""

    def __init__(self) -> None:
        self._step = 0.0  # s taken off every receive time: the host clock's steps found so far
        self._boards: dict[str | None, _Board] = {}

    def __call__(self, board: str | None, t_host: float, chunk: bytes) -> float:
        state = self._boards.get(board)
        if state is None:
            state = self._boards[board] = _Board()
        frames = [frame for frame in state.decoder.feed(chunk) if frame.type in DATA_TYPES]
        t = t_host - self._step
        if frames:
            t_board = state.clock.feed(frames)
            if state.timed is not None and not any(frame.board_restart for frame in frames):
                gap = t - state.timed[0]
                step = gap - (t_board - state.timed[1])
                # The board clock's own count since, modulo its range: a silence past half of it (36 min) reads
                # as a step back or no time at all to the frames alone; the receive times tell how many wraps.
                counted = ((state.clock.last_us - state.timed[2]) % T_US_MODULUS) * 1e-6
                wraps = max(0, round((gap - counted) / WRAP_S))
                if abs(step) > STEP_S and abs(gap - counted - wraps * WRAP_S) <= STEP_S:
                    t_board, step = state.clock.resync(state.timed[1] + counted + wraps * WRAP_S), 0.0
                if abs(step) > STEP_S:
                    log.warning("%s: receive times step %+.3f s against the board clock at %s: taken for a step "
                                "of the host clock (NTP), paced by the board clock across it", board or "recording",
                                step, datetime.fromtimestamp(t_host, timezone.utc).isoformat(timespec="milliseconds"))
                    self._step += step
                    t -= step
            state.timed = (t, t_board, state.clock.last_us)
        elif state.last is not None:
            t = min(t, state.last + STEP_S)
        state.last = t
        return t


def raw_chunks(path: str | Path) -> Iterator[tuple[float, bytes]]:
    """Chunks of a raw capture, read 4 KiB at a time, each timed (s) by the
    latest board time it completes (``BoardClock``), or by the previous
    chunk's time; cut at frame starts so that none spans more than PACE_S of
    board time (``_paced_cuts``)."""
    decoder, clock = Decoder(), BoardClock()
    with open(path, "rb") as source:
        while block := source.read(CHUNK_BYTES):
            yield from _paced_cuts(block, decoder, clock)


def _paced_cuts(block: bytes, decoder: Decoder, clock: BoardClock) -> Iterator[tuple[float, bytes]]:
    """``block`` as (board time s, bytes) chunks, cut before a frame whose
    time is more than PACE_S after the chunk's first frame: a frame goes out
    at most PACE_S after its own time, never before it (a 4 KiB chunk
    across a 1.5 s pause released its frames from before the pause 1.5 s
    late). Each piece from one sync pattern to the next completes the frame
    it starts (a sync inside a payload only makes a piece that completes
    none); ``decoder`` and ``clock`` go on from block to block."""
    start = piece = 0  # the chunk's and the piece's first byte in the block
    first = None  # the board time of the chunk's first data frames
    while piece < len(block):
        end = block.find(SYNC, piece + 1)
        end = len(block) if end < 0 else end
        t_before = clock.t
        frames = [frame for frame in decoder.feed(block[piece:end]) if frame.type in DATA_TYPES]
        t = clock.feed(frames)
        if first is not None and t > first + PACE_S:
            yield t_before, block[start:piece]
            start, first = piece, None
        if first is None and frames:
            first = t
        piece = end
    yield clock.t, block[start:]


def bulk_chunks(path: str | Path, size: int = BULK_BYTES) -> Iterator[tuple[float, bytes]]:
    """(0.0, bytes) in ``size`` chunks: for a replay that waits for no clock
    (no decoding just to time the chunks)."""
    with open(path, "rb") as source:
        while chunk := source.read(size):
            yield 0.0, chunk


READERS = {".mcap": read_raw}  # by suffix; any other file is a raw capture


def timed_chunks(path: str | Path, paced: bool = True, board: str | None = None,
                 from_read: int = 0) -> Iterator[tuple[float, bytes]]:
    """(time s, bytes) of a recording (an MCAP one from the board's read
    ``from_read`` on); FileNotFoundError or ValueError (not
    the format its suffix says) at once, before the first chunk is asked for.
    A recording is timed by ``HostTime``; ``paced=False`` (nothing waits
    for the times): by its receive times as recorded, and a raw capture
    comes in large untimed chunks. A recording keeps its reads as they
    came: a live pipeline's frames depend on where a read ends (a tare
    completed within a read applies to the whole read), and its replay
    equals the live run."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    if path.suffix in READERS:
        chunks = READERS[path.suffix](path, board, from_read)
        if not paced:
            return chunks
        host_time = HostTime()
        return ((host_time(board, t, chunk), chunk) for t, chunk in chunks)
    if board is not None:
        raise ValueError(f"{path} is a raw capture of one board: it has no board {board!r} to choose")
    return raw_chunks(path) if paced else bulk_chunks(path)


def is_timed_by_host(path: str | Path) -> bool:
    """Whether the recording carries receive times (and replays as it ran
    live) rather than board times only."""
    return Path(path).suffix in READERS

"""Board serial protocol v1: bytes in, frames out; frames in, bytes out. No I/O.

The decoder is incremental: feed it chunks of any size (one byte, a whole file)
and it returns the frames completed so far, keeping partial frames across
calls. A frame whose version, type, length or CRC is wrong is discarded and
the search for the next sync pattern restarts one byte after the bad frame's
first sync byte, as the protocol requires, so a sync pattern inside a payload
or a corrupted length cannot hide the following frames for long.

Every byte that does not end up inside a good frame is counted in
``bytes_discarded``; CRC errors are attributed to the sensor id the bad header
claims (it may itself be corrupt, so the per-sensor figure is indicative and
the stream total is exact).

Sequence bookkeeping per sensor, after the protocol's "Restarts and repeats":
a data frame whose board clock does not advance is one of three things. After
an INFO that the board sent before this scan (a power-up INFO; a reply to
INFO? or PING comes after the scans it follows), it is the first scan of a
board that restarted (``board_restarts``; however soon, even if its bytes
equal an older scan's). Otherwise, when its bytes equal those of the last
frame its sensor passed on (or counted late) with its sequence number, it is
a repeat, however late within the 65 536 scans until that number comes round
again (dropped, counted in ``duplicates``): a board's run sends one frame per
(seq, t_us), so one fingerprint per sequence number (512 KiB a sensor) holds
every frame a repeat can still copy. Else,
if the clock went back, it is a restart whose INFO was lost (at the same board
time it is sequenced like any scan). After an INFO stamped before the
sensor's last scan (a power-up INFO; a reply to INFO? after a reconnect is
stamped after it), a frame whose clock ran on but whose sequence fell back
is a restart too (a board that ran for less time than it was off), and so
is one, after an INFO, whose sequence jumped by twice the scans its clock's
step holds at 5 000 scans/s (a power-up just after the clock wrapped: the
clock looks a moment on). A frame whose sequence is the next one (other
than 0 after 65 535) and other bytes than the last with its number is in
order whatever its clock did: a pause of more than half the clock's period
(STOP … START) looks like a step back. None of
these is a gap of 65 000 scans. A frame a link delivered late — one of the
sensor's last 256 scans that was missing (counted in a gap when the next one
came), its clock behind by no more than those scans take at 1 Hz, no INFO
since — is no restart either: it is dropped and counted in ``late_frames``
(the frames after it are in order again; a restart whose INFO was lost
sends sequence numbers that were not missing). Any other frame whose
sequence number is the last one passed on or up to 256 before it, with
other bytes, sooner than a gap of ~65 000 scans could take, is none of the
protocol's frames: dropped and counted in ``conflicting``, not taken for
such a gap.
Data frames from id 255, the board's own, are dropped (``board_id_data``).
"""
from __future__ import annotations

import struct
from binascii import crc_hqx
from collections import deque
from dataclasses import dataclass, field
from enum import IntEnum
from typing import NamedTuple

import numpy as np

SYNC = b"\xa5\x5a"
VERSION = 1
HEADER_SIZE = 14
CRC_SIZE = 2
MAX_PAYLOAD = 1024
BOARD_SENSOR_ID = 255
SEQ_MODULUS = 1 << 16
T_US_MODULUS = 1 << 32
RECENT_SCANS = 256  # per sensor, how far back a missing scan may still come late, or a scan conflict
RESTART_JUMP_US = 1_000_000  # a clock that jumps more than this after an INFO, back towards 0
MAX_SCAN_PERIOD_US = 1_000_000  # RATE is at least 1 Hz
MIN_SCAN_PERIOD_US = 200  # and at most 5 000 Hz
_HALF_CLOCK = 1 << 31  # a board clock step beyond this is a step back (wrapped)

FLAG_SATURATED = 0x01
FLAG_OVERRUN = 0x02

_HEADER = struct.Struct("<BBBBHIH")  # version, type, sensor, flags, seq, t_us, len
_CRC = struct.Struct("<H")


class FrameType(IntEnum):
    INFO = 0x01
    GRID = 0x10
    QUAD = 0x11
    ERROR = 0x7F


DATA_TYPES = frozenset({FrameType.GRID, FrameType.QUAD})
_KNOWN_TYPES = frozenset(int(t) for t in FrameType)


class Frame(NamedTuple):
    """One frame that passed every check of the protocol (a named tuple:
    built 5x faster than a frozen dataclass, ~1 µs less per frame).

    ``gap`` is the number of scans of this sensor missing just before this
    frame according to ``seq`` (0 when the sequence is continuous or this is
    the sensor's first frame). ``board_restart`` marks the sensor's first
    frame from a board that restarted (after its power-up INFO, or with its
    clock gone back), counting from seq 0 again: nothing was missed.
    """

    type: FrameType
    sensor: int
    flags: int
    seq: int
    t_us: int
    payload: bytes
    gap: int = 0
    board_restart: bool = False


@dataclass(slots=True)
class SensorCounters:
    frames: int = 0
    crc_errors: int = 0
    seq_gaps: int = 0
    missed_frames: int = 0
    duplicates: int = 0
    board_restarts: int = 0
    late_frames: int = 0  # delivered out of order by the link: dropped
    conflicting: int = 0  # a scan number already passed on, other bytes (not a repeat, restart or late scan): dropped


@dataclass(slots=True)
class StreamCounters:
    bytes_in: int = 0
    frames: int = 0
    crc_errors: int = 0
    header_errors: int = 0
    truncated: int = 0
    bytes_discarded: int = 0
    board_id_data: int = 0  # data frames claiming sensor 255, the board's own id
    sensors: dict[int, SensorCounters] = field(default_factory=dict)

    def sensor(self, sensor_id: int) -> SensorCounters:
        counters = self.sensors.get(sensor_id)
        if counters is None:
            counters = self.sensors[sensor_id] = SensorCounters()
        return counters

    def as_dict(self) -> dict:
        return {
            "bytes_in": self.bytes_in,
            "frames": self.frames,
            "crc_errors": self.crc_errors,
            "header_errors": self.header_errors,
            "truncated": self.truncated,
            "bytes_discarded": self.bytes_discarded,
            "board_id_data": self.board_id_data,
            "sensors": {
                str(sid): {
                    "frames": c.frames,
                    "crc_errors": c.crc_errors,
                    "seq_gaps": c.seq_gaps,
                    "missed_frames": c.missed_frames,
                    "duplicates": c.duplicates,
                    "board_restarts": c.board_restarts,
                    "late_frames": c.late_frames,
                    "conflicting": c.conflicting,
                }
                # An id that never sent a valid frame is a damaged header's (its CRC errors are in the
                # stream's count): listed, it showed phantom sensors (116, 255) in summaries.
                for sid, c in sorted(self.sensors.items()) if c.frames
            },
        }


def _length_is_valid(frame_type: int, length: int) -> bool:
    if length > MAX_PAYLOAD:
        return False
    if frame_type == FrameType.QUAD:
        return length == 16
    if frame_type == FrameType.GRID:
        return length > 0 and length % 4 == 0
    return True


class _SensorState:
    """Where a sensor's sequence stands: its last frame passed on, the INFO
    count then, and per sequence number the fingerprint (hash of the bytes)
    of the last frame with that number."""

    __slots__ = ("seq", "t_us", "infos", "seen", "missing")

    def __init__(self) -> None:
        # calloc'd: pages are touched only as the sequence reaches them; a memoryview sets an item 2x faster than numpy.
        self.seen = memoryview(np.zeros(SEQ_MODULUS, np.int64))
        self.missing: deque[int] = deque(maxlen=RECENT_SCANS)  # sequence numbers of recent gaps


class Decoder:
    """Incremental protocol decoder with per-stream and per-sensor counters."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._states: dict[int, _SensorState] = {}
        self._infos = 0  # INFO frames seen, and the board time of the last one
        self._info_t_us = 0
        self.counters = StreamCounters()

    def feed(self, data: bytes) -> list[Frame]:
        """Add received bytes; return the frames they complete, in order."""
        self.counters.bytes_in += len(data)
        self._buffer += data
        return self._parse(final=False)

    def held(self) -> bytes:
        """The bytes kept for a frame not complete yet: where a recording
        begun now has to start for its replay to decode that frame too."""
        return bytes(self._buffer)

    def finish(self) -> list[Frame]:
        """End of stream: resolve what is left, recovering frames trapped
        behind a corrupt length, and count the remainder as discarded."""
        frames = self._parse(final=True)
        self.counters.bytes_discarded += len(self._buffer)
        self._buffer.clear()
        return frames

    def reset(self) -> None:
        """Forget a partial frame (the link dropped); keep counters and the
        sequence state, so the scans lost across a reconnect count as a gap."""
        self.counters.bytes_discarded += len(self._buffer)
        self._buffer.clear()

    def _parse(self, final: bool) -> list[Frame]:
        buf = self._buffer
        counters = self.counters
        n = len(buf)
        pos = 0
        frames: list[Frame] = []
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                # A trailing 0xA5 may be the first half of the next sync.
                keep = 1 if (not final and n > pos and buf[-1] == SYNC[0]) else 0
                counters.bytes_discarded += n - keep - pos
                pos = n - keep
                break
            counters.bytes_discarded += start - pos
            pos = start
            if n - pos < HEADER_SIZE:
                if final:
                    counters.truncated += 1
                    counters.bytes_discarded += 1
                    pos += 1
                    continue
                break
            version, ftype, sensor, flags, seq, t_us, length = _HEADER.unpack_from(buf, pos + 2)
            if version != VERSION or ftype not in _KNOWN_TYPES or not _length_is_valid(ftype, length):
                counters.header_errors += 1
                counters.bytes_discarded += 1
                pos += 1
                continue
            end = pos + HEADER_SIZE + length + CRC_SIZE
            if end > n:
                if final:
                    counters.truncated += 1
                    counters.bytes_discarded += 1
                    pos += 1
                    continue
                break
            (crc,) = _CRC.unpack_from(buf, end - CRC_SIZE)
            body = bytes(buf[pos + 2 : end - CRC_SIZE])  # all but sync and crc: the frame's identity
            if crc_hqx(body, 0xFFFF) != crc:
                counters.crc_errors += 1
                counters.sensor(sensor).crc_errors += 1
                counters.bytes_discarded += 1
                pos += 1
                continue
            frame = self._accept(ftype, sensor, flags, seq, t_us, body)
            if frame is None:
                counters.bytes_discarded += end - pos
            else:
                frames.append(frame)
            pos = end
        del buf[:pos]
        return frames

    def _accept(self, ftype: int, sensor: int, flags: int, seq: int, t_us: int, body: bytes) -> Frame | None:
        """A good frame, with its place in its sensor's sequence; None for a
        repeat and for a data frame from the board's own id."""
        frame_type = FrameType(ftype)
        gap = 0
        restart = False
        if frame_type in DATA_TYPES:
            if sensor == BOARD_SENSOR_ID:
                self.counters.board_id_data += 1
                return None
            sensor_counters = self.counters.sensor(sensor)
            fingerprint = hash(body)
            state = self._states.get(sensor)
            if state is None:
                state = self._states[sensor] = _SensorState()
            else:
                # The board clock only runs forward (wrapping every 71.6 min):
                # only when it did not is the frame a repeat or a restart.
                step = (t_us - state.t_us) % T_US_MODULUS
                if step > _HALF_CLOCK and seq == state.seq + 1 and state.seen[seq] != fingerprint:
                    # The next scan after a pause longer than half the clock's period (STOP … START): in order.
                    # (Not 0 after 65 535: that may be a restart; nor the bytes 65 536 scans back: a repeat.)
                    pass
                elif step == 0 or step > _HALF_CLOCK:
                    info_step = (t_us - self._info_t_us) % T_US_MODULUS
                    restart = state.infos != self._infos and 0 < info_step < _HALF_CLOCK
                    if not restart:
                        if state.seen[seq] == fingerprint:
                            sensor_counters.duplicates += 1
                            return None
                        behind = (state.seq - seq) % SEQ_MODULUS
                        if step and behind <= RECENT_SCANS and seq in state.missing and \
                                T_US_MODULUS - step <= behind * MAX_SCAN_PERIOD_US:
                            state.missing.remove(seq)
                            state.seen[seq] = fingerprint  # so that a repeat of it is one
                            sensor_counters.late_frames += 1  # a scan the gap before missed, delivered late
                            return None
                        restart = step != 0
                elif state.infos != self._infos and ((t_us < state.t_us and step > RESTART_JUMP_US)
                                                     or ((seq - state.seq) % SEQ_MODULUS >= SEQ_MODULUS // 2
                                                         and 0 < (state.t_us - self._info_t_us) % T_US_MODULUS
                                                         < _HALF_CLOCK)
                                                     or (seq - state.seq - 1) % SEQ_MODULUS * MIN_SCAN_PERIOD_US
                                                     > 2 * step):
                    # After an INFO the clock fell back towards 0 (a board that had run more
                    # than half the clock's period: not a forward step), or, after an INFO
                    # stamped before this sensor's last scan (a power-up INFO, not a reply to
                    # INFO?), the clock ran on but the sequence started again (a board that had
                    # run for less time than it was off), or the sequence jumped by twice the
                    # scans the clock's step holds at the fastest rate (a power-up just after
                    # the clock wrapped): a restart, not a gap.
                    restart = True
                if restart:
                    sensor_counters.board_restarts += 1
                    state.missing.clear()  # the gaps of the run before: none of those scans can still come
                else:
                    forward = (seq - state.seq) % SEQ_MODULUS
                    if conflicting(forward, step):
                        # The scan just passed on or one shortly before, with other bytes: the protocol has no
                        # such frame (a repeat is identical). Not a gap of 65 535 scans, nor published twice.
                        sensor_counters.conflicting += 1
                        return None
                    gap = (forward - 1) % SEQ_MODULUS
                    if gap:
                        sensor_counters.seq_gaps += 1
                        sensor_counters.missed_frames += gap
                        if gap <= RECENT_SCANS:  # one of them may still come, late
                            state.missing.extend((state.seq + k) % SEQ_MODULUS for k in range(1, gap + 1))
            state.seq, state.t_us, state.infos = seq, t_us, self._infos
            state.seen[seq] = fingerprint
            sensor_counters.frames += 1
        elif frame_type == FrameType.INFO:
            self._infos += 1
            self._info_t_us = t_us
        self.counters.frames += 1
        return Frame(frame_type, sensor, flags, seq, t_us, body[HEADER_SIZE - 2 :], gap, restart)


def conflicting(forward: int, step: int) -> bool:
    """Whether a data frame ``forward`` scans on from its sensor's last
    (mod 65 536) with the board clock ``step`` µs on is the scan just passed
    on, or one shortly before it, sent again with other bytes: a sequence
    that did not advance (or fell back by up to RECENT_SCANS) in less time
    than as many scans as a gap would mean take at the fastest rate."""
    behind = forward == 0 or forward > SEQ_MODULUS - RECENT_SCANS
    return behind and step < ((forward - 1) % SEQ_MODULUS) * MIN_SCAN_PERIOD_US


def encode_frame(
    frame_type: int, sensor: int, seq: int, t_us: int, payload: bytes, flags: int = 0
) -> bytes:
    """Serialise one frame exactly as a board sends it."""
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload of {len(payload)} bytes exceeds the protocol maximum {MAX_PAYLOAD}")
    if not 0 <= sensor <= 255:
        raise ValueError(f"sensor id {sensor} is outside 0..255")
    body = _HEADER.pack(
        VERSION, frame_type, sensor, flags, seq % SEQ_MODULUS, t_us % T_US_MODULUS, len(payload)
    ) + payload
    return SYNC + body + _CRC.pack(crc_hqx(body, 0xFFFF))

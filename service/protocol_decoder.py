"""Board serial protocol v1, decoding: bytes in, frames out. No I/O.

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

Where each data frame stands in its sensor's sequence (repeats, restarts,
gaps, late frames) is protocol_sequence.py's; the layout is protocol.py's.
"""
from __future__ import annotations

from binascii import crc_hqx
from dataclasses import dataclass, field

from .protocol import _CRC, _HEADER, _KNOWN_TYPES, CRC_SIZE, HEADER_SIZE, SYNC, VERSION, Frame, _length_is_valid
from .protocol_sequence import Sequencing, _SensorState


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
    control_frames: int = 0  # INFO and ERROR frames (in ``frames``): the board's own, no sensor's data
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
            "control_frames": self.control_frames,
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


class Decoder(Sequencing):
    """Incremental protocol decoder with per-stream and per-sensor counters."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._states: dict[int, _SensorState] = {}
        self._infos = 0  # INFO frames seen, and the board time of the last one
        self._info_t_us = 0
        self.restarts_without_info = 0  # restarts found with their power-up INFO lost (protocol_sequence.py)
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

"""The decoder of protocol_decoder.py with its common case inlined, for the live path.

At 1 kHz per sensor a read holds one small frame per sensor, so what a
frame costs is Python's per-call and per-lookup overhead, not its bytes.
``BulkDecoder`` walks the buffer in one loop with its lookups bound once and
takes the usual data frame — a sensor seen before whose board clock ran
forward, no INFO in between — without a call; every other frame (the
first of a sensor, a repeat, a restart, INFO, ERROR, a bad header or CRC)
goes through ``Decoder``'s own code. Its decisions, frames and counters
are those of ``Decoder`` byte for byte (tests/test_protocol_fuzz.py runs its
fuzz on both).
"""
from __future__ import annotations

from binascii import crc_hqx

from .protocol import (_CRC, _HEADER, _KNOWN_TYPES, CRC_SIZE, HEADER_SIZE, SEQ_MODULUS, SYNC, T_US_MODULUS, VERSION, Frame,
                       FrameType, _length_is_valid)
from .protocol_decoder import Decoder
from .protocol_sequence import _HALF_CLOCK, RECENT_SCANS, conflicting

_DATA = {int(FrameType.GRID): FrameType.GRID, int(FrameType.QUAD): FrameType.QUAD}
_PAYLOAD_AT = HEADER_SIZE - 2  # the payload's offset in a frame's body (all but sync and crc)
_new = tuple.__new__  # a Frame from all its fields, without NamedTuple's Python-level __new__ (half the cost)
# (version, type, length) → whether the header is valid: a live stream repeats a few of them.
_HEADER_OK: dict[tuple[int, int, int], bool] = {}


def _header_ok(version: int, ftype: int, length: int) -> bool:
    ok = version == VERSION and ftype in _KNOWN_TYPES and _length_is_valid(ftype, length)
    if len(_HEADER_OK) < 4096:  # a garbage stream's headers must not grow it without bound
        _HEADER_OK[(version, ftype, length)] = ok
    return ok


class BulkDecoder(Decoder):
    """``Decoder`` with the same results in fewer Python operations per frame."""

    def _parse(self, final: bool) -> list[Frame]:
        buf = self._buffer
        counters = self.counters
        per_sensor = counters.sensors
        states = self._states
        infos = self._infos
        header_ok = _HEADER_OK
        find, unpack_header, unpack_crc = buf.find, _HEADER.unpack_from, _CRC.unpack_from
        n = len(buf)
        pos = 0
        discarded = 0
        frames: list[Frame] = []
        append = frames.append
        while True:
            start = find(SYNC, pos)
            if start < 0:
                keep = 1 if (not final and n > pos and buf[-1] == SYNC[0]) else 0
                discarded += n - keep - pos
                pos = n - keep
                break
            discarded += start - pos
            pos = start
            if n - pos >= HEADER_SIZE:
                version, ftype, sensor, flags, seq, t_us, length = unpack_header(buf, pos + 2)
                ok = header_ok.get((version, ftype, length))
                if ok is None:
                    ok = _header_ok(version, ftype, length)
                if not ok:
                    counters.header_errors += 1
                    discarded += 1
                    pos += 1
                    continue
                end = pos + HEADER_SIZE + length + CRC_SIZE
            else:
                end = n + 1  # not even its header yet
            if end > n:  # truncated: wait for the rest, or at the end of the stream skip its first byte
                if not final:
                    break
                counters.truncated += 1
                discarded += 1
                pos += 1
                continue
            body = bytes(buf[pos + 2:end - CRC_SIZE])
            if crc_hqx(body, 0xFFFF) != unpack_crc(buf, end - CRC_SIZE)[0]:
                counters.crc_errors += 1
                counters.sensor(sensor).crc_errors += 1
                discarded += 1
                pos += 1
                continue
            state = states.get(sensor)
            frame_type = _DATA.get(ftype)
            step = 0 if state is None else (t_us - state.t_us) % T_US_MODULUS
            if frame_type is not None and 0 < step <= _HALF_CLOCK and state.infos == infos and \
                    not conflicting((seq - state.seq) % SEQ_MODULUS, step):
                # A sensor's next scan: its clock ran forward, its sequence did not fall back, no INFO came since.
                sensor_counter = per_sensor[sensor]
                gap = (seq - state.seq - 1) % SEQ_MODULUS
                if gap:
                    sensor_counter.seq_gaps += 1
                    sensor_counter.missed_frames += gap
                    if gap <= RECENT_SCANS:  # Decoder._accept's bookkeeping: one of them may still come, late
                        state.missing.extend((state.seq + k) % SEQ_MODULUS for k in range(1, gap + 1))
                state.seq, state.t_us = seq, t_us
                state.seen[seq] = hash(body)
                sensor_counter.frames += 1
                counters.frames += 1
                append(_new(Frame, (frame_type, sensor, flags, seq, t_us, body[_PAYLOAD_AT:], gap, False)))
            else:
                frame = self._accept(ftype, sensor, flags, seq, t_us, body)
                infos = self._infos
                if frame is None:
                    discarded += end - pos
                else:
                    append(frame)
            pos = end
        counters.bytes_discarded += discarded
        del buf[:pos]
        return frames

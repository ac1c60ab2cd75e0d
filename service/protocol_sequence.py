"""Where a data frame stands in its sensor's sequence: next, after a gap,
a repeat, a restart, late or conflicting (``Decoder``'s bookkeeping per
sensor; protocol_decoder.py finds the frames).

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

from collections import deque

import numpy as np

from .protocol import BOARD_SENSOR_ID, DATA_TYPES, HEADER_SIZE, SEQ_MODULUS, T_US_MODULUS, Frame, FrameType

RECENT_SCANS = 256  # per sensor, how far back a missing scan may still come late, or a scan conflict
RESTART_JUMP_US = 1_000_000  # a clock that jumps more than this after an INFO, back towards 0
MAX_SCAN_PERIOD_US = 1_000_000  # RATE is at least 1 Hz
MIN_SCAN_PERIOD_US = 200  # and at most 5 000 Hz
_HALF_CLOCK = 1 << 31  # a board clock step beyond this is a step back (wrapped)


class _SensorState:
    """Where a sensor's sequence stands: its last frame passed on, the INFO
    count then, and per sequence number the fingerprint (hash of the bytes)
    of the last frame with that number."""

    __slots__ = ("seq", "t_us", "infos", "seen", "missing")

    def __init__(self) -> None:
        # calloc'd: pages are touched only as the sequence reaches them; a memoryview sets an item 2x faster than numpy.
        self.seen = memoryview(np.zeros(SEQ_MODULUS, np.int64))
        self.missing: deque[int] = deque(maxlen=RECENT_SCANS)  # sequence numbers of recent gaps


class Sequencing:
    """``Decoder``'s sequence bookkeeping: ``_states`` (per sensor), the INFO
    count ``_infos`` and the last INFO's board time ``_info_t_us``, the
    ``counters`` it adds to and ``restarts_without_info`` (restarts found by
    a sensor's clock going back, with no INFO of the new run before them:
    its power-up INFO was lost; all set by ``Decoder``)."""

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
                        self.restarts_without_info += restart  # its power-up INFO lost: the live path asks INFO?
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
        else:
            self.counters.control_frames += 1
            if frame_type == FrameType.INFO:
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

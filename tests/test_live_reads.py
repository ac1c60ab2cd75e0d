"""A live read's readings with their scan times against the frame-by-frame reference.

``Interpreter.interpret_many(frames, t_host, clock)`` gives each reading its
scan's host time from ``ClockMap.scan_times`` (plain Python): the same
values, bit for bit, as ``interpret`` frame by frame with ``ClockMap.observe``
(numpy) per read, through INFO, board restarts, sentinels and a counter
that wraps.
"""
from pathlib import Path

import numpy as np
import pytest

from service.clock_map import ClockMap
from service.protocol import FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.interpreter import Interpreter

DATA = Path(__file__).parent / "data"


def _reference(chunks):
    """interpret frame by frame, observe per read (the pipeline before)."""
    decoder, interpreter, clock = Decoder(), Interpreter(clock=lambda: 0.0), ClockMap()
    out = []
    for data, t_host in chunks:
        read = [r for r in (interpreter.interpret(f, t_host) for f in decoder.feed(data)) if r is not None]
        if read:
            if any(r.board_restart for r in read):
                clock.restart()
            for r, scan in zip(read, clock.observe(np.array([r.t_us for r in read]), t_host).tolist()):
                r.t_host_scan = scan
        out += read
    return out, clock


def _live(chunks):
    decoder, interpreter, clock = Decoder(), Interpreter(clock=lambda: 0.0), ClockMap()
    out = []
    for data, t_host in chunks:
        out += interpreter.interpret_many(decoder.feed(data), t_host, clock)
    return out, clock


def _fields(r):
    return (r.sensor, r.seq, r.t_us, r.t_host, r.board_flags, r.gap, r.capacitance_pF.tobytes(), r.open_channel,
            r.shorted_channel, r.board_restart, r.t_host_scan)


@pytest.mark.parametrize("capture", sorted(DATA.glob("*.bin")), ids=lambda p: p.stem)
def test_recorded_reads_get_the_scan_times_of_the_reference(capture):
    data = capture.read_bytes()
    rng = np.random.default_rng(2)
    cuts = np.sort(rng.choice(len(data), size=len(data) // 300, replace=False))
    chunks = [(data[a:b], 100.0 + i * 1e-3 + rng.uniform(0, 4e-4)) for i, (a, b) in
              enumerate(zip(np.r_[0, cuts], np.r_[cuts, len(data)]))]
    (want, want_clock), (got, got_clock) = _reference(chunks), _live(chunks)
    assert [_fields(r) for r in got] == [_fields(r) for r in want] and len(got) > 500
    assert got_clock.status() == want_clock.status()


def test_restarts_and_a_wrapping_counter_get_the_scan_times_of_the_reference():
    info = encode_frame(FrameType.INFO, 255, 0, 0, b'{"board": "b", "sensors": [{"id": 1, "kind": "quad"}]}')
    chunks, t_host = [], 50.0
    for run, start in enumerate(((1 << 32) - 40_000, 7_000)):  # the first run's counter wraps; then a restart
        chunks.append((info, t_host))
        for k in range(120):
            t_host += 1e-3
            frames = [encode_frame(FrameType.QUAD, 1, 2 * k + j, (start + (2 * k + j) * 500) % (1 << 32),
                                   np.array([2_200_000 + k, 0 if k == 7 else 2_180_000, 2_240_000, 0xFFFFFFFF * (k == 9)],
                                            dtype="<u4").tobytes()) for j in range(2)]
            chunks.append((b"".join(frames), t_host + 1e-4 * (k % 3)))
    (want, _), (got, _) = _reference(chunks), _live(chunks)
    assert [_fields(r) for r in got] == [_fields(r) for r in want]
    assert sum(r.board_restart for r in got) == 1 and any(r.open_channel for r in got) and any(r.shorted_channel for r in got)

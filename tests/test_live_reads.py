"""A live read's readings with their scan times, and the history's pending
writes, against the frame-by-frame reference.

``Interpreter.interpret_many(frames, t_host, clock)`` gives each reading its
scan's host time from ``ClockMap.scan_times`` (plain Python): the same
values, bit for bit, as ``interpret`` frame by frame with ``ClockMap.observe``
(numpy) per read, through INFO, board restarts, sentinels and a counter
that wraps. History rings written in batches show every frame appended,
whenever they are read.
"""
from pathlib import Path

import numpy as np
import pytest

from service.clock_map import ClockMap
from service.history import PENDING_FRAMES, Histories, History
from service.protocol import Decoder, FrameType, encode_frame
from service.readings import Interpreter, SensorInfo
from service.reconstruct import ForceFrame

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


GRID = SensorInfo(0, "grid", 2, 2)
QUAD = SensorInfo(1, "quad", 2, 2)


def _frame(info, seq):
    n = 4 if info.kind == "grid" else 3
    forces = np.arange(n) * 0.5 + seq
    return ForceFrame(info, seq, seq * 1000, 10.0 + seq * 1e-3, forces, np.arange(4) + 2.0 + seq, ["seq_gap"] * (seq % 2),
                      "full", np.full(4, seq % 3, np.uint8) if info.kind == "grid" and seq % 5 else None, f"c{seq % 2}",
                      None if seq % 7 == 0 else forces * 0.01, 9.9 + seq * 1e-3)


@pytest.mark.parametrize("info", [GRID, QUAD], ids=["grid", "quad"])
@pytest.mark.parametrize("capacity", [1, 7, PENDING_FRAMES, 3 * PENDING_FRAMES + 5])
def test_a_history_read_at_any_time_shows_every_frame_appended(info, capacity):
    history = History(info, capacity, 4 if info.kind == "grid" else 3)
    for seq in range(4 * PENDING_FRAMES + 3):
        history.append(_frame(info, seq))
        if seq % 11 == 0 or seq == 2 * PENDING_FRAMES - 1:
            assert len(history) == min(seq + 1, capacity)
            kept = history.window(100.0, 10_000)
            assert [f.seq for f in kept] == list(range(max(0, seq + 1 - capacity), seq + 1))
            for got in kept:
                want = _frame(info, got.seq)
                np.testing.assert_array_equal(got.forces_N, want.forces_N)
                np.testing.assert_array_equal(got.capacitance_pF, want.capacitance_pF)
                np.testing.assert_array_equal(got.sigma_N, np.full(len(want.forces_N), np.nan) if want.sigma_N is None
                                              else np.asarray(want.sigma_N, np.float32))
                if info.kind == "grid":
                    np.testing.assert_array_equal(got.taxel_flags, np.zeros(4, np.uint8) if want.taxel_flags is None
                                                  else want.taxel_flags)
                assert (got.t_us, got.t_host, got.t_host_scan, got.flags, got.calibration) == \
                    (want.t_us, want.t_host, want.t_host_scan, want.flags, want.calibration)


def test_a_ring_shrunk_with_frames_pending_keeps_the_newest():
    histories = Histories(budget_bytes=60 * History.bytes_per_frame(GRID, 4), frames=60)
    for seq in range(50):
        histories.for_frame(_frame(GRID, seq)).append(_frame(GRID, seq))
    other = SensorInfo(2, "grid", 2, 2)
    histories.for_frame(_frame(other, 0)).append(_frame(other, 0))  # two sensors: 30 frames each
    assert histories[0].capacity == 30
    assert [f.seq for f in histories[0].window(100.0, 100)] == list(range(20, 50))
    assert sorted(histories[0].numbers(np.arange(30)).tolist()) == list(range(30))  # a shrink renumbers

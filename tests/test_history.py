"""The per-sensor history ring: what goes in comes out, windowed and decimated."""
import numpy as np
import pytest

from service.history import History
from service.readings import SensorInfo
from service.reconstruct import ForceFrame

GRID = SensorInfo(0, "grid", 2, 2)


def frame(seq: int, info: SensorInfo = GRID) -> ForceFrame:
    forces = np.array([seq, seq + 0.5, np.nan, -seq], dtype=float)
    flags = ["seq_gap"] if seq % 3 == 0 else []
    return ForceFrame(info, seq, seq * 1000, 100.0 + seq * 1e-3, forces, forces + 10.0, flags, "full",
                      np.array([0, 1, 1, 0], dtype=np.uint8) * (seq % 2), f"cal{seq % 2}",
                      np.array([0.01, 0.02, np.nan, 0.03]) * (1 + seq), 99.9 + seq * 1e-3)


def test_the_ring_keeps_the_newest_frames_as_they_were():
    history = History(GRID, capacity=50, outputs=4)
    originals = [frame(seq) for seq in range(120)]
    for f in originals:
        history.append(f)
    assert len(history) == 50
    out = history.window(seconds=10.0, max_points=1000)
    assert [f.seq for f in out] == list(range(70, 120))
    for got, want in zip(out, originals[70:]):
        np.testing.assert_array_equal(got.forces_N, want.forces_N)
        np.testing.assert_array_equal(got.capacitance_pF, want.capacitance_pF)
        np.testing.assert_array_equal(got.taxel_flags, want.taxel_flags)
        assert (got.t_us, got.t_host, got.flags, got.level) == (want.t_us, want.t_host, want.flags, want.level)


def test_window_is_measured_back_from_the_newest_frame_and_decimated():
    history = History(GRID, capacity=5000, outputs=4)
    for seq in range(1000):  # 1 s at 1 kHz
        history.append(frame(seq))
    recent = history.window(seconds=0.1, max_points=1000)
    assert recent[0].seq == 899 and recent[-1].seq == 999  # stamps 0.899 … 0.999 s
    sparse = history.window(seconds=1.0, max_points=11)
    assert len(sparse) == 11 and sparse[0].seq == 0 and sparse[-1].seq == 999
    assert set(np.diff([f.seq for f in sparse])) <= {99, 100}  # evenly spread over the window


def test_frames_of_another_sensor_are_refused():
    history = History(GRID, capacity=10, outputs=4)
    with pytest.raises(ValueError, match="sensor 0 was given a frame of sensor 5"):
        history.append(frame(1, SensorInfo(5, "grid", 2, 2)))
    assert history.window(1.0, 10) == []


def test_histories_share_one_budget_and_keep_the_newest_frames():
    from service.history import Histories

    sensors = [SensorInfo(sid, "grid", 2, 2) for sid in range(4)]
    per_frame = History.bytes_per_frame(sensors[0], 4)
    # stamps (t_host, scan, seq, t_us), forces, σ (float32), raw, taxel flags, flags/level/calibration references
    assert per_frame == 32 + 32 + 16 + 32 + 4 + 24
    histories = Histories(budget_bytes=40 * per_frame, frames=30)
    for seq in range(25):  # sensor 0 alone: 30 frames fit, 25 kept
        histories.for_frame(frame(seq)).append(frame(seq))
    assert histories[0].capacity == 30 and len(histories[0]) == 25
    for info in sensors[1:]:  # four sensors: 10 frames each
        histories.for_frame(frame(0, info)).append(frame(0, info))
    assert [h.capacity for h in histories.values()] == [10, 10, 10, 10]
    assert histories.bytes <= 40 * per_frame
    kept = histories[0].window(100.0, 100)
    assert [f.seq for f in kept] == list(range(15, 25))  # the newest ten, oldest first, values intact
    for got in kept:
        np.testing.assert_array_equal(got.forces_N, frame(got.seq).forces_N)
        np.testing.assert_array_equal(got.taxel_flags, frame(got.seq).taxel_flags)
        assert got.flags == frame(got.seq).flags
        assert got.calibration == frame(got.seq).calibration and got.t_host_scan == frame(got.seq).t_host_scan
        np.testing.assert_array_equal(got.sigma_N, np.asarray(frame(got.seq).sigma_N, np.float32))
    for seq in range(25, 40):  # the shrunk ring goes on from where it was
        histories.for_frame(frame(seq)).append(frame(seq))
    assert [f.seq for f in histories[0].window(100.0, 100)] == list(range(30, 40))

import numpy as np
import pytest

from service.physics.paper_data import table1
from service.readings import Reading, SensorInfo
from service.reconstruct import Reconstructor
from service.reconstruct.baseline import Baseline
from service.reconstruct.level0 import grid_forces, quad_forces

GRID = SensorInfo(0, "grid", 8, 8)
QUAD = SensorInfo(1, "quad", 2, 2)


def reading(info, capacitance, seq=0):
    capacitance = np.asarray(capacitance, dtype=float)
    return Reading(info, seq, seq * 1000, 0.0, 0, 0, capacitance, bool(np.isnan(capacitance).any()), False)


def test_table1_copied_faithfully():
    cal = table1()
    # Spot values from the paper's table 1 (row, col): C0 pF, sensitivity %/N.
    assert cal.c0_pF[(2 - 1) * 8 + 3 - 1] == 7.82
    assert cal.c0_pF[(8 - 1) * 8 + 5 - 1] == 12.63
    assert cal.sensitivity_per_N[(4 - 1) * 8 + 4 - 1] == pytest.approx(0.01189)
    # Paper: mean C0 10.64 ± 1.03 pF, mean sensitivity 1.24 ± 0.01 %/N.
    assert cal.c0_pF.mean() == pytest.approx(10.64, abs=0.01)
    assert cal.c0_pF.std(ddof=1) == pytest.approx(1.03, abs=0.01)
    assert cal.sensitivity_per_N.mean() * 100 == pytest.approx(1.247, abs=0.001)


def test_grid_level0_recovers_linear_forces_per_taxel():
    cal = table1()
    rng = np.random.default_rng(1)
    forces = rng.uniform(0, 10, (5, 64))
    baseline = cal.c0_pF * 1.01  # a board whose zero differs from table 1
    capacitance = baseline * (1 + cal.sensitivity_per_N * forces)
    np.testing.assert_allclose(grid_forces(capacitance, baseline, cal), forces, atol=1e-12)


def test_paper_crosstalk_example_in_level0():
    # U44: 9.68 pF -> 10.27 pF at 5.21 N in paper 000; with its sensitivity
    # 1.189 %/N level 0 reads (10.27/9.68 - 1)/0.01189 = 5.126 N.
    cal = table1()
    capacitance = cal.c0_pF.copy()
    capacitance[27] = 10.27
    assert grid_forces(capacitance, cal.c0_pF, cal)[27] == pytest.approx(5.126, abs=1e-3)


def test_quad_level0_axes_and_signs():
    baseline = np.array([2.0, 2.2, 2.1, 2.3])
    fx, fy, fz = 2.0, -1.0, 4.0
    sx = np.array([-1, 1, -1, 1])  # C12, C22 on +X
    sy = np.array([-1, -1, 1, 1])  # C21, C22 on +Y
    relative = 0.0343 * fz + sx * 0.0077 * fx + sy * 0.0077 * fy
    np.testing.assert_allclose(quad_forces(baseline * (1 + relative), baseline), [fx, fy, fz], atol=1e-12)


def test_quad_with_a_dead_electrode_has_no_force():
    baseline = np.full(4, 2.2)
    assert np.isnan(quad_forces(np.array([2.3, np.nan, 2.3, 2.3]), baseline)).all()


def test_baseline_mean_of_first_frames_ignoring_sentinels():
    base = Baseline(3, frames=4)
    for row in ([1.0, 2.0, np.nan], [3.0, 2.0, np.nan], [1.0, 2.0, np.nan], [3.0, 2.0, np.nan]):
        base.update(np.array(row))
    assert base.ready
    np.testing.assert_array_equal(base.value[:2], [2.0, 2.0])
    assert np.isnan(base.value[2])
    base.update(np.array([100.0, 100.0, 100.0]))
    np.testing.assert_array_equal(base.value[:2], [2.0, 2.0])


def test_a_tare_window_gone_on_with_elsewhere_gives_the_zero_of_the_whole_window():
    """A recording begun mid-tare stores the window so far (JSON); a replay
    goes on with it: a 3-channel window of 4 readings, 2 before (a sentinel
    among them) and 2 after, gives mean [2, 2] and spread [1, 0] as one
    baseline fed all 4 does; a window of another size is refused by name."""
    import json

    rows = [[1.0, 2.0, np.nan], [3.0, 2.0, np.nan], [1.0, 2.0, np.nan], [3.0, 2.0, np.nan]]
    live = Baseline(3, frames=4)
    for row in rows[:2]:
        live.update(np.array(row))
    so_far = json.loads(json.dumps(live.window_so_far()))
    again = Baseline(3, frames=4)
    again.resume_window(so_far)
    assert not again.ready
    for row in rows[2:]:
        again.update(np.array(row))
    assert again.ready
    np.testing.assert_array_equal(again.value[:2], [2.0, 2.0])
    np.testing.assert_array_equal(again.std[:2], [1.0, 0.0])
    assert np.isnan(again.value[2]) and again.window_so_far() is None
    with pytest.raises(ValueError, match="of 3 channels: this baseline has 4 channels"):
        Baseline(4, frames=4).resume_window(so_far)


def test_reconstructor_tares_then_reports_and_retares():
    rec = Reconstructor(tare_frames=3, level="level0")
    c0 = table1().c0_pF
    out = [rec.process(reading(GRID, c0, seq))[0] for seq in range(3)]
    assert out[0].flags == ["taring"] and np.isnan(out[0].forces_N).all()
    assert out[2].flags == [] and np.allclose(out[2].forces_N, 0)
    loaded = c0 * (1 + table1().sensitivity_per_N * 2.0)
    np.testing.assert_allclose(rec.process(reading(GRID, loaded, 3))[0].forces_N, 2.0)
    rec.tare(0)
    assert rec.process(reading(GRID, loaded, 4))[0].flags == ["taring"]


def test_hold_until_tared_releases_every_frame_with_forces():
    rec = Reconstructor(tare_frames=3, hold_until_tared=True, level="level0")
    baseline = np.full(4, 2.0)
    assert rec.process(reading(QUAD, baseline, 0)) == []
    assert rec.process(reading(QUAD, baseline, 1)) == []
    released = rec.process(reading(QUAD, baseline, 2))
    assert [f.seq for f in released] == [0, 1, 2]
    assert all(np.allclose(f.forces_N, 0) and f.flags == [] for f in released)


def test_flush_releases_untared_frames_as_null():
    rec = Reconstructor(tare_frames=10, hold_until_tared=True)
    rec.process(reading(QUAD, np.full(4, 2.0), 0))
    (frame,) = rec.flush()
    assert np.isnan(frame.forces_N).all() and "taring" in frame.flags


def test_unknown_level_is_named():
    with pytest.raises(ValueError, match="'level9'"):
        Reconstructor(level="level9")


def test_hold_keeps_arrival_order_across_sensors():
    rec = Reconstructor(tare_frames=2, hold_until_tared=True)
    out = []
    for seq in range(3):
        out += rec.process(reading(GRID, table1().c0_pF, seq))
        out += rec.process(reading(QUAD, np.full(4, 2.0), seq))
    assert [(f.sensor.id, f.seq) for f in out] == [(0, 0), (1, 0), (0, 1), (1, 1), (0, 2), (1, 2)]


def test_a_channel_open_during_the_tare_gets_its_baseline_late():
    base = Baseline(2, frames=3)
    for _ in range(3):
        base.update(np.array([1.0, np.nan]))
    assert base.ready and np.isnan(base.value[1])
    for value in (2.0, 2.2, 2.4):
        base.update(np.array([5.0, value]))
    assert base.value[0] == 1.0 and base.value[1] == pytest.approx(2.2)
    assert base.std[1] == pytest.approx(np.std([2.0, 2.2, 2.4]))

"""Full-fidelity reconstruction on simulated data: crosstalk detection and
compensation, drift, flags, contact summary, errors against ground truth."""
import numpy as np
import pytest

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import Drift, SimGrid, SimQuad
from service.reports.bench import noise_floor_N
from service.pipeline import Pipeline
from service.protocol import FLAG_SATURATED, FrameType, encode_frame
from service.reconstruct import Reconstructor
from service.reconstruct.levels import SceneConfig

NOISE_FLOOR = noise_floor_N()  # checked against table 1 in test_reports.py
PRESSED = 27  # row 4, col 4


def run(scene, seconds, level="full", **grid_options):
    config = BoardConfig(sensors=[SimGrid(0, **grid_options), SimQuad(1)], scene=scene, seed=3)
    data, board = capture(config, seconds, keep_truth=True)
    pipeline = Pipeline(Reconstructor(hold_until_tared=True, level=level), clock=lambda: 0.0)
    frames = []
    for i in range(0, len(data), 16384):  # as replay and the live port deliver it
        frames += pipeline.feed(data[i : i + 16384], 0.0)
    frames += pipeline.finish(0.0)
    truth = {(t.sensor, t.seq): t.values for t in board.truth}
    grid = [f for f in frames if f.sensor.kind == "grid"]
    forces = np.stack([f.forces_N for f in grid])
    expected = np.stack([truth[(0, f.seq)] for f in grid])
    return pipeline, grid, forces, expected


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


def test_mechanical_crosstalk_never_leaves_a_negative_or_phantom_neighbour():
    pipeline, grid, forces, expected = run("press", 3.0)
    neighbours = [18, 19, 20, 26, 28, 34, 35, 36]
    assert forces.min() >= 0.0
    pressed = expected[:, PRESSED] > 4.0
    assert rms(forces[pressed][:, neighbours]) < 1.5 * NOISE_FLOOR
    report = pipeline.reconstructor.crosstalk_report(0)
    assert report["mechanical_coupling_in_use"] == pytest.approx(-0.0028, abs=0.0008)


def test_mux_leakage_is_detected_estimated_and_compensated():
    pipeline, grid, forces, expected = run("press", 4.0, electrical_leakage=0.01)
    report = pipeline.reconstructor.crosstalk_report(0)
    assert report["isolated_loads_adopted"] >= 50
    assert report["electrical_leakage_in_use"] == pytest.approx(0.01, abs=0.0015)
    late = np.arange(len(grid)) > len(grid) // 2  # after the estimate was adopted
    loaded = expected > 0.05
    assert rms((forces - expected)[late][loaded[late]]) < 2 * NOISE_FLOOR
    assert any("crosstalk_corrected" in f.flags for f in grid)
    _, _, table_forces, _ = run("press", 4.0, level="table", electrical_leakage=0.01)
    assert rms((table_forces - expected)[loaded]) > 3 * NOISE_FLOOR  # uncompensated, for contrast


def test_drift_is_followed_without_eating_a_slow_press():
    """A drift of 0.5 %/min at its fastest (this ran 1.9 %/min, faster than
    drift.py's bound for PDMS, 1 %/min) is followed; a press creeping on one
    taxel is not."""
    drift = Drift(amplitude=0.005, period_s=360.0)
    _, grid, forces, expected = run("slow_press", 10.0, drift=drift)
    unloaded = np.ones(64, bool)
    unloaded[PRESSED] = False
    assert rms(forces[:, unloaded]) < 1.5 * NOISE_FLOOR
    # The press creeps from 0 to 3 N over 8 s: the tracker must leave it whole.
    held = expected[:, PRESSED] > 2.5
    assert np.abs(forces[held, PRESSED] - expected[held, PRESSED]).mean() < 2 * NOISE_FLOOR
    _, _, level0_forces, _ = run("slow_press", 10.0, level="level0", drift=drift)
    assert level0_forces[-1000:, unloaded].mean() > 5 * NOISE_FLOOR  # what an untracked drift costs by 10 s


def test_contact_summary_counts_and_locates_contacts():
    _, grid, forces, expected = run("two_contacts", 2.0)
    contact = grid[-1].contact
    assert contact["contacts"] == 2
    assert contact["total_N"] == pytest.approx(5.0, rel=0.05)
    _, press_grid, press_forces, press_expected = run("press", 2.0)
    peak = int(np.argmax(press_expected[:, PRESSED]))
    summary = press_grid[peak].contact
    assert summary["contacts"] == 1
    assert (summary["cop_x_mm"], summary["cop_y_mm"]) == pytest.approx((-2.0, -2.0), abs=0.05)
    assert summary["area_mm2"] == 16.0


def reconstruct(frames, level="full", tare_frames=10):
    pipeline = Pipeline(Reconstructor(tare_frames=tare_frames, hold_until_tared=True, level=level), clock=lambda: 0.0)
    return pipeline.feed(b"".join(frames), 0.0) + pipeline.finish(0.0)


def grid_frame(seq, counts, flags=0):
    return encode_frame(FrameType.GRID, 0, seq, seq * 1000, np.asarray(counts, "<u4").tobytes(), flags)


def quad_frame(seq, counts):
    return encode_frame(FrameType.QUAD, 1, seq, seq * 1000, np.asarray(counts, "<u4").tobytes())


def test_every_out_of_range_case_is_flagged():
    rng = np.random.default_rng(0)
    base = np.full(64, 10_000_000.0)
    frames = [grid_frame(i, base + rng.normal(0, 1000, 64)) for i in range(10)]
    extreme = base + rng.normal(0, 1000, 64)
    extreme[0] *= 2.0  # ΔC/C0 = 1, past the table's top (0.78, where the gap would close by half)
    extreme[1] *= 0.99  # a 1 % drop: no compressive force explains it
    extreme[2] = 0xFFFFFFFF  # open channel
    frames.append(grid_frame(10, extreme, FLAG_SATURATED))
    out = reconstruct(frames)
    last = out[-1]
    assert last.taxel_flag_lists()["saturated"] == [0]
    assert last.taxel_flag_lists()["out_of_range"] == [1]
    assert last.taxel_flag_lists()["no_reading"] == [2]
    assert last.forces_N[1] == 0 and np.isnan(last.forces_N[2])
    assert last.forces_N[0] == pytest.approx(37.7 / 1.05, rel=0.1)  # held at the table's top
    assert {"saturated", "out_of_range", "open_channel"} <= set(last.flags)


@pytest.mark.parametrize("level", ["level0", "table", "full"])
def test_a_stuck_channel_is_flagged_stale_and_gives_no_force(level):
    """A converter that stopped converting repeats one count: after 50 such
    frames the taxel is stale, its force null (not the old count's force:
    a stuck channel latched under a load would feed a controller and the
    contact summary a load that is gone), as a missing one."""
    rng = np.random.default_rng(1)
    frames = []
    for i in range(80):
        counts = 10_000_000 + rng.normal(0, 1000, 64)
        counts[5] = 10_000_123 if i < 10 else 13_000_000  # latched loaded after the tare
        frames.append(grid_frame(i, counts))
    out = reconstruct(frames, level)
    assert "stale" in out[-1].flags and out[-1].taxel_flag_lists()["stale"] == [5]
    assert "stale" not in out[20].flags and out[20].forces_N[5] > 5.0
    assert np.isnan(out[-1].forces_N[5]) and np.isnan(out[-1].sigma_N[5])
    assert out[-1].contact["total_N"] < 1.0 and np.isfinite(np.delete(out[-1].forces_N, 5)).all()


@pytest.mark.parametrize("level", ["level0", "table", "full"])
def test_a_stuck_quad_electrode_leaves_its_frames_null_and_stale(level):
    """A quad's converter latched on one electrode under a load: from the
    50th repeat on its frames have no forces (each axis combines all four
    electrodes) and say ``stale``, instead of the latched load's wrench; when
    the electrode converts again, so do the forces."""
    c0 = np.full(4, 2_200_000.0)
    rng = np.random.default_rng(3)
    latched = c0 * np.array([1.0, 1.0, 1.08, 1.0])
    frames = []
    for i in range(130):
        counts = c0 + rng.normal(0, 1000, 4)
        if 20 <= i < 100:
            counts[2] = latched[2]  # the same count 80 frames running: repeats 1..79
        frames.append(quad_frame(i, counts))
    out = reconstruct(frames, level)
    assert [i for i, f in enumerate(out) if "stale" in f.flags] == list(range(70, 100))
    assert all(np.isnan(out[i].forces_N).all() and np.isnan(out[i].sigma_N).all() for i in range(70, 100))
    assert np.isfinite(out[69].forces_N).all() and abs(out[69].forces_N[2]) > 0.5  # a load held 49 repeats: believed
    assert np.isfinite(out[100].forces_N).all() and not out[100].flags


def test_a_quiet_quad_converter_is_not_called_stale():
    """Without noise (a simulated board), equal counts are normal: never stale."""
    c0 = np.full(4, 2_200_000.0)
    out = reconstruct([quad_frame(i, c0) for i in range(120)])
    assert not any("stale" in f.flags for f in out) and np.isfinite(out[-1].forces_N).all()


def test_quad_out_of_range_and_electrode_fault_are_flagged():
    c0 = np.array([2_200_000.0] * 4)
    rng = np.random.default_rng(2)
    frames = [quad_frame(i, c0 + rng.normal(0, 1000, 4)) for i in range(10)]
    frames.append(quad_frame(10, c0 * 1.40))  # ΔC/C0 = 0.40: past fit (34)'s maximum
    frames.append(quad_frame(11, c0 * (1 + np.array([-1, 1, -1, 1]) * 0.05)))  # past the shear domain
    frames.append(quad_frame(12, c0 * (1 + np.array([0.0, 0.0, 0.0, 0.08]))))  # one electrode alone
    out = reconstruct(frames)
    assert "normal_out_of_range" in out[10].flags
    assert out[10].forces_N[2] == pytest.approx(0.9 * 0.0343 / 0.0018)
    assert "shear_out_of_range" in out[11].flags and abs(out[11].forces_N[0]) == pytest.approx(0.9 * 0.0077 / 0.0008)
    assert "electrode_fault" in out[12].flags
    assert not any(out[i].flags for i in range(10))


def test_full_level_meets_the_error_target_on_the_slide_scene():
    _, grid, forces, expected = run("slide", 4.0)
    loaded = expected > 0.05
    assert rms((forces - expected)[loaded]) < 2 * NOISE_FLOOR
    assert rms((forces - expected)[~loaded]) < NOISE_FLOOR


def test_auto_level_follows_the_scene():
    assert Reconstructor(level="auto").level == "full"
    clean = Reconstructor(level="auto", scene=SceneConfig(contacts="single", clean_board=True, mounting="curved"))
    assert clean.level == "table" and clean.mounting == "curved"
    with pytest.raises(ValueError, match="contacts must be"):
        SceneConfig(contacts="many")


def test_forces_do_not_depend_on_how_the_stream_is_cut():
    """Frame by frame (the live path's fast paths) and in one batch (quads of
    several sensors solved together) give the same forces and flags, bit for
    bit, through estimator adoption."""
    grid = SimGrid(0, electrical_leakage=0.01, drift=Drift(0.002, 5.0))
    config = BoardConfig(sensors=[grid, SimQuad(1), SimQuad(2)], scene="demo", seed=5)
    data, _ = capture(config, 1.5)

    def reconstruct(chunk_bytes):
        pipeline = Pipeline(Reconstructor(hold_until_tared=True), clock=lambda: 0.0)
        frames = []
        for i in range(0, len(data), chunk_bytes):
            frames += pipeline.feed(data[i : i + chunk_bytes], 0.0)
        return frames + pipeline.finish(0.0)

    whole, single = reconstruct(len(data)), reconstruct(100)  # less than one frame at a time
    assert len(whole) == len(single) == 3 * 1500
    for a, b in zip(whole, single):
        assert (a.sensor.id, a.seq) == (b.sensor.id, b.seq)
        np.testing.assert_array_equal(a.forces_N, b.forces_N)
    np.testing.assert_array_equal(*(np.stack([f.taxel_flags for f in frames if f.taxel_flags is not None]) for frames in (whole, single)))
    assert [f.flags for f in whole] == [f.flags for f in single]


def test_a_sensors_forces_do_not_depend_on_the_other_sensors():
    """Grids (and quads) of a board are reconstructed together, one call per
    step; each sensor must get exactly what it would get alone."""
    from service.protocol_decoder import Decoder
    from service.interpreter import Interpreter

    sensors = [SimGrid(0, electrical_leakage=0.01, drift=Drift(0.002, 5.0)), SimGrid(1, mechanical_coupling=-0.004),
               SimQuad(2), SimGrid(3, rows=4, cols=4)]
    data, _ = capture(BoardConfig(sensors=sensors, scene="demo", seed=9), 1.2)
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [r for r in (interpreter.interpret(f, 0.0) for f in Decoder().feed(data)) if r is not None]

    def forces(subset, step):
        reconstructor = Reconstructor(hold_until_tared=True)
        out = []
        for i in range(0, len(subset), step):
            out += reconstructor.process_many(subset[i : i + step])
        out += reconstructor.flush()
        return {(f.sensor.id, f.seq): (f.forces_N, f.taxel_flags, f.flags) for f in out}

    together = forces(readings, 12)
    for sid in (0, 1, 3):
        alone = forces([r for r in readings if r.sensor.id == sid], 3)
        assert len(alone) == 1200
        for key, (f, taxel_flags, flags) in alone.items():
            np.testing.assert_array_equal(together[key][0], f)
            np.testing.assert_array_equal(together[key][1], taxel_flags)
            assert together[key][2] == flags


@pytest.mark.parametrize("kind", ["grid", "quad"])
def test_a_calibration_changed_during_a_stale_run_keeps_the_channel_stale(kind):
    """The stale count belongs to the converter, not to the calibration: a
    new one mid-run does not give the latched load's forces 50 frames more."""
    rng = np.random.default_rng(4)
    pipeline = Pipeline(Reconstructor(tare_frames=10, hold_until_tared=True, level="full"), clock=lambda: 0.0)
    out = []
    for i in range(200):
        if kind == "grid":
            counts = 10_000_000 + rng.normal(0, 1000, 64)
            counts[5] = 10_000_123 if i < 20 else 13_000_000
            out += pipeline.feed(grid_frame(i, counts), 0.0)
        else:
            counts = 2_200_000.0 + rng.normal(0, 1000, 4)
            if 20 <= i:
                counts[2] = 2_200_000.0 * 1.08
            out += pipeline.feed(quad_frame(i, counts), 0.0)
        if i == 100:
            info = next(iter(pipeline.interpreter.sensors.values()))
            upload = ({"sensitivity_pct_per_N": [1.3] * 64} if kind == "grid"
                      else {"normal_fit": [-0.0008, 0.031], "shear_fit": [0.0075, 0.0004]})
            pipeline.set_calibration(info, upload)
    out += pipeline.finish(0.0)
    assert [i for i, f in enumerate(out) if "stale" in f.flags] == list(range(70, 200))

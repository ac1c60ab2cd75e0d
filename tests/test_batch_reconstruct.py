"""The batched live path against the per-sensor reference.

Sensors of a kind go through one call per step for a whole read (stuck.py,
the quads' stacked baselines, grid_full.py; fatigue.update_many: test_live_fatigue.py): every
sensor's frames must be, bit for bit, what the sensor gives when it is
reconstructed alone one frame at a time — with different calibrations,
stuck channels, reads that pile up (several frames per sensor), and a
sensor whose reconstruction fails.
"""
import numpy as np
import pytest

from firmware_sim.board import BoardConfig, capture
from firmware_sim.sensors import SimGrid, SimQuad
from service.physics.paper_data import table1
from service.protocol_decoder import Decoder
from service.interpreter import Interpreter
from service.readings import Reading
from service.reconstruct import Reconstructor
from service.reconstruct import reconstructor as reconstructor_module
from service.reconstruct.stuck import run_lengths

STUCK_FROM_SEQ = 300  # grid 3's channels 5 and 17 repeat one count from here on, in runs of 70 and 53 frames
RELEASE_FROM_SEQ = 1350  # grid 7 and quad 4 let go of the scene's load here (to count load cycles)


def _boom(*_args, **_kwargs):
    raise RuntimeError("boom")


@pytest.fixture(scope="module")
def reads():
    """1.6 s of a mixed board, cut into reads as the live path gets them: one
    scan each, and now and then three that piled up."""
    sensors = [SimGrid(0, electrical_leakage=0.01), SimGrid(1), SimGrid(2, mechanical_coupling=-0.004), SimGrid(3),
               SimQuad(4), SimQuad(5), SimQuad(6), SimGrid(7)]
    data, _ = capture(BoardConfig(sensors=sensors, scene="demo", seed=5), 1.6)
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [r for r in (interpreter.interpret(f, 0.0) for f in Decoder().feed(data)) if r is not None]
    readings = [_stuck(r) if r.sensor.id == 3 and r.seq >= STUCK_FROM_SEQ else r for r in readings]
    unloaded = {(r.sensor.id, r.seq): r.capacitance_pF for r in readings if r.seq < 1000}
    readings = [_with(r, unloaded[(r.sensor.id, r.seq - 1000)]) if r.sensor.id in (4, 7) and r.seq >= RELEASE_FROM_SEQ
                else r for r in readings]
    scans: dict[int, list[Reading]] = {}
    for r in readings:
        scans.setdefault(r.t_us, []).append(r)
    scans = list(scans.values())
    rng = np.random.default_rng(1)
    out, i = [], 0
    while i < len(scans):
        n = 3 if rng.random() < 0.15 else 1
        out.append([r for scan in scans[i:i + n] for r in scan])
        i += n
    return out


def _stuck(r: Reading) -> Reading:
    c = r.capacitance_pF.copy()
    c[[5, 17]] = [2.0 + 1e-3 * (r.seq // 70), 2.5 + 1e-3 * (r.seq // 53)]
    return _with(r, c)


def _with(r: Reading, capacitance: np.ndarray) -> Reading:
    return Reading(r.sensor, r.seq, r.t_us, r.t_host, r.board_flags, r.gap, capacitance, r.open_channel,
                   r.shorted_channel)


def _calibrate(rec: Reconstructor, infos: dict) -> None:
    """Calibrations that differ per sensor: grid 1 its own gains, grid 2 a
    measured C0, quads 5 and 6 their own fits (so the quads form two batches)."""
    rng = np.random.default_rng(3)
    rec.set_calibration(infos[1], {"sensitivity_pct_per_N": (1.25 * rng.uniform(0.8, 1.2, 64)).tolist()})
    rec.set_calibration(infos[2], {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": table1().c0_pF.tolist()})
    for sid in (5, 6):
        rec.set_calibration(infos[sid], {"normal_fit": [-0.0008, 0.031], "shear_fit": [0.0075, 0.0004]})


def _run(reads, level, alone_sensor=None, fail=None):
    """Frames by (sensor, seq), and the reconstructor. ``alone_sensor``: only
    its readings, one at a time (the reference); ``fail(rec)`` breaks a
    sensor from the middle on."""
    infos = {r.sensor.id: r.sensor for read in reads for r in read}
    rec = Reconstructor(level=level, clock=lambda: 0.0)
    _calibrate(rec, infos)
    frames = {}
    for k, read in enumerate(reads):
        if fail is not None and k == len(reads) // 2:
            fail(rec)
        if alone_sensor is not None:
            batches = [[r] for r in read if r.sensor.id == alone_sensor]
        else:
            batches = [read]
        for batch in batches:
            for frame in rec.process_many(batch):
                frames[(frame.sensor.id, frame.seq)] = frame
    return frames, rec


def _assert_same(a, b):
    np.testing.assert_array_equal(a.forces_N, b.forces_N)
    np.testing.assert_array_equal(a.sigma_N, b.sigma_N)
    assert a.flags == b.flags  # (calibration ids differ: an upload's document is dated)
    if a.taxel_flags is None:
        assert b.taxel_flags is None
    else:
        np.testing.assert_array_equal(a.taxel_flags, b.taxel_flags)


@pytest.mark.parametrize("level", ["level0", "table", "full"])
def test_each_sensor_of_a_batch_gets_what_it_gets_alone(reads, level):
    together, rec = _run(reads, level)
    ids = sorted({sid for sid, _ in together})
    for sid in ids:
        alone, reference = _run(reads, level, alone_sensor=sid)
        assert len(alone) == len([key for key in together if key[0] == sid])
        for key, frame in alone.items():
            _assert_same(together[key], frame)
        assert rec.cycle_counts()[sid][2] == reference.cycle_counts()[sid][2]
    stale = [f for (sid, seq), f in together.items() if sid == 3 and seq >= STUCK_FROM_SEQ + 60 and "stale" in f.flags]
    assert stale, "the stuck channels were flagged"
    counted = {sid for sid, (_, _, counts) in rec.cycle_counts().items() if sum(counts)}
    assert {4, 7} <= counted, "the releases counted load cycles"


def test_a_failing_grid_of_a_batch_leaves_the_others_as_alone(reads):
    def fail(rec):
        rec._sensors[3].processor._stuck = _boom

    together, rec = _run(reads, "full", fail=fail)
    for sid in (0, 1, 2, 7):
        alone, _ = _run(reads, "full", alone_sensor=sid)
        for key, frame in alone.items():
            _assert_same(together[key], frame)
    late = [f for (sid, _), f in together.items() if sid == 3 and "reconstruction_error" in f.flags]
    assert late and all(np.isnan(f.forces_N).all() for f in late)
    assert set(rec.errors()) == {3}


def test_run_lengths_of_several_sensors_equal_a_frame_by_frame_count():
    rng = np.random.default_rng(7)
    sensors, frames, n = 5, 40, 6
    capacitance = rng.choice([1.0, 2.0, np.nan], size=(sensors, frames, n), p=[0.45, 0.45, 0.1])
    expected = np.zeros((sensors, frames, n), dtype=np.int64)
    for s in range(sensors):
        for t in range(1, frames):
            same = capacitance[s, t] == capacitance[s, t - 1]
            expected[s, t] = np.where(same, expected[s, t - 1] + 1, 0)
    previous, prior = np.full((sensors, n), np.nan), np.zeros((sensors, n), dtype=np.int64)
    start = 0
    for size in (1, 3, 1, 1, 10, 2, 22):  # batches of any size continue the runs
        got = run_lengths(previous, prior, capacitance[:, start:start + size])
        np.testing.assert_array_equal(got, expected[:, start:start + size])
        previous, prior = capacitance[:, start + size - 1], got[:, -1]
        start += size
    assert start == frames


def test_grids_of_different_sizes_in_one_read_get_what_they_get_alone(monkeypatch):
    calls = []
    monkeypatch.setattr(reconstructor_module, "process_full",
                        lambda jobs, original=reconstructor_module.process_full: calls.append(len(jobs)) or original(jobs))
    sensors = [SimGrid(0), SimGrid(1, rows=4, cols=4), SimGrid(2), SimGrid(3, rows=4, cols=6)]
    data, _ = capture(BoardConfig(sensors=sensors, scene="demo", seed=2), 1.3)
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [r for r in (interpreter.interpret(f, 0.0) for f in Decoder().feed(data)) if r is not None]
    scans: dict[int, list[Reading]] = {}
    for r in readings:
        scans.setdefault(r.t_us, []).append(r)
    together, alone = Reconstructor(level="full"), {s.id: Reconstructor(level="full") for s in sensors}
    for scan in scans.values():
        calls.append("read")
        frames = {f.sensor.id: f for f in together.process_many(scan)}
        calls.append("alone")
        for r in scan:
            (expected,) = alone[r.sensor.id].process(r)
            _assert_same(frames[r.sensor.id], expected)
    batched = [calls[i + 1] for i, c in enumerate(calls) if c == "read" and calls[i + 1] != "alone"]
    assert batched and set(batched) == {4}  # the four grids of a tared read in one call
    assert not together.errors() and frames[1].forces_N.shape == (16,) and np.isfinite(frames[1].forces_N).all()

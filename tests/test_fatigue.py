"""Load cycles and fatigue compensation (paper 001 §5.2): counting against a
plain loop, the decay model against the paper's three statements, the
quad's forces compensated, counts kept across a restart and reset by a new
calibration."""
import numpy as np
import pytest

from service.calibration.book import CalibrationBook
from service.physics.quad_model import NOMINAL_C0_PF, QuadModel
from service.readings import Reading, SensorInfo
from service.reconstruct import Reconstructor
from service.reconstruct.fatigue import HIGH_N, JUDGE_EVERY, LOW_N, PAPER_001, CycleCounter

QUAD = SensorInfo(1, "quad", 2, 2, "Q-7")


def reference_cycles(forces: np.ndarray) -> np.ndarray:
    """A frame-by-frame loop: armed above HIGH_N, a cycle when it then falls below LOW_N."""
    counts = np.zeros(forces.shape[1], dtype=int)
    armed = np.zeros(forces.shape[1], dtype=bool)
    for row in forces:
        for k, f in enumerate(row):
            if f > HIGH_N:
                armed[k] = True
            elif f < LOW_N and armed[k]:
                counts[k] += 1
                armed[k] = False
    return counts


@pytest.mark.parametrize("batch", [1, 7, 250, 5000])
def test_cycles_are_counted_with_hysteresis_whatever_the_batching(batch):
    rng = np.random.default_rng(4)
    t = np.arange(5000)[:, None]
    forces = 1.5 * (1 - np.cos(2 * np.pi * t / rng.integers(40, 400, 8))) + rng.normal(0, 0.25, (5000, 8))
    forces[rng.random(forces.shape) < 0.01] = np.nan  # lost readings change nothing
    counter = CycleCounter(8)
    for k in range(0, len(forces), batch):
        counter.update(forces[k:k + batch])
    expected = reference_cycles(forces[::JUDGE_EVERY])  # every JUDGE_EVERY-th frame of the stream is judged
    assert expected.min() > 10
    np.testing.assert_array_equal(counter.counts, expected)


def test_noise_around_one_threshold_counts_nothing():
    counter = CycleCounter(1)
    counter.update(HIGH_N + np.random.default_rng(0).normal(0, 0.1, (2000, 1)))  # the band is 7σ wide
    assert counter.counts[0] == 0


def test_the_decay_model_follows_the_papers_three_statements():
    drop = 1 - PAPER_001.factor(10_000)
    assert drop == pytest.approx(0.22, abs=0.002)  # 0.18 → 0.14 normal (22.2 %), 0.023 → 0.018 shear (21.7 %)
    assert (1 - PAPER_001.factor(1000)) / drop > 0.6  # "decreased rapidly in the first 1000 cycles"
    assert PAPER_001.factor(7500) - PAPER_001.factor(10_000) < 0.001  # "relatively stable after about 7500"
    assert PAPER_001.factor(0) == 1.0


def quad_readings(fz: np.ndarray, start_seq: int = 0) -> list[Reading]:
    relative = QuadModel().forward(np.stack([np.zeros_like(fz), np.zeros_like(fz), fz], axis=1))
    return [Reading(QUAD, (start_seq + k) % 65536, (start_seq + k) * 1000, 0.0, 0, 0, NOMINAL_C0_PF * (1 + r), False, False)
            for k, r in enumerate(relative)]


def test_a_fatigued_quad_reads_its_true_force():
    cycles = 3000
    reconstructor = Reconstructor(tare_frames=10, level="table")
    reconstructor.load_cycles = lambda info, cid: [cycles]
    reconstructor.process_many(quad_readings(np.zeros(10)))
    model = QuadModel()
    true_fz = 3.0
    # The fatigued sensor: its ΔC/C0 is the fresh one's times s(n).
    fresh = model.forward(np.array([[0.0, 0.0, true_fz]]))[0]
    tired = NOMINAL_C0_PF * (1 + fresh * PAPER_001.factor(cycles))
    frame = reconstructor.process(Reading(QUAD, 10, 10_000, 0.0, 0, 0, tired, False, False))[0]
    assert frame.forces_N[2] == pytest.approx(true_fz, abs=1e-6)
    uncompensated = Reconstructor(tare_frames=10, level="table")
    uncompensated.process_many(quad_readings(np.zeros(10)))
    low = uncompensated.process(Reading(QUAD, 10, 10_000, 0.0, 0, 0, tired, False, False))[0].forces_N[2]
    assert low < 0.9 * true_fz  # a sensor 3000 cycles old reads ~18 % low without compensation
    assert reconstructor.fatigue(1)["cycles_max"] == cycles


def test_counts_survive_a_restart_and_a_new_calibration_starts_from_zero(tmp_path):
    registry = tmp_path / "registry.sqlite3"
    board = {"board": "hand-left", "serial": "B-1"}
    presses = np.tile(np.r_[np.zeros(20), np.full(20, 3.0)], 25)  # 25 presses of 3 N
    book = CalibrationBook(registry)
    first = Reconstructor(tare_frames=10, level="table")
    first.load_cycles = lambda info, cid: book.load_cycles(board, info, cid)
    first.process_many(quad_readings(np.r_[np.zeros(10), presses, np.zeros(5)]))
    assert first.fatigue(1)["cycles_max"] == 25
    book.save_cycles(board, list(first.cycle_counts().values()))

    second = Reconstructor(tare_frames=10, level="table")  # the service restarted
    second.load_cycles = lambda info, cid: CalibrationBook(registry).load_cycles(board, info, cid)
    second.process_many(quad_readings(np.zeros(10)))
    assert second.fatigue(1)["cycles_max"] == 25
    factor = second.fatigue(1)["sensitivity_factor"]
    assert factor == pytest.approx(float(PAPER_001.factor(25)))
    second.set_calibration(QUAD, {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]})
    assert second.fatigue(1)["cycles_max"] == 0  # counts belong to a calibration


def test_a_fatigue_factor_follows_the_cycles_counted_within_one_large_batch():
    """An offline replay feeds megabyte reads (tens of thousands of quad
    frames): with one fatigue factor per call, a quad cycled 2 000 times read
    its final 3 N hold as 2.95 N. Calls are sliced, so the factor lags by at
    most a slice's cycles: the same forces as read by read, within 0.5 %."""
    cycles = 2000
    model = QuadModel()
    fz = np.concatenate([np.zeros(10), np.tile(3.0 * np.sin(np.pi * np.arange(40) / 40) ** 2, cycles), np.full(300, 3.0)])
    counted = np.concatenate([np.zeros(10), np.repeat(np.arange(cycles), 40), np.full(300, cycles)])
    relative = model.forward(np.stack([np.zeros_like(fz), np.zeros_like(fz), fz], axis=1))
    tired = NOMINAL_C0_PF * (1 + relative * PAPER_001.factor(counted)[:, None])
    readings = [Reading(QUAD, k % 65536, k * 1000, 0.0, 0, 0, c, False, False) for k, c in enumerate(tired)]
    whole, by_read = Reconstructor(tare_frames=10, level="table"), Reconstructor(tare_frames=10, level="table")
    at_once = whole.process_many(readings)
    one_by_one = [f for k in range(0, len(readings), 2) for f in by_read.process_many(readings[k:k + 2])]
    hold = slice(-250, None)
    assert np.mean([f.forces_N[2] for f in at_once[hold]]) == pytest.approx(3.0, abs=0.01)
    np.testing.assert_allclose([f.forces_N[2] for f in at_once[hold]], [f.forces_N[2] for f in one_by_one[hold]], rtol=5e-3)


def test_a_simulated_board_neither_takes_nor_keeps_load_cycles(tmp_path):
    """A sim:// sensor is new every run: the counts of earlier runs (1 195 after a few demos) made the demo quad
    read ever higher, and each run added its own to the user's registry."""
    import sqlite3
    import time

    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from service.calibration.registry import Registry
    from service.live_service import TactileService
    from service.physics.paper_data import BUILTIN_QUAD_ID

    path = tmp_path / "registry.sqlite3"
    key = "board:tactile-sim-8x8-quad/sensor:1"
    with Registry(path) as registry:
        registry.save_cycles([(key, BUILTIN_QUAD_ID, [3000])])
    service = TactileService("sim://?sensors=grid,quad&scene=press", calibrations=CalibrationBook(path))
    with TestClient(create_app(service), base_url="http://localhost"):
        deadline = time.monotonic() + 10
        while service.pipeline.reconstructor.fatigue(1) is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert service.pipeline.reconstructor.fatigue(1)["cycles_max"] == 0
    rows = sqlite3.connect(path).execute("SELECT sensor_key, counts FROM cycles").fetchall()
    assert rows == [(key, "[3000]")]

"""Another sensor at an address (its INFO names another serial): its own
calibration, tare and load-cycle count, never those of the sensor before it
(reconstruct/identity.py); told in /health and /sensors; replayed as live.
Quads, whose built-in calibration compensates fatigue: a count inherited
is a force off by the fatigue factor (0.82 at 3000 cycles)."""
import time

import numpy as np
import orjson
import pytest

from service.calibration import registry as reg
from service.calibration.book import CalibrationBook, book_from_options
from service.physics.paper_data import BUILTIN_QUAD_ID
from service.physics.quad_model import NOMINAL_C0_PF, QuadModel
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.readings import Reading, SensorInfo
from service.reconstruct import Reconstructor
from service.reconstruct.fatigue import JUDGE_EVERY, PAPER_001

A, B = SensorInfo(1, "quad", 2, 2, "Q-A"), SensorInfo(1, "quad", 2, 2, "Q-B")
STIFF = {"normal_fit": [-0.0009, 0.0686], "shear_fit": [0.0077, 0.0004]}  # A's upload: twice the paper's normal slope
PRESS = np.r_[np.full(8 * JUDGE_EVERY, 3.0), np.zeros(8 * JUDGE_EVERY)]  # one load cycle of 3 N


def electrodes(fz: np.ndarray, model: QuadModel, factor: float = 1.0) -> np.ndarray:
    """(n, 4) pF of a quad whose response is ``model``'s, weakened by ``factor`` (fatigue), under Fz."""
    return NOMINAL_C0_PF * (1 + factor * model.forward(np.stack([0 * fz, 0 * fz, fz], axis=1)))


def readings(info: SensorInfo, fz: np.ndarray, model: QuadModel = QuadModel(), factor: float = 1.0) -> list[Reading]:
    return [Reading(info, k, 1000 * k, 0.0, 0, 0, c, False, False) for k, c in enumerate(electrodes(fz, model, factor))]


def test_the_sensor_plugged_in_gets_its_own_calibration_and_count_and_the_first_gets_its_own_back():
    """Q-A (3000 cycles, its upload) pressed 5 times; Q-B (new, none stored)
    in its place; Q-A again. Q-B was read with Q-A's upload: a true 3 N read
    1.5 N. Forces against the models' truth."""
    stiff = QuadModel.from_fits(STIFF["normal_fit"], STIFF["shear_fit"])
    states = Reconstructor(tare_frames=10, level="table")
    states.load_cycles = lambda info, cid: {"Q-A": [3000]}.get(info.serial)  # what the registry keeps
    states.process_many(readings(A, np.zeros(10)))
    upload = states.set_calibration(A, STIFF)["id"]
    states.process_many(readings(A, np.tile(PRESS, 5), stiff, PAPER_001.factor(3000)))
    assert states.fatigue(1)["cycles_max"] == 3005

    states.process_many(readings(B, np.zeros(10)))
    frame = states.process(readings(SensorInfo(1, "quad", 2, 2, "Q-B"), np.array([3.0]))[0])[0]  # described again
    assert frame.calibration == BUILTIN_QUAD_ID and frame.forces_N[2] == pytest.approx(3.0, abs=1e-6)
    assert states.replaced(1) == {"count": 1, "from": "serial 'Q-A'", "to": "serial 'Q-B'"}  # the same again is no other

    states.process_many(readings(A, np.zeros(10)))
    assert states.calibration(1).id == upload and states.fatigue(1)["cycles_max"] == 3005  # not the registry's 3000
    frame = states.process(readings(A, np.array([3.0]), stiff, PAPER_001.factor(3005))[0])[0]
    assert frame.forces_N[2] == pytest.approx(3.0, abs=1e-6)
    assert states.replaced(1) == {"count": 2, "from": "serial 'Q-B'", "to": "serial 'Q-A'"}

    own = states.set_calibration(B, {**STIFF, "normal_fit": [-0.0009, 0.05]})["id"]  # Q-B's, while Q-A streams
    assert states.calibration(1).id == upload  # Q-A keeps its own
    states.process_many(readings(B, np.zeros(10)))
    assert states.calibration(1).id == own


def board_bytes(serial: str, fz: np.ndarray, factor: float) -> bytes:
    """A board restarting with quad 1 of ``serial``: its INFO, then scans from seq 0."""
    info = orjson.dumps({"board": "tmux", "serial": "TMX-1", "sensors": [{"id": 1, "kind": "quad", "serial": serial}]})
    counts = np.round(electrodes(fz, QuadModel(), factor) * 1e6).astype("<u4")
    return encode_frame(FrameType.INFO, 255, 0, 0, info) + b"".join(
        encode_frame(FrameType.QUAD, 1, k, 1000 * (k + 1), c.tobytes()) for k, c in enumerate(counts))


def test_a_swap_of_sensors_on_one_calibration_replays_with_each_ones_count(tmp_path):
    """Q-A (3000 cycles in the registry) and Q-B (new) both on the built-in
    calibration: the recording kept one count for the address, so Q-B's
    replay started at Q-A's 3000 and read a true 3 N as 3.89 N (live: 3.0 N)."""
    from service.record.recorder import Recorder

    registry = tmp_path / "registry.sqlite3"
    with reg.Registry(registry) as r:
        r.save_cycles([("sensor:Q-A", BUILTIN_QUAD_ID, [3000])])
    settle = np.r_[np.zeros(150), np.full(40, 3.0), np.zeros(40)]
    raw = board_bytes("Q-A", settle, PAPER_001.factor(3000)) + board_bytes("Q-B", settle, 1.0)
    live = Pipeline(Reconstructor(), calibrations=CalibrationBook(registry))
    recorder = Recorder(tmp_path / "swap.mcap")
    recorder.attach(live)
    frames = [f for k in range(0, len(raw), 2048) for f in live.feed(raw[k:k + 2048], 1000.0 + k * 1e-6)]
    assert recorder.stop()["error"] is None
    pressed = [f.forces_N[2] for f in frames if f.capacitance_pF[0] > electrodes(np.array([2.9]), QuadModel())[0, 0]]
    np.testing.assert_allclose(pressed[-30:], 3.0, atol=1e-3)  # Q-B's own count (0): its true 3 N
    replayed = Pipeline(Reconstructor(), calibrations=book_from_options(str(registry), None,
                                                                        recording=tmp_path / "swap.mcap"))
    again = [f for k in range(0, len(raw), 2048) for f in replayed.feed(raw[k:k + 2048], 1000.0 + k * 1e-6)]
    assert len(again) == len(frames)
    assert all(np.array_equal(a.forces_N, b.forces_N, equal_nan=True) for a, b in zip(again, frames))


def test_health_and_sensors_name_the_serial_and_the_change():
    from service.api.routes_sensors import sensors
    from service.health import health_report
    from service.live_service import TactileService

    service = TactileService("sim://")
    service.pipeline.feed(board_bytes("Q-A", np.zeros(150), 1.0), time.time())
    assert not any("another sensor" in p for p in health_report(service)["problems"])
    service.pipeline.feed(board_bytes("Q-B", np.zeros(150), 1.0), time.time())
    report = health_report(service)
    sensor = report["sensors"]["1"]
    assert sensor["serial"] == "Q-B" and sensor["replaced"] == {"count": 1, "from": "serial 'Q-A'", "to": "serial 'Q-B'"}
    assert any(p.startswith("sensor 1 is another sensor: serial 'Q-B' where serial 'Q-A' was") for p in report["problems"])
    listed = orjson.loads(sensors(service).body)["sensors"]
    assert [(s["id"], s["serial"]) for s in listed] == [(1, "Q-B")]


def test_two_sensors_swapped_between_addresses_each_keep_counting_their_own_cycles():
    """Q-A at 1 and Q-B at 2, pressed 5 times each, then swapped (scans
    interleaved, address 1 first): Q-B at 1 went on from the registry's stale
    200, its live counter parked as one that left and saved after the live
    one under the same key (the registry froze at 205 while it counted on)."""
    a1, b2 = SensorInfo(1, "quad", 2, 2, "Q-A"), SensorInfo(2, "quad", 2, 2, "Q-B")
    b1, a2 = SensorInfo(1, "quad", 2, 2, "Q-B"), SensorInfo(2, "quad", 2, 2, "Q-A")
    states = Reconstructor(tare_frames=10, level="table")
    states.load_cycles = lambda info, cid: {"Q-A": [100], "Q-B": [200]}.get(info.serial)
    for info in (a1, b2):
        states.process_many(readings(info, np.zeros(10)))
        states.process_many(readings(info, np.tile(PRESS, 5)))
    assert (states.fatigue(1)["cycles_max"], states.fatigue(2)["cycles_max"]) == (105, 205)
    swapped = [r for pair in zip(readings(b1, np.zeros(10)), readings(a2, np.zeros(10))) for r in pair]
    states.process_many(swapped)
    assert (states.fatigue(1)["cycles_max"], states.fatigue(2)["cycles_max"]) == (205, 105)
    states.process_many(readings(b1, np.tile(PRESS, 3)))
    kept = {info.serial: counts for info, _, counts in [*states.cycle_counts().values(),
                                                         *states.replacements.left_counts()]}
    assert kept == {"Q-B": [208], "Q-A": [105]}

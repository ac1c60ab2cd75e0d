"""A calibration activated in the registry by another process (`tactile
calibrations activate`, `tactile calibrate`) while `tactile serve` runs is
used within the poll period, as an upload is: the frames name it and their
forces follow it, /health shows it and when it was activated, a recording
records the change and its replay makes it at the same frame. One the sensor
cannot use is not applied, and /health says so. Before, the sensor kept the
calibration chosen when it was first seen until a restart, /health "ok"."""
import io
import logging
import time

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from firmware_sim.board import BoardConfig, capture
from firmware_sim.scenes import SCENES
from firmware_sim.sensors import SimGrid
from service.api.app import create_app
from service.calibration import registry as reg
from service.calibration.book import CalibrationBook, book_from_options
from service.health import health_report
from service.live_service import ACTIVE_POLL_S, TactileService
from service.replay import replay

from .test_record_tare import by_frame, recorded_forces

SOURCE = "sim://?scene=press&sensors=grid&rate=200"
KEY = "board:tactile-sim-8x8-quad/sensor:0"  # the simulator's serial-less board, sensor 0 (registry.sensor_identity)
PRESSED = 3 * 8 + 3  # row 4, col 4: the press scene's taxel
MARGIN_S = 1.5  # a frame's way through the loop, and the test's own polling


def stored(path, scale: float, note: str, shape: tuple[int, int] = (8, 8)) -> str:
    """A calibration of the simulator's sensor 0 whose sensitivities (and the
    gains they come with) are table 1's times ``scale``, stored inactive; its id."""
    document = reg.builtin_document(*shape)
    taxels = document["taxels"]
    taxels["gain"] = [scale * g for g in taxels["gain"]]
    taxels["sensitivity_pct_per_N"] = [scale * s for s in taxels["sensitivity_pct_per_N"]]
    document |= {"note": note, "created": "2026-11-24T00:00:00Z",
                 "sensor": {"key": KEY, "sensor_serial": None, "board_serial": None, "board": "tactile-sim-8x8-quad",
                            "sensor_id": 0}}
    with reg.Registry(path) as registry:
        return registry.add({k: v for k, v in document.items() if k != "id"})


def activate(path, cid: str) -> None:
    """As `tactile calibrations activate ID` does, from another process's connection."""
    with reg.Registry(path) as registry:
        registry.activate(cid)


def wait_until(condition, seconds: float) -> float | None:
    """Seconds until ``condition()`` held, None if it did not within ``seconds``."""
    start = time.monotonic()
    while time.monotonic() - start < seconds:
        if condition():
            return time.monotonic() - start
        time.sleep(0.02)
    return None


@pytest.fixture
def running(tmp_path):
    """(service, client, registry path, {name: id}, frames as published: [(sensor, seq, t_us, calibration, F27)]):
    a live simulated grid, recorded to run.mcap, on a registry where calibration A (table 1's sensitivities)
    is active."""
    path = tmp_path / "registry.sqlite3"
    ids = {"A": stored(path, 1.0, "A"), "B": stored(path, 0.8, "B"), "4x4": stored(path, 1.0, "4x4", (4, 4))}
    activate(path, ids["A"])
    service = TactileService(SOURCE, calibrations=CalibrationBook(path), recordings_dir=tmp_path)
    service.start_recording("run.mcap")  # from the first byte: a recording begun mid-stream replays within ~1 mN only
    frames = []
    service.pipeline.listeners.append(lambda batch: frames.extend(
        (f.sensor.id, f.seq, f.t_us, f.calibration, float(f.forces_N[PRESSED])) for f in batch))
    with TestClient(create_app(service), base_url="http://localhost") as client:
        assert wait_until(lambda: frames and frames[-1][3] == ids["A"], 10) is not None
        yield service, client, path, ids, frames


SIM_GRID = SimGrid(0)


def truth_27(t_us: int) -> float:
    """The press scene's force on the pressed taxel at board time ``t_us`` (the simulator's clock is exact)."""
    return float(SCENES["press"](SIM_GRID, t_us * 1e-6)[PRESSED])


def test_an_activation_by_another_process_is_used_within_the_poll_period(running, caplog):
    service, client, path, ids, frames = running
    assert wait_until(lambda: sum(truth_27(f[2]) > 2.0 for f in frames if f[3] == ids["A"]) > 100, 10) is not None
    with caplog.at_level(logging.INFO, logger="service.board"):
        activate(path, ids["B"])
        took = wait_until(lambda: frames[-1][3] == ids["B"], ACTIVE_POLL_S + MARGIN_S)
        assert took is not None, f"still {frames[-1][3]} after {ACTIVE_POLL_S + MARGIN_S} s"
        assert wait_until(lambda: sum(truth_27(f[2]) > 2.0 for f in frames if f[3] == ids["B"]) > 100, 10) is not None
    service.stop_recording()
    print(f"\nB in use {took:.2f} s after its activation (poll period {ACTIVE_POLL_S} s)")
    assert f"sensor tactile-sim-8x8-quad/0: calibration {ids['B']} in place of {ids['A']}" in caplog.text

    calibration = client.get("/health").json()["sensors"]["0"]["calibration"]
    with reg.Registry(path) as registry:
        assert calibration["activated"] == registry.activated_at(KEY) is not None
    assert (calibration["id"], calibration["builtin"], calibration["not_applied"]) == (ids["B"], False, None)

    # Forces follow the documents: F = response⁻¹(ΔC/C0) scales as 1/sensitivity, so B reads
    # s_A/s_B of A's force on the same load (the load: the simulator's truth at each frame's time).
    with reg.Registry(path) as registry:
        s_a, s_b = (registry.get(ids[name])["taxels"]["sensitivity_pct_per_N"][PRESSED] for name in "AB")
    ratio = {name: np.median([f[4] / truth_27(f[2]) for f in frames if f[3] == ids[name] and truth_27(f[2]) > 2.0])
             for name in "AB"}
    print(f"F/truth on taxel {PRESSED} above 2 N: A {ratio['A']:.4f}, B {ratio['B']:.4f}, expected B/A {s_a / s_b:.4f}")
    assert ratio["A"] == pytest.approx(1.0, abs=0.03)  # A is the simulator's own table 1
    assert ratio["B"] / ratio["A"] == pytest.approx(s_a / s_b, rel=0.01)

    # The recording holds the switch where it took effect: its replay names, frame by frame, the calibration live used.
    recorded = by_frame(recorded_forces(service.recordings_dir / "run.mcap"))
    live = {(sid, seq, t_us): cid for sid, seq, t_us, cid, _ in frames}
    assert {d["calibration"] for d in recorded.values()} == {ids["A"], ids["B"]}
    assert [key for key, d in recorded.items() if d["calibration"] != live[key]] == []
    out = io.BytesIO()  # as `tactile replay run.mcap --registry …` does, B active there now
    mcap = service.recordings_dir / "run.mcap"
    replay(mcap, out, calibrations=book_from_options(str(path), None, recording=mcap))
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert again.keys() == recorded.keys()
    assert [key for key in recorded if again[key] != recorded[key]] == []


def test_a_calibration_the_sensor_cannot_use_is_not_applied_and_health_says_so(running):
    service, client, path, ids, frames = running
    activate(path, ids["4x4"])  # filed under this sensor's key, but made for a 4x4 grid
    problem = f"sensor 0: calibration {ids['4x4']}, activated in the registry, cannot be used for it ("

    def said() -> bool:
        return any(p.startswith(problem) for p in client.get("/health").json()["problems"])

    assert wait_until(said, ACTIVE_POLL_S + MARGIN_S) is not None
    health = client.get("/health").json()
    line, = [p for p in health["problems"] if p.startswith(problem)]
    assert line.endswith(f"not applied, it keeps calibration {ids['A']}") and "4x4" in line
    assert health["status"] == "degraded"
    calibration = health["sensors"]["0"]["calibration"]
    assert (calibration["id"], calibration["not_applied"]["id"]) == (ids["A"], ids["4x4"])
    shown = len(frames)
    assert wait_until(lambda: len(frames) > shown + 100, 5) is not None
    assert {f[3] for f in frames[shown:]} == {ids["A"]}  # the old one stays, the data goes on

    activate(path, ids["A"])  # the one in use again: nothing to say
    assert wait_until(lambda: not said(), ACTIVE_POLL_S + MARGIN_S) is not None
    activate(path, ids["4x4"])  # and the unusable one once more: said again
    assert wait_until(said, ACTIVE_POLL_S + MARGIN_S) is not None

    activate(path, ids["B"])  # a usable one next: applied, and the line goes
    assert wait_until(lambda: frames[-1][3] == ids["B"], ACTIVE_POLL_S + MARGIN_S) is not None
    health = client.get("/health").json()
    assert not any("activated in the registry" in p for p in health["problems"])
    assert health["sensors"]["0"]["calibration"]["not_applied"] is None


def test_a_sensor_on_the_built_in_whose_activated_calibration_cannot_be_used_says_so(tmp_path):
    """No calibration active at the start (table 1), then one for another shape: /health's line of a sensor
    whose own calibration could not be used names it; the data goes on with table 1."""
    path = tmp_path / "registry.sqlite3"
    small = stored(path, 1.0, "4x4", (4, 4))
    service = TactileService(SOURCE, calibrations=CalibrationBook(path), recordings_dir=tmp_path)
    with TestClient(create_app(service), base_url="http://localhost") as client:
        assert wait_until(lambda: 0 in service.pipeline.latest, 10) is not None
        assert service.pipeline.latest[0].calibration == "builtin-table1"
        activate(path, small)
        line = f"sensor 0 uses the built-in calibration: its own could not be used (ValueError: calibration {small}"
        assert wait_until(lambda: any(p.startswith(line) for p in client.get("/health").json()["problems"]),
                          ACTIVE_POLL_S + MARGIN_S) is not None
        assert service.pipeline.latest[0].calibration == "builtin-table1"


def test_a_replay_never_follows_the_registry(tmp_path):
    """A recording served through the live path keeps its own calibrations whatever is activated meanwhile."""
    path = tmp_path / "registry.sqlite3"
    a, b = stored(path, 1.0, "A"), stored(path, 0.8, "B")
    activate(path, a)
    live = TactileService(SOURCE, calibrations=CalibrationBook(path), recordings_dir=tmp_path)
    with TestClient(create_app(live), base_url="http://localhost"):
        assert wait_until(lambda: 0 in live.pipeline.latest, 10) is not None
        live.start_recording("run.mcap")
        time.sleep(1.0)
        live.stop_recording()
    mcap = tmp_path / "run.mcap"
    served = TactileService(f"replay://{mcap}", calibrations=book_from_options(str(path), None, recording=mcap))
    assert not served.primary.follows_registry
    with TestClient(create_app(served), base_url="http://localhost"):
        assert wait_until(lambda: 0 in served.pipeline.latest, 10) is not None
        activate(path, b)
        time.sleep(ACTIVE_POLL_S + MARGIN_S)
        served.primary.follow_registry()  # and asked directly: nothing
        assert served.pipeline.reconstructor.calibration(0).id == a


def test_only_sensors_on_the_registry_follow_it(tmp_path):
    """A sensor pinned with --calibration keeps its pin, and a replay's book follows nothing."""
    from service.readings import SensorInfo

    path = tmp_path / "registry.sqlite3"
    a, b = stored(path, 1.0, "A"), stored(path, 0.8, "B")
    activate(path, b)
    board, info = {"board": "tactile-sim-8x8-quad"}, SensorInfo(0, "grid", 8, 8, board="tactile-sim-8x8-quad")
    (sensor, active), = CalibrationBook(path).registry_active(board, [info]).values()
    assert (sensor["key"], active) == (KEY, b)
    with reg.Registry(path) as registry:
        assert CalibrationBook(path, [registry.get(a)]).registry_active(board, [info]) == {}
    assert CalibrationBook(path, replaying=True).registry_active(board, [info]) == {}


def test_an_upload_to_a_sensor_whose_own_calibration_could_not_be_used_ends_the_line(tmp_path):
    """The registry's active calibration is a 4x4 grid's, the sensor 8x8: the
    built-in is used, /health says why. A PUT of 64 sensitivities answered
    200 and its frames used it, yet the line stayed (the registry switch
    cleared it, the upload did not); now it goes, as the switch's does."""
    path = tmp_path / "registry.sqlite3"
    activate(path, stored(path, 1.0, "4x4", (4, 4)))
    service = TactileService(SOURCE, calibrations=CalibrationBook(path), recordings_dir=tmp_path)
    data, _ = capture(BoardConfig(sensors=[SimGrid(0)], scene="idle"), 0.3)
    service.pipeline.feed(data[:len(data) // 2], 1000.0)
    line = "sensor 0 uses the built-in calibration: its own could not be used (ValueError: rows, cols: calibration "
    assert [p for p in health_report(service)["problems"] if p.startswith(line)] != []
    client = TestClient(create_app(service), base_url="http://localhost")  # no lifespan: the frames are fed here
    answer = client.put("/sensors/0/calibration", json={"sensitivity_pct_per_N": [1.25] * 64})
    assert answer.status_code == 200
    service.pipeline.feed(data[len(data) // 2:], 1000.3)
    assert service.pipeline.latest[0].calibration == answer.json()["id"]
    health = health_report(service)
    assert [p for p in health["problems"] if "built-in calibration" in p] == []
    assert health["sensors"]["0"]["calibration"]["problem"] is None

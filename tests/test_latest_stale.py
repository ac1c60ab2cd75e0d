"""A sensor gone quiet still has a latest frame: GET .../latest and .../contact
(and the Python client's latest()/contact()) say it is no longer current, by
/health's rule, and how old it is."""
import time

from fastapi.testclient import TestClient

from firmware_sim.board import BoardConfig, capture
from service.api.app import create_app
from service.client import TactileClient
from service.live_service import TactileService
from tests.conftest import live_server

THRESHOLD_S = 0.5  # max(0.5 s, 20 periods of the simulator's 1 kHz scan), docs/api.md


def fed_service(age_s: float) -> TactileService:
    """A service (not started: nothing else feeds it) whose grid 0 and quad 1
    last read ``age_s`` ago, past their tare."""
    service = TactileService("sim://")
    data, _ = capture(BoardConfig(scene="press"), 0.6)
    service.pipeline.feed(data, time.time() - age_s)
    assert all("taring" not in service.pipeline.latest[sid].flags for sid in (0, 1))
    return service


def test_the_latest_frame_is_flagged_sensor_stale_past_the_health_threshold_and_not_before():
    service = fed_service(0.25)
    client = TestClient(create_app(service), base_url="http://localhost")  # no lifespan: the service stays unstarted
    for path in ("/sensors/0/latest", "/sensors/1/latest"):
        reply = client.get(path)
        assert float(reply.headers["X-Frame-Age-S"]) < THRESHOLD_S
        assert "sensor_stale" not in reply.json()["flags"]
    assert client.get("/sensors/0/contact").json()["stale"] is False
    time.sleep(0.45)  # 0.7 s old now: past the threshold
    assert client.get("/health").json()["sensors"]["0"]["stale"] is True
    for path in ("/sensors/0/latest", "/sensors/1/latest"):
        reply = client.get(path)
        assert float(reply.headers["X-Frame-Age-S"]) > THRESHOLD_S
        frame = reply.json()
        assert frame["flags"].count("sensor_stale") == 1
        assert frame["flags"][:-1] == service.pipeline.latest[frame["header"]["sensor_id"]].flags
    assert client.get("/sensors/0/contact").json()["stale"] is True
    # The frames themselves, which the live stream sent, are not changed.
    assert not any("sensor_stale" in f.flags for f in service.pipeline.latest.values())


def test_the_client_gives_the_age_and_the_flag():
    service = fed_service(2.0)
    with live_server(service, 2, lifespan="off") as server:
        client = TactileClient(f"http://127.0.0.1:{server.config.port}")
        frame = client.latest(1)
        expected = time.time() - frame["header"]["stamp"]  # its read was received 2 s ago
        assert abs(frame["header"]["age_s"] - expected) < 0.05 and frame["header"]["age_s"] > 1.9
        assert "sensor_stale" in frame["flags"] and frame["force_N"][2] is not None  # old, still a force
        summary = client.contact(0)
        assert summary["stale"] is True and 1.9 < summary["age_s"] < expected + 0.05


def test_a_gateway_board_s_frame_is_stale_by_the_gateway_s_rule():
    from service.health import frame_stale
    from service.history import Histories
    from service.remote_board import LOST_AFTER_S, RemoteBoard

    service = fed_service(0.0)
    frame = service.pipeline.latest[1]
    board = RemoteBoard("left", Histories())
    now = frame.t_host + 1.0
    board.on_alive(True, now)
    board.receive([frame], now)
    assert frame_stale(board, frame, frame.t_host + 1.0) is False  # 1 s: stale on a board, not yet on a gateway
    board.on_alive(True, frame.t_host + LOST_AFTER_S + 0.5)
    assert frame_stale(board, frame, frame.t_host + LOST_AFTER_S + 0.5) is True

"""The API in-process with TestClient, reading the built-in simulator."""
import time

import orjson
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.runtime import TactileService


@pytest.fixture(scope="module")
def client():
    service = TactileService("sim://?scene=press&rate=1000")
    with TestClient(create_app(service)) as client:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(service.pipeline.latest) < 2:
            time.sleep(0.01)
        yield client


def test_health_reports_link_rates_and_counters(client):
    time.sleep(1.1)  # one full rate window
    body = client.get("/health").json()
    assert body["link"]["up"] is True and body["link"]["source"].startswith("sim://")
    assert body["stream"]["crc_errors"] == 0
    for sid in ("0", "1"):
        assert 800 <= body["sensors"][sid]["rate_hz"] <= 1200
        assert body["sensors"][sid]["frames"] > 500


def test_sensors_lists_what_the_board_announced(client):
    body = client.get("/sensors").json()
    assert body["board"]["board"] == "tactile-sim-8x8-quad"
    assert [(s["id"], s["kind"]) for s in body["sensors"]] == [(0, "grid"), (1, "quad")]


def test_latest_grid_and_quad(client):
    grid = client.get("/sensors/0/latest").json()
    assert grid["kind"] == "grid" and len(grid["taxels_N"]) == 64 and (grid["rows"], grid["cols"]) == (8, 8)
    assert len(grid["capacitance_pF"]) == 64 and grid["level"] == "full"
    assert set(grid["contact"]) == {"total_N", "cop_x_mm", "cop_y_mm", "area_mm2", "contacts"}
    quad = client.get("/sensors/1/latest").json()
    assert len(quad["fxyz_N"]) == 3 and "t_us" in quad and "seq" in quad


def test_unknown_sensor_is_404_naming_known_ids(client):
    response = client.get("/sensors/9/latest")
    assert response.status_code == 404
    assert response.json()["detail"] == "unknown sensor id 9; known: 0, 1"
    assert client.get("/sensors/abc/latest").status_code == 422
    assert client.post("/sensors/9/tare").status_code == 404


def test_tare_restarts_the_baseline(client):
    assert client.post("/sensors/0/tare").json() == {"tared": [0], "frames": 100}
    assert client.post("/tare").json()["tared"] == [0, 1]


def test_websocket_streams_frames_as_json(client):
    with client.websocket_connect("/ws?sensors=1") as ws:
        message = orjson.loads(ws.receive_text())
    assert message["type"] == "frames"
    assert {f["sensor"] for f in message["frames"]} == {1}
    assert all(len(f["fxyz_N"]) == 3 for f in message["frames"])


def test_websocket_decimates_on_request(client):
    with client.websocket_connect("/ws?sensors=0&max_rate=20") as ws:
        t = []
        while len(t) < 6:
            t += [f["t_host"] for f in orjson.loads(ws.receive_text())["frames"]]
    gaps = [b - a for a, b in zip(t, t[1:])]
    assert min(gaps) >= 0.045  # 20 Hz, minus scheduling slack


@pytest.mark.parametrize("query, message", [("max_rate=-1", "max_rate='-1'"), ("sensors=a,b", "sensors='a,b'")])
def test_websocket_rejects_bad_parameters(client, query, message):
    with client.websocket_connect(f"/ws?{query}") as ws:
        reply = orjson.loads(ws.receive_text())
    assert reply["type"] == "error" and message in reply["detail"]


def test_dashboard_is_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "/static/app.js" in page.text
    assert client.get("/static/app.js").status_code == 200

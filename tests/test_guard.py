"""What a web page, a rebinding DNS name or an unauthenticated client can do: nothing."""
import time

import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.live_service import TactileService


@pytest.fixture(scope="module")
def client():
    with TestClient(create_app(TactileService("sim://?scene=idle")), base_url="http://localhost:8000") as client:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and not client.get("/sensors").json()["sensors"]:
            time.sleep(0.02)
        yield client


def test_a_form_posted_by_another_site_changes_nothing(client):
    form = client.post("/tare", data={"x": "1"}, headers={"Origin": "http://evil.example"})
    assert form.status_code == 403 and "http://evil.example" in form.json()["detail"]
    plain = client.post("/tare", content=b"x=1", headers={"Content-Type": "text/plain"})  # no Origin (not a browser)
    assert plain.status_code == 415 and "application/json" in plain.json()["detail"]
    assert client.post("/tare", headers={"Origin": "http://localhost:8000"}).status_code == 200  # the dashboard itself


def test_a_rebound_dns_name_is_not_this_service(client):
    rebound = client.get("/health", headers={"Host": "attacker.example:8000"})
    assert rebound.status_code == 403 and "attacker.example" in rebound.json()["detail"]
    for host in ("127.0.0.1:8000", "[::1]:8000", "localhost", "192.168.1.20:8000"):
        assert client.get("/health", headers={"Host": host}).status_code == 200, host


def test_a_websocket_from_another_origin_is_refused(client):
    from starlette.websockets import WebSocketDisconnect

    with pytest.raises(WebSocketDisconnect) as refused:
        with client.websocket_connect("ws://localhost/ws", headers={"Origin": "http://evil.example"}) as ws:
            ws.receive_text()
    assert refused.value.code == 1008
    with client.websocket_connect("ws://localhost/ws?sensors=0", headers={"Origin": "http://localhost"}) as ws:
        assert "frames" in ws.receive_text()


def test_a_large_body_is_refused_before_it_is_read_or_parsed(client):
    huge = b'{"sensitivity_pct_per_N": [' + b"1.0," * 400_000 + b"1.0]}"
    response = client.put("/sensors/0/calibration", content=huge, headers={"Content-Type": "application/json"})
    assert response.status_code == 413 and "1048576" in response.json()["detail"]


def test_non_finite_json_is_a_422(client):
    for text in (b"NaN", b'{"sensitivity_pct_per_N": [NaN]}', b'{"normal_fit": [Infinity, 1]}'):
        response = client.put("/sensors/0/calibration", content=text, headers={"Content-Type": "application/json"})
        assert response.status_code == 422 and "not JSON" in response.json()["detail"], text


def test_the_token_is_checked_before_the_body_and_any_header_is_a_401():
    service = TactileService("sim://?scene=idle")
    with TestClient(create_app(service, token="s3cret"), base_url="http://localhost") as client:
        big = client.put("/sensors/0/calibration", content=b"x" * (2 << 20), headers={"Content-Type": "application/json"})
        assert big.status_code == 401  # not 413: nothing was read
        for header in ("Bearer é", "Basic abc", "Bearer", "bearer s3cret"):
            response = client.post("/tare", headers={"Authorization": header.encode("utf-8")})
            assert response.status_code == 401, header
        assert client.post("/tare", headers={"Authorization": "Bearer s3cret"}).status_code in (200, 409)


def test_history_reads_beyond_the_cap_are_told_to_retry(client):
    gate = client.app.state.heavy_reads
    held = [gate.acquire(blocking=False) for _ in range(2)]  # two long reads in flight
    try:
        busy = client.get("/sensors/0/history?seconds=4.5&max_points=5000")
        assert busy.status_code == 429 and busy.headers["retry-after"] == "1"
    finally:
        for taken in held:
            if taken:
                gate.release()
    frames = client.get("/sensors/0/history?seconds=1&max_points=250").json()
    assert 1 <= len(frames) <= 250 and all(f["header"]["sensor_id"] == 0 for f in frames)
    seqs = [f["header"]["seq"] for f in frames]
    assert seqs == sorted(seqs)


def test_a_subscription_to_sensors_the_board_has_not_announced_is_told_so(client):
    with client.websocket_connect("ws://localhost/ws?sensors=0,99") as ws:
        notice = ws.receive_json()
        assert notice == {"type": "notice", "detail": "sensors 99 are not known (yet); known: 0, 1"}
        assert ws.receive_json()["type"] == "frames"  # sensor 0 streams all the same


def test_a_calibration_upload_is_checked_physically_and_a_linear_one_works(client):
    absurd = client.put("/sensors/1/calibration", json={"normal_fit": [-1e300, 0.0343], "shear_fit": [0.0077, 0.0004]})
    assert absurd.status_code == 422 and "normal_fit" in absurd.json()["detail"]
    linear = client.put("/sensors/1/calibration", json={"normal_fit": [0.0, 0.0343], "shear_fit": [0.0077, 0.0004]})
    assert linear.status_code == 200
    seq = client.get("/sensors/1/latest").json()["header"]["seq"]
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and client.get("/sensors/1/latest").json()["header"]["seq"] < seq + 50:
        time.sleep(0.02)
    latest = client.get("/sensors/1/latest").json()
    assert latest["header"]["seq"] >= seq + 50 and "reconstruction_error" not in latest["flags"]
    assert latest["wrench"]["force"]["z"] is not None
    assert not client.get("/health").json()["reconstruction"]["errors"]


def test_the_same_history_read_within_its_age_is_answered_once():
    from service.api.routes_sensors import RecentReads

    now = [100.0]
    recent = RecentReads(max_age_s=0.2, clock=lambda: now[0])
    recent.put(("a",), b"[1]")
    now[0] += 0.15
    assert recent.get(("a",)) == b"[1]" and recent.get(("b",)) is None
    now[0] += 0.1
    assert recent.get(("a",)) is None  # too old: encoded again
    recent.put(("b",), b"[2]")
    assert recent.get(("b",)) == b"[2]"


def test_heavy_reads_beyond_the_admitted_rate_are_refused_before_the_routes():
    from service.api.admission import Admission

    now = [0.0]
    admission = Admission(app=None, rate_per_s=10.0, burst=5.0, clock=lambda: now[0])
    assert [admission.admit() for _ in range(6)] == [True] * 5 + [False]  # the burst, then empty
    now[0] += 0.1  # one token back every 0.1 s
    assert admission.admit() and not admission.admit()

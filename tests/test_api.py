"""The API in-process with TestClient, reading the built-in simulator."""
import asyncio
import time

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.fanout.encoding import decode_binary
from service.fanout.hub import MERGE_FRAMES, QUEUE_MESSAGES, Hub, Outgoing, Subscriber
from service.live_service import TactileService


def wait_for_frames(service, sensors=2, seconds=5.0):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and (len(service.pipeline.latest) < sensors or
                                           any("taring" in f.flags for f in service.pipeline.latest.values())):
        time.sleep(0.01)


def get_history(client, url):
    """GET a history read once the service admits it: the module's tests share
    one service, whose history reads are admitted at 4 a second (admission.py;
    a refusal says "retry", as this does), so on a fast host one test's reads
    left the next none."""
    for _ in range(20):
        reply = client.get(url)
        if reply.status_code != 429:
            return reply
        time.sleep(0.25)
    return reply


@pytest.fixture(scope="module")
def client():
    service = TactileService("sim://?scene=press&rate=1000")
    with TestClient(create_app(service), base_url="http://localhost") as client:
        wait_for_frames(service)
        yield client


def test_health_reports_link_rates_counters_and_reconstruction(client):
    time.sleep(1.1)  # one full rate window
    body = client.get("/health").json()
    assert body["link"]["up"] is True and body["link"]["source"].startswith("sim://")
    assert body["stream"]["crc_errors"] == 0 and body["replay"] is False
    for sid in ("0", "1"):
        assert 800 <= body["sensors"][sid]["rate_hz"] <= 1200
        assert body["sensors"][sid]["frames"] > 500
    assert body["reconstruction"]["level"] == "full"
    assert body["reconstruction"]["crosstalk"]["0"]["mechanical_coupling_in_use"] < 0


def test_health_reports_latency_through_the_service(client):
    with client.websocket_connect("ws://localhost/ws?sensors=1&encoding=binary") as ws:
        for _ in range(20):
            ws.receive_bytes()
    latency = client.get("/health").json()["latency"]
    assert latency["published"]["samples"] > 100
    assert latency["sent_unbatched"]["samples"] >= 19
    for stage in ("published", "sent_unbatched"):
        summary = latency[stage]
        assert 0 <= summary["p50_ms"] <= summary["p99_ms"] <= summary["max_ms"] < 1000
    assert set(latency) == {"published", "sent_unbatched", "sent_batched"}


def test_clients_lists_each_subscription_with_its_own_latency(client):
    with client.websocket_connect("ws://localhost/ws?sensors=1&encoding=binary&fields=force") as ws:
        for _ in range(30):
            ws.receive_bytes()
        listed = client.get("/clients").json()["clients"]
    assert len(listed) == 1
    mine = listed[0]
    assert {k: mine[k] for k in ("sensors", "fields", "encoding", "max_rate_hz", "batch_ms", "dropped_frames")} == {
        "sensors": [1], "fields": ["force"], "encoding": "binary", "max_rate_hz": None, "batch_ms": None,
        "dropped_frames": 0}
    assert mine["latency"]["samples"] >= 29 and 0 <= mine["latency"]["p50_ms"] <= mine["latency"]["p99_ms"] < 1000
    assert client.get("/clients").json() == {"clients": []}


def test_sensors_lists_what_the_board_announced(client):
    body = client.get("/sensors").json()
    assert body["board"]["board"] == "tactile-sim-8x8-quad"
    assert [(s["id"], s["kind"], s["name"]) for s in body["sensors"]] == [(0, "grid", "grid0"), (1, "quad", "quad1")]


def test_latest_message_shape(client):
    grid = client.get("/sensors/0/latest").json()
    header = grid["header"]
    assert (header["sensor_id"], header["sensor_name"], header["kind"]) == (0, "grid0", "grid")
    assert isinstance(header["seq"], int) and isinstance(header["board_time_us"], int) and isinstance(header["stamp"], float)
    assert (grid["rows"], grid["cols"]) == (8, 8) and len(grid["force_N"]) == 64
    assert len(grid["raw"]["capacitance_pF"]) == 64
    assert set(grid["contact"]) == {"total_N", "cop_x_mm", "cop_y_mm", "area_mm2", "contacts"}
    assert isinstance(grid["flags"], list) and isinstance(grid["taxel_flags"], dict)
    quad = client.get("/sensors/1/latest").json()
    assert set(quad["wrench"]["force"]) == {"x", "y", "z"} and "force_N" not in quad
    response = client.get("/sensors/1/latest")  # how old the latest frame is, beside it: a quiet board still has one
    stamp = response.json()["header"]["stamp"]
    age = float(response.headers["X-Frame-Age-S"])
    assert 0.0 <= age <= time.time() - stamp + 0.002 and float(client.get("/sensors/0/contact").headers["X-Frame-Age-S"]) >= 0


def test_contact_and_history(client):
    assert set(client.get("/sensors/0/contact").json()) == {"total_N", "cop_x_mm", "cop_y_mm", "area_mm2", "contacts",
                                                            "stale"}
    assert client.get("/sensors/1/contact").status_code == 400
    history = get_history(client, "/sensors/0/history?seconds=0.5&max_points=50").json()
    assert 2 <= len(history) <= 50
    # The history keeps what the live frames carried: calibration id, σ and the scan stamp.
    kept = get_history(client, "/sensors/0/history?seconds=0.5&max_points=5&fields=force,sigma").json()
    assert {m["header"]["calibration"] for m in kept} == {"builtin-table1"}
    assert all(len(m["sigma_N"]) == 64 and all(s is None or s > 0 for s in m["sigma_N"]) for m in kept)
    assert all(m["header"]["scan_stamp"] <= m["header"]["stamp"] for m in kept)
    stamps = [m["header"]["stamp"] for m in history]
    assert stamps == sorted(stamps) and stamps[-1] - stamps[0] <= 0.5
    bad = get_history(client, "/sensors/0/history?seconds=50")
    assert bad.status_code == 422 and "seconds" in str(bad.json()["detail"])
    assert get_history(client, "/sensors/0/history?fields=force,nope").status_code == 422


def test_unknown_sensor_is_404_naming_known_ids(client):
    response = client.get("/sensors/9/latest")
    assert response.status_code == 404
    assert response.json()["detail"] == "unknown sensor id 9; known: 0, 1"
    assert client.get("/sensors/abc/latest").status_code == 422
    assert client.post("/sensors/9/tare").status_code == 404


def test_a_body_that_fails_validation_is_not_sent_back(client):
    """FastAPI's 422 repeated the whole input in each error (once per union
    member): a 15 KB upload came back as 52 KB. The answer names where and
    what, and a bad value only where it is short."""
    body = {"taxels": {"c0_pF": ["x"] * 2000}, "junk": "y" * 5000}
    answer = client.put("/sensors/0/calibration", json=body)
    assert answer.status_code == 422 and len(answer.content) < 2000
    detail = answer.json()["detail"]
    assert detail and all({"type", "loc", "msg"} <= set(error) for error in detail)
    assert {error["input"] for error in detail if "input" in error} <= {"<object with 2 keys>"}
    path = client.get("/sensors/abc/latest")
    assert path.status_code == 422 and path.json()["detail"][0]["loc"] == ["path", "sensor_id"]
    assert path.json()["detail"][0]["input"] == "abc"


def test_tare_restarts_the_baseline(client):
    assert client.post("/sensors/0/tare").json() == {"tared": [0], "frames": 100}
    assert client.post("/tare").json()["tared"] == [0, 1]


def test_calibration_upload_is_validated_and_applied(client):
    ok = client.put("/sensors/0/calibration", json={"sensitivity_pct_per_N": [1.25] * 64})
    assert ok.status_code == 200
    short = client.put("/sensors/0/calibration", json={"sensitivity_pct_per_N": [1.25] * 10})
    assert short.status_code == 422 and "expected 64 values" in short.json()["detail"]
    negative = client.put("/sensors/0/calibration", json={"sensitivity_pct_per_N": [1.25] * 63 + [-1.0]})
    assert negative.status_code == 422 and "sensitivity_pct_per_N[63]" in negative.json()["detail"]
    fits = {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]}
    measured = client.put("/sensors/1/calibration", json={**fits, "c0_pF": [2.2, 2.21, 2.19, 2.2]})
    assert measured.status_code == 200 and measured.json()["c0_pF"] == [2.2, 2.21, 2.19, 2.2]  # sets its tare window
    three = client.put("/sensors/1/calibration", json={**fits, "c0_pF": [2.2, 2.21, 2.19]})
    assert three.status_code == 422 and "c0_pF: expected 4 values" in three.json()["detail"]
    quad = client.put("/sensors/1/calibration", json=fits)
    assert quad.status_code == 200 and quad.json()["normal_usable_N"] == pytest.approx(17.15)
    assert "c0_pF" not in quad.json()  # none given: the document (and its id) as before
    wrong = client.put("/sensors/1/calibration", json={"normal_fit": [0.001, 0.0343], "shear_fit": [0.0077, 0.0004]})
    assert wrong.status_code == 422 and "normal_fit" in wrong.json()["detail"]
    assert client.put("/sensors/1/calibration", json={"normal_fit": "x"}).status_code == 422


def test_websocket_json_stream_with_fields(client):
    with client.websocket_connect("ws://localhost/ws?sensors=1&fields=force,raw") as ws:
        message = orjson.loads(ws.receive_text())
    assert message["type"] == "frames"
    frame = message["frames"][0]
    assert frame["header"]["sensor_id"] == 1 and "wrench" in frame and "raw" in frame and "flags" not in frame


def test_websocket_binary_stream(client):
    with client.websocket_connect("ws://localhost/ws?sensors=0&encoding=binary&fields=force,raw") as ws:
        records = decode_binary(ws.receive_bytes())
    assert records[0]["kind"] == "grid" and records[0]["force_N"].shape == (64,)
    assert records[0]["capacitance_pF"].shape == (64,) and np.all(records[0]["capacitance_pF"] > 5)


def test_websocket_decimates_and_batches_on_request(client):
    with client.websocket_connect("ws://localhost/ws?sensors=0&max_rate=20") as ws:
        t = []
        while len(t) < 6:
            t += [f["header"]["stamp"] for f in orjson.loads(ws.receive_text())["frames"]]
    # 20 Hz keeping its phase (hub.py): one frame per 50 ms slot, whatever the host's delays bunch together;
    # a late frame may be followed closely by the next slot's, so any three frames span more than a slot
    # (slots counted from the first frame missed a phase restarted after a pause on a loaded host).
    assert all(c - a > 0.05 - 1e-9 for a, c in zip(t, t[2:])) and (t[-1] - t[0]) / (len(t) - 1) >= 0.045
    with client.websocket_connect("ws://localhost/ws?sensors=0&batch_ms=100") as ws:
        sizes = [len(orjson.loads(ws.receive_text())["frames"]) for _ in range(3)]
    # ~100 frames of 1 kHz per batch (fewer on a loaded host), sent as messages of at most MERGE_FRAMES
    # (each is encoded in one go): the batch's first two messages are full, the third holds the rest
    assert sizes[:2] == [MERGE_FRAMES] * 2 and 0 < sizes[2] <= MERGE_FRAMES


@pytest.mark.parametrize(
    "query, message",
    [("max_rate=-1", "max_rate='-1'"), ("sensors=a,b", "sensors='a,b'"), ("fields=x", "fields='x'"),
     ("encoding=xml", "encoding='xml'"), ("batch_ms=0", "batch_ms='0'"),
     # A typo, a repeat or an empty value took the default, silently; ids no sensor can have got a notice only.
     ("max_rte=100", "unknown parameter 'max_rte'"), ("sensors=0&sensors=1", "sensors given 2 times"),
     ("fields=", "fields= is empty"), ("sensors=-1", "-1 is no sensor id"), ("sensors=left/999", "999 is no sensor id"),
     ("sensors=1_0", "sensors='1_0' must be")],
)
def test_websocket_rejects_bad_parameters(client, query, message):
    with client.websocket_connect(f"ws://localhost/ws?{query}") as ws:
        reply = orjson.loads(ws.receive_text())
    assert reply["type"] == "error" and message in reply["detail"]


def test_a_stream_client_past_the_limit_is_refused_and_the_others_keep_theirs(client, monkeypatch):
    from starlette.websockets import WebSocketDisconnect

    from service.api import routes_stream

    monkeypatch.setattr(routes_stream, "MAX_STREAM_CLIENTS", 2)
    with client.websocket_connect("ws://localhost/ws?sensors=1") as first, \
            client.websocket_connect("ws://localhost/ws?sensors=1") as second:
        assert orjson.loads(first.receive_text())["type"] == "frames"
        with client.websocket_connect("ws://localhost/ws?sensors=1") as third:
            reply = orjson.loads(third.receive_text())
            assert reply["type"] == "error" and "too many stream clients (2)" in reply["detail"]
            with pytest.raises(WebSocketDisconnect) as closed:
                third.receive_text()
            assert closed.value.code == 1013
        assert orjson.loads(second.receive_text())["type"] == "frames"


def test_a_client_with_the_token_is_let_in_past_the_limit_in_the_place_of_the_last_anonymous(monkeypatch):
    """Reads need no token, so 64 idle anonymous streams locked every
    controller out (1013 for as long as they stayed). With a token, a client
    presenting it takes the place of the anonymous client that came last;
    one without it is still refused, and the first anonymous keeps its stream."""
    from starlette.websockets import WebSocketDisconnect

    from service.api import routes_stream

    monkeypatch.setattr(routes_stream, "MAX_STREAM_CLIENTS", 2)
    service = TactileService("sim://?sensors=quad&rate=1000")
    with TestClient(create_app(service, token="s3cret"), base_url="http://localhost") as client:
        wait_for_frames(service)
        with client.websocket_connect("ws://localhost/ws?sensors=0") as first, \
                client.websocket_connect("ws://localhost/ws?sensors=0") as last:
            assert orjson.loads(last.receive_text())["type"] == "frames"
            with client.websocket_connect("ws://localhost/ws?sensors=0") as third:
                reply = orjson.loads(third.receive_text())
                assert reply["type"] == "error" and "a client with the service's token is always let in" in reply["detail"]
            with client.websocket_connect("ws://localhost/ws?sensors=0",
                                          headers={"Authorization": "Bearer wrong"}) as guessing:
                assert orjson.loads(guessing.receive_text())["type"] == "error"
            with client.websocket_connect("ws://localhost/ws?sensors=0",
                                          headers={"Authorization": "Bearer s3cret"}) as controller:
                assert orjson.loads(controller.receive_text())["type"] == "frames"
                while (message := orjson.loads(last.receive_text()))["type"] == "frames":
                    pass
                assert message["type"] == "error" and "make room for a client with the service's token" in message["detail"]
                with pytest.raises(WebSocketDisconnect) as closed:
                    last.receive_text()
                assert closed.value.code == 1013
                assert orjson.loads(first.receive_text())["type"] == "frames"
                assert len(service.hub.subscribers) == 2


def test_dashboard_is_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "/static/app.js" in page.text
    assert client.get("/static/app.js").status_code == 200


def test_a_stalled_client_loses_only_its_own_oldest_frames():
    from service.reconstruct import ForceFrame
    from service.readings import SensorInfo

    async def scenario():
        hub = Hub()
        stalled, healthy = Subscriber(), Subscriber()
        hub.add(stalled)
        hub.add(healthy)
        info = SensorInfo(1, "quad", 2, 2)
        received = []
        for seq in range(QUEUE_MESSAGES + 10):
            frame = ForceFrame(info, seq, seq, float(seq), np.zeros(3), np.ones(4), [], "full")
            hub.publish([frame])
            message, _, _ = await healthy.next_message()
            received.append(orjson.loads(message)["frames"][0]["header"]["seq"])
        first, notice, _ = await stalled.next_message()
        return received, orjson.loads(first), orjson.loads(notice), stalled.describe()

    received, first, notice, described = asyncio.run(scenario())
    assert received == list(range(QUEUE_MESSAGES + 10))
    assert notice == {"type": "dropped", "frames": 10}
    assert first["frames"][0]["header"]["seq"] == 10
    assert described["dropped_frames"] == 10  # the total stays after the notice


def test_a_client_that_fell_behind_gets_what_is_queued_in_one_message():
    from service.reconstruct import ForceFrame
    from service.readings import SensorInfo

    info = SensorInfo(1, "quad", 2, 2)
    per_read = 8
    reads = MERGE_FRAMES // per_read + 2  # one merged message and the rest, fewer messages than the queue holds
    assert MERGE_FRAMES % per_read == 0 and reads <= QUEUE_MESSAGES
    total = reads * per_read

    def seqs(message):
        return [f["header"]["seq"] for f in orjson.loads(message)["frames"]]

    async def scenario():
        hub = Hub()
        behind, other = Subscriber(), Subscriber()
        hub.add(behind)
        hub.add(other)
        for read in range(reads):
            hub.publish([ForceFrame(info, seq, seq, float(seq), np.zeros(3), np.ones(4), [], "full")
                         for seq in range(read * per_read, (read + 1) * per_read)])
        first, _, _ = await behind.next_message()
        second, _, _ = await behind.next_message()
        others, _, _ = await other.next_message()
        return seqs(first), seqs(second), seqs(others), behind.pending, other.pending

    first, second, others, behind_left, other_left = asyncio.run(scenario())
    assert first == list(range(MERGE_FRAMES)) and second == list(range(MERGE_FRAMES, total)) and not behind_left
    # Merging must not grow the list the hub handed to every client.
    assert others == list(range(MERGE_FRAMES))
    assert [item.frame.seq for item in other_left[0]] == list(range(MERGE_FRAMES, MERGE_FRAMES + per_read))


def test_mutating_endpoints_need_the_token_when_one_is_set():
    service = TactileService("sim://?scene=idle")
    with TestClient(create_app(service, token="s3cret"), base_url="http://localhost") as client:
        wait_for_frames(service)
        denied = client.post("/tare")
        assert denied.status_code == 401 and "Bearer" in denied.json()["detail"]
        assert client.post("/tare", headers={"Authorization": "Bearer wrong"}).status_code == 401
        assert client.post("/tare", headers={"Authorization": "Bearer s3cret"}).status_code == 200
        assert client.get("/health").status_code == 200


def test_unbatched_clients_are_served_first():
    hub = Hub()
    batched, unbatched = Subscriber(batch_ms=5.0), Subscriber()
    hub.add(batched)
    hub.add(unbatched)
    assert hub.subscribers == [unbatched, batched]
    hub.remove(unbatched)
    assert hub.subscribers == [batched]



def test_a_batch_is_sent_when_its_oldest_frame_has_waited_batch_ms():
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    info = SensorInfo(1, "quad", 2, 2)

    async def scenario():
        subscriber = Subscriber(batch_ms=30.0)
        received = time.time()
        for seq in range(3):  # no further frames arrive to trigger the send
            frame = ForceFrame(info, seq, seq, received + seq * 1e-3, np.zeros(3), np.ones(4), [], "full")
            subscriber.take([Outgoing(frame)])
        assert not subscriber.pending
        message, _, _ = await asyncio.wait_for(subscriber.next_message(), 1.0)
        return [f["header"]["seq"] for f in orjson.loads(message)["frames"]], time.time() - received

    seqs, waited = asyncio.run(scenario())
    assert seqs == [0, 1, 2] and 0.025 < waited < 0.2


def test_a_long_batch_goes_out_as_messages_of_at_most_merge_frames():
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    info = SensorInfo(1, "quad", 2, 2)

    async def scenario():
        subscriber = Subscriber(batch_ms=20.0)
        received = time.time()
        subscriber.take([Outgoing(ForceFrame(info, seq, seq, received, np.zeros(3), np.ones(4), [], "full"))
                         for seq in range(3 * MERGE_FRAMES + 5)])  # a second's batch of a fast sensor, say
        await asyncio.sleep(0.05)
        sizes = []
        while subscriber.pending:
            message, _, _ = await subscriber.next_message()
            sizes.append(len(orjson.loads(message)["frames"]))
        return sizes

    assert asyncio.run(scenario()) == [MERGE_FRAMES] * 3 + [5]



def test_a_frame_is_encoded_once_per_fields_and_encoding_and_never_for_a_client_that_drops_it(monkeypatch):
    from service.fanout import hub as hub_module
    from service.readings import SensorInfo
    from service.reconstruct import ForceFrame

    encoded = []
    real = hub_module.to_json_dict
    monkeypatch.setattr(hub_module, "to_json_dict",
                        lambda frame, fields: encoded.append((frame.seq, fields)) or real(frame, fields))
    info, total, force_only = SensorInfo(1, "quad", 2, 2), QUEUE_MESSAGES + 10, frozenset({"force"})

    async def scenario():
        hub = Hub()
        readers, stalled = [Subscriber(), Subscriber()], Subscriber(fields=force_only)
        for subscriber in (*readers, stalled):
            hub.add(subscriber)
        for seq in range(total):
            hub.publish([ForceFrame(info, seq, seq, float(seq), np.zeros(3), np.ones(4), [], "full")])
            messages = [(await reader.next_message())[0] for reader in readers]
            assert messages[0] == messages[1]
        while stalled.pending:
            await stalled.next_message()

    asyncio.run(scenario())
    assert sorted(encoded, key=lambda e: (len(e[1]), e[0])) == (
        [(seq, force_only) for seq in range(10, total)] + [(seq, hub_module.DEFAULT_FIELDS) for seq in range(total)])


@pytest.mark.parametrize("query, message", [
    ("seconds=1&max_point=10", "unknown parameter 'max_point'"),  # a typo took the default decimation
    ("seconds=1&seconds=2", "seconds given 2 times"),  # the last was taken
])
def test_a_rest_query_with_an_unknown_or_repeated_parameter_is_refused_naming_it(client, query, message):
    reply = get_history(client, f"/sensors/0/history?{query}")
    assert reply.status_code == 422 and message in reply.json()["detail"]
    assert get_history(client, "/sensors/0/history?seconds=1&max_points=10").status_code == 200
    assert client.get("/health?verbose=1").status_code == 422

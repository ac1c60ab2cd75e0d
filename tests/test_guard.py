"""What a web page, a rebinding DNS name or an unauthenticated client can do: nothing."""
import json
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


@pytest.mark.parametrize("c0, named", [(1e-300, "c0_pF[0] = 1e-300 pF is outside [0.01, 1000] pF"),
                                       (1e300, "is outside"), (5e-324, "is outside"), (True, "c0_pF")])
def test_a_grid_upload_with_an_absurd_c0_is_refused_and_the_sensor_keeps_working(client, c0, named):
    """A C0 of 1e-300 pF was stored and made active: every taxel read as
    loaded, no tare was possible, even after a restart (the registry kept it)."""
    before = client.get("/sensors/0/calibration").json()["id"]
    upload = {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": [c0] * 64}
    refused = client.put("/sensors/0/calibration", json=upload)
    assert refused.status_code == 422 and named in str(refused.json()["detail"]), refused.text
    sensitivity = client.put("/sensors/0/calibration", json={"sensitivity_pct_per_N": [True] * 64})
    assert sensitivity.status_code == 422 and "sensitivity_pct_per_N" in str(sensitivity.json()["detail"])
    assert client.get("/sensors/0/calibration").json()["id"] == before  # nothing stored, nothing swapped


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


def test_no_page_of_another_site_may_frame_the_service(client):
    """Clickjacking: a hidden frame of the dashboard under a decoy would send
    the user's click on "Tare all" from the dashboard's own origin."""
    for path in ("/", "/health", "/nope"):
        response = client.get(path)
        assert response.headers["x-frame-options"] == "DENY", path
        assert response.headers["content-security-policy"] == "frame-ancestors 'none'", path
    refused = client.post("/tare", headers={"origin": "https://evil.example"})
    assert refused.status_code == 403 and refused.headers["x-frame-options"] == "DENY"


def _raw_request(base_url: str, request: bytes, timeout: float = 5.0) -> bytes:
    import socket
    import urllib.parse

    address = urllib.parse.urlsplit(base_url)
    with socket.create_connection((address.hostname, address.port), timeout=timeout) as sock:
        try:
            sock.sendall(request)
        except OSError:  # the server may answer and close before taking it all
            pass
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
            if b"\r\n\r\n" in b"".join(chunks):
                break
        return b"".join(chunks)


def test_request_headers_are_bounded_before_anything_reads_them(served):
    """One unauthenticated request with megabytes of headers was read whole
    (and copied) before the guard could refuse it: 35 MB took the service to
    621 MB and stalled the stream for 2 s. The server now answers 400 once
    the headers pass 8 KiB; a browser's ordinary request still passes."""
    import time

    base_url, _ = served
    headers = b"".join(b"X-%d: %s\r\n" % (i, b"a" * 60) for i in range(20_000))  # 1.4 MB
    started = time.monotonic()
    answer = _raw_request(base_url, b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n" + headers + b"\r\n")
    assert answer.startswith(b"HTTP/1.1 400") and time.monotonic() - started < 2.0
    usual = b"".join(b"X-%d: %s\r\n" % (i, b"a" * 60) for i in range(60))  # 4 KB: cookies, user agent, …
    assert _raw_request(base_url, b"GET /health HTTP/1.1\r\nHost: 127.0.0.1\r\n" + usual + b"\r\n").startswith(b"HTTP/1.1 200")


def test_a_websocket_handshake_past_the_parser_limits_is_answered_and_closed(served):
    """A WebSocket handshake with a 9 KB header line passed the HTTP parser
    (it came whole) and was refused by websockets' own parser, after which
    uvicorn's protocol neither answered nor closed: the connection hung open
    for ever. Now 400, closed; an ordinary handshake still upgrades."""
    import time

    base_url, _ = served
    handshake = (b"GET /ws?sensors=0 HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                 b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n")
    started = time.monotonic()
    answer = _raw_request(base_url, handshake + b"X-Big: " + b"a" * 9000 + b"\r\n\r\n", timeout=5)
    assert answer.startswith(b"HTTP/1.1 400") and time.monotonic() - started < 2.0
    assert _raw_request(base_url, handshake + b"\r\n", timeout=5).startswith(b"HTTP/1.1 101")


def test_a_websocket_client_cannot_send_large_messages(served):
    """The service reads a client's messages only to notice it leave: a
    message over 4 KiB closes that connection (1009) instead of being taken."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    base_url, _ = served
    with connect(base_url.replace("http", "ws", 1) + "ws?sensors=0") as ws:
        ws.send(b"x" * 100)
        ws.recv(timeout=5)  # still streaming
        ws.send(b"x" * 100_000)
        with pytest.raises(ConnectionClosed) as closed:
            for _ in range(10_000):
                ws.recv(timeout=5)
    assert closed.value.rcvd is not None and closed.value.rcvd.code == 1009


def test_clients_that_never_read_their_history_hold_no_slot(served):
    """Two history answers nobody reads (a stalled client) held both read
    slots for as long as their sockets stayed open: every other history read
    got 429. A slot now bounds only the encoding."""
    import socket
    import urllib.parse
    import urllib.request

    base_url, _ = served
    address = urllib.parse.urlsplit(base_url)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # answers far larger than the sockets' buffers (~12 MB)
        with urllib.request.urlopen(base_url + "sensors/0/history?seconds=5&max_points=5000&fields=force") as answer:
            if len(json.loads(answer.read())) >= 3000:
                break
        time.sleep(0.3)
    time.sleep(1.0)  # the admission's tokens come back
    stalled = []
    for _ in range(2):
        sock = socket.socket()
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
        sock.connect((address.hostname, address.port))
        sock.sendall(b"GET /sensors/0/history?seconds=5&max_points=5000&fields=force,sigma,raw,contact,flags HTTP/1.1\r\n"
                     b"Host: 127.0.0.1\r\n\r\n")
        stalled.append(sock)
    try:
        assert stalled[0].recv(12) == b"HTTP/1.1 200"  # answered, then never read further
        time.sleep(0.6)  # the admission's tokens come back
        with urllib.request.urlopen(base_url + "sensors/1/history?seconds=0.5&max_points=50", timeout=5) as answer:
            assert answer.status == 200 and len(json.loads(answer.read())) >= 1
    finally:
        for sock in stalled:
            sock.close()



@pytest.fixture
def own_registry_client(tmp_path, monkeypatch):
    """A service whose uploads go to a registry of its own (not the run's,
    which later modules' services read)."""
    monkeypatch.setenv("TACTILE_REGISTRY", str(tmp_path / "registry.sqlite3"))
    with TestClient(create_app(TactileService("sim://?scene=idle")), base_url="http://localhost:8000") as client:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and len(client.get("/sensors").json()["sensors"]) < 2:
            time.sleep(0.02)
        yield client


def test_a_whole_calibration_document_uploads_as_exported_and_an_edited_one_is_refused(own_registry_client):
    """docs/api.md: PUT takes the short forms or a whole document
    (``tactile calibrations export``: gains with their errors, measured C0,
    curves). The body's type let only the short forms through."""
    from service.calibration.registry import sensor_identity
    from service.reconstruct.calibration_upload import upload_document

    client = own_registry_client

    sensors = {s["id"]: s for s in client.get("/sensors").json()["sensors"]}
    board = client.app.state.service.all_boards[0]
    info = board.sensors

    def exported(sid, numbers):  # what tactile calibrations export gives for the sensor
        return upload_document(info[sid], numbers, "flat", sensor_identity(board.info, info[sid]))

    grid = exported(0, {"sensitivity_pct_per_N": [1.3] * 64, "c0_pF": [10.5] * 64})
    quad = exported(1, {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]})
    assert grid["schema"] == quad["schema"] == 1 and sensors[0]["kind"] == "grid"
    for sid, document in ((0, grid), (1, quad)):
        answer = client.put(f"/sensors/{sid}/calibration", json=document)
        assert answer.status_code == 200, answer.text
        assert answer.json()["id"] == document["id"] == client.get(f"/sensors/{sid}/calibration").json()["id"]
    edited = {**grid, "taxels": {**grid["taxels"], "gain": [1.1] * 64}}
    refused = client.put("/sensors/0/calibration", json=edited)
    assert refused.status_code == 422 and "does not match the document's content" in refused.json()["detail"]
    assert client.put("/sensors/0/calibration", json={"schema": 1}).status_code == 422
    other = client.put("/sensors/1/calibration", json=grid)  # sensor 0's document onto sensor 1
    assert other.status_code == 422 and "not this sensor" in other.json()["detail"]


def _exported_documents(client) -> tuple[dict, dict]:
    """What ``tactile calibrations export`` gives for the simulator's grid (sensor 0) and quad (sensor 1)."""
    from service.calibration.registry import sensor_identity
    from service.reconstruct.calibration_upload import upload_document

    board = client.app.state.service.all_boards[0]
    info = board.sensors
    grid = upload_document(info[0], {"sensitivity_pct_per_N": [1.3] * 64, "c0_pF": [10.5] * 64}, "flat",
                           sensor_identity(board.info, info[0]))
    quad = upload_document(info[1], {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]}, "flat",
                           sensor_identity(board.info, info[1]))
    return grid, quad


def test_a_document_with_a_field_of_another_type_or_out_of_range_is_a_422_naming_it_and_nothing_changes(
        own_registry_client):
    """Odd types were a 500 (TypeError, IndexError, AttributeError, or SQLite's binding error for created);
    created = 1 was stored and made /health a 500 for good; a curve to -99 or 1e9 N, a sensitivity of
    0.0001 %/N were taken and read a 5 N load as -99.9 ± 0.018 N, 1.1e8 N, 5.5e4 N (level0), unflagged."""
    client = own_registry_client
    grid, quad = _exported_documents(client)
    for sid, document in ((0, grid), (1, quad)):
        assert client.put(f"/sensors/{sid}/calibration", json=document).status_code == 200
    sensitivities = list(grid["taxels"]["sensitivity_pct_per_N"])
    sensitivities[27] = 0.0001
    cases = [(0, {"created": 1}, "created: "), (0, {"created": {"x": 1}}, "created: "),
             (0, {"created": [1]}, "created: "),
             (0, {"curves": [1]}, "taxels.curves: "), (0, {"curves": "x"}, "taxels.curves: "),
             (0, {"curves": {"27": {"force_N": [-100.0, -99.0], "relative": [0.0, 0.5]}}}, "taxels.curves['27']: "),
             (0, {"curves": {"27": {"force_N": [0.0, 1e9], "relative": [0.0, 0.5]}}}, "taxels.curves['27']: "),
             (0, {"sensitivity_pct_per_N": sensitivities}, "taxels.sensitivity_pct_per_N[27] = 0.0001 "),
             (1, {"normal_fit_se": 5}, "normal_fit_se: "), (1, {"normal_fit_se": [1]}, "normal_fit_se: "),
             (1, {"shear_fit_se": {"a": 1}}, "shear_fit_se: "), (1, {"coupling": [1]}, "coupling: "),
             (1, {"coupling": {"c": 1}}, "coupling: "), (1, {"statistics": "x"}, "statistics: "),
             (1, {"created": {"x": 1}}, "created: ")]
    for sid, change, named in cases:
        base = grid if sid == 0 else quad
        if sid == 0 and "created" not in change:
            change = {"taxels": {**grid["taxels"], **change}}
        document = {k: v for k, v in {**base, **change}.items() if k != "id"}
        answer = client.put(f"/sensors/{sid}/calibration", json=document)
        assert answer.status_code == 422 and answer.json()["detail"].startswith(named), (change, answer.text)
    for sid, document in ((0, grid), (1, quad)):  # nothing half-applied
        assert client.get(f"/sensors/{sid}/calibration").json()["id"] == document["id"]
    assert client.get("/health").status_code == 200


def test_a_stored_document_whose_created_is_not_a_string_leaves_the_sensor_on_the_built_in(own_registry_client):
    """Stored before uploads were checked (created = 1, the registry's active calibration), it made /health
    and GET /sensors/0/calibration a 500 at every start: now the sensor reads with table 1, the problem named."""
    from service.calibration.registry import Registry

    grid, _ = _exported_documents(own_registry_client)
    with Registry() as registry:  # TACTILE_REGISTRY: the fixture's own
        registry.add({**{k: v for k, v in grid.items() if k != "id"}, "created": 1}, activate=True)
    with TestClient(create_app(TactileService("sim://?scene=idle")), base_url="http://localhost:8000") as client:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and client.get("/sensors/0/calibration").status_code == 409:
            time.sleep(0.02)
        state = client.get("/sensors/0/calibration")
        assert state.status_code == 200, state.text
        assert state.json()["id"] == "builtin-table1" and "created: " in state.json()["problem"]
        assert client.get("/health").status_code == 200


def _refused_and_nothing_stored(client, sid: int, base: dict, documents: list[tuple[dict, str]]) -> None:
    """Each of ``documents`` (with the start of the 422's detail that names its field) PUT to
    ``sid`` after ``base``: a 422 naming it, the registry's rows and the active calibration unchanged."""
    from service.calibration.registry import Registry

    assert client.put(f"/sensors/{sid}/calibration", json=base).status_code == 200
    with Registry() as registry:  # TACTILE_REGISTRY: the fixture's own
        rows = registry.list()
    for document, named in documents:
        document = {k: v for k, v in document.items() if k != "id"}
        answer = client.put(f"/sensors/{sid}/calibration", json=document)
        assert answer.status_code == 422 and answer.json()["detail"].startswith(named), (named, answer.text)
    with Registry() as registry:
        assert registry.list() == rows
    assert client.get(f"/sensors/{sid}/calibration").json()["id"] == base["id"]


def test_a_document_whose_mounting_is_not_a_mounting_is_a_422_naming_it_and_nothing_is_stored(own_registry_client):
    """A list was a 500 (TypeError: unhashable); {}, 0 and null were a 200, stored, the service's mounting used."""
    grid, _ = _exported_documents(own_registry_client)
    _refused_and_nothing_stored(own_registry_client, 0, grid, [
        ({**grid, "mounting": value}, f"mounting: {value!r} is not one of flat, curved")
        for value in (["flat"], [1.0, 2.0], {}, 0, None)])


def test_standard_errors_residuals_and_curves_out_of_range_are_a_422_naming_them_nothing_stored(own_registry_client):
    """A taxel's gain_se of -1e150 was a 200, its loaded taxels read ~1 N ± 1e150 N; 1e300 gave σ null (which
    says saturated) beside a number, unflagged; a quad's standard errors and residuals likewise; a curve's
    ΔC/C0 to 1e300 read 5 N as 5e-301 N, σ 0.013 N. The ranges:
    standard errors from 0 to the value they are of (a taxel's gain; c1 0.0343, a 0.0077), residuals
    from 0 to 471 N (a grid's taxel) or the axis's usable force (a quad's)."""
    client = own_registry_client
    grid, quad = _exported_documents(client)

    def taxels(name, value):
        values = list(grid["taxels"].get(name, [None] * 64))
        values[5] = value
        return {**grid, "taxels": {**grid["taxels"], name: values}}

    _refused_and_nothing_stored(client, 0, grid, [
        (taxels("gain_se", -1e150), "taxels.gain_se[5] = -1e+150 is outside [0, "),
        (taxels("gain_se", 1e300), "taxels.gain_se[5] = 1e+300 is outside [0, "),
        (taxels("gain_se", "0.01"), "taxels.gain_se: expected a list of 64 numbers"),
        (taxels("residual_rms_N", 1e300), "taxels.residual_rms_N[5] = 1e+300 is outside [0, 471] N"),
        ({**grid, "taxels": {**grid["taxels"], "curves": {"27": {"force_N": [0.0, 10.0], "relative": [0.0, 1e300]}}}},
         "taxels.curves['27']: relative[1] = 1e+300 at 10 N is outside [")])
    _refused_and_nothing_stored(client, 1, quad, [
        ({**quad, "normal_fit_se": [0.0, 1e300]}, "normal_fit_se[1] = 1e+300 is outside [0, 0.0343], c1"),
        ({**quad, "shear_fit_se": [-1e150, 0.0]}, "shear_fit_se[0] = -1e+150 is outside [0, 0.0077], a"),
        ({**quad, "statistics": {"rms_N": {"x": 0.0, "y": 0.0, "z": 999.0}}},
         "statistics.rms_N.z: 999 is outside [0, ")])


def test_a_body_nested_past_the_guards_bound_is_a_422_naming_its_depth(client):
    """orjson allowed 1024 levels but FastAPI's parser (the stdlib's, within the request's stack) gave up
    sooner: 1000 deep was a vague 400 "There was an error parsing the body". The guard's bound, 64 levels
    (a calibration document nests 5), now binds first, brackets within strings not counted."""
    json_type = {"Content-Type": "application/json"}
    for depth in (65, 700, 1000, 1023, 1100):
        for body in (b"[" * depth + b"]" * depth, b'{"schema": 1, "x": ' + b'{"a": ' * (depth - 1) + b"1" + b"}" * depth):
            answer = client.put("/sensors/0/calibration", content=body, headers=json_type)
            assert answer.status_code == 422, (depth, answer.text)
            assert answer.json()["detail"] == f"the body nests {depth} deep; at most 64 levels are taken", depth
    for body in (b"[" * 64 + b"]" * 64, b'{"schema": 1, "x": "' + b"[" * 100 + b'\\"[{"}'):  # the bound, strings
        answer = client.put("/sensors/0/calibration", content=body, headers=json_type)
        assert answer.status_code == 422 and "nests" not in answer.text, answer.text  # the schema's 422

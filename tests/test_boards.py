"""Several boards in one service: addressing board/sensor everywhere, and
boards that cannot disturb each other (one vanishes, stalls or floods)."""
import time

import numpy as np
import orjson
import pytest
from fastapi.testclient import TestClient

from firmware_sim.board import BoardConfig, capture
from firmware_sim.misbehaving import MisbehavingBoard
from firmware_sim.sensors import SimGrid, SimQuad
from service.api.app import create_app
from service.board import BoardSpec
from service.cli import build_parser, main
from service.cli_serve import board_specs
from service.fanout.encoding import decode_binary
from service.live_service import TactileService
from service.robot_config import load_robot


def wait_until(condition, seconds=5.0):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline and not condition():
        time.sleep(0.01)
    return condition()


@pytest.fixture(scope="module")
def two():
    """left: a grid and a quad; right: a quad only (its id 0 collides with left's grid)."""
    service = TactileService(boards=[BoardSpec("sim://?scene=press&sensors=grid,quad", "left"),
                                     BoardSpec("sim://?scene=press&sensors=quad&seed=3", "right")])
    with TestClient(create_app(service), base_url="http://localhost") as client:
        wait_until(lambda: len(service.board("left").pipeline.latest) == 2 and len(service.board("right").pipeline.latest) == 1)
        yield service, client


def test_sensors_are_listed_and_read_by_board_and_id(two):
    _, client = two
    listed = client.get("/sensors").json()
    assert [(s["address"], s["kind"]) for s in listed["sensors"]] == [("left/0", "grid"), ("left/1", "quad"),
                                                                        ("right/0", "quad")]
    assert [b["name"] for b in listed["boards"]] == ["left", "right"] and listed["board"] is None
    right = client.get("/sensors/right/0/latest").json()
    assert right["header"]["board"] == "right" and right["header"]["kind"] == "quad"
    assert client.get("/sensors/left/0/latest").json()["header"]["kind"] == "grid"
    assert client.get("/sensors/1/latest").json()["header"]["board"] == "left"  # one board has a sensor 1
    ambiguous = client.get("/sensors/0/latest")
    assert ambiguous.status_code == 409 and "left, right" in ambiguous.json()["detail"]
    missing = client.get("/sensors/middle/0/latest")
    assert missing.status_code == 404 and "'middle'" in missing.json()["detail"] and "left, right" in missing.json()["detail"]
    assert client.get("/sensors/right/1/latest").status_code == 404
    history = client.get("/sensors/right/0/history?seconds=0.5&max_points=10").json()
    assert len(history) == 10 and {f["header"]["board"] for f in history} == {"right"}
    assert client.get("/sensors/right/0/calibration").json()["id"].startswith("builtin")


def test_a_stream_subscribes_by_address_and_binary_names_the_board(two):
    _, client = two
    with client.websocket_connect("ws://localhost/ws?sensors=right/0,1&encoding=binary") as ws:
        records = [r for _ in range(40) for r in decode_binary(ws.receive_bytes())]
    assert {(r["board"], r["sensor_id"]) for r in records} == {("right", 0), ("left", 1)}
    with client.websocket_connect("ws://localhost/ws?sensors=right/7") as ws:
        notice = orjson.loads(ws.receive_text())
    assert notice["type"] == "notice" and "right/7" in notice["detail"] and "left/0" in notice["detail"]


def test_health_has_each_board_and_keys_sensors_by_address(two):
    _, client = two
    time.sleep(1.1)  # a full rate window
    health = client.get("/health").json()
    for _ in range(20):  # a loaded host may stall the loop past the 0.5 s staleness for a moment
        if health["status"] == "ok":
            break
        time.sleep(0.1)
        health = client.get("/health").json()
    assert set(health["boards"]) == {"left", "right"} and health["status"] == "ok", health["problems"]
    assert set(health["sensors"]) == {"left/0", "left/1", "right/0"}
    for address, sensor in health["sensors"].items():
        assert f"{sensor['board']}/{sensor['id']}" == address and 800 <= sensor["rate_hz"] <= 1200
    assert "link" not in health  # a link per board: under boards
    assert all(part["link"]["up"] for part in health["boards"].values())


def test_tare_one_board(two):
    _, client = two
    answer = client.post("/tare?board=right&force=true").json()
    assert answer["tared"] == ["right/0"]
    assert client.post("/sensors/right/0/tare?force=true").json()["tared"] == ["right/0"]
    assert client.post("/tare?board=middle").status_code == 404


def test_several_sources_on_the_command_line_and_in_a_robot_file(tmp_path):
    parse = build_parser().parse_args
    specs = board_specs(parse(["serve", "--source", "left=sim://?sensors=quad", "--source", "sim://?seed=2"]))
    assert [(s.name, s.source) for s in specs] == [("left", "sim://?sensors=quad"), (None, "sim://?seed=2")]
    with pytest.raises(ValueError, match="given twice"):
        board_specs(parse(["serve", "--source", "a=sim://", "--source", "a=sim://?seed=1"]))
    robot = tmp_path / "robot.toml"
    robot.write_text('[[board]]\nname = "palm"\nsource = "sim://?sensors=grid"\nlevel = "table"\nmounting = "curved"\n'
                     '[[board]]\nname = "thumb"\nsource = "sim://?sensors=quad"\n')
    specs = board_specs(parse(["serve", "--config", str(robot)]))
    assert [(s.name, s.level, s.mounting) for s in specs] == [("palm", "table", "curved"), ("thumb", "full", "flat")]
    robot.write_text('[[board]]\nname = "palm"\nsource = "sim://"\nspeed = 3\n')
    with pytest.raises(ValueError, match=r"board 1 \('palm'\): unknown key\(s\) \['speed'\]"):
        load_robot(robot, "full", "flat")
    robot.write_text('[[board]]\nname = "9palm"\nsource = "sim://"\n')
    with pytest.raises(ValueError, match="must start with a letter"):
        load_robot(robot, "full", "flat")
    # A bad name before '=' is named as such, not taken for a URL scheme ('1bad=sim' is no URL scheme).
    with pytest.raises(ValueError, match=r"--source 1bad=sim://: board name '1bad' must start with a letter"):
        board_specs(parse(["serve", "--source", "1bad=sim://"]))
    assert [s.name for s in board_specs(parse(["serve", "--source", "sim://?scene=press&seed=3"]))] == [None]


@pytest.mark.parametrize("value", ['["flat"]', '{ kind = "flat" }'])
def test_a_robot_file_whose_mounting_is_no_string_is_named_and_exits_2(tmp_path, capsys, value):
    """``mounting = ["flat"]`` raised TypeError (unhashable list, looked up
    among the mountings) through ``tactile serve``: a traceback. Now the
    CLI's error naming the board and the field, exit 2, before any port is bound."""
    robot = tmp_path / "robot.toml"
    robot.write_text(f'[[board]]\nname = "palm"\nsource = "sim://"\nmounting = {value}\n')
    with pytest.raises(ValueError, match=r"board 1 \('palm'\): mounting .* is not one of flat, curved"):
        load_robot(robot, "full", "flat")
    assert main(["serve", "--config", str(robot)]) == 2
    assert capsys.readouterr().err.startswith(f"tactile serve: error: {robot}: board 1 ('palm'): mounting ")


def test_a_bare_source_is_named_from_its_info():
    service = TactileService("sim://?sensors=quad")
    with TestClient(create_app(service), base_url="http://localhost") as client:
        assert wait_until(lambda: service.pipeline.latest)
        name = service.primary.name
        assert name not in ("", "board")  # the simulator's INFO names it
        assert client.get(f"/sensors/{name}/0/latest").json()["header"]["board"] == name
        assert client.get("/sensors/0/latest").status_code == 200  # one board: a bare id still works


def test_bare_sources_whose_info_never_names_them_do_not_share_a_name():
    """Two unnamed sources whose INFO is invalid (or not come yet) were both
    ``board``: /health showed one of them, /sensors listed board/0 twice and
    board/0 read either. Until an INFO names them they are board, board-2."""
    from service.health import health_report
    from service.protocol import FrameType, encode_frame

    service = TactileService(boards=[BoardSpec("socket://127.0.0.1:1"), BoardSpec("socket://127.0.0.1:2")])
    invalid = encode_frame(FrameType.INFO, 255, 0, 0, b'{"board": "x", "sensors": 3}')
    quad = np.full(4, 2_200_000, "<u4").tobytes()
    for board in service.all_boards:
        board.pipeline.feed(invalid + b"".join(encode_frame(FrameType.QUAD, 0, k, 1000 * (k + 1), quad)
                                               for k in range(5)), time.time())
    assert [b.name for b in service.all_boards] == ["board", "board-2"]
    assert sorted(health_report(service)["boards"]) == ["board", "board-2"]
    assert [f.sensor.address for b in service.all_boards for f in [b.pipeline.latest[0]]] == ["board/0", "board-2/0"]
    # The second then gets a valid INFO naming neither board nor serial: not the first's provisional name.
    nameless = encode_frame(FrameType.INFO, 255, 0, 0, b'{"sensors": [{"id": 0, "kind": "quad"}]}')
    service.all_boards[1].pipeline.feed(nameless, time.time())
    assert [b.name for b in service.all_boards] == ["board", "board-2"]


def test_two_boards_reporting_one_serial_are_a_problem_in_health():
    """Two boards whose INFO give one serial share their sensors' calibration
    keys (an upload to one was the other's after a restart), silently."""
    from service.health import health_report
    from service.protocol import FrameType, encode_frame

    service = TactileService(boards=[BoardSpec("socket://127.0.0.1:1", name="a"), BoardSpec("socket://127.0.0.1:2", name="b")])
    info = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps({"board": "tmux", "serial": "TMX-SAME",
                                                                "sensors": [{"id": 0, "kind": "quad"}]}))
    for board in service.all_boards:
        board.pipeline.feed(info, time.time())
    problems = health_report(service)["problems"]
    assert any(p.startswith("boards a, b report one serial 'TMX-SAME'") for p in problems), problems
    for board, serial in zip(service.all_boards, ("Q-1", "Q-2")):  # sensors with serials of their own share nothing
        board.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(
            {"board": "tmux", "serial": "TMX-SAME", "sensors": [{"id": 0, "kind": "quad", "serial": serial}]})),
            time.time())
    assert not any("one serial" in p for p in health_report(service)["problems"])


def test_a_tare_of_a_board_not_connected_says_so():
    """A tare while the board is away answered as done; it takes the
    board's next frames once it is back, and the answer now says so."""
    from service.protocol import FrameType, encode_frame

    service = TactileService(boards=[BoardSpec("socket://127.0.0.1:1", name="a")])
    quad = np.full(4, 2_200_000, "<u4").tobytes()
    info = encode_frame(FrameType.INFO, 255, 0, 0, b'{"sensors": [{"id": 0, "kind": "quad"}]}')  # its frames wait for it
    with TestClient(create_app(service), base_url="http://localhost") as client:
        service.pipeline.feed(info + b"".join(encode_frame(FrameType.QUAD, 0, k, 1000 * (k + 1), quad)
                                              for k in range(5)), time.time())
        answer = client.post("/tare").json()
    assert answer["tared"] == [0] and "a not connected" in answer["note"]


def test_a_board_that_stalls_floods_or_vanishes_does_not_disturb_another():
    bad = MisbehavingBoard()
    service = TactileService(boards=[BoardSpec("sim://?scene=press&sensors=grid,quad", "good"),
                                     BoardSpec(f"socket://127.0.0.1:{bad.port}", "bad")], silence_s=1.0)
    good_frames: list = []
    with TestClient(create_app(service), base_url="http://localhost") as client:
        good = service.board("good").pipeline
        good.listeners = [*good.listeners, lambda frames: good_frames.extend((f.sensor.id, f.seq, f.t_host, f.flags)
                                                                               for f in frames)]
        assert wait_until(lambda: len(service.board("bad").pipeline.latest) == 2)
        phases, bytes_in = {}, {}
        for phase in ("stream", "silent", "flood", "gone"):
            bad.phase = phase
            if phase == "gone":
                bad.stop.set()  # connection and listening socket closed: reconnects are refused
            start = time.time()
            time.sleep(0.8)
            if phase == "silent":  # stale after 0.5 s; asked INFO? at 1 s, reconnecting at 1.5 s
                health = client.get("/health").json()
                assert health["boards"]["bad"]["link"]["state"] == "stale" and health["boards"]["good"]["status"] == "ok"
            time.sleep(0.7)
            phases[phase] = (start + 0.3, time.time())  # after the phase settled
            bytes_in[phase] = client.get("/health").json()["boards"]["bad"]["stream"]["bytes_in"]
        bad_part = client.get("/health").json()["boards"]["bad"]
    for phase, (start, end) in phases.items():
        quad = [(seq, t) for sid, seq, t, _ in good_frames if sid == 1 and start <= t < end]
        assert 0.85 * 1000 <= len(quad) / (end - start) <= 1.15 * 1000, (phase, len(quad))
    assert not [f for f in good_frames if "seq_gap" in f[3] or "overrun" in f[3]]  # nothing of the good board lost
    seqs = np.array([seq for sid, seq, _, _ in good_frames if sid == 1])
    assert np.all(np.diff(seqs) % 65536 == 1)
    # It did flood: > 1.2 MB in 1.5 s, 3x what this board sends at 1 kHz and 4x what a 2 Mbaud link can carry.
    assert bytes_in["flood"] - bytes_in["silent"] > 1.2e6
    assert bad_part["link"]["state"] != "up"


def test_a_recording_of_two_boards_replays_each_board_bit_for_bit(tmp_path):
    """Two boards' pipelines recorded together: each board's raw bytes under
    /{board}/raw; the replay reconstructs each board apart, exactly as live."""
    from service.pipeline import Pipeline
    from service.reconstruct import Reconstructor
    from service.record.mcap_reader import boards_in, summary
    from service.record.recorder import Recorder
    from service.replay import replay, replay_boards

    captures = {"left": capture(BoardConfig(sensors=[SimGrid(0), SimQuad(1)], scene="press", seed=4), 1.5)[0],
                "right": capture(BoardConfig(sensors=[SimQuad(0)], scene="press", seed=5), 1.5)[0]}
    pipelines = {name: Pipeline(Reconstructor(), board_name=name) for name in captures}
    path = tmp_path / "two.mcap"
    recorder = Recorder(path)
    live: list = []
    for pipeline in pipelines.values():
        recorder.attach(pipeline)
    t, pos = 1000.0, 0
    while pos < max(map(len, captures.values())):
        for name, data in captures.items():  # reads of both boards, interleaved as a live service gets them
            live += pipelines[name].feed(data[pos:pos + 1500], t)
        pos += 1500
        t += 0.005
    assert recorder.stop()["error"] is None
    assert sorted(boards_in(path)) == ["left", "right"]
    assert {"/left/raw", "/right/raw", "/left/sensor/0/forces", "/right/sensor/0/forces"} <= set(summary(path))
    replayed: list = []

    class Collect:
        def write(self, frames):
            replayed.extend(frames)

    assert set(replay_boards(path, writer=Collect())) == {"left", "right"}
    recorded = {(f.sensor.address, f.seq): f for f in live}
    again = {(f.sensor.address, f.seq): f for f in replayed}
    assert recorded.keys() == again.keys() and {a for a, _ in again} == {"left/0", "left/1", "right/0"}
    assert all(np.array_equal(recorded[k].forces_N, again[k].forces_N, equal_nan=True) and
               recorded[k].flags == again[k].flags for k in recorded)
    with pytest.raises(ValueError, match="holds boards"):
        replay(path)
    from service.cli import main

    out = tmp_path / "two.jsonl"
    assert main(["replay", str(path), "--export", str(out)]) == 0
    lines = [orjson.loads(line) for line in out.read_bytes().splitlines()]
    assert {(line["board"], line["sensor"]) for line in lines} == {("left", 0), ("left", 1), ("right", 0)}
    assert len(lines) == len(replayed)


def test_boards_of_one_model_without_serials_keep_their_calibrations_apart():
    from service.calibration.registry import sensor_identity
    from service.readings import SensorInfo

    info = {"board": "tactile-sim-8x8-quad"}
    bare = sensor_identity(info, SensorInfo(0, "quad", 2, 2, board="tactile-sim-8x8-quad"))["key"]
    left = sensor_identity(info, SensorInfo(0, "quad", 2, 2, board="left"))["key"]
    right = sensor_identity(info, SensorInfo(0, "quad", 2, 2, board="right"))["key"]
    assert bare == "board:tactile-sim-8x8-quad/sensor:0"  # a bare source: as before boards were named
    assert len({bare, left, right}) == 3 and left == "board:tactile-sim-8x8-quad@left/sensor:0"
    with_serial = sensor_identity({**info, "serial": "TMX-1"}, SensorInfo(0, "quad", 2, 2, board="left"))["key"]
    assert with_serial == "board:TMX-1/sensor:0"  # a serial says which board it is, whatever it is called


def test_a_calibration_made_for_a_named_board_is_found_by_that_board_only(tmp_path):
    """`tactile calibrate --board left` keys a serial-less board's sensor as
    the service reading `--source left=…` does; the other board does not get it."""
    from firmware_sim.calibration_session import session
    from service.calibration import registry as reg
    from service.calibration.book import CalibrationBook
    from service.calibration.calibrate import calibrate, document
    from service.readings import SensorInfo

    sim = session(rate_hz=200.0, seed=3)
    (tmp_path / "session.bin").write_bytes(sim.raw)
    (tmp_path / "reference.csv").write_text(sim.reference_csv)
    result = calibrate(tmp_path / "session.bin", tmp_path / "reference.csv", board="left")
    key = reg.sensor_identity(result.session.board, result.session.info)["key"]
    assert key.endswith("@left/sensor:0") and not result.session.board.get("serial")
    path = tmp_path / "registry.sqlite3"
    with reg.Registry(path) as registry:
        cid = registry.add(document(result, None), activate=True)
    book = CalibrationBook(path)
    assert book.for_sensor(result.session.board, SensorInfo(0, "grid", 8, 8, board="left")).id == cid
    assert book.for_sensor(result.session.board, SensorInfo(0, "grid", 8, 8, board="right")) is None


def test_a_board_streaming_before_its_info_gets_its_stored_calibration_once_the_info_names_it(tmp_path):
    """A board already streaming when the service connects sends frames
    before its INFO (the reply to INFO?): the sensor's calibration was
    looked up then, under an unknown board, and never again, so the one
    stored for the board's serial was not used (frames said builtin-table1,
    /health ok). Now the INFO's identity looks it up again; the zero is kept."""
    from service.calibration import registry as reg
    from service.calibration.book import CalibrationBook
    from service.pipeline import Pipeline
    from service.protocol import FrameType, encode_frame
    from service.readings import SensorInfo
    from service.reconstruct import Reconstructor

    board = {"board": "tmux-8x8", "serial": "TMX-A", "fw": "1.1.0", "rate_hz": 1000}
    info = SensorInfo(0, "grid", 8, 8, board="a")
    document = reg.builtin_document()
    document["taxels"]["gain"] = [1.2 * g for g in document["taxels"]["gain"]]
    document |= {"id": None, "note": "test", "sensor": reg.sensor_identity(board, info), "created": "2026-11-24T00:00:00Z"}
    path = tmp_path / "registry.sqlite3"
    with reg.Registry(path) as registry:
        cid = registry.add({k: v for k, v in document.items() if k != "id"}, activate=True)
    c0 = np.array(reg.builtin_document()["taxels"]["c0_pF"])
    rng = np.random.default_rng(1)

    def scan(k: int) -> bytes:
        raw = np.round((c0 + rng.normal(0, 0.002, 64)) * 1e6).astype("<u4")  # aF
        return encode_frame(FrameType.GRID, 0, k, 1000 * (k + 1), raw.tobytes())

    info_frame = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(
        board | {"sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]}))
    def fresh() -> Pipeline:
        return Pipeline(Reconstructor(level="table"), calibrations=CalibrationBook(path), board_name="a", map_clock=False)

    scans = [scan(k) for k in range(200)]
    chunks = [b"".join(scans[k:k + 10]) for k in range(0, 150, 10)] + [info_frame + b"".join(scans[150:155])]
    chunks += [b"".join(scans[k:k + 5]) for k in range(155, 200, 5)]
    pipeline = fresh()
    live = [f for chunk in chunks for f in pipeline.feed(chunk, 1.0)]
    before, after = live[:150], live[150:]
    assert {f.calibration for f in before} == {"builtin-table1"}
    assert {f.calibration for f in after} == {cid}
    assert not any("taring" in f.flags for f in after)  # the zero was kept
    assert pipeline.reconstructor.calibration(0).id == cid
    joined = fresh().feed_many([(chunk, 1.0) for chunk in chunks])  # a replay joins recorded reads
    assert [(f.seq, f.calibration) for f in joined] == [(f.seq, f.calibration) for f in live]
    assert all(np.array_equal(a.forces_N, b.forces_N, equal_nan=True) for a, b in zip(joined, live))

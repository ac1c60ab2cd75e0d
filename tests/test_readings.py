import json
from dataclasses import replace

import numpy as np
import orjson
import pytest

from service.protocol import FLAG_SATURATED, FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.board_info import parse_info
from service.interpreter import Interpreter


def feed(interpreter, *frames):
    return [interpreter.interpret(f, 0.0) for f in Decoder().feed(b"".join(frames))]


def info_frame(doc):
    # The standard library, not orjson: it can write integers beyond 64 bits.
    return encode_frame(FrameType.INFO, 255, 0, 0, json.dumps(doc).encode())


def test_grid_without_info_is_8x8_and_in_picofarads():
    counts = np.arange(1, 65, dtype="<u4") * 1_000_000
    (reading,) = feed(Interpreter(), encode_frame(FrameType.GRID, 3, 0, 0, counts.tobytes()))
    assert (reading.sensor.kind, reading.sensor.rows, reading.sensor.cols) == ("grid", 8, 8)
    np.testing.assert_array_equal(reading.capacitance_pF, np.arange(1, 65, dtype=float))


def test_sentinels_are_never_capacitances():
    counts = np.full(4, 2_200_000, dtype="<u4")
    counts[1] = 0xFFFFFFFF
    counts[3] = 0
    (reading,) = feed(Interpreter(), encode_frame(FrameType.QUAD, 1, 0, 0, counts.tobytes(), FLAG_SATURATED))
    assert np.isnan(reading.capacitance_pF[[1, 3]]).all()
    assert reading.capacitance_pF[0] == pytest.approx(2.2)
    assert reading.frame_flags() == ["saturated", "open_channel", "shorted_channel"]


def test_info_announces_grid_shape():
    interpreter = Interpreter()
    doc = {"board": "b", "fw": "1", "rate_hz": 500, "extra": 1,
           "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 16}, {"id": 2, "kind": "quad"}]}
    readings = feed(interpreter, info_frame(doc), encode_frame(FrameType.GRID, 0, 0, 0, bytes(range(256))))
    assert readings[0] is None
    assert (readings[1].sensor.rows, readings[1].sensor.cols) == (4, 16)
    assert interpreter.board == {"board": "b", "fw": "1", "rate_hz": 500, "extra": 1}


def test_payload_not_matching_announced_shape_is_dropped_and_counted():
    interpreter = Interpreter()
    doc = {"sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 4}]}
    readings = feed(interpreter, info_frame(doc), encode_frame(FrameType.GRID, 0, 0, 0, bytes(256)))
    assert readings == [None, None]
    assert interpreter.rejected["shape_mismatch"] == 1


def test_grid_of_unknown_shape_without_info_is_dropped_and_counted():
    interpreter = Interpreter()
    assert feed(interpreter, encode_frame(FrameType.GRID, 0, 0, 0, bytes(64))) == [None]
    assert interpreter.rejected["unknown_shape"] == 1


@pytest.mark.parametrize(
    "payload, message",
    [
        (b"not json", "not JSON"),
        (b"[1]", "JSON object"),
        (b'{"sensors": [{"id": 0, "kind": "grid", "rows": "8", "cols": 8}]}', "rows that is not an integer"),
        (b'{"sensors": [{"id": true, "kind": "quad"}]}', "integer id"),
        (b'{"sensors": [{"kind": "quad"}]}', "integer id"),
    ],
)
def test_bad_info_names_the_problem(payload, message):
    with pytest.raises(ValueError, match=message):
        parse_info(payload)


def test_a_sensor_described_twice_neither_loses_the_board_nor_its_other_sensors(caplog):
    """A firmware that lists a sensor twice: the same description counts
    once; two different ones leave that sensor undescribed (its frames give
    its shape, /health says the INFO describes it twice), the rest is taken."""
    doc, sensors, _ = parse_info(b'{"serial": "TMX-1", "sensors": [{"id": 0, "kind": "quad"}, {"id": 0, "kind": "quad"}, '
                              b'{"id": 1, "kind": "grid", "rows": 4, "cols": 4}, {"id": 1, "kind": "grid", "rows": 8, '
                              b'"cols": 8}, {"id": 2, "kind": "grid", "rows": 2, "cols": 2}]}')
    assert doc["serial"] == "TMX-1" and sorted(sensors) == [0, 2] and sensors[0].kind == "quad"
    assert "sensor 1 twice, differently" in caplog.text
    _, sensors, _ = parse_info(b'{"sensors": [{"id": 1, "kind": "quad"}, {"id": 1, "kind": "thermo"}, {"id": 2, "kind": "quad"}]}')
    assert list(sensors) == [2]
    interpreter = Interpreter(clock=lambda: 0.0)
    frames = Decoder().feed(encode_frame(FrameType.INFO, 255, 0, 0, b'{"serial": "TMX-1", "sensors": [{"id": 0, '
                                         b'"kind": "quad"}, {"id": 0, "kind": "grid", "rows": 2, "cols": 2}]}'))
    interpreter.interpret(frames[0])
    assert interpreter.rejected["info_invalid"] == 0 and interpreter.board["serial"] == "TMX-1"


@pytest.mark.parametrize("entry, why", [
    ('{"id": 6, "kind": "grid", "rows": 0, "cols": 4}', "rows=0, cols=4"),
    ('{"id": 6, "kind": "grid", "rows": 16, "cols": 17}', "rows=16, cols=17"),
    ('{"id": 6, "kind": "grid", "rows": 4}', "rows=4, cols=None"),
    ('{"id": 999, "kind": "quad"}', "an id no sensor can have"),
])
def test_one_sensor_described_with_a_shape_no_grid_has_leaves_the_others_theirs(entry, why):
    """A value out of range (not a wrong JSON type, which invalidates the
    INFO: protocol.md) sets that sensor aside: the board's other sensors
    keep their shapes and their frames are read (the whole INFO was refused
    and a 4x4's every frame rejected as unknown_shape)."""
    payload = ('{"serial": "B-1", "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 4}, ' + entry + "]}").encode()
    _, sensors, undescribed = parse_info(payload)
    assert list(sensors) == [0] and sensors[0].rows == 4
    assert why in undescribed[6 if 6 in undescribed else 999]
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = feed(interpreter, info_frame(orjson.loads(payload)), encode_frame(FrameType.GRID, 0, 0, 0, bytes(64)))
    assert readings[1] is not None and readings[1].sensor.rows == 4
    assert interpreter.rejected["info_invalid"] == 0 and interpreter.info_refused is None


def test_unknown_sensor_kind_does_not_hide_the_others():
    _, sensors, _ = parse_info(b'{"sensors": [{"id": 0, "kind": "thermo"}, {"id": 1, "kind": "grid", "rows": 4, "cols": 4}]}')
    assert list(sensors) == [1] and sensors[1].rows == 4


def test_bad_info_is_counted_not_fatal():
    interpreter = Interpreter()
    feed(interpreter, encode_frame(FrameType.INFO, 255, 0, 0, b"{broken"))
    assert interpreter.rejected["info_invalid"] == 1


def test_error_frames_are_kept_as_text():
    interpreter = Interpreter()
    feed(interpreter, encode_frame(FrameType.ERROR, 255, 0, 0, b"mux settle timeout"))
    assert [text for _, text in interpreter.board_errors] == ["mux settle timeout"]


def test_a_flood_of_board_errors_is_logged_escaped_and_once_a_minute(caplog, monkeypatch):
    """A board sending a 1 KB ERROR every 5 ms wrote 370 KB/s of log, its
    control bytes (terminal escapes) verbatim: now one line a minute, escaped,
    saying how many were held back; /health keeps the last 50 as sent."""
    import service.interpreter as interpreter_module

    clock = [100.0]
    monkeypatch.setattr(interpreter_module.time, "monotonic", lambda: clock[0])
    interpreter = Interpreter()
    decoder = Decoder()
    text = b"\x1b[2J\x1b[31mFAKE: service stopped\nmux " + b"x" * 900
    with caplog.at_level("WARNING", logger="service.interpreter"):
        for k in range(400):  # 2 s at 5 ms, then one 61 s later (a replay's reads may all have one stamp)
            clock[0] = 100.0 + 0.005 * k
            for frame in decoder.feed(encode_frame(FrameType.ERROR, 255, k, k, text)):
                interpreter.interpret(frame, 0.0)
        clock[0] = 163.0
        for frame in decoder.feed(encode_frame(FrameType.ERROR, 255, 400, 400, b"mux settle timeout")):
            interpreter.interpret(frame, 0.0)
    lines = [r.getMessage() for r in caplog.records if r.getMessage().startswith("board error")]
    assert len(lines) == 2 and "\x1b" not in lines[0] and "\n" not in lines[0]
    assert lines[0].startswith("board error: \\x1b[2J\\x1b[31mFAKE: service stopped\\x0amux xxx") and lines[0].endswith("…")
    assert lines[1] == "board error: mux settle timeout (399 more since the last logged, in /health)"
    assert len(interpreter.board_errors) == 50 and interpreter.board_errors[0][1] == text.decode()
    assert interpreter.board_error_count == 401


def test_the_first_frame_after_a_board_restart_says_so_through_to_the_binary_stream():
    from service.fanout.encoding import decode_binary, to_binary
    from service.pipeline import Pipeline

    quad = bytes(np.array([5_000_000, 5_100_000, 4_900_000, 5_050_000], "<u4"))
    before = b"".join(encode_frame(FrameType.QUAD, 1, seq, 10_000_000 + 1000 * seq, quad) for seq in range(200))
    after = b"".join(encode_frame(FrameType.QUAD, 1, seq, 1000 * seq, quad) for seq in range(3))
    pipeline = Pipeline()
    frames = pipeline.feed(before + after, 0.0)
    restarted = [f for f in frames if "board_restart" in f.flags]
    assert [f.seq for f in restarted] == [0] and "seq_gap" not in restarted[0].flags
    record = decode_binary(len([restarted[0]]).to_bytes(2, "little") + to_binary(restarted[0]))[0]
    assert "board_restart" in record["flags"]


GOOD_INFO = {"board": "b", "fw": "1.1.0", "serial": "TMX-1", "rate_hz": 1000,
             "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8, "serial": "A8-2291"}, {"id": 1, "kind": "quad"}]}


def with_board(**fields):
    return {**GOOD_INFO, **fields}


def with_sensor(**fields):
    return {**GOOD_INFO, "sensors": [{**GOOD_INFO["sensors"][0], **fields}, GOOD_INFO["sensors"][1]]}


MALFORMED_INFO = {
    "sensors null": with_board(sensors=None),
    "sensors number": with_board(sensors=3),
    "sensors bool": with_board(sensors=True),
    "sensors string": with_board(sensors="grid"),
    "sensors object": with_board(sensors={"id": 0, "kind": "quad"}),
    "entry not an object": with_board(sensors=[{"id": 1, "kind": "quad"}, 7]),
    "entry a list": with_board(sensors=[[0, "quad"]]),
    "id bool": with_sensor(id=True),
    "id float": with_sensor(id=0.0),
    "id string": with_sensor(id="0"),
    "id null": with_sensor(id=None),
    "id huge": with_sensor(id=2**70),
    "kind number": with_sensor(kind=1),
    "kind null": with_sensor(kind=None),
    "kind missing": {**GOOD_INFO, "sensors": [{"id": 0, "rows": 8, "cols": 8}]},
    "rows string": with_sensor(rows="8"),
    "rows float": with_sensor(rows=8.0),
    "rows bool": with_sensor(rows=True),
    "cols bool": with_sensor(cols=True),
    "board number": with_board(board=7),
    "board null": with_board(board=None),
    "fw number": with_board(fw=1.1),
    "fw list": with_board(fw=[1, 1]),
    "serial number": with_board(serial=123),
    "serial null": with_board(serial=None),
    "rate_hz string": with_board(rate_hz="1000"),
    "rate_hz bool": with_board(rate_hz=True),
    "rate_hz zero": with_board(rate_hz=0),
    "pong string": with_board(pong="yes"),
    "sensor serial number": with_sensor(serial=2291),
    "sensor serial object": with_sensor(serial={"sn": "A8"}),
}


@pytest.mark.parametrize("doc", list(MALFORMED_INFO.values()), ids=list(MALFORMED_INFO))
def test_malformed_info_is_rejected_whole_and_counted_never_raised(doc):
    interpreter = Interpreter()
    first = {"board": "old", "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 16}]}
    feed(interpreter, info_frame(first), info_frame(doc))
    assert interpreter.rejected["info_invalid"] == 1
    assert interpreter.sensors == {0: replace(parse_info(orjson.dumps(first))[1][0], board="old")}
    assert interpreter.board_name == "old"  # named by the first valid INFO, kept
    assert (interpreter.sensors[0].rows, interpreter.sensors[0].cols) == (4, 16)
    assert interpreter.board == {"board": "old"}
    assert interpreter.info_refused  # said in /health


# Values out of range for one sensor (its types right): that sensor is set aside, the rest taken.
SENSOR_SET_ASIDE = {
    "id 255": with_sensor(id=255),
    "id negative": with_sensor(id=-1),
    "rows zero": with_sensor(rows=0),
    "cols negative": with_sensor(cols=-8),
    "rows absurd": with_sensor(rows=2**40, cols=2**40),
    "more channels than a payload holds": with_sensor(rows=16, cols=17),
    "rows missing": {**GOOD_INFO, "sensors": [{"id": 0, "kind": "grid", "cols": 8}, GOOD_INFO["sensors"][1]]},
}


@pytest.mark.parametrize("doc", list(SENSOR_SET_ASIDE.values()), ids=list(SENSOR_SET_ASIDE))
def test_a_sensor_described_out_of_range_is_set_aside_and_the_board_taken(doc):
    interpreter = Interpreter()
    first = {"board": "old", "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 16}]}
    feed(interpreter, info_frame(first), info_frame(doc))
    assert interpreter.rejected["info_invalid"] == 0 and interpreter.info_refused is None
    assert interpreter.board["serial"] == "TMX-1" and interpreter.sensors[1].kind == "quad"
    bad = doc["sensors"][0].get("id")
    assert "gives it" in interpreter.undescribed[bad]
    assert bad not in interpreter.sensors or interpreter.sensors[bad] != replace(
        parse_info(orjson.dumps(first))[1][0], board="old")


def test_well_formed_info_with_every_optional_field_is_accepted():
    interpreter = Interpreter()
    feed(interpreter, info_frame(with_board(pong=True, future={"x": [1]})))
    assert interpreter.rejected["info_invalid"] == 0
    assert sorted(interpreter.sensors) == [0, 1]


def test_serials_of_the_board_and_of_each_sensor_are_kept():
    interpreter = Interpreter()
    feed(interpreter, info_frame(GOOD_INFO))
    assert interpreter.board["serial"] == "TMX-1"
    assert interpreter.sensors[0].serial == "A8-2291"
    assert interpreter.sensors[1].serial is None  # a sensor without its own identity
    # The export format (replay goldens) does not change with the serial.
    assert interpreter.sensors[0].as_dict() == {"id": 0, "kind": "grid", "rows": 8, "cols": 8}


def test_sensors_announced_by_a_board_before_firmware_1_1_have_no_serial():
    interpreter = Interpreter()
    feed(interpreter, info_frame({"board": "b", "fw": "1.0.0", "rate_hz": 1000, "sensors": [{"id": 3, "kind": "quad"}]}))
    assert interpreter.sensors[3].serial is None and "serial" not in interpreter.board


def quad_frame(sensor, seq=0):
    return encode_frame(FrameType.QUAD, sensor, seq, 1000 * seq, bytes(np.full(4, 5_000_000, "<u4")))


def test_every_sensor_id_is_taken_without_info_as_with_it():
    """Ids 0..254 (protocol.md), before an INFO and after one that lists 5..8:
    64 unlisted sensors were taken and the rest dropped, a board of more
    sensors than its INFO can list losing their data."""
    interpreter = Interpreter()
    doc = {"board": "b", "sensors": [{"id": sid, "kind": "quad"} for sid in range(5, 9)]}
    readings = feed(interpreter, *(quad_frame(sid) for sid in range(128)), info_frame(doc),
                    *(quad_frame(sid) for sid in range(128, 255)), quad_frame(254, seq=1))
    assert [r.sensor.id if r else None for r in readings] == list(range(128)) + [None] + list(range(128, 255)) + [254]
    assert sorted(interpreter.sensors) == list(range(255)) and interpreter.unlisted == sorted(set(range(255)) - {5, 6, 7, 8})
    assert interpreter.rejected == {"info_invalid": 0, "shape_mismatch": 0, "unknown_shape": 0}


def test_a_malformed_info_costs_nothing_but_itself_in_the_read_it_arrives_in():
    from service.pipeline import Pipeline

    scans = [quad_frame(1, seq) for seq in range(6)]
    pipeline = Pipeline()
    frames = pipeline.feed(b"".join(scans[:3]) + info_frame({"sensors": None}) + b"".join(scans[3:]), 0.0)
    assert [f.seq for f in frames] == list(range(6))
    assert pipeline.interpreter.rejected["info_invalid"] == 1


def test_another_board_on_the_same_link_makes_its_serial_less_sensors_new_sensors():
    """protocol.md: a sensor without a serial is known by its board's serial
    and its id. When the INFO names another board (a swap on the same port),
    those sensors are new: tared afresh, not read against the old board's
    zero; a sensor with its own serial keeps its identity."""
    from service.reconstruct import Reconstructor

    def board_info(serial):
        return encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps({
            "board": "b", "serial": serial, "sensors": [{"id": 1, "kind": "quad"},
                                                        {"id": 2, "kind": "quad", "serial": "Q-7"}]}))

    def scans(c0_af, start, count):
        return b"".join(encode_frame(FrameType.QUAD, sid, seq, 1000 * (seq + 1), np.full(4, c0_af, "<u4").tobytes())
                        for seq in range(start, start + count) for sid in (1, 2))

    stream = board_info("BOARD-A") + scans(2_200_000, 0, 150) + board_info("BOARD-B") + scans(2_600_000, 0, 150)
    interpreter, reconstructor = Interpreter(clock=lambda: 0.0), Reconstructor(tare_frames=20)
    frames = reconstructor.process_many(interpreter.interpret_many(Decoder().feed(stream), 0.0))
    after = [f for f in frames if f.sensor.id == 1][150:]
    assert {f.sensor.board_identity for f in after} == {"BOARD-B"} and after[0].sensor.board == "BOARD-A"
    assert all("taring" in f.flags for f in after[:19]) and not any("taring" in f.flags for f in after[20:])
    assert max(abs(f.forces_N[2]) for f in after[20:]) < 0.01  # zero against B's own baseline, not A's
    own = [f for f in frames if f.sensor.id == 2][150:]
    assert {f.sensor.board_identity for f in own} == {None} and not any("taring" in f.flags for f in own)


def test_the_first_info_after_data_names_the_same_sensors_and_a_swap_drops_the_old_boards_others():
    """A service that connects to a streaming board sees data before the
    reply to its INFO?: that INFO describes the sensors it already has (no new
    tare). A later INFO of another board drops the sensors it does not list."""
    from service.reconstruct import Reconstructor

    def board_info(serial, ids):
        return encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(
            {"board": "b", "serial": serial, "sensors": [{"id": i, "kind": "quad"} for i in ids]}))

    def scans(start, count, ids=(1, 5)):
        return b"".join(encode_frame(FrameType.QUAD, sid, seq, 1000 * (seq + 1), np.full(4, 2_200_000, "<u4").tobytes())
                        for seq in range(start, start + count) for sid in ids)

    interpreter, reconstructor = Interpreter(clock=lambda: 0.0, board_name="left"), Reconstructor(tare_frames=20)
    frames = reconstructor.process_many(interpreter.interpret_many(
        Decoder().feed(scans(0, 40) + board_info("S1", (1, 5)) + scans(40, 40)), 0.0))
    assert not any("taring" in f.flags for f in frames[2 * 20:])  # one tare, at the start
    interpreter.interpret_many(Decoder().feed(board_info("S2", (1,)) + scans(0, 5, (1,))), 0.0)
    assert sorted(interpreter.sensors) == [1] and interpreter.unlisted == []
    assert interpreter.sensors[1].board_identity == "S2"

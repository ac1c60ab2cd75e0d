import numpy as np
import orjson
import pytest

from service.protocol import FLAG_SATURATED, Decoder, FrameType, encode_frame
from service.readings import Interpreter, parse_info


def feed(interpreter, *frames):
    return [interpreter.interpret(f, 0.0) for f in Decoder().feed(b"".join(frames))]


def info_frame(doc):
    return encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(doc))


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
        (b'{"sensors": [{"id": 0, "kind": "grid", "rows": 0, "cols": 8}]}', "invalid shape"),
        (b'{"sensors": [{"kind": "quad"}]}', "integer id"),
    ],
)
def test_bad_info_names_the_problem(payload, message):
    with pytest.raises(ValueError, match=message):
        parse_info(payload)


def test_unknown_sensor_kind_does_not_hide_the_others():
    _, sensors = parse_info(b'{"sensors": [{"id": 0, "kind": "thermo"}, {"id": 1, "kind": "grid", "rows": 4, "cols": 4}]}')
    assert list(sensors) == [1] and sensors[1].rows == 4


def test_bad_info_is_counted_not_fatal():
    interpreter = Interpreter()
    feed(interpreter, encode_frame(FrameType.INFO, 255, 0, 0, b"{broken"))
    assert interpreter.rejected["info_invalid"] == 1


def test_error_frames_are_kept_as_text():
    interpreter = Interpreter()
    feed(interpreter, encode_frame(FrameType.ERROR, 255, 0, 0, b"mux settle timeout"))
    assert [text for _, text in interpreter.board_errors] == ["mux settle timeout"]


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

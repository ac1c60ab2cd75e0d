"""Interpreter.interpret_many against interpret, frame by frame: the same
readings (every field, channels bit for bit, sentinels as NaN) and the same
rejections, whatever a batch mixes — INFO changing shapes mid-batch, ERROR
text, frames that do not fit, sensors the INFO does not list, open and
shorted channels, grids and quads of one payload size."""
import json
import random
from pathlib import Path

import numpy as np
import pytest

from service.protocol import Frame, FrameType, encode_frame
from service.protocol_decoder import Decoder
from service.interpreter import Interpreter
from service.readings import OPEN_SENTINEL

DATA = Path(__file__).parent / "data"


def grid(sensor, seq, values):
    return encode_frame(FrameType.GRID, sensor, seq, seq * 1000, np.asarray(values, dtype="<u4").tobytes())


def quad(sensor, seq, values):
    return encode_frame(FrameType.QUAD, sensor, seq, seq * 1000, np.asarray(values, dtype="<u4").tobytes())


def info(sensors):
    return encode_frame(FrameType.INFO, 255, 0, 0, json.dumps({"board": "b", "sensors": sensors}).encode())


def fields(reading):
    if reading is None:
        return None
    return (reading.sensor, reading.seq, reading.t_us, reading.t_host, reading.board_flags, reading.gap,
            reading.capacitance_pF.tobytes(), reading.open_channel, reading.shorted_channel, reading.board_restart)


def both(frames: list[Frame], cut: int = 7) -> tuple[list, list, Interpreter, Interpreter]:
    """Readings one frame at a time and in batches of ``cut`` frames."""
    single, many = Interpreter(clock=lambda: 0.0), Interpreter(clock=lambda: 0.0)
    one = [fields(r) for r in (single.interpret(f, 1.5) for f in frames) if r is not None]
    batched = [fields(r) for start in range(0, len(frames), cut)
               for r in many.interpret_many(frames[start:start + cut], 1.5)]
    return one, batched, single, many


def test_a_mixed_batch_reads_as_frame_by_frame():
    rng = np.random.default_rng(1)
    values = rng.integers(1, 40_000_000, size=64)
    stream = [grid(0, 1, values), quad(1, 1, [10_000_000, 0, OPEN_SENTINEL, 3]), grid(2, 1, values[:16]),
              info([{"id": 0, "kind": "grid", "rows": 4, "cols": 4}, {"id": 2, "kind": "grid", "rows": 4, "cols": 4}]),
              grid(0, 2, values), grid(0, 3, values[:16]), grid(2, 2, np.r_[values[:15], OPEN_SENTINEL]),
              encode_frame(FrameType.ERROR, 255, 0, 0, b"mux settle timeout"), quad(0, 4, [1, 2, 3, 4]),
              quad(1, 2, [5, 6, 7, 8])]
    stream += [grid(sensor, 1, np.r_[values[:63], 0]) for sensor in range(10, 20)]  # unlisted, taken as 8x8
    one, batched, single, many = both(Decoder().feed(b"".join(stream)))
    assert batched == one
    assert single.rejected == many.rejected == {"info_invalid": 0, "shape_mismatch": 2, "unknown_shape": 1}
    assert list(single.board_errors) == list(many.board_errors)
    opened = [r[7] for r in one]
    shorted = [r[8] for r in one]
    assert opened.count(True) == 2 and shorted.count(True) == 11  # the sentinels were there to find: 1 + 10 grids


@pytest.mark.parametrize("capture", sorted(DATA.glob("*.bin")), ids=lambda p: p.stem)
def test_recorded_captures_with_faults_read_as_frame_by_frame(capture):
    frames = Decoder().feed(capture.read_bytes())
    for cut in (1, 9, 64, len(frames)):
        one, batched, single, many = both(frames, cut)
        assert batched == one and single.rejected == many.rejected
    assert any(r[7] or r[8] for r in one) and len(one) > 500


def test_random_channels_with_sentinels_read_as_frame_by_frame():
    rng = random.Random(5)
    stream = []
    for seq in range(300):
        values = [rng.choice([0, OPEN_SENTINEL, rng.randrange(1, 2**32 - 1)]) for _ in range(64)]
        stream.append(grid(seq % 3, seq, values))
        stream.append(quad(3 + seq % 2, seq, values[:4]))
    one, batched, _, _ = both(Decoder().feed(b"".join(stream)), cut=16)
    assert batched == one and len(one) == 600


def test_the_pipeline_keeps_latest_history_and_rate_of_every_sensor_of_a_read():
    """Reads of 1 ms, each holding one scan of every sensor, as live: each
    sensor's rate is its frames over the time they took, its history all of
    them and its latest the last."""
    from firmware_sim.board import Board, BoardConfig
    from firmware_sim.urlhandler.protocol_sim import parse_sensors
    from service.pipeline import Pipeline

    board = Board(BoardConfig(sensors=parse_sensors("grid,quad,quad"), scene="press"))
    pipeline = Pipeline(clock=lambda: 0.0)
    pipeline.feed(board.power_up(), 0.0)
    for ms in range(1, 2501):
        pipeline.feed(board.advance(ms / 1000), ms / 1000)
    for sid in (0, 1, 2):
        assert pipeline.rates[sid].count == len(pipeline.history[sid]) == 2500
        assert abs(pipeline.rates[sid].rate_hz - 1000.0) < 1e-6
        assert pipeline.latest[sid].seq == 2499 and pipeline.latest[sid].t_host == 2.5

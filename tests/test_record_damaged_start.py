"""A recording whose first chunk is damaged replays from its first /resume
point after the damage on the calibration each sensor ran on there
(record/resume.py), not on the first one the rest of the file names (which
may have been set only later), and says so where that calibration's
document was lost with the damage."""
import io
import logging

import orjson
import pytest
from mcap.reader import make_reader

from firmware_sim.board import BoardConfig, capture
from service.calibration.book import CalibrationBook, book_from_options
from service.calibration.registry import Registry, sensor_identity
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.record.recorder import Recorder
from service.replay import replay

from .test_record_tare import by_frame, reads, recorded_forces

GRID_UPLOAD = {"sensitivity_pct_per_N": [2.0] * 64}  # %/N: table 1's taxel 27 is ~1.3, so its forces ~35 % lower
RESUMED_AT = 500  # the first /resume point after the damage: 1 s of reads, 2 ms apart


@pytest.fixture(scope="module")
def pressed():
    return capture(BoardConfig(scene="press", seed=7), 4.0)[0]


def record(path, data: bytes, uploads: dict[int, dict], calibrations=None) -> Pipeline:
    """``data`` recorded read by read at the table level (forces replay bit for bit), with {read: upload}
    set on sensor 0 before those reads."""
    pipeline = Pipeline(Reconstructor(level="table"), calibrations=calibrations)
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(data):
        if i in uploads:
            pipeline.set_calibration(pipeline.interpreter.sensors[0], uploads[i])
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    return pipeline


def damaged_copy(path):
    """``path`` with a byte of its first chunk's compressed records flipped (its first reads,
    INFO and first /calibrations lost with it)."""
    with open(path, "rb") as stream:
        first = min(make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = bytearray(path.read_bytes())
    data[first.chunk_start_offset + first.chunk_length - 20] ^= 0xFF
    out = path.with_name("damaged.mcap")
    out.write_bytes(bytes(data))
    return out


def replayed(path, registry) -> dict:
    """The export of ``path`` replayed as `tactile replay` does: with the book of its recorded calibrations."""
    out = io.BytesIO()
    replay(path, out, level="table", calibrations=book_from_options(str(registry), None, recording=path))
    return by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])


def served(path, registry) -> dict:
    """``path`` through the live path (replay --serve): its replay:// board and that board's pipeline."""
    from service.board import Board, BoardSpec
    from service.history import Histories
    from service.sources.protocol_replay import Serial

    url = f"replay://{path}?speed=max"
    board = Board(BoardSpec(url, level="table"), book_from_options(str(registry), None, recording=path), Histories())
    frames, port = [], Serial(url)
    board.pipeline.listeners.append(frames.extend)
    t = 1000.0
    while chunk := port.read(5000):
        board.pipeline.feed_reads([(chunk, t)], lambda work: work())
        t += 0.002
    return {(f.sensor.id, f.seq, f.t_us): f for f in frames}


def test_a_damaged_start_replays_on_the_calibration_in_force_at_the_resume_point_not_a_later_upload(
        tmp_path, pressed, caplog):
    """Sensor 0 ran on builtin-table1, then on an upload from read 900. The
    first chunk (with builtin-table1's /calibrations entry) is damaged: the
    replay, resumed at read 500, reconstructed reads 500–899 on the upload
    (the first entry it could read): taxel 27 ~35 % low, labelled with the
    upload. Now every frame equals the one recorded live, bit for bit, the
    label included, offline and served."""
    record(tmp_path / "run.mcap", pressed, {900: GRID_UPLOAD})
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    damaged = damaged_copy(tmp_path / "run.mcap")
    registry = tmp_path / "empty.sqlite3"
    with caplog.at_level(logging.WARNING):
        rest = replayed(damaged, registry)
    assert f"replayed from read {RESUMED_AT}, where the recording holds those then in force" in caplog.text
    before_upload = [key for key in rest if key[0] == 0 and rest[key]["calibration"] == "builtin-table1"]
    assert len(before_upload) > 700  # reads 500–899: ~0.8 s of 8×8 frames at ~1 kHz
    assert len(rest) > 3000 and rest.keys() <= live.keys()
    assert [key for key in rest if rest[key] != live[key]] == []
    pressed_27 = max(before_upload, key=lambda key: live[key]["taxels_N"][27])
    assert live[pressed_27]["taxels_N"][27] > 1.0  # the check bites where taxel 27 is loaded
    frames = served(damaged, registry)
    assert frames.keys() <= live.keys() and len(frames) > 3000
    assert [key for key, frame in frames.items() if frame.calibration != live[key]["calibration"]
            or live[key]["taxels_N" if key[0] == 0 else "fxyz_N"]
            != [None if v != v else v for v in frame.forces_N.tolist()]] == []


def test_a_calibration_in_force_whose_document_was_lost_is_said_and_never_named_on_the_frames(
        tmp_path, pressed, caplog):
    """Sensor 0 ran on a registry calibration from the start; its document is
    only in the first /calibrations entry, lost with the damaged chunk. The
    replay cannot reconstruct on it: it replays that sensor on the built-in
    calibration, its frames named so (never with the lost id, nor the
    replaying registry's active one), and a warning names the sensor and
    the lost id. The quad's frames are as recorded."""
    probe = Pipeline(Reconstructor())
    probe.feed(pressed[:20000], 1000.0)
    identity = sensor_identity(probe.interpreter.board, probe.interpreter.sensors[0])
    own = probe.reconstructor.set_calibration(probe.interpreter.sensors[0], GRID_UPLOAD, identity)
    with Registry(tmp_path / "recorded.sqlite3") as registry:
        registry.add(own, activate=True)
    other = probe.reconstructor.set_calibration(probe.interpreter.sensors[0], {"sensitivity_pct_per_N": [1.5] * 64},
                                                identity)
    with Registry(tmp_path / "replaying.sqlite3") as registry:  # another machine's: another calibration active
        registry.add(other, activate=True)
    record(tmp_path / "run.mcap", pressed, {}, CalibrationBook(tmp_path / "recorded.sqlite3"))
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    assert {doc["calibration"] for key, doc in live.items() if key[0] == 0} == {own["id"]}
    with caplog.at_level(logging.WARNING):
        rest = replayed(damaged_copy(tmp_path / "run.mcap"), tmp_path / "replaying.sqlite3")
    address = f"{probe.interpreter.name}/0"
    assert f"sensor {address} ran on calibration {own['id']} at read {RESUMED_AT}" in caplog.text
    assert {doc["calibration"] for key, doc in rest.items() if key[0] == 0} == {"builtin-table1"}
    assert all(value is not None for key, doc in rest.items() if key[0] == 0 for value in doc["taxels_N"])
    assert [key for key in rest if key[0] == 1 and rest[key] != live[key]] == []


def test_a_damaged_chunk_is_said_once_however_often_the_replay_reads_the_file(tmp_path, pressed, caplog):
    """A replay reads a recording's file once per kind of message (raw reads, tares, zeros, settings,
    /resume points, …): its damaged first chunk was said 6 times by one `tactile replay`, and again
    by each pass of a served one. Now once, its resume point once."""
    record(tmp_path / "run.mcap", pressed, {})
    damaged = damaged_copy(tmp_path / "run.mcap")
    registry = tmp_path / "empty.sqlite3"
    with caplog.at_level(logging.WARNING):
        replayed(damaged, registry)
        served(damaged, registry)
    messages = [record.getMessage() for record in caplog.records]
    assert sum("is damaged" in message for message in messages) == 1
    assert sum(f"replayed from read {RESUMED_AT}" in message for message in messages) == 1

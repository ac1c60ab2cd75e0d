"""A calibration set while recording (an upload, PUT /sensors/…/calibration)
is recorded where it took effect, and a replay — offline or served through
the live path — sets it there again: its forces equal the recorded ones
after the upload too, where before it kept the first calibration and warned."""
import io
import logging

import orjson
import pytest

from firmware_sim.board import BoardConfig, capture
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.record.mcap_reader import read_changes
from service.record.recorder import Recorder
from service.replay import replay

from .test_record_tare import by_frame, reads, recorded_forces, served_forces

QUAD_FITS = {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]}
GRID_UPLOAD = {"sensitivity_pct_per_N": [1.1 + 0.004 * k for k in range(64)]}


@pytest.fixture(scope="module")
def pressed():
    return capture(BoardConfig(scene="press", seed=7), 4.0)[0]


def record_with_uploads(path, data: bytes, uploads: dict[int, tuple[int, dict]]) -> Pipeline:
    """``data`` recorded read by read, with {read: (sensor id, upload)} set before those reads."""
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(data):
        if i in uploads:
            sensor, upload = uploads[i]
            pipeline.set_calibration(pipeline.interpreter.sensors[sensor], upload)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    return pipeline


def replayed(path) -> dict:
    out = io.BytesIO()
    replay(path, out)
    return by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])


def test_calibrations_set_while_recording_are_set_again_by_the_replay(tmp_path, pressed, caplog):
    record_with_uploads(tmp_path / "run.mcap", pressed, {400: (1, QUAD_FITS), 600: (0, GRID_UPLOAD)})
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    ids = {(d["sensor"], d["calibration"]) for d in live.values()}
    assert len(ids) == 4  # each sensor on its built-in calibration, then on its upload
    with caplog.at_level(logging.WARNING):
        again = replayed(tmp_path / "run.mcap")
    assert again == live
    assert "changed calibration while recording" not in caplog.text


def test_without_the_calibrations_set_the_replay_would_differ(tmp_path, pressed, monkeypatch):
    """The check above is not vacuous: the uploads change the forces after them."""
    record_with_uploads(tmp_path / "run.mcap", pressed, {400: (1, QUAD_FITS), 600: (0, GRID_UPLOAD)})
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    tares_only = {board: [c for c in made if not isinstance(c[2], dict)]
                  for board, made in read_changes(tmp_path / "run.mcap").items()}
    monkeypatch.setattr("service.replay.read_changes", lambda path: tares_only)
    again = replayed(tmp_path / "run.mcap")
    assert again.keys() == live.keys()
    differing = [key for key in live if live[key] != again[key]]
    assert len(differing) > 500 and {key[0] for key in differing} == {0, 1}


def test_a_calibration_set_applies_from_the_read_it_was_set_before(tmp_path, pressed):
    """Recorded with the read count of the recording: the upload before read 400
    (counted from the first recorded read) is placed there, with its document."""
    record_with_uploads(tmp_path / "run.mcap", pressed, {400: (1, QUAD_FITS)})
    (after_reads, sensor, document), = read_changes(tmp_path / "run.mcap")[None]
    assert (after_reads, sensor) == (400, 1)
    assert document["normal_fit"] == QUAD_FITS["normal_fit"] and document["kind"] == "quad"
    first_new = min(seq for (sid, seq, _), d in by_frame(recorded_forces(tmp_path / "run.mcap")).items()
                    if sid == 1 and d["calibration"] == document["id"])
    assert first_new > 0


@pytest.mark.parametrize("read_size, merge", [(64, 1), (5000, 1), (700, 3)])
def test_a_recording_served_through_the_live_path_sets_its_calibrations_again(tmp_path, pressed, read_size, merge):
    """tactile replay --serve (replay://): however the port cuts the bytes."""
    record_with_uploads(tmp_path / "run.mcap", pressed, {300: (0, GRID_UPLOAD), 700: (1, QUAD_FITS)})
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    served = served_forces(tmp_path / "run.mcap", read_size, merge=merge)
    assert served.keys() == live.keys()
    assert [key for key, doc in live.items()
            if doc.get("taxels_N", doc.get("fxyz_N")) != [None if v != v else v for v in served[key].forces_N.tolist()]
            or doc["calibration"] != served[key].calibration] == []
    unscheduled = served_forces(tmp_path / "run.mcap", read_size, schedule=False, merge=merge)
    assert sum(live[key]["calibration"] != unscheduled[key].calibration for key in live) > 500


def test_a_recording_of_a_replay_records_the_calibrations_it_sets_again(tmp_path, pressed):
    from service.sources.protocol_replay import Serial, recorded_changes

    record_with_uploads(tmp_path / "run.mcap", pressed, {400: (1, QUAD_FITS)})
    url = f"replay://{tmp_path / 'run.mcap'}?speed=max"
    served = Pipeline(Reconstructor())
    served.schedule_recorded(recorded_changes(url))
    recorder = Recorder(tmp_path / "second.mcap")
    recorder.attach(served)
    port = Serial(url)
    try:
        t = 1000.0
        while chunk := port.read(3000):
            served.feed_reads([(chunk, t)], lambda work: work())
            t += 0.002
    finally:
        port.close()
    recorder.stop()
    (_, sensor, document), = read_changes(tmp_path / "second.mcap")[None]
    assert sensor == 1 and document["normal_fit"] == QUAD_FITS["normal_fit"]
    assert by_frame(recorded_forces(tmp_path / "second.mcap")) == by_frame(recorded_forces(tmp_path / "run.mcap"))


def test_a_calibration_that_no_longer_fits_is_said_and_skipped(pressed, caplog):
    """A recorded grid calibration set again on a sensor the bytes describe
    as a quad (a recording edited, or replayed against other bytes): the
    replay says so, keeps the quad's calibration and its data."""
    pipeline = Pipeline(Reconstructor())
    pipeline.feed(pressed[:20000], 1000.0)
    grid = pipeline.set_calibration(pipeline.interpreter.sensors[0], GRID_UPLOAD)
    before = pipeline.reconstructor.calibration(1).id
    with caplog.at_level(logging.WARNING, logger="service.pipeline"):
        pipeline.redo(1, grid)
        pipeline.redo(9, grid)
    assert f"sensor 1: the calibration {grid['id']} set while recording cannot be set again (" in caplog.text
    assert f"sensor 9: the calibration {grid['id']} set while recording cannot be set again (no such sensor" in caplog.text
    frames = pipeline.feed(pressed[20000:40000], 1001.0)
    assert pipeline.reconstructor.calibration(1).id == before and {f.sensor.id for f in frames} == {0, 1}


def recorded_with_a_bad_calibration_set(path, data: bytes) -> dict:
    """``data`` recorded with no upload, but a /calibration_set of sensor 0 before read 300 whose
    document the service cannot use ("mounting": [1.0, 2.0], id of its content, as a hand-edited
    recording has); the recording's own forces, by frame (none of them made with it)."""
    from service.reconstruct.sensor_calibration import calibration_id

    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(data):
        if i == 300:
            good = pipeline.reconstructor.prepare_calibration(pipeline.interpreter.sensors[0], GRID_UPLOAD)[2]
            bad = {**{k: v for k, v in good.items() if k != "id"}, "mounting": [1.0, 2.0]}
            for listener in pipeline.calibration_listeners:
                listener(i, 0, {**bad, "id": calibration_id(bad)})  # before read i, as an upload is
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    assert [(s, d["mounting"]) for _, s, d in read_changes(path)[None]] == [(0, [1.0, 2.0])]
    return by_frame(recorded_forces(path))


def test_a_recorded_calibration_the_service_cannot_use_is_skipped_and_the_replay_goes_on(tmp_path, pressed, caplog):
    """It was a TypeError (unhashable list) that ended the replay: tactile replay --export left 334 of
    2326 lines and exited 1; now the replay says so and gives every frame as recorded."""
    live = recorded_with_a_bad_calibration_set(tmp_path / "run.mcap", pressed)
    with caplog.at_level(logging.WARNING, logger="service.pipeline"):
        again = replayed(tmp_path / "run.mcap")
    assert again == live and len(live) > 1500
    assert "sensor 0: the calibration " in caplog.text
    assert "(mounting: [1.0, 2.0] is not one of flat, curved); kept the one in use" in caplog.text


def test_a_recorded_calibration_the_service_cannot_use_is_skipped_when_served(tmp_path, pressed):
    """tactile replay --serve: the error ended LoopHandover.drain, losing the reads it held."""
    live = recorded_with_a_bad_calibration_set(tmp_path / "run.mcap", pressed)
    served = served_forces(tmp_path / "run.mcap", 700, merge=3)
    assert served.keys() == live.keys()
    assert [key for key, doc in live.items()
            if doc.get("taxels_N", doc.get("fxyz_N")) != [None if v != v else v for v in served[key].forces_N.tolist()]
            or doc["calibration"] != served[key].calibration] == []


def test_a_recorded_calibration_that_fails_past_the_checks_is_skipped_too(pressed, caplog, monkeypatch):
    """A recording is any file: whatever a recorded document raises where it is prepared (here a
    TypeError, as the list mounting raised before it was checked) skips it, never the replay."""
    pipeline = Pipeline(Reconstructor())
    pipeline.feed(pressed[:20000], 1000.0)
    document = pipeline.set_calibration(pipeline.interpreter.sensors[0], GRID_UPLOAD)

    def unforeseen(*args):
        raise TypeError("unhashable type: 'list'")

    monkeypatch.setattr(pipeline.reconstructor, "prepare_calibration", unforeseen)
    with caplog.at_level(logging.WARNING, logger="service.pipeline"):
        pipeline.redo(0, {**document, "id": "edited"})
    assert ("sensor 0: the calibration edited set while recording cannot be set again (TypeError: unhashable type: "
            "'list'); kept the one in use") in caplog.text
    frames = pipeline.feed(pressed[20000:40000], 1001.0)
    assert pipeline.reconstructor.calibration(0).id == document["id"] and {f.sensor.id for f in frames} == {0, 1}

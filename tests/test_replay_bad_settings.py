"""A recording is any file: a recorded /settings whose mounting is a list,
or a /calibration_set whose document is a list, is said and skipped, the
replay made as the rest of the recording says. Before, the list mounting
raised TypeError (unhashable) in ``tactile replay`` before any frame, and
the list document was taken for a tare (the replay tared under the press)."""
import logging

import orjson
import pytest

from firmware_sim.board import BoardConfig, capture
from service.cli import main
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.record.mcap_reader import read_changes, read_settings
from service.record.recorder import Recorder

from .test_record_tare import by_frame, reads, recorded_forces
from .test_replay_holds import rewritten

SET_AT = 150  # the read the list document is recorded before: mid-press


@pytest.fixture(scope="module")
def pressed():
    return capture(BoardConfig(scene="press", seed=7), 1.5)[0]


def record(path, data: bytes, document=None) -> dict:
    """``data`` recorded read by read (flat, the defaults), with ``document``
    as a /calibration_set of sensor 0 before read SET_AT if given; the
    recording's own forces, by frame."""
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(data):
        if i == SET_AT and document is not None:
            for listener in pipeline.calibration_listeners:
                listener(i, 0, document)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    return by_frame(recorded_forces(path))


def exported(path, out) -> dict:
    """``tactile replay PATH --export OUT``'s frames, by frame (exit 0 asserted)."""
    assert main(["replay", str(path), "--export", str(out)]) == 0
    return by_frame([orjson.loads(line) for line in out.read_bytes().splitlines()])


def test_a_recorded_mounting_that_is_a_list_is_said_and_the_default_used(tmp_path, pressed, caplog, monkeypatch):
    live = record(tmp_path / "run.mcap", pressed)
    rewritten(tmp_path / "run.mcap", tmp_path / "edited.mcap", lambda doc: doc | {"mounting": ["flat"]},
              topics=("/settings",))
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        settings = read_settings(tmp_path / "edited.mcap")
    assert settings[None]["level"] == "full" and "mounting" not in settings[None]
    assert "recorded /settings' mounting ['flat'] is not one of flat, curved: skipped" in caplog.text
    again = exported(tmp_path / "edited.mcap", tmp_path / "out.jsonl")
    assert again == live and len(live) > 500  # recorded flat: the default mounting gives its forces
    served = []  # tactile replay --serve's boards, taken where the service would start
    monkeypatch.setattr("service.cli_recordings.cmd_serve", lambda args: served.extend(args.board_specs) or 0)
    assert main(["replay", str(tmp_path / "edited.mcap"), "--serve"]) == 0
    assert [(spec.level, spec.mounting) for spec in served] == [("full", "flat")]


def test_a_recorded_calibration_set_that_is_no_object_is_said_and_skipped(tmp_path, pressed, caplog):
    live = record(tmp_path / "run.mcap", pressed, [1.0, 2.0])
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        assert read_changes(tmp_path / "run.mcap") == {}
    assert f"/calibration_set of sensor 0 before read {SET_AT}: its document [1.0, 2.0] is no object: skipped" in caplog.text
    again = exported(tmp_path / "run.mcap", tmp_path / "out.jsonl")
    assert again == live and len(live) > 500  # no tare made of it: the press read as recorded

"""A board of more sensors than its INFO can list (protocol.md: ids 0..254, an
INFO payload of at most 1024 bytes, ~33 spaced quad entries): every sensor's
frames are served, and /health says once, as a note, how many sensors were
taken from their data frames, not once per sensor as a problem."""
import json
import time

import numpy as np
from fastapi.testclient import TestClient

from service.api.app import create_app
from service.history import Histories
from service.live_service import TactileService
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.protocol_decoder import Decoder

QUAD = np.full(4, 2_200_000, "<u4").tobytes()


def full_info(count: int) -> tuple[bytes, int]:
    """(an INFO payload of a board of ``count`` quads that lists as many as 1024 bytes hold, as a board's
    json.dumps spaces them, how many it lists)."""
    doc = {"board": "tmux-many", "fw": "1.0.0", "rate_hz": 20, "serial": "MANY-1",
           "sensors": [{"id": sid, "kind": "quad"} for sid in range(count)]}
    listed = count
    while len(json.dumps({**doc, "sensors": doc["sensors"][:listed]}).encode()) > 1024:
        listed -= 1
    return json.dumps({**doc, "sensors": doc["sensors"][:listed]}).encode(), listed


def test_a_board_of_120_quads_whose_info_lists_33_serves_all_120_and_notes_it_once():
    payload, listed = full_info(120)
    assert listed == 33 and 1024 - len(payload) < len(', {"id": 33, "kind": "quad"}')  # no room for a 34th
    service = TactileService("sim://")
    scans = b"".join(encode_frame(FrameType.QUAD, sid, s, 50_000 * (s + 1), QUAD) for s in range(5) for sid in range(120))
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, payload) + scans, time.time())
    client = TestClient(create_app(service), base_url="http://localhost")  # no lifespan: the service stays unstarted
    report = client.get("/health").json()  # within the second a 20 Hz sensor takes to be stale
    assert len(report["sensors"]) == 120 and all(s["frames"] == 5 for s in report["sensors"].values())
    assert sum(report["rejected"].values()) == 0
    assert not [p for p in report["problems"] if "sensor" in p]  # (the link itself is down: never started)
    assert report["notes"] == report["boards"]["MANY-1"]["notes"] == [
        f"the board's INFO is full ({len(payload)} of 1024 bytes, listing {listed} sensors): {120 - listed} more "
        "sensors were taken from their data frames (a QUAD frame is a quad, a 256-byte GRID frame an 8x8 grid)"]
    for sid in range(120):
        reply = client.get(f"/sensors/{sid}/latest")
        assert reply.status_code == 200 and reply.json()["header"]["seq"] == 4


def test_every_id_the_protocol_allows_is_taken_without_info_and_history_stays_within_its_budget():
    """255 sensors (a grid and a quad alternately), no INFO: all are read, where 64 were and the rest
    dropped. An 8x8 grid's kept frame is 1400 bytes (4 stamps of 8, 64 forces of 8 and σ of 4, 64 raw of 8,
    64 taxel flags of 1, 3 references of 8), a quad's 124 (its 3 outputs, 4 raw, no taxel flags): with a
    budget of 6 grid frames a sensor, each keeps budget // 255 of them, none is dropped."""
    grid_frame, quad_frame = 4 * 8 + 12 * 64 + 8 * 64 + 64 + 3 * 8, 4 * 8 + 12 * 3 + 8 * 4 + 3 * 8
    budget = 255 * 6 * grid_frame
    pipeline = Pipeline(histories=Histories(budget_bytes=budget))
    grid = np.full(64, 10_000_000, "<u4").tobytes()
    scans = b"".join(encode_frame(FrameType.GRID, sid, s, 1000 * (s + 1), grid) if sid % 2 == 0 else
                     encode_frame(FrameType.QUAD, sid, s, 1000 * (s + 1), QUAD) for s in range(8) for sid in range(255))
    pipeline.feed(scans, time.time())
    assert sorted(pipeline.latest) == list(range(255)) and sum(pipeline.interpreter.rejected.values()) == 0
    share = budget // 255
    assert {sid: len(h) for sid, h in pipeline.history.items()} == {
        sid: min(8, share // (grid_frame if sid % 2 == 0 else quad_frame)) for sid in range(255)}
    assert pipeline.history.bytes <= budget


def test_a_recording_begun_mid_stream_keeps_that_the_info_was_full():
    """A replay takes the INFO in force from the recording's document, whose JSON is not the board's: its
    size (999 bytes, 33 entries) goes with it, and stays out of the board's fields."""
    from service.interpreter import Interpreter

    payload, listed = full_info(120)
    live = Interpreter()
    live.interpret_many(Decoder().feed(encode_frame(FrameType.INFO, 255, 0, 0, payload)), 0.0)
    replayed = Interpreter()
    replayed.preset_info(json_roundtrip(live.info_document()))
    assert live.info_full and replayed.info_full and replayed.info_size == (len(payload), listed) == (999, 33)
    assert replayed.board == {"board": "tmux-many", "fw": "1.0.0", "rate_hz": 20, "serial": "MANY-1"}
    small = Interpreter()
    small.interpret_many(Decoder().feed(encode_frame(FrameType.INFO, 255, 0, 0, b'{"board": "b", "sensors": []}')), 0.0)
    assert not small.info_full  # 1000 bytes of room


def json_roundtrip(document: dict) -> dict:
    """The document as a recording stores and reads it back (JSON)."""
    return json.loads(json.dumps(document))

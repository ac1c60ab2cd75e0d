"""Recording to MCAP and replaying it: round trips, crash safety, errors, pacing."""
import io
import logging
import math
import os
import time

import orjson
import pytest
from fastapi.testclient import TestClient

from firmware_sim.board import BoardConfig, capture
from service.api.app import create_app
from service.pipeline import Pipeline
from service.protocol_decoder import Decoder
from service.reconstruct import Reconstructor
from service.record.mcap_reader import iter_messages, read_raw, summary
from service.record.recorder import Recorder
from service.record.pacing import MAX_SLEEP_S, MIN_SPEED
from service.replay import Pacer, replay
from service.live_service import TactileService


def live_recording(tmp_path, seconds=1.5, scene="press"):
    """Feed a capture through a live pipeline in irregular reads, recording it."""
    data, _ = capture(BoardConfig(scene=scene, seed=4), seconds)
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap", tmp_path / "run.bin")
    recorder.attach(pipeline)
    live, pos, t = [], 0, 1000.0
    sizes = [1, 700, 3000, 31, 4096, 17]
    i = 0
    while pos < len(data):
        chunk = data[pos : pos + sizes[i % len(sizes)]]
        live += pipeline.feed(chunk, t)
        pos += len(chunk)
        t += 0.002
        i += 1
    status = recorder.stop()
    return data, live, status, tmp_path / "run.mcap", tmp_path / "run.bin"


def test_record_then_replay_is_bit_for_bit(tmp_path):
    data, live, status, mcap_path, raw_path = live_recording(tmp_path)
    assert status["error"] is None and status["bytes_in"] == len(data)
    assert raw_path.read_bytes() == data
    assert b"".join(chunk for _, chunk in read_raw(mcap_path)) == data
    # The frames decoded from the recording are the frames decoded live.
    decoded = Decoder().feed(b"".join(chunk for _, chunk in read_raw(mcap_path)))
    assert [(f.sensor, f.seq, f.t_us, f.payload) for f in decoded] == [(f.sensor, f.seq, f.t_us, f.payload) for f in Decoder().feed(data)]
    # Replaying gives the forces recorded live, bit for bit (after the tare window,
    # which live reports as null and a replay fills in).
    out = io.BytesIO()
    replay(mcap_path, out)
    replayed = {(d["sensor"], d["seq"]): d for d in map(orjson.loads, out.getvalue().splitlines())}
    recorded = [orjson.loads(m.data) for topic, m in iter_messages(mcap_path) if topic.endswith("/forces")]
    assert len(recorded) == len(live) == len(replayed)
    compared = 0
    for doc in recorded:
        if "taring" not in doc["flags"]:
            assert replayed[(doc["sensor"], doc["seq"])] == doc
            compared += 1
    assert compared > 0.8 * len(recorded)


def test_every_file_written_opens_in_the_mcap_reader(tmp_path):
    *_, mcap_path, _ = live_recording(tmp_path, seconds=1.2)
    counts = summary(mcap_path)
    assert counts["/sensor/0/forces"] == counts["/sensor/0/raw"] == counts["/sensor/0/grid"] == 1200
    assert counts["/sensor/1/forces"] == 1200 and "/sensor/1/grid" not in counts
    assert counts["/diagnostics"] >= 1
    grid = next(orjson.loads(m.data) for t, m in iter_messages(mcap_path) if t == "/sensor/0/grid")
    assert grid["column_count"] == 8 and grid["cell_stride"] == 4 and grid["fields"][0]["type"] == 7


def test_the_recorder_counts_the_messages_the_file_holds(tmp_path):
    *_, status, mcap_path, _ = live_recording(tmp_path, seconds=1.0)
    assert status["messages"] == sum(summary(mcap_path).values())  # a quad frame is 2 messages, a grid frame 3


def test_diagnostics_carry_what_their_schema_declares(tmp_path):
    from service.record import schemas

    *_, mcap_path, _ = live_recording(tmp_path, seconds=2.5)  # reads 2 ms apart: one snapshot per 500 reads
    docs = [orjson.loads(m.data) for t, m in iter_messages(mcap_path) if t == "/diagnostics"]
    declared = set(schemas.DIAGNOSTICS["properties"])
    assert docs and all(set(doc) == declared for doc in docs)
    last = docs[-1]
    assert last["counters"]["crc_errors"] == 0 and last["counters"]["sensors"]["0"]["frames"] > 900
    assert last["rejected"] == {"info_invalid": 0, "shape_mismatch": 0, "unknown_shape": 0}


def test_a_crash_leaves_the_file_readable_up_to_the_last_chunk(tmp_path, caplog):
    *_, mcap_path, _ = live_recording(tmp_path, seconds=2.0)
    whole = sum(1 for _ in iter_messages(mcap_path))
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(mcap_path.read_bytes()[: int(0.6 * mcap_path.stat().st_size)])
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        survived = sum(1 for _ in iter_messages(cut))
    assert 0.3 * whole < survived < whole
    assert "cut.mcap cannot be read past byte" in caplog.text  # a replay of it says it is incomplete
    chunks = list(read_raw(cut))
    assert chunks and all(isinstance(c, bytes) for _, c in chunks)


def test_a_complete_recording_is_read_through_its_index_as_the_stream_reads_it(tmp_path):
    from service.record import mcap_reader

    *_, mcap_path, _ = live_recording(tmp_path, seconds=1.0)
    streamed = [(topic, m.channel_id, m.log_time, m.data) for topic, m in mcap_reader._messages(mcap_path, None)]
    indexed = [(topic, m.channel_id, m.log_time, m.data) for topic, m in iter_messages(mcap_path)]
    assert indexed == streamed and len({topic for topic, *_ in streamed}) >= 4
    raw = [entry for entry in streamed if entry[0] == "/raw"]
    assert [(t, chunk) for _, t, chunk in mcap_reader.read_boards(mcap_path)] == \
        [mcap_reader._raw_chunk(m) for topic, m in mcap_reader._messages(mcap_path, {"/raw"})] and len(raw) > 100


def test_a_damaged_chunk_loses_its_messages_only(tmp_path, caplog):
    from mcap.reader import make_reader

    *_, mcap_path, _ = live_recording(tmp_path, seconds=1.5)
    with open(mcap_path, "rb") as stream:
        chunks = sorted(make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 3
    middle = chunks[len(chunks) // 2]
    data = bytearray(mcap_path.read_bytes())
    data[middle.chunk_start_offset + middle.chunk_length - 20] ^= 0xFF  # inside its compressed records
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    whole = list(read_raw(mcap_path))
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        kept = list(read_raw(damaged))
    assert f"chunk at byte {middle.chunk_start_offset} (or its index) is damaged" in caplog.text
    assert 0 < len(whole) - len(kept) < len(whole) / 2
    assert set(kept) < set(whole)


def test_recordings_without_message_indexes_or_with_a_damaged_one_are_read_whole_but_that(tmp_path, caplog):
    """Message indexes are optional in MCAP: a file without them is read as a
    stream; a damaged index loses its chunk's messages only; read numbers
    stay the recorded ones (a tare's position does not move)."""
    import base64

    from mcap.reader import make_reader
    from mcap.writer import CompressionType, IndexType, Writer

    from service.record import mcap_reader

    def write(path, **options):
        with open(path, "wb") as stream:
            writer = Writer(stream, chunk_size=200, compression=CompressionType.NONE, **options)
            writer.start()
            schema = writer.register_schema("s", "jsonschema", b"{}")
            a, b = (writer.register_channel(f"/{name}/raw", "json", schema) for name in "ab")
            numbers = {a: 0, b: 0}
            for i in range(40):
                channel = a if i % 3 else b
                writer.add_message(channel, 1000 + i, orjson.dumps({"t_host": float(i), "data": base64.b64encode(bytes([i])).decode()}),
                                   0, numbers[channel])
                numbers[channel] += 1
            writer.finish()

    whole = tmp_path / "whole.mcap"
    write(whole)
    streamed = [(board, t, data) for board, t, data in
                ((mcap_reader.raw_board(topic), *mcap_reader._raw_chunk(m)) for topic, m in mcap_reader._messages(whole, None))]
    assert list(mcap_reader.read_boards(whole)) == streamed and len(streamed) == 40
    write(tmp_path / "no-index.mcap", index_types=IndexType.CHUNK)
    assert list(mcap_reader.read_boards(tmp_path / "no-index.mcap")) == streamed
    with open(whole, "rb") as stream:
        second = sorted(make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)[1]
    damaged = bytearray(whole.read_bytes())
    offset = next(iter(second.message_index_offsets.values()))
    damaged[offset + 11 : offset + 15] = b"\xff\xff\xff\x7f"  # a message index claiming 2 GB of entries
    (tmp_path / "damaged.mcap").write_bytes(bytes(damaged))
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        kept = list(mcap_reader.read_numbered(tmp_path / "damaged.mcap"))
    assert f"chunk at byte {second.chunk_start_offset} (or its index) is damaged" in caplog.text
    assert 0 < len(kept) < 40
    numbered = {(board, number): data for board, number, _, data in mcap_reader.read_numbered(whole)}
    assert all(numbered[(board, number)] == data for board, number, _, data in kept)  # numbers not shifted


def test_write_errors_are_reported(tmp_path):
    with pytest.raises(FileNotFoundError):
        Recorder(tmp_path / "missing" / "run.mcap")
    with pytest.raises(ValueError, match="must end in .mcap"):
        Recorder(tmp_path / "run.json")
    full = tmp_path / "full.mcap"
    os.symlink("/dev/full", full)
    recorder = Recorder(full)
    pipeline = Pipeline(Reconstructor())
    recorder.attach(pipeline)
    for _ in range(300):
        for listener in pipeline.byte_listeners:
            listener(b"x" * 4096, time.time())
    status = recorder.stop()
    assert status["error"] and "No space left" in status["error"] and not status["active"]


def test_pacer_follows_recorded_time_at_any_speed():
    now = [0.0]
    slept = []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    pacer = Pacer(2.0, clock=lambda: now[0], sleep=sleep)
    for t in (10.0, 10.5, 11.0, 11.0, 13.0):
        pacer.wait(t)
    assert slept == pytest.approx([0.25, 0.25, 1.0])
    with pytest.raises(ValueError, match="speed must be > 0"):
        Pacer(0)
    assert Pacer(math.inf, sleep=lambda dt: pytest.fail("max speed never sleeps")).wait(5.0) is None


def test_a_wait_longer_than_time_sleep_takes_is_slept_in_pieces():
    """An 11-day recording at the slowest speed waits 9.5e9 s, past time.sleep's 2**63 ns (OverflowError):
    slept in pieces of MAX_SLEEP_S, the whole wait, ending on time."""
    now, slept = [0.0], []

    def sleep(dt):
        if dt * 1e9 > 2**63:
            raise OverflowError("timestamp too large to convert to C _PyTime_t")
        slept.append(dt)
        now[0] += dt

    pacer = Pacer(MIN_SPEED, clock=lambda: now[0], sleep=sleep)
    pacer.wait(0.0)
    pacer.wait(11 * 86400.0)
    assert max(slept) == MAX_SLEEP_S and sum(slept) == pytest.approx(11 * 86400.0 / MIN_SPEED)
    assert now[0] == pytest.approx(11 * 86400.0 / MIN_SPEED)


def test_replay_served_through_the_live_api(tmp_path):
    *_, mcap_path, _ = live_recording(tmp_path, seconds=1.5)
    service = TactileService(f"replay://{mcap_path}?speed=max")
    with TestClient(create_app(service), base_url="http://localhost") as client:
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and service.pipeline.decoder.counters.frames < 3000:
            time.sleep(0.02)
        health = client.get("/health").json()
        assert health["replay"] is True and health["link"]["source"].startswith("replay://")
        assert health["sensors"]["0"]["frames"] == 1500
        assert client.get("/sensors/0/latest").json()["header"]["seq"] == 1499


def test_a_recording_made_through_the_api_is_served_again(tmp_path):
    """POST /record/start (the dashboard's Record) records the board's INFO
    with its zeros (/baselines); serving that recording (replay --serve,
    serve --source replay://) crashed building the service (its board named
    itself from that INFO before the service held its boards). Served, it
    gives every frame recorded, under the board's recorded name, the last
    not taring (it starts from the recorded zeros)."""
    live = TactileService("sim://?scene=press&rate=200", recordings_dir=tmp_path)
    with TestClient(create_app(live), base_url="http://localhost") as client:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and len(live.pipeline.latest) < 2:
            time.sleep(0.02)
        assert client.post("/record/start", json={"name": "api.mcap"}).status_code == 200
        time.sleep(0.5)
        assert client.post("/record/stop").json()["error"] is None
    # What serving it must give: every frame of the recorded bytes (the recorded forces may lack the last
    # read's, reconstructed after the stop).
    recorded = {}
    for frame in Decoder().feed(b"".join(chunk for _, chunk in read_raw(tmp_path / "api.mcap"))):
        recorded.setdefault(frame.sensor, []).append(frame.seq)
    board = next(orjson.loads(m.data)["board"] for topic, m in iter_messages(tmp_path / "api.mcap")
                 if topic == "/baselines")
    assert len(recorded[0]) > 20  # 0.5 s at 200 Hz: ~100, fewer on a loaded machine
    service = TactileService(f"replay://{tmp_path / 'api.mcap'}?speed=max")
    assert service.primary.name == board
    with TestClient(create_app(service), base_url="http://localhost") as client:
        def served():
            sensors = client.get("/health").json()["sensors"]
            return {sid: sensors.get(str(sid), {}).get("frames") for sid in recorded}

        deadline = time.monotonic() + 20  # a loaded machine's worst; done in well under a second
        while time.monotonic() < deadline and served() != {sid: len(seqs) for sid, seqs in recorded.items()}:
            time.sleep(0.05)
        assert served() == {sid: len(seqs) for sid, seqs in recorded.items()}
        latest = client.get("/sensors/0/latest").json()
        assert latest["header"]["seq"] == recorded[0][-1] and "taring" not in latest["flags"]


def test_record_from_the_api_into_the_recordings_directory_only(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious")
    service = TactileService("sim://?scene=press", recordings_dir=tmp_path / "recordings")
    with TestClient(create_app(service), base_url="http://localhost") as client:
        assert client.post("/record/stop").status_code == 409
        for body in ({"path": str(victim)}, {"name": str(victim)}, {"name": "../victim.mcap"}, {"name": ".hidden.mcap"},
                     {"name": "run.txt"}, {"raw_path": str(victim)}, {"name": "x:y.mcap"}, {"name": "a\\b.mcap"},
                     {"name": "run\x00.mcap"}, {"name": "é" * 130 + ".mcap"}, {"name": "CON .mcap"}):
            refused = client.post("/record/start", json=body)
            assert refused.status_code == 422, body
        assert victim.read_text() == "precious" and not (tmp_path / "victim.mcap").exists()
        started = client.post("/record/start", json={"name": "api.mcap"})
        assert started.status_code == 200 and started.json()["active"]
        assert started.json()["path"] == str(tmp_path / "recordings" / "api.mcap")
        assert started.json()["raw_path"] == str(tmp_path / "recordings" / "api.bin")
        assert client.post("/record/start", json={"name": "b.mcap"}).status_code == 409  # already recording
        assert client.get("/record").json()["path"] == started.json()["path"]
        time.sleep(0.5)
        stopped = client.post("/record/stop").json()
        assert stopped["error"] is None and stopped["messages"] > 100
        again = client.post("/record/start", json={"name": "api.mcap"})
        assert again.status_code == 409 and "exists" in again.json()["detail"]  # never overwritten
        default = client.post("/record/start")
        assert default.status_code == 200 and default.json()["path"].startswith(str(tmp_path / "recordings" / "recording-"))
        client.post("/record/stop")
    assert summary(tmp_path / "recordings" / "api.mcap")["/raw"] > 10


def test_a_file_that_is_no_recording_is_refused_by_name(tmp_path):
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(bytes(range(100)))
    with pytest.raises(ValueError, match="junk.mcap is not an MCAP recording"):
        list(iter_messages(junk))
    with pytest.raises(ValueError, match="not an MCAP recording"):
        replay(junk, io.BytesIO())


def test_a_complete_recording_reads_without_a_warning(tmp_path, caplog):
    *_, mcap_path, _ = live_recording(tmp_path, seconds=1.2)
    with caplog.at_level(logging.WARNING, logger="service.record.mcap_reader"):
        assert sum(1 for _ in iter_messages(mcap_path)) > 0
    assert "cannot be read past" not in caplog.text


def test_a_recording_is_synced_to_disk_when_it_stops_and_every_few_seconds(tmp_path, monkeypatch):
    import os

    from service.record import recorder as recorder_module

    synced = []
    monkeypatch.setattr(recorder_module.os, "fsync", lambda fd: synced.append(os.readlink(f"/proc/self/fd/{fd}")))
    monkeypatch.setattr(recorder_module, "FLUSH_PERIOD_S", 0.0)
    monkeypatch.setattr(recorder_module, "FSYNC_PERIOD_S", 0.2)
    recorder = Recorder(tmp_path / "run.mcap", tmp_path / "run.bin")
    pipeline = Pipeline(Reconstructor())
    recorder.attach(pipeline)
    for i in range(30):
        for listener in pipeline.byte_listeners:
            listener(b"x", float(i))
        time.sleep(0.02)
    status = recorder.stop()
    assert status["fsyncs"] >= 3  # ~0.6 s of writing at one sync per 0.2 s, and one at the stop
    assert synced[-2:] == [str(tmp_path / "run.mcap"), str(tmp_path / "run.bin")]  # both files, last thing done


def stepped_recording(path, step_s):
    """30 s of a board at 100 Hz, one read per scan received 2 ms after it: the board silent (STOP …
    START) from 3 s to 23 s, the host clock stepped by ``step_s`` (NTP) at 26 s."""
    from firmware_sim.board import Board
    from service.record.mcap_writer import McapLog

    board = Board(BoardConfig(rate_hz=100, seed=2))
    with open(path, "wb") as stream:
        log = McapLog(stream)
        log.raw(board.power_up(), 1e9)
        for k in range(1, 3001):
            board.streaming = not 300 < k <= 2300
            data = board.advance(k / 100)
            if data:
                log.raw(data, 1e9 + k / 100 + 0.002 + (step_s if k > 2600 else 0.0))
        log.close()
    return path


def virtual_pacer():
    now, slept = [0.0], []

    def sleep(dt):
        slept.append(dt)
        now[0] += dt

    return Pacer(1.0, clock=lambda: now[0], sleep=sleep), slept


@pytest.mark.parametrize("step_s", [3600.0, -3600.0, 0.0])
def test_a_paced_recording_keeps_its_pauses_but_not_the_host_clocks_steps(tmp_path, step_s, caplog):
    """Receive times are the wall clock's: a step of +1 h while recording stalled a paced replay (export and
    --serve) for an hour, one of -1 h let the rest through unpaced. The board clock shows the step for what
    it is; the 20 s the board was silent show on both clocks and stay a 20 s wait."""
    from service.sources.protocol_replay import Serial

    path = stepped_recording(tmp_path / "step.mcap", step_s)
    fast, paced = io.BytesIO(), io.BytesIO()
    replay(path, fast)
    pacer, slept = virtual_pacer()
    replay(path, paced, pacer=pacer)
    assert sum(slept) == pytest.approx(30.002, abs=0.01) and max(slept) == pytest.approx(20.0, abs=0.01)
    assert paced.getvalue() == fast.getvalue() and fast.getvalue().count(b"\n") == 2 * 1000
    assert sum("host clock" in r.message for r in caplog.records) == (step_s != 0)

    # --serve: the replay:// port, paced alike, delivers every byte.
    pacer, slept = virtual_pacer()
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("service.sources.protocol_replay.Pacer", lambda speed: pacer)
        port = Serial(f"replay://{path}?speed=1")
        served = b""
        while not (port.finished and not port.in_waiting):
            served += port.read(1 << 16)
    assert served == b"".join(chunk for _, chunk in read_raw(path))
    assert sum(slept) == pytest.approx(30.002, abs=0.01) and max(slept) == pytest.approx(20.0, abs=0.01)


def test_a_paced_replay_emits_each_read_at_its_own_recorded_time(tmp_path):
    """Each read of stepped_recording is one scan, received 2 ms after it:
    paced, its frames go out when the replay reaches its receive time, as
    far after the first frame as their scan is on the board clock. They
    went out one read late, after the wait for the next read: the last
    scan before the board's 20 s silence came out 20 s late."""
    path = stepped_recording(tmp_path / "pause.mcap", 0.0)
    pacer, _ = virtual_pacer()
    now = pacer._clock
    emitted = []

    class Times:
        def write(self, frames):
            emitted.extend((now(), frame.t_us * 1e-6) for frame in frames)

    replay(path, pacer=pacer, writer=Times())
    assert len(emitted) == 2 * 1000
    (w0, b0) = emitted[0]
    late = [(w - w0) - (b - b0) for w, b in emitted]
    assert max(late) == pytest.approx(0.0, abs=1e-6) and min(late) == pytest.approx(0.0, abs=1e-6)


def recorded_diagnostics(path):
    return [orjson.loads(m.data) for t, m in iter_messages(path) if t == "/diagnostics"]


def test_the_last_diagnostics_count_every_byte_recorded(tmp_path):
    """Snapshots were taken when frames came, at most once a second, none
    at the stop: the last one lagged the end by up to a second (22 CRC
    errors recorded where the bytes hold 24). The last is now taken at the
    stop: the counters of exactly the bytes recorded."""
    from firmware_sim.faults import inject

    damaged = inject(capture(BoardConfig(scene="press", seed=4), 2.5)[0], rate=0.05, seed=5).data
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    for i, pos in enumerate(range(0, len(damaged), 700)):  # ~0.7 ms of stream a read, 2 ms apart
        pipeline.feed(damaged[pos : pos + 700], 1000.0 + 0.002 * i)
    recorder.stop()
    docs = recorded_diagnostics(tmp_path / "run.mcap")
    decoder = Decoder()
    decoder.feed(b"".join(chunk for _, chunk in read_raw(tmp_path / "run.mcap")))
    truth = decoder.counters.as_dict()
    assert truth["bytes_in"] == len(damaged) and truth["crc_errors"] > 20
    assert docs[-1]["counters"] == truth
    assert docs[0]["counters"]["bytes_in"] == 0 and len(docs) == 4  # at the first read, at 1 s and 2 s, at the stop


def test_a_board_whose_every_frame_is_corrupt_has_its_diagnostics_recorded(tmp_path):
    """No frame, so no snapshot was ever taken: the recording held /raw only.
    Snapshots are driven by reads."""
    from service.protocol import FrameType, encode_frame

    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    for seq in range(3000):  # a read a scan, at 1 kHz
        frame = bytearray(encode_frame(FrameType.QUAD, 0, seq, 1000 * seq, bytes(16)))
        frame[-1] ^= 0xFF  # its CRC
        pipeline.feed(bytes(frame), 1000.0 + 0.001 * seq)
    recorder.stop()
    docs = recorded_diagnostics(tmp_path / "run.mcap")
    assert len(docs) == 1 + 2 + 1  # at the first read, at 1 s and 2 s, at the stop
    last = docs[-1]["counters"]
    assert (last["bytes_in"], last["frames"], last["crc_errors"]) == (3000 * len(frame), 0, 3000)
    assert [doc["counters"]["crc_errors"] for doc in docs[:3]] == [0, 1000, 2000]  # the reads before each


@pytest.mark.parametrize("silent_s", [600.0, 2400.0, 9000.0])
def test_a_silence_past_half_the_board_clocks_range_stays_a_pause_in_a_paced_replay(tmp_path, silent_s):
    """The board clock wraps every 71.6 min: silent 40 min, its frames alone read a step back, and the replay
    took the receive times' 40 min for a host clock step (NTP), replaying the pause in no time."""
    from firmware_sim.board import Board
    from service.record.mcap_writer import McapLog

    board = Board(BoardConfig(rate_hz=100, seed=2, clock_offset_us=2**32 - 3_000_000))
    path = tmp_path / "silent.mcap"
    with open(path, "wb") as stream:
        log = McapLog(stream)
        log.raw(board.power_up(), 1e9)
        for now, streaming in [(k / 100, True) for k in range(1, 201)] + [(2.0 + silent_s, False)] + \
                [(2.0 + silent_s + k / 100, True) for k in range(1, 201)]:
            board.streaming = streaming
            data = board.advance(now)
            if data:
                log.raw(data, 1e9 + now + 0.002)
        log.close()
    pacer, slept = virtual_pacer()
    replay(path, io.BytesIO(), pacer=pacer)
    assert sum(slept) == pytest.approx(silent_s + 4.0, abs=0.05) and max(slept) == pytest.approx(silent_s, abs=0.05)

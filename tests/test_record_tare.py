"""Tares made while recording are recorded where they took effect, and a
replay makes them there again: its forces equal the live ones after them too."""
import io

import numpy as np
import orjson
import pytest

from firmware_sim.board import BoardConfig, capture
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.record.mcap_reader import iter_messages, read_changes
from service.record.recorder import Recorder
from service.replay import replay

SIZES = [1, 700, 3000, 31, 4096, 17]  # irregular reads, as a port delivers them


def reads(data: bytes):
    """(index, bytes) of each read; there are ~230 per second of capture."""
    pos, i = 0, 0
    while pos < len(data):
        chunk = data[pos : pos + SIZES[i % len(SIZES)]]
        yield i, chunk
        pos += len(chunk)
        i += 1


def recorded_forces(path):
    return [orjson.loads(m.data) for topic, m in iter_messages(path) if topic.endswith("/forces")]


def replayed_forces(path):
    out = io.BytesIO()
    replay(path, out)
    return [orjson.loads(line) for line in out.getvalue().splitlines()]


def by_frame(docs):
    return {(d["sensor"], d["seq"], d["t_us"]): d for d in docs}


@pytest.fixture(scope="module")
def pressed():
    data = capture(BoardConfig(scene="press", seed=7), 4.0)[0]
    assert sum(1 for _ in reads(data)) > 900
    return data


def test_a_tare_in_the_middle_of_a_recording_replays_where_it_was_made(tmp_path, pressed):
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    t = 1000.0
    tares = {300: (None, True), 700: (1, False)}  # at these reads: (sensor or all, forced)
    for i, chunk in reads(pressed):
        if i in tares:
            sensor, forced = tares[i]
            pipeline.tare(sensor, force=forced)
        pipeline.feed(chunk, t)
        t += 0.002
    recorder.stop()
    made = read_changes(tmp_path / "run.mcap")[None]
    assert [(sensor, judge) for _, sensor, judge in made] == [(0, False), (1, False), (1, True)]
    live, again = by_frame(recorded_forces(tmp_path / "run.mcap")), by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert live.keys() == again.keys() and len(live) > 4000
    assert sum("taring" in d["flags"] for d in live.values()) > 3 * 100  # the first tare and both made later
    assert [key for key in live if live[key] != again[key]] == []


def test_a_tare_while_grids_wait_for_the_loop_applies_to_them_in_the_replay_too(tmp_path, pressed):
    """Live, grids wait for the loop (feed_reads); a tare made meanwhile
    (from the API's thread) starts with those waiting frames, and the
    recording says so."""
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    waiting = []
    batch, t = [], 1000.0
    for i, chunk in reads(pressed):
        batch.append((chunk, t))
        t += 0.002
        if len(batch) == 3:
            pipeline.feed_reads(batch, waiting.append)
            batch = []
            if i in (302, 602, 851):  # grids of the reads just fed are still waiting
                assert waiting
                pipeline.tare(None if i != 602 else 0, force=True)
            if i % 2:  # the loop's turn comes every other time
                while waiting:
                    waiting.pop(0)()
    pipeline.feed_reads(batch, waiting.append)
    while waiting:
        waiting.pop(0)()
    recorder.stop()
    made = read_changes(tmp_path / "run.mcap")[None]
    by_sensor = {}
    for after, sensor, _ in made:
        by_sensor.setdefault(sensor, []).append(after)
    assert len(by_sensor[0]) == 3 and len(by_sensor[1]) == 2
    live, again = by_frame(recorded_forces(tmp_path / "run.mcap")), by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert live.keys() == again.keys() and len(live) > 4000
    assert [key for key in live if live[key] != again[key]] == []


def test_without_its_tares_the_replay_would_differ(tmp_path, pressed, monkeypatch):
    """The check above can fail: the same recording replayed with its tares
    ignored gives other forces after them."""
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    for i, chunk in reads(pressed):
        if i == 500:
            pipeline.tare(force=True)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    monkeypatch.setattr("service.replay.read_changes", lambda path: {})
    live, again = by_frame(recorded_forces(tmp_path / "run.mcap")), by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert sum(live[key] != again[key] for key in live) > 500


def test_a_board_restarted_with_another_shape_is_no_calibration_change_the_replay_misses(tmp_path, caplog):
    """A restart's INFO makes sensor 0 a 16x16 grid, from 4x4: its built-in
    calibration is another (built-in ids name the shape), live and in the
    replay alike, whose frames all equal the recorded ones; it was warned
    that the replay's forces after the change differ."""
    import logging

    from service.protocol import FrameType, encode_frame
    from service.record.calibrations import recorded_calibrations

    rng = np.random.default_rng(4)
    pipeline = Pipeline(Reconstructor(level="table"))
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    t = 1000.0
    for rows in (4, 16):  # the board, then the board restarted
        info = {"board": "hand", "serial": "H-7", "sensors": [{"id": 0, "kind": "grid", "rows": rows, "cols": rows}]}
        pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(info)), t)
        for seq in range(300):
            counts = (10_660_000 + rng.normal(0, 800, rows * rows)).astype("<u4").tobytes()
            t += 0.001
            pipeline.feed(encode_frame(FrameType.GRID, 0, seq, 1000 * (seq + 1), counts), t)
    recorder.stop()
    live = recorded_forces(tmp_path / "run.mcap")
    assert [d["calibration"] for d in live[::300]] == ["builtin-mean-4x4", "builtin-mean-16x16"]
    with caplog.at_level(logging.WARNING, logger="service.record.calibrations"):
        recorded_calibrations(tmp_path / "run.mcap")
    assert caplog.text == ""
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level="table")
    assert len(live) == 600 and [orjson.loads(line) for line in out.getvalue().splitlines()] == live


@pytest.mark.parametrize("later, warned", [("builtin-mean-16x16", False), ("builtin-mean-4x4", True),
                                           ("builtin-fits34-35", False), ("0123456789ab", True)])
def test_only_a_calibration_change_the_replay_does_not_make_is_warned_of(tmp_path, caplog, later, warned):
    """A sensor that began on its own 4x4 calibration: the replay keeps it
    wherever it fits, the built-in one of the sensor's shape where not (a
    16x16 grid or a quad after a restart, as live); another calibration it
    never has."""
    import logging

    from service.readings import SensorInfo
    from service.record.calibrations import recorded_calibrations
    from service.record.mcap_writer import McapLog

    sensor = SensorInfo(0, "grid", 4, 4, board="hand")
    with open(tmp_path / "run.mcap", "wb") as stream:
        log = McapLog(stream)
        log.calibration(sensor, "fedcba987654", {"id": "fedcba987654", "kind": "grid", "rows": 4, "cols": 4}, None, 1.0)
        log.calibration(sensor, later, None, None, 2.0)
        log.close()
    with caplog.at_level(logging.WARNING, logger="service.record.calibrations"):
        recorded_calibrations(tmp_path / "run.mcap")
    assert caplog.text.count(f"sensor hand/0 changed calibration while recording (fedcba987654 → {later}); "
                             f"the replay reconstructs with the first throughout") == warned
    assert f"so its forces with {later} differ from the recorded ones" in caplog.text or not warned


def test_a_forced_tare_recorded_before_a_sensors_first_frame_is_judged_as_it_was(pressed):
    """A recording begun while the board streamed can hold a forced tare
    (the load is the zero) before a sensor's first recorded frame: the
    replay's fresh sensor then tares unjudged too, not against the C0 of its
    calibration."""
    pipeline = Pipeline(Reconstructor())
    pipeline.retare(1, judge=False)
    for i, chunk in reads(pressed[:20_000]):
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    states = pipeline.reconstructor._sensors
    assert states[1].judge_tare is False and states[0].judge_tare is True


def recorded(path, data: bytes, tares: dict) -> Pipeline:
    """A recording of ``data`` fed read by read (as ``reads`` cuts it), with a
    forced tare {read: sensor id, or None for all} made before those reads."""
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(data):
        if i in tares:
            pipeline.tare(tares[i], force=True)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    return pipeline


def served_forces(path, read_size: int, schedule: bool = True, merge: int = 1):
    """The recording through the live path's pieces: its replay:// port read
    ``read_size`` bytes at a time (not as recorded), ``merge`` port reads
    fed to a pipeline as one (as a serial read takes what has piled up), as
    the loop feeds one, with the tares recorded_changes gives scheduled."""
    from service.sources.protocol_replay import Serial, recorded_changes

    url = f"replay://{path}?speed=max"
    pipeline = Pipeline(Reconstructor())
    if schedule:
        pipeline.schedule_recorded(recorded_changes(url))
    frames = []
    pipeline.listeners.append(frames.extend)
    port = Serial(url)  # opened; no timeout: an empty read at the end
    try:
        t = 1000.0
        while chunk := b"".join(port.read(read_size) for _ in range(merge)):
            pipeline.feed_reads([(chunk, t)], lambda work: work())
            t += 0.002
    finally:
        port.close()
    return {(f.sensor.id, f.seq, f.t_us): f for f in frames}


@pytest.mark.parametrize("read_size, merge", [(64, 1), (5000, 1), (700, 3)])
def test_a_recording_served_through_the_live_path_makes_its_tares_again(tmp_path, pressed, read_size, merge):
    """tactile replay --serve (replay://): the recorded tares are made where
    the stream reaches the bytes of the read they preceded, however the
    port's reads cut it: every force equals the recorded one, null where it
    was null; without the schedule they differ after the first tare."""
    recorded(tmp_path / "run.mcap", pressed, {300: None, 700: 1})
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))

    def differing(served):
        assert served.keys() == live.keys()
        # clock_suspect tells how the reads came (here 64 bytes each 2 ms: slower than the board), not the forces
        return [key for key, doc in live.items()
                if doc.get("taxels_N", doc.get("fxyz_N")) != [None if v != v else v for v in served[key].forces_N.tolist()]
                or doc["flags"] != [f for f in served[key].flags if f != "clock_suspect"]]

    assert differing(served_forces(tmp_path / "run.mcap", read_size, merge=merge)) == []  # merged: reads cut at a tare
    assert len(differing(served_forces(tmp_path / "run.mcap", read_size, schedule=False, merge=merge))) > 500


def test_a_board_serving_a_recording_schedules_its_tares(tmp_path, pressed):
    """The live service's Board for a replay:// source hands the recording's
    tares to its pipeline (a raw capture has none)."""
    from service.board import Board, BoardSpec
    from service.calibration.book import CalibrationBook
    from service.history import Histories

    recorded(tmp_path / "run.mcap", pressed, {400: 1})
    board = Board(BoardSpec(f"replay://{tmp_path / 'run.mcap'}?speed=max"), CalibrationBook(), Histories())
    offset = sum(len(chunk) for i, chunk in reads(pressed) if i < 400)
    assert board.pipeline._recorded == [(offset, 1, False)] and board.pipeline.interpreter.board_name is None
    (tmp_path / "run.bin").write_bytes(pressed)
    assert Board(BoardSpec(f"replay://{tmp_path / 'run.bin'}"), CalibrationBook(), Histories()).pipeline._recorded == []


@pytest.mark.parametrize("level", ["table", "full"])
def test_a_recording_begun_on_a_running_service_replays_from_the_zeros_it_began_with(tmp_path, pressed, level):
    """POST /record/start (the dashboard's Record) attaches to a pipeline
    whose sensors were tared long before: the replay tared again on the
    recording's first frames, under whatever load was there (every frame
    differed, by up to 4 N). The zeros in force are recorded (/baselines)
    and the replay starts from them: bit for bit at a level without tracked
    state; at the full level, whose drift and crosstalk estimates start
    afresh, within a few mN."""
    from service.record.mcap_reader import read_baselines

    pipeline = Pipeline(Reconstructor(level=level))
    recorder = None
    for i, chunk in reads(pressed):
        if i == 400:  # well after the tare, in the middle of the presses
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    began = read_baselines(tmp_path / "run.mcap")[None]
    zeros = began["sensors"]
    assert began["board"] == pipeline.interpreter.name != "board"
    assert [z["sensor"] for z in zeros] == sorted(pipeline.interpreter.sensors) and len(zeros[0]["baseline_pF"]) == 64
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level=level)
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    # Every recorded frame replayed, that of the first read too (it began before it: the recording holds its start).
    assert again.keys() == live.keys() and len(again) > 2000
    assert not any("taring" in d["flags"] for d in again.values())

    def values(doc):
        return np.array([np.nan if v is None else v for v in doc.get("taxels_N", doc.get("fxyz_N"))])

    worst = max(np.nanmax(np.abs(values(live[key]) - values(again[key])), initial=0.0) for key in live)
    if level == "table":
        assert [key for key in live if live[key] != again[key]] == []
    else:
        assert worst < 0.02
    from service.board import Board, BoardSpec  # served live (replay --serve): the same zeros and name
    from service.calibration.book import CalibrationBook
    from service.history import Histories

    board = Board(BoardSpec(f"replay://{tmp_path / 'run.mcap'}?speed=max"), CalibrationBook(), Histories())
    assert board.pipeline.interpreter.board_name == began["board"]
    assert sorted(board.pipeline.reconstructor._preset) == [z["sensor"] for z in zeros]


@pytest.mark.parametrize("forced_at", [None, 600])
def test_a_recording_begun_while_a_sensor_tares_replays_its_tare_as_it_ran_live(tmp_path, pressed, forced_at):
    """Begun during the auto-tare (``forced_at`` None) or a forced tare made
    just before: the zeros then in force (/baselines) had none for the
    taring sensors, so the replay tared them afresh on the recording's first
    100 frames: frames null and flagged ``taring`` that had forces live, and
    another zero after. The window so far is recorded with the zeros and the
    replay goes on with it: its frames equal the live ones, the taring ones
    included, bit for bit."""
    pipeline = Pipeline(Reconstructor(level="table"))
    taring = []  # frames of the window live: the recording begins in its middle
    pipeline.listeners.append(lambda frames: taring.extend(f for f in frames if "taring" in f.flags))
    begin = None if forced_at is None else forced_at + 4  # ~25 frames of sensor 0 into the forced tare's window
    recorder = None
    for i, chunk in reads(pressed):
        if i == forced_at:
            pipeline.tare(force=True)
            taring.clear()
        if recorder is None and (i == begin or begin is None and sum(f.sensor.id == 0 for f in taring) >= 30):
            before = sum(f.sensor.id == 0 for f in taring)
            assert 0 < before < 100
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    again = by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert again.keys() == live.keys() and len(live) > 2000
    # The rest of the window live, and only that, is null and flagged in the replay (of its 100 readings the
    # last completes it: it has forces).
    rest = [key for key, doc in live.items() if key[0] == 0 and "taring" in doc["flags"]]
    assert len(rest) == 99 - before
    assert [key for key, doc in again.items() if key[0] == 0 and "taring" in doc["flags"]] == rest
    assert [key for key in live if live[key] != again[key]] == []


def test_a_tare_made_again_by_a_replay_is_recorded_by_a_recording_of_it(tmp_path, pressed):
    """Recording a served replay (replay:// with a Recorder attached): the
    replayed tares are tares of that stream too, so the new recording holds
    them where they took effect and replays as served."""
    recorded(tmp_path / "first.mcap", pressed, {500: 1})
    served = Pipeline(Reconstructor())
    again = Recorder(tmp_path / "second.mcap")
    again.attach(served)
    from service.sources.protocol_replay import Serial, recorded_changes

    url = f"replay://{tmp_path / 'first.mcap'}?speed=max"
    served.schedule_recorded(recorded_changes(url))
    port = Serial(url)
    t = 1000.0
    while chunk := port.read(4096):
        served.feed_reads([(chunk, t)], lambda work: work())
        t += 0.002
    port.close()
    again.stop()
    assert [(sensor, judge) for _, sensor, judge in read_changes(tmp_path / "second.mcap")[None]] == [(1, False)]
    first, second = by_frame(recorded_forces(tmp_path / "first.mcap")), by_frame(replayed_forces(tmp_path / "second.mcap"))
    assert [key for key in first if first[key].get("taxels_N", first[key].get("fxyz_N")) !=
            second[key].get("taxels_N", second[key].get("fxyz_N"))] == []


def test_a_recording_begun_during_a_stale_run_replays_it_as_it_ran(tmp_path):
    """A grid taxel and a quad electrode repeat one count (a stuck
    converter) from scan 100 to 259 — stale from 150 — and the recording
    begins at scan ~180: the replay continues each stale count where the
    live one stood (recorded with the zeros), not from nothing (its first
    50 frames then had the latched load's forces)."""
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(2)
    grid0, quad0 = np.full(64, 10_660_000.0), np.full(4, 2_200_000.0)
    scans = []
    for seq in range(400):
        grid, quad = grid0 + rng.normal(0, 800, 64), quad0 + rng.normal(0, 800, 4)
        if 100 <= seq < 260:
            grid[5], quad[2] = 10_660_000.0 * 1.04, 2_200_000.0 * 1.06  # latched under a load
        scans.append(encode_frame(FrameType.GRID, 0, seq, 1000 * seq, grid.astype("<u4").tobytes())
                     + encode_frame(FrameType.QUAD, 1, seq, 1000 * seq, quad.astype("<u4").tobytes()))
    pipeline = Pipeline(Reconstructor(level="table"))
    recorder = None
    for seq, scan in enumerate(scans):
        if seq == 180:
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        pipeline.feed(scan, 1000.0 + 0.001 * seq)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level="table")
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert again == live and len(live) == 2 * 220
    stale = sorted((sensor, seq) for (sensor, seq, _), doc in again.items() if "stale" in doc["flags"])
    assert stale == [(sensor, seq) for sensor in (0, 1) for seq in range(180, 260)]


def test_a_recording_replays_its_reads_joined_and_equal_to_what_ran_live(tmp_path, monkeypatch):
    """At full speed a recording's reads go through the pipeline joined
    (JOIN_READS a call: a live read is a frame or two per sensor, and the
    per-read cost was most of a replay), split at the tares made while
    recording; the frames equal the recorded ones bit for bit, through load
    cycles that move a quad's fatigue factor inside joined reads."""
    from service import replay as replay_module
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(5)
    c0 = np.array([2.31, 2.12, 2.27, 2.19]) * 1e6
    scans = []
    for seq in range(3000):
        pressed = seq >= 300 and seq // 40 % 2  # quad 0 pressed ~3 N and let go every 40 scans: load cycles
        quad0 = c0 * (1.0 + (0.09 if pressed else 0.0)) + rng.normal(0, 300, 4)
        quad1 = c0 + rng.normal(0, 300, 4)
        scans.append(encode_frame(FrameType.QUAD, 0, seq, 1000 * seq, quad0.astype("<u4").tobytes())
                     + encode_frame(FrameType.QUAD, 1, seq, 1000 * seq, quad1.astype("<u4").tobytes()))
    pipeline = Pipeline(Reconstructor(level="full"))
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    i = read = 0
    while i < len(scans):
        n = int(rng.choice([1, 2, 3], p=[0.7, 0.2, 0.1]))  # reads that piled up
        if read == 900:
            pipeline.tare(1)
        pipeline.feed(b"".join(scans[i:i + n]), 1000.0 + 0.001 * i)
        i, read = i + n, read + 1
    recorder.stop()
    joined = []
    original = Pipeline.feed_many
    monkeypatch.setattr(Pipeline, "feed_many", lambda self, chunks: joined.append(len(chunks)) or original(self, chunks))
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    pipelines = replay_module.replay_boards(tmp_path / "run.mcap", out)
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert again == live and len(live) == 6000
    assert sum(joined) == read and len(joined) < read / 50  # joined, and split at the tare
    assert sum(next(iter(pipelines.values())).reconstructor.cycle_counts()[0][2]) > 20


def test_an_interrupted_replay_exports_every_frame_made_before(tmp_path, pressed, monkeypatch):
    """The JSON lines writer gathers frames; a replay stopped by Ctrl-C (or
    an error) writes what it gathered instead of losing it."""
    recorded(tmp_path / "run.mcap", pressed, {})
    made, original = [], Pipeline.feed_many

    def feed_many(self, chunks):
        if len(made) == 3:
            raise KeyboardInterrupt
        frames = original(self, chunks)
        made.append(len(frames))
        return frames

    monkeypatch.setattr(Pipeline, "feed_many", feed_many)
    out = io.BytesIO()
    with pytest.raises(KeyboardInterrupt):
        replay(tmp_path / "run.mcap", out)
    assert len(made) == 3 and len(out.getvalue().splitlines()) == sum(made)  # the last call's frames waited


@pytest.mark.parametrize("level", ["table", "full"])
def test_a_late_zero_completing_inside_joined_reads_applies_from_there_on(tmp_path, level):
    """Channel 5 sends the open-channel value for the first 150 scans, so
    it gets its zero late (100 plausible readings later, at scan 249): a
    replay joining 256 reads applied that zero to the frames before it
    (150 frames differed at table, 501 at full through the drift state).
    The batch is split where a late zero completes: bit for bit."""
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(1)
    c0 = rng.uniform(10.0, 11.0, 64) * 1e6
    pipeline = Pipeline(Reconstructor(level=level))
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    for seq in range(600):
        counts = c0 + rng.normal(0, 1000, 64)
        if 200 <= seq < 400:
            counts[20:22] *= 1.05
        counts = counts.astype("<u4")
        if seq < 150:
            counts[5] = 0xFFFFFFFF
        pipeline.feed(encode_frame(FrameType.GRID, 0, seq, 1000 * seq, counts.tobytes()), 1000.0 + 0.001 * seq)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level=level)
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert again == live
    assert live[(0, 248, 248_000)]["taxels_N"][5] is None and live[(0, 249, 249_000)]["taxels_N"][5] is not None


@pytest.mark.parametrize("begin", [1001, 1521, 2003])
def test_a_recording_begun_mid_stream_counts_load_cycles_as_live(tmp_path, begin):
    """A quad pressed and let go every 40 scans from scan 1 500 (load cycles
    move its fatigue factor); the recording begins at scan ``begin``: before,
    among the cycles (1001), while pressed (1521: a cycle pending) or after
    some (2003). Its /baselines carry where the count stood (counts, which
    frames are judged, a load on), so the replay's factors are live's: 93,
    62, 31 frames differed when the judged frames' phase was lost."""
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(5)
    c0 = np.array([2.31, 2.12, 2.27, 2.19]) * 1e6
    pipeline = Pipeline(Reconstructor(level="full"))
    recorder = None
    for seq in range(4000):
        if seq == begin:
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        pressed = seq >= 1500 and seq // 40 % 2
        counts = c0 * (1.0 + (0.09 if pressed else 0.0)) + rng.normal(0, 300, 4)
        pipeline.feed(encode_frame(FrameType.QUAD, 0, seq, 1000 * seq, counts.astype("<u4").tobytes()), 1000.0 + 0.001 * seq)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    again = by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert again == live and len(live) == 4000 - begin


@pytest.mark.parametrize("dropped", [False, True])
def test_a_recording_begun_mid_stream_keeps_the_info_its_bytes_do_not_hold(tmp_path, dropped):
    """A 4x4 grid and a quad, described by an INFO sent before the recording
    began: its bytes hold no INFO, and without one a 64-byte grid payload has
    no shape (every 4x4 frame was rejected in the replay). The INFO in force
    is recorded with the zeros; the replay takes it first. ``dropped``: a
    later INFO lists only the quad, the grid goes on (its shape from the
    older INFO, kept as unlisted)."""
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(3)
    info = orjson.dumps({"board": "hand", "serial": "H-7", "rate_hz": 1000,
                         "sensors": [{"id": 0, "kind": "grid", "rows": 4, "cols": 4}, {"id": 1, "kind": "quad"}]})
    pipeline = Pipeline(Reconstructor(level="table"))
    pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, info), 1000.0)
    if dropped:
        only_quad = orjson.dumps({"board": "hand", "serial": "H-7", "sensors": [{"id": 1, "kind": "quad"}]})
        pipeline.feed(encode_frame(FrameType.INFO, 255, 1, 500, only_quad), 1000.0)
    recorder = None
    for seq in range(400):
        if seq == 200:
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        grid = (10_660_000 + rng.normal(0, 800, 16)).astype("<u4").tobytes()
        quad = (2_200_000 + rng.normal(0, 800, 4)).astype("<u4").tobytes()
        pipeline.feed(encode_frame(FrameType.GRID, 0, seq, 1000 * (seq + 1), grid)
                      + encode_frame(FrameType.QUAD, 1, seq, 1000 * (seq + 1), quad), 1000.0 + 0.001 * seq)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level="table")
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert len(live) == 400 and again == live
    assert {(d["sensor"], d.get("rows"), d.get("cols")) for d in again.values()} == {(0, 4, 4), (1, None, None)}


@pytest.mark.parametrize("level, mounting", [("level0", "curved"), ("table", "flat")])
def test_a_recording_replays_at_the_level_and_mounting_it_was_recorded_with(tmp_path, pressed, level, mounting):
    """A recording made at another level than the replay's default came back at the default: 2401 of 2500
    frames a sensor differed, by up to 0.29 N, without a word."""
    path = tmp_path / "run.mcap"
    pipeline = Pipeline(Reconstructor(level=level, mounting=mounting))
    recorder = Recorder(path)
    recorder.attach(pipeline)
    for i, chunk in reads(pressed):
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    live, again = by_frame(recorded_forces(path)), by_frame(replayed_forces(path))
    assert live.keys() == again.keys() and len(live) > 4000
    assert [key for key in live if live[key] != again[key]] == []
    default = io.BytesIO()
    replay(path, default, level="full", mounting="flat")  # told otherwise: as told
    other = by_frame(orjson.loads(line) for line in default.getvalue().splitlines())
    grids = [key for key in live if live[key]["kind"] == "grid"]  # a quad's forces are the same at table and full
    assert sum(live[key] != other[key] for key in grids) > 0.9 * len(grids)


def test_the_replay_command_says_when_it_is_told_another_level_than_recorded(tmp_path, pressed, capsys):
    from service import cli

    path = tmp_path / "run.mcap"
    pipeline = Pipeline(Reconstructor(level="level0"))
    recorder = Recorder(path)
    recorder.attach(pipeline)
    pipeline.feed(pressed[:200_000], 1000.0)
    recorder.stop()
    assert cli.main(["replay", str(path), "--export", str(tmp_path / "a.jsonl")]) == 0
    assert "recorded at" not in capsys.readouterr().err
    assert cli.main(["replay", str(path), "--export", str(tmp_path / "b.jsonl"), "--level", "table"]) == 0
    assert f"{path} was recorded at level level0; replaying at table" in capsys.readouterr().err


def test_a_recording_begun_inside_a_frame_holds_its_start_and_replays_it(tmp_path, pressed):
    """Begun while the decoder held the start of a frame (the recording's
    first read completes it): the recorder recorded that frame's forces, but
    its bytes began at the read, so the replay could not make it (1916 frames
    of 1917). The first /raw message now begins with the bytes the decoder
    held: the raw bytes are the stream's from that frame's sync on, and the
    replay gives every recorded frame, bit for bit."""
    from firmware_sim.faults import split_frames

    starts = set(np.cumsum([0] + [len(frame) for frame in split_frames(pressed)]).tolist())
    pipeline = Pipeline(Reconstructor(level="table"))
    recorder, position = None, 0
    for i, chunk in reads(pressed):
        if recorder is None and i >= 400 and position not in starts:  # a read that begins inside a frame
            began = max(start for start in starts if start < position)
            recorder = Recorder(tmp_path / "run.mcap", tmp_path / "run.bin")
            recorder.attach(pipeline)
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
        position += len(chunk)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    out = io.BytesIO()
    replay(tmp_path / "run.mcap", out, level="table")
    again = by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])
    assert len(again) == len(live) > 2000 and again == live
    assert (tmp_path / "run.bin").read_bytes() == pressed[began:]


def test_a_recording_of_boards_at_their_own_levels_is_served_at_each_ones(tmp_path, pressed, monkeypatch):
    """robot.toml gives each board its level and mounting: replay --serve served them all at the defaults."""
    from service import cli, cli_recordings
    from service.cli_serve import board_specs

    path = tmp_path / "two.mcap"
    left = Pipeline(Reconstructor(level="level0", mounting="curved"), board_name="left")
    right = Pipeline(Reconstructor(level="table"), board_name="right")
    recorder = Recorder(path)
    recorder.attach(left)
    recorder.attach(right)
    for i, chunk in reads(pressed[:100_000]):
        left.feed(chunk, 1000.0 + 0.002 * i)
        right.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    served = []
    monkeypatch.setattr(cli_recordings, "cmd_serve", lambda args: served.append(board_specs(args)) or 0)
    assert cli.main(["replay", str(path), "--serve"]) == 0
    assert sorted((s.name, s.level, s.mounting) for s in served[0]) == [("left", "level0", "curved"),
                                                                      ("right", "table", "flat")]
    assert cli.main(["replay", str(path), "--serve", "--level", "full"]) == 0  # told: every board so
    assert sorted((s.name, s.level, s.mounting) for s in served[1]) == [("left", "full", "curved"),
                                                                      ("right", "full", "flat")]


@pytest.mark.parametrize("level", ["table", "full"])
def test_a_recording_whose_first_chunk_is_damaged_replays_the_rest_described_and_zeroed_as_recorded(
        tmp_path, pressed, level, caplog):
    """The chunk holding a recording's first reads (its INFO, the tare on its
    first frames) is damaged: the replay described the sensors by their
    frames under the name "board" and tared them again on whatever load
    came next (every frame differed). It begins at the first second of
    reads after the damage, from the INFO and zeros recorded there
    (/resume): its frames are those of the whole recording's replay, bit
    for bit at a level without tracked state, within a few mN at the full
    level (its drift and crosstalk estimates start afresh)."""
    import logging

    from mcap.reader import make_reader

    from service.protocol import DATA_TYPES
    from service.protocol_decoder import Decoder

    pipeline = Pipeline(Reconstructor(level=level))
    recorder = Recorder(tmp_path / "run.mcap")
    recorder.attach(pipeline)
    for i, chunk in reads(pressed):
        pipeline.feed(chunk, 1000.0 + 0.002 * i)
    recorder.stop()
    with open(tmp_path / "run.mcap", "rb") as stream:
        first = min(make_reader(stream).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    damaged = bytearray((tmp_path / "run.mcap").read_bytes())
    damaged[first.chunk_start_offset + first.chunk_length - 20] ^= 0xFF  # inside its compressed records
    (tmp_path / "damaged.mcap").write_bytes(bytes(damaged))

    def replayed(name):
        out = io.BytesIO()
        replay(tmp_path / name, out, level=level)
        return by_frame([orjson.loads(line) for line in out.getvalue().splitlines()])

    whole = replayed("run.mcap")
    with caplog.at_level(logging.WARNING):
        rest = replayed("damaged.mcap")
    assert {d["board"] for d in rest.values()} == {pipeline.interpreter.name} != {"board"}
    assert not any("taring" in d["flags"] for d in rest.values())

    def values(doc):
        return np.array([np.nan if v is None else v for v in doc.get("taxels_N", doc.get("fxyz_N"))])

    if level == "table":
        assert [key for key in rest if rest[key] != whole[key]] == []
    else:
        assert max(np.nanmax(np.abs(values(rest[key]) - values(whole[key])), initial=0.0) for key in rest) < 0.005
    # The frames the reads from 500 on (1.0 s of reads, 2 ms apart) complete are replayed, every one.
    tail = Decoder().feed(b"".join(chunk for i, chunk in reads(pressed) if i >= 500))
    assert rest.keys() == {(f.sensor, f.seq, f.t_us) for f in tail if f.type in DATA_TYPES} and len(rest) > 3000
    assert "replayed from read 500, where the recording holds those then in force" in caplog.text
    from service.board import Board, BoardSpec  # served live (replay --serve): the same reads, name and zeros
    from service.calibration.book import CalibrationBook
    from service.history import Histories
    from service.sources.protocol_replay import Serial

    board = Board(BoardSpec(f"replay://{tmp_path / 'damaged.mcap'}?speed=max"), CalibrationBook(), Histories())
    assert board.pipeline.interpreter.board_name == pipeline.interpreter.name
    assert sorted(board.pipeline.reconstructor._preset) == sorted(pipeline.interpreter.sensors)
    port, served = Serial(f"replay://{tmp_path / 'damaged.mcap'}?speed=max"), b""
    while not (port.finished and not port.in_waiting):
        served += port.read(1 << 16)
    assert served == b"".join(chunk for i, chunk in reads(pressed) if i >= 500)


def test_a_forced_zero_a_recording_began_with_is_not_judged_again_at_a_calibration_set_while_recording(tmp_path):
    """Taxel 27 holds +5 % ΔC/C0 (~4 N) when sensor 0 is tared with
    force=true (the load is its zero, as asked); a recording begins, then a
    calibration with its measured C0 is set. Live, the forced zero stays (27
    reads ~0 N); the replay started from the zero without knowing it was
    forced, judged it against the new C0 and read 27 at its full load
    (4.82 N, flagged loaded_at_tare) on all 300 frames after the upload."""
    from service.calibration.registry import builtin_document
    from service.protocol import FrameType, encode_frame

    rng = np.random.default_rng(3)
    c0 = np.array(builtin_document()["taxels"]["c0_pF"])  # pF (64,): the emulated sensor's own C0
    reads_ = []
    for read in range(90):  # 10 scans a read
        chunk = b""
        for seq in range(10 * read, 10 * read + 10):
            grid = c0 * np.where((np.arange(64) == 27) & (seq >= 200), 1.05, 1.0) + rng.normal(0, 0.002, 64)
            chunk += encode_frame(FrameType.GRID, 0, seq, 1000 * seq, np.round(grid * 1e6).astype("<u4").tobytes())
        reads_.append(chunk)
    pipeline = Pipeline(Reconstructor(level="table"))
    recorder = None
    for read, chunk in enumerate(reads_):
        if read == 30:
            pipeline.tare(0, force=True)  # zero ready at scan 400
        if read == 50:
            recorder = Recorder(tmp_path / "run.mcap")
            recorder.attach(pipeline)
        if read == 60:
            pipeline.set_calibration(pipeline.interpreter.sensors[0],
                                     {"sensitivity_pct_per_N": [1.1] * 64, "c0_pF": c0.tolist()})
        pipeline.feed(chunk, 1000.0 + 0.01 * read)
    recorder.stop()
    live = by_frame(recorded_forces(tmp_path / "run.mcap"))
    uploaded = [d for d in live.values() if d["calibration"] != "builtin-table1"]
    assert len(live) == 400 and len(uploaded) == 300
    assert all(abs(d["taxels_N"][27]) <= 3 * d["sigma_N"][27] and "loaded_at_tare" not in d["flags"] for d in uploaded)
    again = by_frame(replayed_forces(tmp_path / "run.mcap"))
    assert again == live

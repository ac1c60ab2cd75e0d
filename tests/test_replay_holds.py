"""A replay holds the frames a live link held for the board's INFO (identify.py),
where live held them: a recording keeps the wait's state when it began and
the link's events by read (/link: where it dropped, where a wait passed), so
its frames come out as a client received them live, board by board —
through the export (joined or paced) and through replay:// alike. Without
them (a recording made before), board B's first frames replayed under A's
description and on A's zero."""
import asyncio
import math
import time

import orjson
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from service.board import Board, BoardSpec
from service.calibration.book import CalibrationBook
from service.history import Histories
from service.pipeline import Pipeline
from service.readout import INFO_REPLY_S
from service.reconstruct import Reconstructor
from service.record.mcap_reader import read_changes, read_settings
from service.record.pacing import Pacer
from service.record.recorder import Recorder
from service.replay import replay_boards
from service.sources.protocol_replay import Serial
from tests.test_reidentify import GRID_C0, QUAD_C0, Scans, TcpBoard


class Frames:
    """A replay's writer: the frames, as they come."""

    def __init__(self) -> None:
        self.frames = []

    def write(self, frames) -> None:
        self.frames.extend(frames)


def received(frame, clock: bool = True) -> tuple:
    """What a client gets of ``frame``: its sensor, scan, the INFO it was
    read under, its calibration, flags and forces with σ as bits.
    ``clock`` False leaves out clock_suspect (replay:// stamps its reads with
    the replay's own clock: it says how they came, not what they hold)."""
    flags = [flag for flag in frame.flags if clock or flag != "clock_suspect"]
    sigma = None if frame.sigma_N is None else frame.sigma_N.tobytes()
    return (frame.sensor.id, frame.seq, frame.t_us, frame.sensor.board_info.get("serial"), frame.sensor.serial,
            frame.calibration, flags, frame.forces_N.tobytes(), sigma)


def by_sensor(frames, clock: bool = True) -> dict[int, list[tuple]]:
    """Each sensor's frames in the order published."""
    out: dict[int, list[tuple]] = {}
    for frame in frames:
        out.setdefault(frame.sensor.id, []).append(received(frame, clock))
    return out


def exported(path, paced: bool = False):
    """The recording's frames through ``tactile replay`` (--export): reads
    joined at full speed, or one by one paced (a virtual clock: no waiting)."""
    writer = Frames()
    now = [0.0]
    pacer = Pacer(1e3, clock=lambda: now[0], sleep=lambda s: now.__setitem__(0, now[0] + s)) if paced else None
    replay_boards(path, writer=writer, pacer=pacer)
    return writer.frames


def served(path, read_size: int = 4096, merge: int = 1):
    """The recording through ``tactile replay --serve``'s Board for its
    replay:// URL, its port read ``read_size`` bytes at a time and ``merge``
    port reads fed as one (not as recorded), as the loop feeds them."""
    url = f"replay://{path}?speed=max"
    board = Board(BoardSpec(url, level="table"), CalibrationBook(use_registry=False), Histories())
    frames = []
    board.pipeline.listeners.append(frames.extend)
    port = Serial(url)
    try:
        t = 5000.0
        while chunk := b"".join(port.read(read_size) for _ in range(merge)):
            board.pipeline.feed_reads([(chunk, t)], lambda work: work())
            t += 0.002
    finally:
        port.close()
    board.pipeline.link_lost()  # the service stopping: what a hold still had goes on, as live at its stop
    return frames


def rewritten(path, out, edit, topics: tuple[str, ...] = ("/link", "/settings", "/resume")) -> None:
    """``path`` copied to ``out``, message by message in file order, each
    message of ``topics`` as ``edit(doc)`` makes it (None: left out)."""
    with open(path, "rb") as source, open(out, "wb") as stream:
        writer = Writer(stream)
        writer.start()
        schemas, channels = {}, {}
        for schema, channel, message in make_reader(source).iter_messages(log_time_order=False):
            data = message.data
            if channel.topic.endswith(topics):
                doc = edit(orjson.loads(data))
                if doc is None:
                    continue
                data = orjson.dumps(doc)
            if schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas[schema.id])
            writer.add_message(channels[channel.id], message.log_time, data, message.publish_time, message.sequence)
        writer.finish()


def as_before(path, old) -> None:
    """``path`` as a recording made before 2026-11-25: no /link, no wait's state in /settings or /resume."""
    rewritten(path, old, lambda doc: None if "event" in doc else {k: v for k, v in doc.items() if k != "identify"})


# On a pipeline, its timers run by hand: every kind of hold, each end, a tare during one.

B = dict(grid_c0=GRID_C0 * 1.06, quad_c0=QUAD_C0 * 1.06, seq=12000, t_us=60_000_000)


@pytest.fixture(scope="module")
def by_hand(tmp_path_factory):
    """(recording, frames published live) of a pipeline on a live link
    (identify_on_link, its timers kept): board A; the link lost and board B
    on it, its INFO 40 ms late; B restarted with grid G2 (C0 10 % higher),
    its INFO lost, a forced tare made while its frames wait, released by the
    hold's timer; the link lost again and board C, which never answers,
    released by a read 0.3 s on."""
    path = tmp_path_factory.mktemp("holds") / "run.mcap"
    pipeline = Pipeline(Reconstructor(level="table"))
    timers, published = [], []
    pipeline.identify_on_link(INFO_REPLY_S, lambda: None, lambda delay, fn: timers.append(fn))
    pipeline.listeners.append(published.extend)
    recorder = Recorder(path)
    recorder.attach(pipeline)
    a = Scans("A-1", seed=1)
    pipeline.feed(a.info() + a.next(10), 0.0)
    for k in range(1, 30):
        pipeline.feed(a.next(10), 0.02 * k)
    pipeline.link_lost()
    b = Scans("B-2", seed=2, **B)
    pipeline.feed(b.next(10), 1.0)
    pipeline.feed(b.next(10), 1.02)
    pipeline.feed(b.info() + b.next(10), 1.04)
    for k in range(20):
        pipeline.feed(b.next(10), 1.06 + 0.02 * k)
    g2 = Scans("B-2", "G2", grid_c0=GRID_C0 * 1.10, quad_c0=QUAD_C0 * 1.06, seed=3)  # restarted: seq, t_us from 0
    pipeline.feed(g2.next(10), 2.0)
    pipeline.feed(g2.next(10), 2.02)
    assert pipeline.identification.holding
    pipeline.tare(force=True)
    timers[-1]()  # its wait passed between two reads
    for k in range(20):
        pipeline.feed(g2.next(10), 2.04 + 0.02 * k)
    pipeline.link_lost()
    c = Scans("C-3", seq=30000, t_us=120_000_000, reply_s=None, seed=4)
    for k in range(4):
        pipeline.feed(c.next(10), 3.0 + 0.1 * k)  # the fourth, received past the wait, releases the rest
    for k in range(10):
        pipeline.feed(c.next(10), 3.32 + 0.02 * k)
    recorder.stop()
    return path, published


def test_the_recording_keeps_where_the_link_dropped_and_where_waits_passed(by_hand):
    """Read numbers counted from the recording's first: 30 of A, the link lost
    (before read 30), 23 of B, 2 of G2 and its timer (before read 55), 20 more,
    lost (before read 75), C's fourth read past its wait (read 78)."""
    path, _ = by_hand
    assert [(n, change) for n, _, change in read_changes(path)[None] if isinstance(change, str)] == \
        [(30, "lost"), (55, "expired"), (75, "lost"), (79, "expired")]
    assert read_settings(path)[None]["identify"] == {"wait_s": INFO_REPLY_S, "expecting": "opened", "holding": False}


@pytest.mark.parametrize("paced", [False, True])
def test_an_exported_replay_holds_what_the_live_link_held(by_hand, paced):
    """Sensor by sensor and scan by scan, the frames of the export are those
    published live: B's first 20 scans read under B's INFO (none under A's),
    the 20 held after B's restart read after the tare made meanwhile (the
    first of its window, 99 frames) and where the timer let them go, C's
    unidentified where its wait ended."""
    path, live = by_hand
    assert by_sensor(exported(path, paced)) == by_sensor(live)
    b_quad = [f for f in live if f.sensor.id == 1 and 12000 <= f.seq < 30000]
    assert len(b_quad) == 230 and {f.sensor.board_info["serial"] for f in b_quad} == {"B-2"}
    restarted = quad_after_restart(live)
    assert [f.seq for f in restarted] == list(range(220))
    assert ["taring" in f.flags for f in restarted[:101]] == [True] * 99 + [False] * 2


def quad_after_restart(frames):
    """The quad's frames from B's restart on (B's INFO in force: its own was lost)."""
    return [f for f in frames if f.sensor.id == 1 and f.seq < 12000 and f.sensor.board_info["serial"] == "B-2"]


@pytest.mark.parametrize("read_size, merge", [(4096, 1), (64, 1), (700, 3)])
def test_a_served_replay_holds_what_the_live_link_held(by_hand, read_size, merge):
    """replay:// (tactile replay --serve), its port's reads cut otherwise
    than recorded: the same frames as live, but for clock_suspect (its
    reads come at the replay's pace)."""
    path, live = by_hand
    assert by_sensor(served(path, read_size, merge), clock=False) == by_sensor(live, clock=False)


def test_a_recording_made_before_replays_as_it_did(by_hand, tmp_path):
    """Without /link nor the wait's state, nothing is held: B's first 20 quad
    scans come out under A's INFO and on A's zero (Fz up to ~1.8 N, flagged
    only seq_gap), and the 20 after B's restart before the tare made while
    live held them, as every replay did before 2026-11-25; the rest replays."""
    path, live = by_hand
    as_before(path, tmp_path / "old.mcap")
    assert "identify" not in read_settings(tmp_path / "old.mcap")[None]
    again = exported(tmp_path / "old.mcap")
    assert [received(f)[:3] for f in again] != [] and \
        sorted(received(f)[:3] for f in again) == sorted(received(f)[:3] for f in live)
    b_quad = [f for f in again if f.sensor.id == 1 and 12000 <= f.seq < 30000]
    under_a = [f for f in b_quad if f.sensor.board_info["serial"] == "A-1"]
    assert [f.seq for f in under_a] == list(range(12000, 12020))
    assert 1.0 < max(abs(f.forces_N[2]) for f in under_a) < 3.0
    assert {flag for f in under_a for flag in f.flags} == {"seq_gap"}
    assert ["taring" in f.flags for f in quad_after_restart(again)[:121]] == [False] * 20 + [True] * 99 + [False] * 2


def test_a_recording_whose_link_state_is_none_written_replays_as_it_came(by_hand, tmp_path, caplog):
    """A recording is any file: a wait's state or a link event no recorder
    writes is said, naming it, and the replay goes on as for a recording
    made before (nothing held), never cut short."""
    path, _ = by_hand
    rewritten(path, tmp_path / "odd.mcap", lambda doc: {**doc, "event": "dropped"} if "event" in doc else
              {**doc, "identify": {**doc["identify"], "expecting": "closed"}})
    as_before(path, tmp_path / "old.mcap")
    assert by_sensor(exported(tmp_path / "odd.mcap")) == by_sensor(exported(tmp_path / "old.mcap"))
    assert "'expecting': 'closed'" in caplog.text and "the link event 'dropped' recorded is none of lost, expired" \
        in caplog.text
    old = by_sensor(exported(tmp_path / "old.mcap"), clock=False)
    assert by_sensor(served(tmp_path / "odd.mcap"), clock=False) == old


# Live: a board behind TCP, the service's Board on an event loop, a recording of it.

def record_live(path) -> tuple[list, dict]:
    """(frames a client received, what was done) from a live Board on a
    TcpBoard, recorded to ``path``: board A; the port given to B, which
    answers INFO? 50 ms late; B restarted with grid G2, its INFO lost, and a
    forced tare made while its frames wait for the reply (150 ms late); the
    port given to C, which never answers."""
    device = TcpBoard(Scans("A-1", seed=1))
    published, done = [], {}

    async def run():
        spec = BoardSpec(f"socket://127.0.0.1:{device.port}", level="table")
        board = Board(spec, CalibrationBook(use_registry=False), Histories())
        board.pipeline.listeners.append(published.extend)
        recorder = Recorder(path)
        recorder.attach(board.pipeline)

        async def until(predicate, timeout=8.0):
            deadline = time.monotonic() + timeout
            while not predicate() and time.monotonic() < deadline:
                await asyncio.sleep(0.002)
            assert predicate()

        def frames_of(sid, low, high=math.inf):
            return sum(1 for f in published if f.sensor.id == sid and low <= f.seq < high)

        board.start(asyncio.get_running_loop())
        try:
            await until(lambda: frames_of(0, 0, 12000) >= 150)
            device.swap(Scans("B-2", reply_s=0.05, seed=2, **B))
            await until(lambda: frames_of(0, 12000, 30000) >= 250 and frames_of(1, 12000, 30000) >= 250)
            restarted = len(published)
            device.restart(Scans("B-2", "G2", grid_c0=GRID_C0 * 1.10, quad_c0=QUAD_C0 * 1.06, reply_s=0.15, seed=3))
            await until(lambda: board.pipeline.identification.holding)
            done["tared"] = board.tare(force=True)[0]
            await until(lambda: sum(1 for f in published[restarted:] if f.sensor.id == 0 and f.seq < 12000) >= 250)
            device.swap(Scans("C-3", seq=30000, t_us=120_000_000, reply_s=None, seed=4))
            await until(lambda: frames_of(0, 30000) >= 200 and frames_of(1, 30000) >= 200)
            board.readout.stop()
            await asyncio.sleep(0.1)  # the link's last word (lost) and grids deferred, on the loop
        finally:
            board.readout.stop()
            recorder.stop()

    try:
        asyncio.run(run())
    finally:
        device.close()
    return published, done


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    path = tmp_path_factory.mktemp("live") / "run.mcap"
    published, done = record_live(path)
    return path, published, done


def test_a_live_recording_replays_the_frames_a_client_received(live):
    """Over TCP, as ``tactile serve`` reads a board: B's frames waited for
    its late INFO, G2's for the reply to INFO? at its restart, and a tare
    made meanwhile took them into its window; C's went on after the wait.
    The export gives every one of them as published live, bit for bit."""
    path, published, done = live
    assert done["tared"] == [0, 1]
    events = [change for _, _, change in read_changes(path)[None] if isinstance(change, str)]
    assert events.count("lost") >= 3 and events.count("expired") >= 1  # two swaps and the stop; C's wait
    b = [f for f in published if f.sensor.id == 1 and 12000 <= f.seq < 30000]
    assert b and {f.sensor.board_info["serial"] for f in b} == {"B-2"}
    g2 = [f for f in published if f.sensor.id == 0 and f.sensor.serial == "G2"]
    assert len(g2) >= 250 and g2[0].seq == 0  # from its power-up on, under its own INFO
    assert by_sensor(exported(path)) == by_sensor(published)


def test_the_same_live_recording_without_its_link_events_replays_otherwise(live, tmp_path):
    """The check above can fail: made as before 2026-11-25, B's first scans
    (~25 of each sensor: 50 ms) replay under A's INFO."""
    path, published, _ = live
    as_before(path, tmp_path / "old.mcap")
    again = exported(tmp_path / "old.mcap")
    assert sorted(received(f)[:3] for f in again) == sorted(received(f)[:3] for f in published)
    for sid in (0, 1):
        under_a = [f.seq for f in again if f.sensor.id == sid and 12000 <= f.seq < 30000
                   and f.sensor.board_info["serial"] == "A-1"]
        assert 10 <= len(under_a) and under_a == list(range(12000, 12000 + len(under_a)))


def test_a_live_recording_served_again_gives_the_frames_a_client_received(live):
    path, published, _ = live
    assert by_sensor(served(path, 700, 3), clock=False) == by_sensor(published, clock=False)

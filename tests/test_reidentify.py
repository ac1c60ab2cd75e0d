"""Frames wait for the board on a live link to say what it is (identify.py):
after a restart whose power-up INFO was lost, and after the link reopens on
another board, no frame is read under another sensor's description or
zero. Over TCP with a fake board (as a USB board re-enumerated), and on the
pipeline with its timer and its INFO? asks in hand."""
import asyncio
import socket
import threading
import time

import numpy as np
import orjson

from service.board import Board, BoardSpec
from service.calibration.registry import builtin_document
from service.history import Histories
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.readout import INFO_REPLY_S
from service.reconstruct import Reconstructor

GRID_C0 = np.array(builtin_document()["taxels"]["c0_pF"])  # pF (64,): table 1's unloaded 8x8 taxels
QUAD_C0 = np.array([5.0, 5.1, 4.9, 5.05])  # pF (4,): a quad's electrodes unloaded
SCAN_US = 2000  # 500 scans/s per sensor
TAPER = [True] * 99 + [False] * 2  # "taring" on a sensor's first 101 frames when it tares afresh (100 frames)


class Scans:
    """One board's byte stream: its INFO, and scans of grid 0 (``rows`` x
    ``cols``, channels ``grid_c0`` pF) and quad 1 (``quad_c0`` pF), both
    unloaded (noise 2 fF), from ``seq`` and board time ``t_us`` on.
    ``reply_s``: how late it answers INFO? (None: never)."""

    def __init__(self, serial: str, grid_serial: str | None = None, grid_c0: np.ndarray = GRID_C0,
                 quad_c0: np.ndarray = QUAD_C0, rows: int = 8, cols: int = 8, seq: int = 0, t_us: int = 0,
                 reply_s: float | None = 0.0, seed: int = 0) -> None:
        grid = {"id": 0, "kind": "grid", "rows": rows, "cols": cols} | ({"serial": grid_serial} if grid_serial else {})
        self.doc = {"board": "fake", "fw": "1.1.0", "serial": serial, "rate_hz": 500,
                    "sensors": [grid, {"id": 1, "kind": "quad"}]}
        self.grid_c0, self.quad_c0 = np.resize(grid_c0, rows * cols), quad_c0
        self.seq, self.t_us, self.reply_s = seq, t_us, reply_s
        self.rng = np.random.default_rng(seed)

    def info(self) -> bytes:
        return encode_frame(FrameType.INFO, 255, 0, self.t_us, orjson.dumps(self.doc))

    def next(self, n: int) -> bytes:
        out = bytearray()
        for _ in range(n):
            grid = np.round((self.grid_c0 + self.rng.normal(0, 0.002, self.grid_c0.size)) * 1e6).astype("<u4")
            quad = np.round((self.quad_c0 + self.rng.normal(0, 0.002, 4)) * 1e6).astype("<u4")
            out += encode_frame(FrameType.GRID, 0, self.seq, self.t_us, grid.tobytes())
            out += encode_frame(FrameType.QUAD, 1, self.seq, self.t_us + 500, quad.tobytes())
            self.seq, self.t_us = self.seq + 1, self.t_us + SCAN_US
        return bytes(out)


class TcpBoard:
    """A board behind TCP, one connection at a time: 5 scans every 10 ms,
    INFO? answered ``reply_s`` late; ``swap`` closes the connection and
    gives the port to another board (USB re-enumeration), ``restart`` powers
    it up again on the same connection with its power-up INFO corrupted."""

    def __init__(self, scans: Scans) -> None:
        self.scans = scans
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.05)
        self.port = self.server.getsockname()[1]
        self.asked: list[float] = []  # when INFO? came
        self._conn: socket.socket | None = None
        self._accepted: list[socket.socket] = []  # all closed at the end
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._accept, daemon=True),
                         threading.Thread(target=self._stream, daemon=True)]
        for thread in self._threads:
            thread.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except OSError:
                continue
            with self._lock:
                self._accepted.append(conn)
                self._conn = conn
            threading.Thread(target=self._commands, args=(conn,), daemon=True).start()

    def _commands(self, conn: socket.socket) -> None:
        buffer = b""
        while True:
            try:
                data = conn.recv(4096)
            except OSError:
                return
            if not data:
                return
            buffer += data
            while b"\n" in buffer:
                line, buffer = buffer.split(b"\n", 1)
                if line == b"INFO?":
                    self.asked.append(time.monotonic())
                    scans = self.scans
                    if scans.reply_s is not None:
                        threading.Timer(scans.reply_s, self._send, (conn, scans.info())).start()

    def _send(self, conn: socket.socket, data: bytes) -> None:
        with self._lock:
            if conn is self._conn:
                try:
                    conn.sendall(data)
                except OSError:
                    self._conn = None

    def _stream(self) -> None:
        while not self._stop.wait(0.01):
            with self._lock:
                conn = self._conn
                if conn is not None:
                    try:
                        conn.sendall(self.scans.next(5))
                    except OSError:
                        self._conn = None

    def swap(self, scans: Scans) -> None:
        with self._lock:
            if self._conn is not None:
                self._conn.close()
                self._conn = None
            self.scans = scans

    def restart(self, scans: Scans) -> None:
        with self._lock:
            self.scans = scans
            lost = bytearray(scans.info())
            lost[30] ^= 1  # the power-up INFO, corrupted on the wire: its CRC fails
            self._conn.sendall(bytes(lost))

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(1.0)
        with self._lock:
            for conn in self._accepted:
                conn.close()
        self.server.close()


def serve(device: TcpBoard, scenario) -> list:
    """Run a live board (its readout on an event loop, as ``tactile serve``)
    on ``device`` through ``scenario(frames, until)``; returns the frames
    published, each with the time it was published."""
    published = []

    async def run():
        board = Board(BoardSpec(f"socket://127.0.0.1:{device.port}", level="table"), None, Histories())
        board.pipeline.listeners.append(lambda frames: published.extend((f, time.time()) for f in frames))

        async def until(predicate, timeout=8.0):
            deadline = time.monotonic() + timeout
            while not predicate() and time.monotonic() < deadline:
                await asyncio.sleep(0.01)
            assert predicate()

        board.start(asyncio.get_running_loop())
        try:
            await scenario(published, until)
        finally:
            board.readout.stop()

    try:
        asyncio.run(run())
    finally:
        device.close()
    return published


def count(published, sid: int, since: int = 0):
    return lambda: sum(1 for f, _ in published[since:] if f.sensor.id == sid)


def unloaded_within_3_sigma(frames) -> float:
    """Share of the forces of ``frames`` (unloaded: truth 0 N) within 3σ of 0 (a NaN is not)."""
    return np.mean(np.concatenate([np.abs(f.forces_N) <= 3 * f.sigma_N for f in frames]))


def test_a_restart_whose_info_was_lost_asks_info_once_and_reads_the_new_sensor_on_its_own_zero():
    """Grid G1 swapped for G2 (C0 10 % higher, unloaded) while the board was
    off; its power-up INFO corrupted. The service asked nothing and read all
    450 of G2's frames as G1 on G1's zero: 8.55 N on its most loaded taxel
    (σ 0.60), unflagged (the tester's 4x6: 12.1 N). Now: one INFO? at the
    restart, G2 described and tared afresh, 0 N within 3σ; nothing lost."""
    device = TcpBoard(Scans("E-1", "G1", seed=1))
    restarted = []

    async def scenario(published, until):
        await until(lambda: count(published, 0)() >= 300)  # G1 read and tared
        restarted.append((len(published), len(device.asked)))
        device.restart(Scans("E-1", "G2", grid_c0=GRID_C0 * 1.10, seed=2))
        await until(lambda: count(published, 0, restarted[0][0])() >= 450)

    published = serve(device, scenario)
    since, asked_before = restarted[0]
    grid = [f for f, _ in published[since:] if f.sensor.id == 0]
    g2 = grid[next(k for k, f in enumerate(grid) if "board_restart" in f.flags):]
    assert len(device.asked) - asked_before == 1  # INFO? once, at the restart
    assert sum(f.sensor.serial != "G2" for f in g2) == 0  # no frame of G2 under G1's description
    assert [f.seq for f in g2] == list(range(len(g2)))  # every scan since its power-up, in order
    assert ["taring" in f.flags for f in g2[:101]] == TAPER  # its own zero, not G1's
    assert unloaded_within_3_sigma(g2[150:]) >= 0.98
    quad = [f for f, _ in published[since:] if f.sensor.id == 1]
    assert not any("taring" in f.flags for f in quad)  # the quad, described as before, keeps its zero
    assert unloaded_within_3_sigma(quad) >= 0.98


def test_another_board_on_the_reopened_port_answering_late_is_never_read_as_the_first():
    """Board B (ahead of A: seq 12000, clock +60 s; C0 6 % above A's) takes
    the port and answers INFO? 50 ms late: its first ~25 scans per sensor
    were read as A's, on A's zeros (grid 12 N, quad Fz 4.5 N). Now they wait
    for its INFO and are read under it: 0 of them as A's, B tared afresh."""
    device = TcpBoard(Scans("A-1", seed=1))
    marks = []

    async def scenario(published, until):
        await until(lambda: count(published, 0)() >= 300)
        marks.append(len(published))
        device.swap(Scans("B-2", grid_c0=GRID_C0 * 1.06, quad_c0=QUAD_C0 * 1.06, seq=12000, t_us=60_000_000,
                          reply_s=0.05, seed=2))
        await until(lambda: count(published, 0, marks[0])() >= 400 and count(published, 1, marks[0])() >= 400)

    published = serve(device, scenario)
    b = [(f, at) for f, at in published[marks[0]:] if f.seq >= 12000]
    assert sum(f.sensor.board_info.get("serial") != "B-2" for f, _ in b) == 0  # none under A's description
    for sid in (0, 1):
        frames = [f for f, _ in b if f.sensor.id == sid]
        assert [f.seq for f in frames] == list(range(12000, 12000 + len(frames)))  # every scan, in order
        assert ["taring" in f.flags for f in frames[:101]] == TAPER  # B's own zero
        assert unloaded_within_3_sigma(frames[150:]) >= 0.98
    late = [at - f.t_host for f, at in b[200:]]
    assert np.median(late) < 0.05  # once B is identified, nothing waits


def test_a_board_that_never_answers_info_still_streams_after_the_wait():
    """Board B never answers INFO?: its frames wait INFO_REPLY_S, then go on
    as before the wait was made (under the description in force), none lost."""
    device = TcpBoard(Scans("A-1", seed=1))
    marks = []

    async def scenario(published, until):
        await until(lambda: count(published, 0)() >= 300)
        marks.append(len(published))
        device.swap(Scans("B-2", seq=12000, t_us=60_000_000, reply_s=None, seed=2))
        await until(lambda: count(published, 0, marks[0])() >= 300)

    published = serve(device, scenario)
    b = [(f, at) for f, at in published[marks[0]:] if f.seq >= 12000]
    grid = [f for f, _ in b if f.sensor.id == 0]
    assert [f.seq for f in grid] == list(range(12000, 12000 + len(grid)))
    assert {f.sensor.board_info.get("serial") for f, _ in b} == {"A-1"}  # unidentified, it cannot be told from A
    first_wait = b[0][1] - b[0][0].t_host
    assert INFO_REPLY_S - 0.02 <= first_wait <= INFO_REPLY_S + 0.3  # held the bound, not for good
    assert np.median([at - f.t_host for f, at in b[200:]]) < 0.05  # then streamed as it comes


def live_pipeline():
    """A pipeline whose frames wait for INFO as on a live link: its INFO?
    asks and its timers kept to be run by hand."""
    pipeline = Pipeline(Reconstructor(level="table"), map_clock=False)
    asked, timers, published = [], [], []
    pipeline.identify_on_link(INFO_REPLY_S, lambda: asked.append(True), lambda delay, fn: timers.append((delay, fn)))
    pipeline.listeners.append(published.extend)
    return pipeline, asked, timers, published


def test_frames_of_a_new_shape_after_a_lost_info_wait_for_the_reply_and_none_is_dropped():
    """A 4x6 grid replaced by an 8x8 while the board was off, its INFO lost:
    every 8x8 frame was dropped as shape_mismatch, 200/s, for good. Held
    until the reply to INFO?, each is read as the 8x8 it is."""
    pipeline, asked, timers, published = live_pipeline()
    small = Scans("E-1", grid_c0=np.full(24, 5.0), rows=4, cols=6, seed=1)
    t = 0.0
    pipeline.feed(small.info() + small.next(10), t)
    for _ in range(20):
        t += 0.02
        pipeline.feed(small.next(10), t)
    large = Scans("E-1", seed=2)
    for _ in range(3):  # 30 scans before the reply, 60 ms
        t += 0.02
        pipeline.feed(large.next(10), t)
    assert len(timers) == 2 and len(asked) == 1  # a hold on connect (the readout asked), one at the restart: asked
    before = len(published)
    t += 0.02
    pipeline.feed(large.info() + large.next(10), t)
    after = [f for f in published[before:] if f.sensor.id == 0]
    assert [(f.seq, f.sensor.rows, f.sensor.cols) for f in after] == [(k, 8, 8) for k in range(40)]
    assert pipeline.interpreter.rejected["shape_mismatch"] == 0
    assert len(asked) == 1


def test_held_frames_go_on_at_the_bound_when_no_reply_comes():
    """No reply to the INFO? at a restart: the hold's timer releases its frames,
    in order, under the description in force; a read past the bound does too."""
    pipeline, asked, timers, published = live_pipeline()
    board = Scans("E-1", seed=1)
    pipeline.feed(board.info() + board.next(200), 0.0)
    assert len(published) == 400
    board.seq, board.t_us = 0, 0  # a restart, INFO lost
    pipeline.feed(board.next(10), 1.0)
    assert len(published) == 400 and len(asked) == 1
    delay, expire = timers[-1]
    assert delay == INFO_REPLY_S
    expire()
    assert [(f.sensor.id, f.seq) for f in published[400:]] == [(sid, k) for k in range(10) for sid in (0, 1)]
    pipeline.feed(board.next(10), 1.3)  # the stream goes on as it comes
    assert len(published) == 440
    board.seq, board.t_us = 0, 0  # another restart: its frames go on with the first read past the bound
    pipeline.feed(board.next(10), 3.0)
    pipeline.feed(board.next(10), 3.0 + INFO_REPLY_S / 2)
    assert len(published) == 440
    pipeline.feed(board.next(10), 3.0 + INFO_REPLY_S)
    assert [f.seq for f in published[440:] if f.sensor.id == 0] == list(range(30))
    timers[-1][1]()  # that hold's timer, late: nothing left to release
    assert len(published) == 500


def test_a_frame_its_description_cannot_read_asks_info():
    """Without a restart found, a frame of another size than its sensor's
    INFO gives asks INFO? (the readout sends one a second at most)."""
    pipeline, asked, _, _ = live_pipeline()
    board = Scans("E-1", seed=1)
    pipeline.feed(board.info() + board.next(10), 0.0)
    assert len(asked) == 0  # the readout asked on connect
    odd = encode_frame(FrameType.GRID, 0, board.seq, board.t_us, bytes(4 * 24))  # a 4x6's payload, next in sequence
    board.seq, board.t_us = board.seq + 1, board.t_us + SCAN_US
    pipeline.feed(odd, 0.01)
    assert pipeline.interpreter.rejected["shape_mismatch"] == 1 and len(asked) == 1
    pipeline.feed(board.next(10), 0.02)
    assert len(asked) == 1  # frames that fit ask nothing


def test_a_sensor_the_info_leaves_undescribed_on_purpose_asks_nothing():
    """A thermistor in the board's INFO (a kind this service does not read: no fault, board_info.UNKNOWN_KIND)
    sending a reading with every read: each read asked INFO?, 100 of 100 (the readout let one a second
    through, for ever, each reply re-describing every sensor). Its frames are still counted, and ask nothing."""
    pipeline, asked, _, published = live_pipeline()
    board = Scans("E-1", seed=1)
    board.doc["sensors"].append({"id": 2, "kind": "thermistor"})
    pipeline.feed(board.info() + board.next(10), 0.0)
    for k in range(1, 101):
        therm = encode_frame(FrameType.GRID, 2, k, board.t_us, (2500).to_bytes(4, "little"))
        pipeline.feed(board.next(10) + therm, 0.02 * k)
    assert len(asked) == 0 and pipeline.interpreter.rejected["unknown_shape"] == 100
    assert len(published) == 2 * 1010


def test_frames_that_do_not_fit_ask_info_once_per_sensor_and_info():
    """A grid its INFO describes as 4x6 sending 8x8 frames, and a sensor 3 no INFO describes sending 4x4 ones:
    every read asked INFO?, and the reply (the same INFO) changed nothing. Now each sensor asks once under the
    INFO in force: grid 0 once, the same INFO again nothing, sensor 3 once, an INFO that differs (it describes
    sensor 3) once more for grid 0, which it still does not fit."""
    pipeline, asked, _, _ = live_pipeline()
    board = Scans("E-1", rows=4, cols=6, seed=1)
    info = board.info()
    board.grid_c0 = GRID_C0  # 8x8 frames under a 4x6's description

    def reads(count: int, start_s: float, sensor_3: bool = False) -> None:
        for k in range(count):
            small = encode_frame(FrameType.GRID, 3, board.seq, board.t_us, bytes(4 * 16)) if sensor_3 else b""
            pipeline.feed(board.next(10) + small, start_s + 0.02 * k)

    pipeline.feed(info + board.next(10), 0.0)
    assert len(asked) == 1
    reads(50, 0.02)
    pipeline.feed(info + board.next(10), 1.02)  # its answer to INFO?, the same
    reads(50, 1.04)
    assert len(asked) == 1
    reads(50, 2.04, sensor_3=True)
    assert len(asked) == 2
    board.doc["sensors"].append({"id": 3, "kind": "grid", "rows": 4, "cols": 4})
    pipeline.feed(board.info() + board.next(10), 3.04)
    reads(50, 3.06, sensor_3=True)
    assert len(asked) == 3
    # Every frame not read is still counted: grid 0's 10 a read over 203 reads, sensor 3's until described
    assert pipeline.interpreter.rejected == {"info_invalid": 0, "shape_mismatch": 2030, "unknown_shape": 50}


def test_info_is_asked_with_the_pipeline_free():
    """At a restart whose INFO was lost the pipeline asked INFO? holding its lock, so a readout waiting on its
    port held every tare, calibration and recorder stop with it. Both asks (the restart's, a frame its
    description cannot read) now come with the lock free."""
    pipeline = Pipeline(Reconstructor(level="table"), map_clock=False)
    locked = []
    pipeline.identify_on_link(INFO_REPLY_S, lambda: locked.append(pipeline._lock.locked()), lambda delay, fn: None)
    board = Scans("E-1", seed=1)
    pipeline.feed(board.info() + board.next(10), 0.0)
    board.seq, board.t_us = 0, 0  # a restart, its INFO lost
    pipeline.feed(board.next(10), 1.0)
    pipeline.feed(board.info() + encode_frame(FrameType.GRID, 0, 10, board.t_us, bytes(4 * 24)), 1.02)
    assert locked == [False, False]


def test_a_link_lost_while_holding_releases_its_frames_and_the_next_link_waits():
    """Frames held when the link drops go on (nothing lost); the next link's wait for its INFO."""
    pipeline, _, _, published = live_pipeline()
    board = Scans("E-1", seed=1)
    pipeline.feed(board.info() + board.next(100), 0.0)
    pipeline.link_lost()
    pipeline.feed(board.next(5), 1.0)
    assert len(published) == 200
    pipeline.link_lost()
    assert [f.seq for f in published[200:] if f.sensor.id == 0] == list(range(100, 105))
    pipeline.feed(board.next(5), 2.0)
    assert len(published) == 210
    pipeline.feed(board.info() + board.next(5), 2.01)
    assert [f.seq for f in published[210:] if f.sensor.id == 0] == list(range(105, 115))


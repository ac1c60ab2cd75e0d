"""The readout over TCP, by its thread or by an event loop: reading, and
surviving the device going away."""
import asyncio
import threading
import time
from functools import partial

import pytest

from firmware_sim import frontends
from firmware_sim.board import Board, BoardConfig
from service.pipeline import Pipeline
from service.handover import ThreadSink
from service.readout import ASK_INFO_EVERY_S, INFO_REPLY_S, Readout


def wait_for(predicate, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.01)
    return False


class TcpBoard:
    """A simulated board behind TCP that can be unplugged and plugged back."""

    def __init__(self):
        self.board = Board(BoardConfig(scene="idle"))
        self.t0 = time.monotonic()
        self.port = None
        self.plug()

    def plug(self):
        server = frontends.tcp_server("127.0.0.1", self.port or 0)
        self.port = server.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, args=(server,), daemon=True)
        self.thread.start()

    def _serve(self, server):
        with server:
            frontends.serve_tcp(self.board, server, self.stop, self.t0)

    def unplug(self):
        self.stop.set()
        self.thread.join()


def test_reads_and_reconnects_after_the_device_goes_away():
    device = TcpBoard()
    pipeline = Pipeline()
    readout = Readout(f"socket://127.0.0.1:{device.port}", ThreadSink(pipeline.feed, pipeline.link_lost), backoff_s=(0.02, 0.1))
    readout.start()
    try:
        assert wait_for(lambda: pipeline.decoder.counters.sensor(0).frames > 200)
        assert readout.link.up and readout.link.connects == 1
        device.unplug()
        assert wait_for(lambda: not readout.link.up)
        time.sleep(0.3)  # the board keeps scanning while unplugged
        frames_before = pipeline.decoder.counters.sensor(0).frames
        device.plug()
        assert wait_for(lambda: pipeline.decoder.counters.sensor(0).frames > frames_before + 200)
        assert readout.link.connects == 2 and readout.link.up
        counters = pipeline.decoder.counters.sensor(0)
        assert counters.seq_gaps >= 1
        assert counters.missed_frames >= 250  # at least ~0.3 s of 1 kHz scans
        assert pipeline.decoder.counters.crc_errors == 0
        assert readout.is_alive()
    finally:
        readout.stop()
        device.unplug()


def test_an_event_loop_reads_a_source_with_a_descriptor_and_survives_unplugging():
    device = TcpBoard()
    pipeline = Pipeline()
    reading_threads = set()

    class Sink:
        """Tells which way each chunk came, and on which thread."""

        def on_loop(self, data, t_host):
            reading_threads.add(("on_loop", threading.get_ident()))
            pipeline.feed(data, t_host)

        def from_thread(self, data, t_host):
            reading_threads.add(("from_thread", threading.get_ident()))
            pipeline.feed(data, t_host)

        def link_lost(self):
            pipeline.link_lost()

    def frames():
        return pipeline.decoder.counters.sensor(0).frames

    async def until(predicate, timeout=5.0):
        deadline = time.monotonic() + timeout
        while not predicate() and time.monotonic() < deadline:
            await asyncio.sleep(0.01)
        return predicate()

    async def scenario():
        loop = asyncio.get_running_loop()
        readout = Readout(f"socket://127.0.0.1:{device.port}", Sink(), backoff_s=(0.02, 0.1))
        readout.start(loop)
        try:
            assert await until(lambda: frames() > 200)
            device.unplug()
            assert await until(lambda: not readout.link.up)
            await asyncio.sleep(0.3)  # the board keeps scanning while unplugged
            before = frames()
            device.plug()
            assert await until(lambda: frames() > before + 200)
            assert readout.link.connects == 2 and readout.link.up
        finally:
            started = time.monotonic()
            readout.stop()  # on the loop's own thread: it must not wait for the loop
            stop_took = time.monotonic() - started
            device.unplug()
        return threading.get_ident(), stop_took, readout

    loop_thread, stop_took, readout = asyncio.run(scenario())
    assert reading_threads == {("on_loop", loop_thread)}  # every read was the loop's, none the readout thread's
    assert stop_took < 0.5 and not readout.is_alive()
    counters = pipeline.decoder.counters.sensor(0)
    assert counters.seq_gaps >= 1 and counters.missed_frames >= 250
    assert pipeline.decoder.counters.crc_errors == 0


def test_unreachable_source_keeps_retrying_and_reports_why():
    pipeline = Pipeline()
    readout = Readout("socket://127.0.0.1:1", ThreadSink(pipeline.feed, pipeline.link_lost), backoff_s=(0.01, 0.02))
    readout.start()
    try:
        assert wait_for(lambda: readout.link.last_error is not None)
        assert "127.0.0.1:1" in readout.link.last_error
        assert not readout.link.up and readout.is_alive()
    finally:
        readout.stop()


class MuteBoard:
    """Accepts connections, records what the host sends, and sends nothing."""

    def __init__(self):
        import socket

        self.server = socket.create_server(("127.0.0.1", 0))
        self.port = self.server.getsockname()[1]
        self.received = b""
        self.accepted = 0
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        self.server.settimeout(0.05)
        connections = []
        while self.server.fileno() != -1:
            try:
                conn, _ = self.server.accept()
                conn.setblocking(False)
                connections.append(conn)
                self.accepted += 1
            except OSError:
                pass
            for conn in connections:
                try:
                    self.received += conn.recv(4096)
                except OSError:
                    pass
        for conn in connections:
            conn.close()

    def close(self):
        self.server.close()
        self.thread.join(1.0)


@pytest.mark.parametrize("on_loop", [False, True])
def test_a_board_that_connects_and_says_nothing_is_stale_then_asked_then_reopened(on_loop):
    board = MuteBoard()
    pipeline = Pipeline()
    sink = ThreadSink(pipeline.feed, pipeline.link_lost)
    readout = Readout(f"socket://127.0.0.1:{board.port}", sink, backoff_s=(0.02, 0.1), silence_s=0.6)

    def scenario():
        started = time.monotonic()
        assert wait_for(lambda: readout.link.up)
        assert readout.link.state(time.time()) == "up"
        assert wait_for(lambda: readout.link.state(time.time()) == "stale", 2.0)
        stale_after = time.monotonic() - started
        assert wait_for(lambda: board.received.count(b"INFO?\n") >= 2, 2.0)  # on connect, then asked again
        assert wait_for(lambda: readout.link.connects >= 2, 2.0)  # and reopened
        return stale_after, time.monotonic() - started

    try:
        if on_loop:
            async def run():
                readout.start(asyncio.get_running_loop())
                return await asyncio.to_thread(scenario)

            stale_after, reopened_after = asyncio.run(run())
        else:
            readout.start()
            stale_after, reopened_after = scenario()
    finally:
        readout.stop()
        board.close()
    assert 0.45 < stale_after < 1.0  # stale after 0.5 s of silence
    assert 0.6 + 0.5 <= reopened_after < 2.0  # INFO? at 0.6 s of silence, reopened 0.5 s later
    assert "no bytes for" in readout.link.last_error


def test_a_replugged_device_is_read_again_within_half_a_second():
    device = TcpBoard()
    pipeline = Pipeline()
    readout = Readout(f"socket://127.0.0.1:{device.port}", ThreadSink(pipeline.feed, pipeline.link_lost))
    readout.start()
    took = []
    try:
        for away_s in (0.3, 1.1, 2.3):  # at different points of the backoff
            assert wait_for(lambda: readout.link.up)
            device.unplug()
            assert wait_for(lambda: not readout.link.up)
            time.sleep(away_s)
            connects = readout.link.connects
            device.plug()
            replugged = time.monotonic()
            assert wait_for(lambda: readout.link.connects > connects)
            took.append(time.monotonic() - replugged)
    finally:
        readout.stop()
        device.unplug()
    assert max(took) < 0.6  # backoff capped at 0.5 s


class Port:
    """A source that reads nothing and keeps what is written to it."""

    def __init__(self):
        self.written = b""

    def read(self, timeout):
        time.sleep(timeout)
        return b""

    def write(self, data):
        self.written += data

    def finished(self):
        return False

    def fileno(self):
        return None

    def close(self):
        pass


def test_info_is_asked_at_most_once_a_second_and_not_while_the_link_is_down():
    """A board that never answers, sending frames its INFO cannot read: the
    pipeline asks at every read; the board gets INFO? once a second (written
    by the readout's thread, waited for here)."""
    now = [100.0]
    port = Port()
    readout = Readout("fake://", ThreadSink(lambda data, t_host: None, lambda: None), opener=lambda url: port,
                      clock=lambda: now[0], silence_s=1e9)
    assert not readout.ask_info()  # not connected yet
    readout.start()
    try:
        deadline = time.monotonic() + 2
        while not readout.link.up and time.monotonic() < deadline:
            time.sleep(0.01)
        asks = []
        for _ in range(40):  # 5 s of reads 1/8 s apart
            asks.append(readout.ask_info())
            assert wait_for(lambda: port.written.count(b"INFO?") == 1 + sum(asks))
            now[0] += 0.125
    finally:
        readout.stop()
    assert port.written.count(b"INFO?") == 1 + 5  # on connect, then once a second
    assert [k for k, sent in enumerate(asks) if sent] == [round(k * ASK_INFO_EVERY_S / 0.125) for k in range(5)]


class StuckPort(Port):
    """A port that stops taking bytes (flow control held, hung firmware: pyserial's write has no timeout) until
    ``release`` is set."""

    def __init__(self):
        super().__init__()
        self.release = threading.Event()

    def write(self, data):
        self.release.wait()
        super().write(data)


def test_ask_info_never_waits_for_a_port_that_does_not_take_bytes():
    """The readout's thread stuck writing START/INFO? on connect: ask_info (called on the event loop) waited on
    its write lock, and had not returned after 2 s, stalling every board and the API. It now returns at once
    (asked), and the readout's thread writes the INFO? when the port takes bytes again."""
    port = StuckPort()
    readout = Readout("fake://", ThreadSink(lambda data, t_host: None, lambda: None), opener=lambda url: port,
                      silence_s=1e9)
    readout.start()
    try:
        assert wait_for(lambda: readout.link.up)
        asked = []
        threading.Thread(target=lambda: asked.append(readout.ask_info()), daemon=True).start()
        assert wait_for(lambda: asked, 0.1) and asked == [True]
        port.release.set()
        assert wait_for(lambda: port.written == b"START\nINFO?\nINFO?\n", 1.0), port.written
    finally:
        port.release.set()
        readout.stop()


def test_every_restart_without_info_is_asked_unless_an_info_is_still_awaited():
    """A board restarting 0.9 s apart, its INFO lost each time: the second
    restart was not asked (the once-a-second limit), its frames went on
    unidentified. Now each restart's wait asks; only an INFO? sent less than
    INFO_REPLY_S before (its answer may still come) holds it back, and the
    limit still holds back repeats asked for unreadable frames."""
    from tests.test_reidentify import Scans

    now = [100.0]
    port = Port()
    readout = Readout("fake://", ThreadSink(lambda data, t_host: None, lambda: None), opener=lambda url: port,
                      clock=lambda: now[0], silence_s=1e9)
    readout.start()
    try:
        assert wait_for(lambda: readout.link.up)
        pipeline = Pipeline(map_clock=False)
        pipeline.identify_on_link(INFO_REPLY_S, readout.ask_info, lambda delay, fn: None,
                                  partial(readout.ask_info, restart=True))  # as board.py does
        board = Scans("E-1", seed=1)
        pipeline.feed(board.info() + board.next(20), now[0])
        for k, step in enumerate((1.0, 0.9, 0.9)):  # restarts at 101.0, 101.9, 102.8
            now[0] += step
            board.seq, board.t_us = 0, 0
            pipeline.feed(board.next(10), now[0])
            wait_for(lambda: port.written.count(b"INFO?") == 2 + k, 0.5)  # the readout's thread writes it
            pipeline.feed(board.info() + board.next(5), now[0] + 0.01)  # answered: the next restart waits again
        asked = port.written.count(b"INFO?")
        now[0] += 0.1  # 0.1 s after the last restart's INFO?: an unreadable frame's ask waits for the limit
        assert not readout.ask_info()
        now[0] += 0.2
        assert readout.ask_info(restart=True) and not readout.ask_info(restart=True)  # a repeat within INFO_REPLY_S
        assert wait_for(lambda: port.written.count(b"INFO?") == 1 + 4, 0.5)
    finally:
        readout.stop()
    assert asked == 1 + 3  # on connect, then at each restart

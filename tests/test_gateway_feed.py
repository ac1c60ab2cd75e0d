"""What a gateway's Zenoh feed (service/net/zenoh_feed.py) takes from peers
it cannot authenticate, in this process: the feed's session listens on
loopback (multicast off) and made-up services connect to it, announce their
sensors' shapes and put frames. Before, an announced 3000x3000 grid was
taken as said: every 64-force frame became a frame of 9 million channels
(the gateway grew from 84 to ~700 MB over 20 frames, and one latest frame
was 20 MB of JSON)."""
import threading
import time

import numpy as np
import orjson
import pytest

from service.fanout.encoding import to_json_dict
from service.net.zenoh_config import alive_key, frame_key, open_session, sensors_key, session_config
from service.net.zenoh_feed import ZenohFeed
from service.net.zenoh_publisher import encode
from service.readings import SensorInfo
from service.reconstruct import ForceFrame
from tests.conftest import free_port


class Peer:
    """A Zenoh session publishing ``board`` as the service ``instance``,
    answering its sensors query with ``sensors`` (a list of shape entries)."""

    def __init__(self, endpoint: str, board: str, instance: str, sensors: list) -> None:
        self.board, self.instance = board, instance
        self.session = open_session(session_config(connect=[endpoint], multicast=False))
        self.token = self.session.liveliness().declare_token(alive_key(board, instance))
        document = orjson.dumps({"board": board, "instance": instance, "info": {}, "sensors": sensors})
        self.queryable = self.session.declare_queryable(sensors_key(board),
                                                        lambda query: query.reply(sensors_key(board), document))

    def put(self, kind: str, n: int, seq: int, sensor: int = 0) -> None:
        """One frame of ``sensor`` with ``n`` forces of 1 N each (σ 0.1 N)."""
        info = SensorInfo(sensor, kind, 8, 8, board=self.board)
        frame = ForceFrame(info, seq, 1000 * seq, time.time(), np.ones(n), np.zeros(n), [], "full",
                           calibration="x", sigma_N=np.full(n, 0.1), t_host_scan=time.time())
        self.session.put(frame_key(self.board, sensor), encode([frame]), attachment=self.instance.encode())


@pytest.fixture
def feed():
    """(feed, endpoint, delivered): a ZenohFeed listening on loopback; ``delivered`` its (board, frames)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    delivered: list = []
    lock = threading.Lock()

    def deliver(board, frames):
        with lock:
            delivered.append((board, frames))

    feed = ZenohFeed(session_config(listen=[endpoint], multicast=False), deliver=deliver,
                     on_health=lambda *_: None, on_alive=lambda *_: None).start()
    yield feed, endpoint, delivered
    feed.close()


def test_an_announced_shape_no_frame_can_have_and_forces_that_do_not_fill_the_shape_are_refused_and_named(feed):
    feed, endpoint, delivered = feed
    peers = {"evil": Peer(endpoint, "evil", "rogue:1:aaaaaa", [{"id": 0, "kind": "grid", "rows": 3000, "cols": 3000}]),
             "liar": Peer(endpoint, "liar", "rogue:2:bbbbbb", [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]),
             "good": Peer(endpoint, "good", "lab:3:cccccc", [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]),
             "wide": Peer(endpoint, "wide", "lab:4:dddddd", [{"id": 0, "kind": "grid", "rows": 16, "cols": 16}])}
    try:
        time.sleep(0.5)  # the peers' sessions joined
        for seq in range(30):  # ~1.5 s: queries asked and answered, several retries for the refused
            if seq % 6 == 0:  # 5 frames (each 9 million channels before: 72 MB of NaN)
                peers["evil"].put("grid", 64, seq)  # 64 forces, as rogue.py's
            peers["liar"].put("grid", 16, seq)  # 16 forces under an 8x8 shape
            peers["good"].put("grid", 64, seq)
            peers["wide"].put("grid", 256, seq)  # 16x16: the most channels a payload holds (1024 bytes / 4)
            time.sleep(0.05)
        time.sleep(0.5)
    finally:
        for peer in peers.values():
            peer.session.close()
    by_board: dict[str, list] = {}
    for board, frames in delivered:
        by_board.setdefault(board, []).extend(frames)
    assert set(by_board) == {"good", "wide"}  # nothing of evil's or liar's, not even one frame
    status, problems = feed.status(), feed.problems(time.monotonic())
    assert len(by_board["good"]) >= 25 and len(by_board["wide"]) >= 25
    good = by_board["good"][-1]
    assert (good.sensor.rows, good.sensor.cols, good.forces_N.shape, good.capacitance_pF.shape) == (8, 8, (64,), (64,))
    assert good.forces_N.sum() == pytest.approx(64.0)  # 64 taxels of 1 N, as put
    assert by_board["wide"][-1].forces_N.shape == (256,)
    assert status["shapes_refused"] >= 1 and status["misfit_frames"] >= 25
    [evil] = [p for p in problems if "board evil" in p]
    assert "3000x3000" in evil and "256 channels" in evil and "rogue:1:aaaaaa" in evil
    [liar] = [p for p in problems if "board liar" in p]
    assert "16 forces" in liar and "8x8 grid" in liar and "64" in liar
    assert not [p for p in problems if "board good" in p or "board wide" in p]


@pytest.mark.parametrize("entry, why", [
    ({"id": 0, "kind": "grid", "rows": 16, "cols": 17}, "16x17 grid"),
    ({"id": 0, "kind": "grid", "rows": 0, "cols": 8}, "0x8 grid"),
    ({"id": 0, "kind": "grid", "rows": "8", "cols": 8}, "'8'x8 grid"),
    ({"id": 0, "kind": "quad", "rows": 1000, "cols": 1000}, "1000x1000 quad"),
    ({"id": 255, "kind": "grid", "rows": 8, "cols": 8}, "id 255"),
    ({"id": True, "kind": "quad", "rows": 2, "cols": 2}, "id True"),
    ("grid", "no sensor entry"),
])
def test_each_announced_shape_beyond_the_protocol_is_refused_naming_it(entry, why):
    from service.net.zenoh_feed import announced_shapes

    shapes, refused = announced_shapes({"sensors": [entry, {"id": 1, "kind": "quad", "rows": 2, "cols": 2}]}, "b")
    assert list(shapes) == [1] and shapes[1].channels == 4  # the other sensor is still taken
    [reason] = refused
    assert why in reason, reason


def test_the_first_frames_of_a_restarted_service_are_marked_board_restart_and_name_its_instance(feed):
    """A service restarted behind the gateway begins seq and board_time_us
    again: each sensor's first frame from the new instance is flagged
    board_restart (protocol.md: a restart is not a gap, and is told apart),
    and every frame's JSON header names the instance. Before, a gateway
    client saw seq 6304 -> 2733 with flags [] and no instance."""
    feed, endpoint, delivered = feed
    shapes = [{"id": 0, "kind": "quad", "rows": 2, "cols": 2}, {"id": 1, "kind": "quad", "rows": 2, "cols": 2}]
    first = Peer(endpoint, "d", "lab:10:aaaaaa", shapes)
    time.sleep(0.5)
    for seq in range(6280, 6305):
        first.put("quad", 3, seq, sensor=0)
        first.put("quad", 3, seq, sensor=1)
        time.sleep(0.02)
    time.sleep(0.3)
    first.session.close()  # its token withdrawn: the name is free for its successor
    time.sleep(0.3)
    second = Peer(endpoint, "d", "lab:11:bbbbbb", shapes)
    try:
        time.sleep(0.5)
        for seq in range(2733, 2758):
            second.put("quad", 3, seq, sensor=0)
            if seq >= 2740:  # sensor 1 comes later: its first frame is marked too
                second.put("quad", 3, seq, sensor=1)
            time.sleep(0.02)
        time.sleep(0.5)
    finally:
        second.session.close()
    got = [f for board, frames in delivered if board == "d" for f in frames]
    for sensor, restart_seq in ((0, 2733), (1, 2740)):
        mine = [f for f in got if f.sensor.id == sensor]
        seqs = [f.seq for f in mine]
        assert seqs == [*range(6280, 6305), *range(restart_seq, 2758)], seqs  # every frame of both, in order
        marked = [(f.seq, f.instance) for f in mine if "board_restart" in f.flags]
        assert marked == [(restart_seq, "lab:11:bbbbbb")]  # the new instance's first frame only
        assert {f.instance for f in mine if f.seq >= 6280} == {"lab:10:aaaaaa"}
        assert {f.instance for f in mine if f.seq < 6280} == {"lab:11:bbbbbb"}
    header = to_json_dict(next(f for f in got if f.seq == 2733 and f.sensor.id == 0))["header"]
    assert header["instance"] == "lab:11:bbbbbb" and header["seq"] == 2733
    assert to_json_dict(got[0])["header"]["instance"] == "lab:10:aaaaaa"


def test_what_a_service_sends_under_a_name_after_renaming_it_is_dropped_and_counted(feed):
    """A bare board's frames go out as `board` until its INFO names it; its
    service then says {"renamed_to": NAME}: the frames taken before are
    delivered, and the frames still in flight under the old name are
    dropped, counted (the gateway forgets the name at once)."""
    feed, endpoint, delivered = feed
    peer = Peer(endpoint, "board", "lab:20:eeeeee", [{"id": 0, "kind": "quad", "rows": 2, "cols": 2}])
    try:
        time.sleep(0.5)
        for seq in range(20):
            peer.put("quad", 3, seq)
            time.sleep(0.02)
        time.sleep(0.3)
        peer.session.put("tactile/board/health", orjson.dumps({"board": "board", "renamed_to": "LATE-1"}),
                         attachment=peer.instance.encode())
        time.sleep(0.3)
        for seq in range(20, 30):
            peer.put("quad", 3, seq)
            time.sleep(0.02)
        time.sleep(0.3)
    finally:
        peer.session.close()
    time.sleep(0.3)
    assert [f.seq for board, frames in delivered for f in frames] == list(range(20))
    assert feed.status()["samples_renamed"] >= 10  # the 10 frames, and its token's withdrawal

"""A gateway's boards come and go (service/gateway.py): the gateway is fed
by hand, as its Zenoh feed would feed it, on a clock the test sets; and a
service's publisher tells a renamed board's old name (its own session).

Before, a board was never forgotten: a bare board whose INFO came after its
first frames stayed `board`, lost, beside its INFO's name for good (/health
degraded, its sensor listed twice, /sensors/0/latest a 409), and 64 health
samples of made-up names from a peer that then left filled the 64 places,
so a real service was refused, without a word in /health."""
import threading
import time

import numpy as np
import orjson
import pytest
import zenoh

from service.gateway import GatewayService
from service.net.zenoh_config import open_session, session_config
from service.net.zenoh_publisher import ZenohPublisher
from service.readings import SensorInfo
from service.reconstruct import ForceFrame
from tests.conftest import free_port

FORGET_S = 60.0  # docs/scale.md: a lost board is reported lost for a minute, then forgotten
LOST_S = 2.5  # docs/scale.md: silent for 2.5 s is lost


class Clock:
    """time.time() as the test sets it."""

    def __init__(self) -> None:
        self.now = 1.8e9

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def clock(monkeypatch):
    clock = Clock()
    monkeypatch.setattr(time, "time", clock)
    return clock


def frames(board: str, seqs: range, instance: str = "") -> list[ForceFrame]:
    """A quad's frames of 1 N along z (σ 0.1 N), stamped now."""
    info = SensorInfo(0, "quad", 2, 2, board=board)
    return [ForceFrame(info, seq, 1000 * seq, time.time(), np.array([0.0, 0.0, 1.0]), np.full(4, np.nan), [],
                       "remote", sigma_N=np.full(3, 0.1)) for seq in seqs]


def names(gateway: GatewayService) -> list[str]:
    return [board.name for board in gateway.all_boards]


def test_a_lost_board_is_reported_lost_for_a_minute_then_forgotten(clock):
    gateway = GatewayService(None)
    start = clock.now
    gateway._on_alive("gone", True)
    gateway._receive("gone", frames("gone", range(10)))
    gateway._on_alive("silent", True)
    gateway._receive("silent", frames("silent", range(10)))
    clock.now += 1.0
    gateway._on_alive("gone", False)  # its service ended; "silent" just stops
    clock.now = start + 1.0 + FORGET_S - 1.0
    gateway._prune(clock.now)
    health = gateway.health()
    assert names(gateway) == ["gone", "silent"] and health["status"] == "degraded"
    assert [p for p in health["problems"] if p.startswith("board gone: lost")]
    assert [p for p in health["problems"] if p.startswith("board silent: lost")]
    clock.now = start + 1.0 + FORGET_S + 0.5
    gateway._prune(clock.now)
    assert names(gateway) == ["silent"]  # lost when its token went, 1 s after the start: a minute ago
    clock.now = start + LOST_S + FORGET_S + 0.5
    gateway._prune(clock.now)
    health = gateway.health()
    assert names(gateway) == [] and gateway.board("silent") is None  # lost 2.5 s after its last frame
    assert health["status"] == "ok" and health["problems"] == [] and health["gateway"]["boards"] == 0


def test_a_board_heard_again_before_the_minute_is_kept(clock):
    gateway = GatewayService(None)
    gateway._on_alive("arm", True)
    gateway._receive("arm", frames("arm", range(10)))
    clock.now += 30.0  # lost for 27.5 s
    gateway._receive("arm", frames("arm", range(10, 20)))
    clock.now += FORGET_S - 1.0
    gateway._prune(clock.now)
    assert names(gateway) == ["arm"]


def test_a_name_its_service_renamed_is_forgotten_at_once(clock):
    """A bare board's frames before its INFO are published as `board`; at the
    INFO its service renames it and says so: the gateway keeps `LATE-1` only."""
    gateway = GatewayService(None)
    gateway._on_alive("board", True)
    gateway._receive("board", frames("board", range(50)))
    gateway._on_alive("LATE-1", True)
    gateway._receive("LATE-1", frames("LATE-1", range(50, 60)))
    renamed = {"board": "board", "renamed_to": "LATE-1"}
    gateway._on_health("board", renamed)
    gateway._on_alive("board", False)  # its token, withdrawn after the notice
    health = gateway.health()
    assert names(gateway) == ["LATE-1"] and [a for b in gateway.all_boards for a in b.sensors] == [0]
    assert health["status"] == "ok", health["problems"]
    gateway._on_alive("board-2", True)  # another service's bare board: its token withdrawn first
    gateway._receive("board-2", frames("board-2", range(50)))
    gateway._on_alive("board-2", False)
    assert gateway.health()["status"] == "degraded"  # lost, for the moment
    gateway._on_health("board-2", {**renamed, "board": "board-2"})
    assert names(gateway) == ["LATE-1"] and gateway.health()["status"] == "ok"


def test_health_samples_alone_make_no_board_and_the_cap_counts_live_boards_only(clock):
    gateway = GatewayService(None, max_boards=4)
    for i in range(64):  # a peer's health samples under made-up names, no token, no frame
        gateway._on_health(f"ghost{i}", {})
    assert names(gateway) == [] and gateway.health()["status"] == "ok"
    for name in "abcd":
        gateway._on_alive(name, True)
        gateway._receive(name, frames(name, range(5)))
    gateway._on_alive("e", True)
    gateway._receive("e", frames("e", range(5)))
    health = gateway.health()
    assert names(gateway) == ["a", "b", "c", "d"] and health["gateway"]["boards_refused"] == 2
    [refused] = [p for p in health["problems"] if "board e" in p]
    assert "refused" in refused and "at most 4 live boards" in refused
    gateway._on_alive("a", False)  # a's service ended: a is lost, and counts no more
    clock.now += 0.5
    gateway._receive("e", frames("e", range(5, 10)))
    health = gateway.health()
    assert names(gateway) == ["b", "c", "d", "e"]  # the lost one gives its place (the places hold memory)
    assert not [p for p in health["problems"] if "board e" in p]
    assert gateway.board("e").latest[0].seq == 9


def test_a_renamed_board_s_old_name_is_told_by_its_service_as_its_token_goes():
    """ZenohPublisher: when a board's name changes (its first INFO), a sample
    {"renamed_to": NEW} under the old name's health key, with the instance,
    and the old name's token withdrawn, the new one's declared. (Put before
    the withdrawal, it may arrive after it: Zenoh sends declarations first;
    the gateway forgets the name either way, as the test above.)"""

    class Board:
        name = "board"

    class Service:
        all_boards = [Board()]

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    publisher = ZenohPublisher(session_config(listen=[endpoint], multicast=False))
    watcher = open_session(session_config(connect=[endpoint], multicast=False))
    events: list = []
    lock = threading.Lock()

    def seen(what):
        with lock:
            events.append(what)

    try:
        watcher.liveliness().declare_subscriber(
            "tactile/*/alive/**", lambda s: seen(("token", str(s.key_expr).split("/")[1], s.kind == zenoh.SampleKind.PUT)),
            history=True)
        watcher.declare_subscriber("tactile/*/health", lambda s: seen(
            ("health", str(s.key_expr).split("/")[1], orjson.loads(s.payload.to_bytes()), s.attachment.to_bytes().decode())))
        publisher._service = Service()
        publisher._declare_boards()
        time.sleep(0.5)
        Board.name = "LATE-1"
        publisher._declare_boards()
        time.sleep(0.5)
    finally:
        publisher._service = None
        watcher.close()
        publisher.session.close()
    with lock:
        told = [e for e in events if e[0] == "health"]
        tokens = [e for e in events if e[0] == "token"]
    assert told == [("health", "board", {"board": "board", "renamed_to": "LATE-1", "instance": publisher.instance},
                     publisher.instance)]
    assert tokens[0] == ("token", "board", True)
    assert sorted(tokens[1:]) == [("token", "LATE-1", True), ("token", "board", False)]


def feeder(gateway, board, clock):
    """(alive(instance, up), sample(instance, seqs)): tokens and frames of ``board`` from
    service instances, passed on to the gateway as ZenohFeed._take does (through its claims)."""
    def alive(instance, up):
        if gateway.claims.heard(board, instance, clock.now, up):
            gateway._on_alive(board, up)

    def sample(instance, seqs):
        if gateway.claims.heard(board, instance, clock.now):
            gateway._receive(board, frames(board, seqs))

    return alive, sample


def test_a_lost_board_s_name_never_goes_to_the_service_it_refused(clock):
    """Two hosts both call their board `arm`: the hand-pc's service is refused
    while the arm-pc's holds it. The arm-pc's service ends; its board is
    lost, and stays so, the clash named, while the refused one lives; none
    of the refused one's frames is served, a minute on or later. Before, the
    board was forgotten 60 s after the loss with every claim, and the
    refused one's next sample took the name: at 62 s `arm` served the
    hand-pc's sensor, /health `ok`."""
    gateway = GatewayService(None)
    arm_pc, hand_pc = "arm-pc:100:aaaaaa", "hand-pc:200:bbbbbb"

    alive, sample = feeder(gateway, "arm", clock)
    alive(arm_pc, True)
    sample(arm_pc, range(5))
    alive(hand_pc, True)
    sample(hand_pc, range(100, 105))
    clock.now += 1.0
    alive(arm_pc, False)
    for t in range(1, 3 * int(FORGET_S)):
        clock.now += 1.0
        sample(hand_pc, range(100 + 10 * t, 105 + 10 * t))
        gateway._prune(clock.now)
    health = gateway.health()
    assert names(gateway) == ["arm"] and gateway.board("arm").latest[0].seq == 4  # the arm-pc's last frame
    assert [p for p in health["problems"] if "lost: the service of board arm" in p]
    [clash] = [p for p in health["problems"] if "name clash" in p]
    assert f"{hand_pc} (refused, 180 samples ignored)" in clash
    alive(hand_pc, False)  # the refused one ends too: the name is forgotten, free for whichever comes
    clock.now += 1.0
    gateway._prune(clock.now)
    assert names(gateway) == [] and gateway.health()["problems"] == []
    alive("arm-pc:300:cccccc", True)  # the arm-pc's service restarted
    sample("arm-pc:300:cccccc", range(3))
    assert names(gateway) == ["arm"] and gateway.board("arm").latest[0].seq == 2


def test_a_successor_declared_before_its_predecessor_left_is_served_alive_and_kept(clock):
    """A service restarted on its host: the new token declared 1 s before the
    old one's withdrawal, so the new one was refused until then and takes
    the name at its first sample after (board_claims.py). Its board is not
    lost, and keeps its history a minute on. Before, no token of the new one
    reached the board: /health said "lost … liveliness token is gone" for
    59 s while it streamed, then the board was forgotten and made again."""
    gateway = GatewayService(None)
    old, new = "arm-pc:100:aaaaaa", "arm-pc:200:bbbbbb"

    alive, sample = feeder(gateway, "left", clock)
    alive(old, True)
    sample(old, range(10))
    clock.now += 1.0
    alive(new, True)
    clock.now += 0.1
    alive(old, False)
    assert gateway.board("left").lost(clock.now)  # the old one gone, the new one not yet heard since
    board = gateway.board("left")
    for t in range(int(FORGET_S) + 10):
        clock.now += 1.0
        sample(new, range(10 * t, 10 * t + 10))
        gateway._prune(clock.now)
        assert not board.lost(clock.now), (t, gateway.health()["problems"])
    health = gateway.health()
    assert gateway.board("left") is board and health["status"] == "ok", health["problems"]
    assert board.alive is True and board.latest[0].seq == 10 * (int(FORGET_S) + 10) - 1
    assert health["boards"]["left"]["remote"]["publisher"] == new

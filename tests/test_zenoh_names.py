"""Two services in this process that both name their board `arm`, each on
its own Zenoh session (loopback, multicast off), and a ZenohClient connected
to both, without a gateway: it follows one (that one's frames only, as its
pipeline made them, at one quad's rate, seq never going back), drops and
counts the other's, warns once naming both instances, and when the followed
one stops it follows the other, saying so. Before, it interleaved both
services' frames under arm/0 and said nothing."""
import asyncio
import logging
import threading
import time

import numpy as np
import orjson
import zenoh

from service.board import BoardSpec
from service.client_zenoh import ZenohClient
from service.live_service import TactileService
from service.net.zenoh_config import health_key, session_config
from service.net.zenoh_publisher import ZenohPublisher
from tests.test_zenoh import Captured, on_loop

ENDPOINTS = ("tcp/127.0.0.1:18571", "tcp/127.0.0.1:18572")
RATE_HZ = 200
SOURCES = (f"sim://?sensors=quad&rate={RATE_HZ}&scene=press&seed=1",
           f"sim://?sensors=quad&rate={RATE_HZ}&scene=idle&seed=2")


class Live:
    """A TactileService publishing board `arm` on Zenoh at ``endpoint``; its pipeline's frames captured."""

    def __init__(self, source: str, endpoint: str) -> None:
        self.service = TactileService(boards=[BoardSpec(source, "arm")])
        self.service.zenoh = ZenohPublisher(session_config(listen=[endpoint], multicast=False))
        self.instance = self.service.zenoh.instance
        self.captured = Captured()
        self.service.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.service.loop.run_forever, daemon=True)
        self._thread.start()
        on_loop(self.service, self.service.start)
        self.service.pipeline.listeners = [*self.service.pipeline.listeners, self.captured]
        self.stopped = False

    def stop(self) -> None:
        if not self.stopped:
            self.stopped = True
            on_loop(self.service, self.service.stop)  # closes its session: its liveliness token goes
            self.service.loop.call_soon_threadsafe(self.service.loop.stop)
            self._thread.join(10)


def read(frames, seconds: float) -> list[tuple[float, dict]]:
    end, got = time.monotonic() + seconds, []
    while time.monotonic() < end:
        got.append((time.monotonic(), next(frames)))
    return got


def instances(client: ZenohClient) -> list[str]:
    return [p["instance"] for p in client.clashes().get("arm", {}).get("publishers", [])]


def check(got: list[tuple[float, dict]], live: Live) -> tuple[float, int]:
    """Frames per second and how often seq went back; every frame ``live``'s, with the forces it made."""
    headers = [f["header"] for _, f in got]
    assert {h["instance"] for h in headers} == {live.instance}
    for _, frame in got:
        stamp, forces = live.captured.frames[(0, frame["header"]["seq"])]
        assert frame["header"]["stamp"] == stamp and np.array_equal(frame["force_N"], forces, equal_nan=True)
    seqs = [h["seq"] for h in headers]
    return len(got) / (got[-1][0] - got[0][0]), sum(b < a for a, b in zip(seqs, seqs[1:]))


def test_a_client_follows_one_of_two_services_of_one_name_and_moves_to_the_other_when_it_stops(caplog):
    caplog.set_level(logging.INFO, logger="service.client_zenoh")
    services: list[Live] = []
    try:
        services = [Live(source, endpoint) for source, endpoint in zip(SOURCES, ENDPOINTS)]
        with ZenohClient(ENDPOINTS, timeout=3) as client:
            frames = client.subscribe("arm", sensors=[0])
            next(frames)
            deadline = time.monotonic() + 5
            while "arm" not in client.clashes() and time.monotonic() < deadline:
                next(frames)  # both services heard
            followed = client.followed("arm")
            [first] = [s for s in services if s.instance == followed]
            [other] = [s for s in services if s is not first]
            refused_before = client.refused
            window = read(frames, 1.5)
            refused = client.refused - refused_before
            clash = client.clashes()["arm"]
            health, latest = client.health("arm"), client.latest("arm", 0)
            warned = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]

            # A service older than instance ids: its health has no attachment, and is not taken either.
            with zenoh.open(session_config(connect=[ENDPOINTS[0]], multicast=False)) as older:
                deadline = time.monotonic() + 3
                while "" not in instances(client) and time.monotonic() < deadline:
                    older.put(health_key("arm"), orjson.dumps({"status": "ok", "older": True}))  # until routed
                    time.sleep(0.05)
            older_clash = client.clashes()["arm"]

            stopped = time.monotonic()
            first.stop()
            after = read(frames, 1.5)
            moved = next(t for t, f in after if f["header"]["instance"] == other.instance) - stopped
            moved_warnings = [r.getMessage() for r in caplog.records if "having gone" in r.getMessage()]
    finally:
        for service in services:
            service.stop()

    rate, back = check(window, first)
    print(f"\nclient: arm/0 {rate:.0f} frames/s, seq back {back} times, {refused} of the other's frames dropped; "
          f"moved to the other {moved:.3f} s after the followed one stopped")
    assert 0.8 * RATE_HZ < rate < 1.2 * RATE_HZ and back == 0  # one quad at 200 Hz, not two interleaved
    assert 0.8 * RATE_HZ * 1.5 < refused < 1.2 * RATE_HZ * 1.6
    assert clash["publisher"] == followed and [p["samples_refused"] > 0 for p in clash["publishers"]
                                               if p["instance"] == other.instance] == [True]
    assert [p for p in clash["problems"] if followed in p and other.instance in p]
    [warning] = [w for w in warned if "two services" in w]
    assert "board arm" in warning and followed in warning and other.instance in warning
    assert health["zenoh"]["instance"] == followed
    assert latest["header"]["instance"] == followed and (0, latest["header"]["seq"]) in first.captured.frames
    assert "older" not in client.health("arm") and "" in [p["instance"] for p in older_clash["publishers"]]

    switched = [(t, f) for t, f in after if t >= stopped + moved]
    rate_after, back_after = check(switched, other)
    assert moved < 1.0 and 0.8 * RATE_HZ < rate_after < 1.2 * RATE_HZ and back_after == 0
    assert {f["header"]["instance"] for t, f in after if t < stopped + moved} <= {first.instance}
    [message] = moved_warnings
    assert f"board arm: following {other.instance} now, {first.instance} having gone (its liveliness token went)" \
        in message


def test_a_client_drops_a_board_name_its_service_renamed():
    """A bare board's provisional name `board` is renamed `LATE-1` at its first
    INFO; its service says so with {"renamed_to": "LATE-1"} under the old
    name's health key. The client forgets `board`. Before, it kept that notice
    as `board`'s health document (no status) and listed `board` for good."""

    class Board:
        name = "board"

    class Service:
        all_boards = [Board()]

    endpoint = "tcp/127.0.0.1:9981"
    publisher = ZenohPublisher(session_config(listen=[endpoint], multicast=False))

    def put_health(name: str) -> None:
        publisher.session.put(health_key(name), orjson.dumps({"status": "ok", "board": name}),
                              attachment=publisher._attachment)

    def wait_for(condition) -> None:
        deadline = time.monotonic() + 5.0
        while not condition() and time.monotonic() < deadline:
            time.sleep(0.02)

    try:
        with ZenohClient([endpoint], timeout=3) as client:
            time.sleep(0.3)  # the client's subscriptions reach the publisher's session
            publisher._service = Service()
            publisher._declare_boards()
            put_health("board")
            wait_for(lambda: client.boards() == ["board"])
            assert client.health("board") == {"status": "ok", "board": "board"}
            Board.name = "LATE-1"
            publisher._declare_boards()  # tells {"renamed_to": "LATE-1"} under board's health key
            put_health("LATE-1")
            wait_for(lambda: client.boards() == ["LATE-1"])
            assert client.boards() == ["LATE-1"] and client.health("board") is None
            assert client.last_health_age_s("board") is None
            assert client.health("LATE-1") == {"status": "ok", "board": "LATE-1"}
    finally:
        publisher._service = None
        publisher.session.close()

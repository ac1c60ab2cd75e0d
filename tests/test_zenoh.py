"""`tactile serve --zenoh` on one machine, loopback endpoints, multicast scouting off: a service and
ZenohClient subscribers (two services in processes of their own: test_zenoh_hosts.py). What the
service published is read from its pipeline (a listener beside the publisher)."""
import asyncio
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from service.cli import main
from service.client import TactileError
from service.client_zenoh import ZenohClient, subscribe_zenoh
from service.live_service import TactileService
from service.board import BoardSpec
from service.net.zenoh_config import health_key, session_config
from service.net.zenoh_publisher import FrameQueue, ZenohPublisher
from tests.conftest import free_port

SOURCE = "sim://?scene=press&sensors=grid,quad"  # 1 kHz: 2 000 frames/s
BOARD = "lab_board-1"
SNDBUF = 65536  # the service's TCP send buffer: a stalled peer is congested within ~0.1 s, not after megabytes


class Captured:
    """A pipeline listener keeping (sensor, seq) → (stamp, float32 forces) of every frame, while open."""

    def __init__(self) -> None:
        self.frames, self.open = {}, True

    def __call__(self, frames) -> None:
        if self.open:
            for f in frames:
                self.frames[(f.sensor.id, f.seq)] = (f.t_host, np.asarray(f.forces_N, dtype=np.float32).copy())


def on_loop(service, function):
    async def call():
        return function()
    return asyncio.run_coroutine_threadsafe(call(), service.loop).result(10)


@pytest.fixture(scope="module")
def live():
    """(service, endpoint): a TactileService publishing on Zenoh, on an event loop in a thread."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = session_config(listen=[endpoint], multicast=False)
    config.insert_json5("transport/link/tcp/so_sndbuf", str(SNDBUF))
    service = TactileService(boards=[BoardSpec(SOURCE, BOARD)])
    service.zenoh = ZenohPublisher(config)
    service.loop = asyncio.new_event_loop()
    thread = threading.Thread(target=service.loop.run_forever, daemon=True)
    thread.start()
    on_loop(service, service.start)
    deadline = time.monotonic() + 10
    while len(service.pipeline.latest) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    yield service, endpoint
    on_loop(service, service.stop)
    service.loop.call_soon_threadsafe(service.loop.stop)
    thread.join(10)
    service.loop.close()


@pytest.fixture(scope="module")
def client(live):
    with ZenohClient([live[1]]) as client:
        yield client


def capture(service, seconds: float, subscription, until: float = 0.3) -> tuple[Captured, dict]:
    """What the service published during ``seconds`` and what ``subscription``
    yielded of it (read ``until`` s longer, for the frames in flight)."""
    captured = Captured()
    got: dict = {}
    frame = next(subscription)  # subscribed and flowing before the window opens
    service.pipeline.listeners = [*service.pipeline.listeners, captured]
    end = time.monotonic() + seconds
    while time.monotonic() < end + until:
        if time.monotonic() > end:
            captured.open = False
        got[(frame["header"]["sensor_id"], frame["header"]["seq"])] = frame
        frame = next(subscription)
    service.pipeline.listeners = [f for f in service.pipeline.listeners if f is not captured]
    return captured, got


def test_keys_and_session_options_follow_zenohs_own_keys(tmp_path):
    config = session_config(connect=["tcp/10.0.0.2:7447"], listen=["tcp/0.0.0.0:7447"], mode="client", multicast=False)
    assert [config.get_json(key) for key in ("connect/endpoints", "listen/endpoints", "mode", "scouting/multicast/enabled")] \
        == ['["tcp/10.0.0.2:7447"]', '["tcp/0.0.0.0:7447"]', '"client"', "false"]
    (tmp_path / "zenoh.json5").write_text('{mode: "router", listen: {endpoints: ["tcp/127.0.0.1:7448"]}}  // JSON5')
    config = session_config(tmp_path / "zenoh.json5", listen=["tcp/127.0.0.1:7449"])  # the options over the file
    assert (config.get_json("mode"), config.get_json("listen/endpoints")) == ('"router"', '["tcp/127.0.0.1:7449"]')
    with pytest.raises(ValueError, match="mode 'hub'"):
        session_config(mode="hub")
    with pytest.raises(ValueError, match="zenoh configuration /nonexistent.json5"):
        session_config("/nonexistent.json5")


def test_the_frame_queue_never_blocks_drops_the_oldest_and_counts_them():
    queue = FrameQueue(capacity=10)
    for start in range(0, 25, 5):
        queue.push(list(range(start, start + 5)))
    assert queue.dropped == 15 and len(queue) == 10
    assert queue.take(timeout=0) == list(range(15, 25)) and len(queue) == 0
    assert queue.take(timeout=0.01) == []


def test_every_frame_reaches_the_subscriber_with_the_services_forces(live, client):
    service, endpoint = live
    board = BOARD
    subscription = subscribe_zenoh(board, endpoints=[endpoint])
    captured, got = capture(service, 3.0, subscription)
    subscription.close()
    assert len(captured.frames) > 0.9 * 2 * 1000 * 3.0
    arrived = [key for key in captured.frames if key in got]
    assert len(arrived) >= 0.999 * len(captured.frames)
    for key in arrived:
        (stamp, forces), frame = captured.frames[key], got[key]
        assert frame["header"]["stamp"] == stamp and frame["header"]["board"] == board
        assert np.array_equal(frame["force_N"], forces, equal_nan=True)
    grid = next(got[key] for key in arrived if key[0] == 0)
    assert (grid["rows"], grid["cols"], grid["force_N"].size) == (8, 8, 64)
    assert client.sensors(board) == [{"id": 0, "kind": "grid", "rows": 8, "cols": 8},
                                     {"id": 1, "kind": "quad", "rows": 2, "cols": 2}]


def test_latest_answers_the_frame_the_service_holds(live, client):
    service, _ = live
    captured = Captured()
    service.pipeline.listeners = [*service.pipeline.listeners, captured]
    for sensor in (0, 1):
        before = service.pipeline.latest[sensor].seq
        frame = client.latest(BOARD, sensor)
        after = service.pipeline.latest[sensor].seq
        seq = frame["header"]["seq"]
        assert frame["header"]["sensor_id"] == sensor and before <= seq <= after
        if seq != before:  # a frame that came during the query: the listener saw it
            assert np.array_equal(frame["force_N"], captured.frames[(sensor, seq)][1], equal_nan=True)
    service.pipeline.listeners = [f for f in service.pipeline.listeners if f is not captured]
    with ZenohClient([live[1]], timeout=0.5) as other, pytest.raises(TactileError, match="no answer"):
        other.latest("no-such-board", 0)


def test_health_comes_once_a_second_under_the_boards_key(live, client):
    service, _ = live
    arrivals = []
    subscriber = client.session.declare_subscriber(health_key(BOARD), lambda _: arrivals.append(time.monotonic()))
    time.sleep(3.3)
    subscriber.undeclare()
    assert len(arrivals) in (3, 4)
    gaps = np.diff(arrivals)
    assert np.all(np.abs(gaps - 1.0) < 0.25), gaps
    document = client.health(BOARD)
    assert document["zenoh"]["board"] == BOARD and set(document["sensors"]) == {"0", "1"}
    assert client.last_health_age_s(BOARD) < 1.3 and client.boards() == [BOARD]
    assert service.health()["zenoh"]["health_published"] >= len(arrivals)


def test_a_slow_consumer_loses_the_oldest_frames_and_is_told(client):
    subscription, dropped_before = client.subscribe(BOARD, queue_samples=10), client.dropped
    first = next(subscription)["header"]
    time.sleep(0.5)  # ~1 000 frames published meanwhile
    woke = time.time()
    stamps = [next(subscription)["header"]["stamp"] for _ in range(40)]  # the rest of the first's sample, then the kept
    subscription.close()
    assert max(stamps) > woke - 0.1 > first["stamp"]  # the newest waited, not the oldest
    assert client.dropped - dropped_before > 0.8 * 2 * 1000 * 0.5 - 10 * 32  # all but the 10 samples kept (≤ 32 frames each)


STALLED_SUBSCRIBER = r"""
import json, sys, zenoh
config = zenoh.Config.from_json5(json.dumps({"scouting": {"multicast": {"enabled": False}},
    "connect": {"endpoints": [sys.argv[1]]}, "transport": {"link": {"tcp": {"so_rcvbuf": 4096}}}}))
session, count = zenoh.open(config), [0]
subscriber = session.declare_subscriber("tactile/**/frame", lambda sample: count.__setitem__(0, count[0] + 1))
print("ready", flush=True)
sys.stdin.readline()
print(count[0], flush=True)
session.close()
"""


def test_a_stalled_subscriber_loses_its_own_frames_only(live, client):
    """A subscriber process stopped (SIGSTOP) for 2 s: the publisher drops its
    frames (congestion control DROP) while the other subscriber gets them all
    and the publisher's own queue never overflows (its puts do not block)."""
    service, endpoint = live
    publisher = service.zenoh
    stalled = subprocess.Popen([sys.executable, "-c", STALLED_SUBSCRIBER, endpoint], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)
    try:
        assert stalled.stdout.readline().strip() == "ready"
        time.sleep(0.3)
        published_before, dropped_before = publisher.frames_published, publisher.queue.dropped
        stalled.send_signal(signal.SIGSTOP)
        captured, got = capture(service, 2.0, client.subscribe(BOARD))
        stalled.send_signal(signal.SIGCONT)
        time.sleep(0.5)
        published = publisher.frames_published - published_before
        stalled_got = int(stalled.communicate("\n", timeout=10)[0])
    finally:
        stalled.kill()
        stalled.wait(10)
    assert stalled_got < published - 1000  # it was congested: ~2 s of frames dropped for it
    assert sum(key in got for key in captured.frames) >= 0.999 * len(captured.frames)
    assert publisher.queue.dropped == dropped_before


def test_a_blocked_sender_never_blocks_the_pipeline_and_counts_its_drops(live):
    """The sender thread held for 1.5 s: the pipeline keeps handing frames to
    the publisher in microseconds; the queue keeps the newest 2 048 and
    counts every frame it dropped, exactly."""
    service, _ = live
    publisher = service.zenoh
    release, blocked, durations, pushed = threading.Event(), threading.Event(), [], [0]

    def held(frames):
        blocked.set()
        release.wait(10)

    def timed(frames):  # the publisher's listener, timed and counted
        start = time.perf_counter()
        publisher.on_frames(frames)
        durations.append(time.perf_counter() - start)
        pushed[0] += len(frames)

    def state():
        return pushed[0], len(publisher.queue), publisher.queue.dropped

    publisher._send = held
    service.pipeline.listeners = [timed if f == publisher.on_frames else f for f in service.pipeline.listeners]
    try:
        assert blocked.wait(5)
        start = on_loop(service, state)
        time.sleep(1.5)
        end = on_loop(service, state)
    finally:
        service.pipeline.listeners = [publisher.on_frames if f is timed else f for f in service.pipeline.listeners]
        del publisher._send
        release.set()
    assert end[0] - start[0] > 0.9 * 2 * 1000 * 1.5
    assert end[0] - start[0] == (end[1] - start[1]) + (end[2] - start[2])
    assert end[1] == publisher.queue.capacity and end[2] - start[2] > 500
    assert np.percentile(durations, 99) < 1e-3


def test_serve_refuses_zenoh_options_without_zenoh_and_a_zenoh_port_in_use(live, capsys):
    port = str(free_port())
    assert main(["serve", "--port", port, "--zenoh-listen", "tcp/127.0.0.1:7447"]) == 2
    assert "--zenoh-listen needs --zenoh" in capsys.readouterr().err
    assert main(["serve", "--port", port, "--zenoh", "--zenoh-listen", live[1], "--no-multicast"]) == 2
    err = capsys.readouterr().err
    assert "zenoh session" in err and "in use" in err



def test_without_a_config_or_listen_endpoint_the_service_is_reachable_from_loopback_only():
    from argparse import Namespace

    from service.cli_zenoh import zenoh_config

    options = dict(zenoh_endpoint=[], zenoh_mode=None, multicast=False, no_multicast=False)
    config, note = zenoh_config(Namespace(zenoh="", zenoh_listen=[], **options))
    assert config.get_json("listen/endpoints") == '["tcp/127.0.0.1:7447"]'
    assert config.get_json("scouting/multicast/enabled") == "false" and "127.0.0.1" in note
    config, note = zenoh_config(Namespace(zenoh="", zenoh_listen=["tcp/0.0.0.0:7448"], **options))
    assert config.get_json("listen/endpoints") == '["tcp/0.0.0.0:7448"]' and note is None


def test_explicit_endpoints_do_not_turn_multicast_scouting_on(tmp_path):
    """The documented two-host commands (--zenoh-listen, --zenoh-endpoint) stay
    off the LAN's other Zenoh networks unless --multicast or a CONFIG asks."""
    from service.cli import build_parser
    from service.cli_zenoh import gateway_zenoh_config, zenoh_config

    def scouting(command: str) -> str:
        args = build_parser().parse_args(command.split())
        config, _ = (zenoh_config if args.command == "serve" else gateway_zenoh_config)(args)
        return config.get_json("scouting/multicast/enabled")

    listen, connect = "--zenoh-listen tcp/0.0.0.0:7448", "--zenoh-endpoint tcp/10.0.0.7:7447"
    assert scouting(f"serve --zenoh {listen}") == "false"
    assert scouting(f"serve --zenoh {listen} {connect}") == "false"
    assert scouting(f"gateway {connect}") == "false"
    assert scouting(f"gateway {listen}") == "false"
    assert scouting(f"serve --zenoh {listen} --multicast") == "true"
    assert scouting(f"gateway {connect} --multicast") == "true"
    config = tmp_path / "zenoh.json5"
    config.write_text('{scouting: {multicast: {enabled: true}}}')
    assert scouting(f"serve --zenoh {config}") == "true"  # a CONFIG says for itself
    assert scouting(f"gateway --zenoh {config} --no-multicast") == "false"
    with pytest.raises(SystemExit):
        build_parser().parse_args(["gateway", "--multicast", "--no-multicast"])


def test_a_second_service_on_the_same_zenoh_port_is_told_how_to_run_beside_the_first():
    from service.net.zenoh_config import open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    first = open_session(session_config(listen=[endpoint], multicast=False))
    try:
        with pytest.raises(OSError, match=rf'cannot listen on \["{endpoint}"\]: address already in use .*--zenoh-listen'):
            open_session(session_config(listen=[endpoint], multicast=False))
    finally:
        first.close()

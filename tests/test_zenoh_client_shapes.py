"""ZenohClient when a board's sensor changes shape mid-stream (a restarted board with another
sensor, another board on the same link): shapes are asked over Zenoh (``tactile/<board>/sensors``,
per board and service), never over HTTP; a record whose sensor's shape is unknown or does not fit
it is skipped, counted in ``unshaped`` and told in ``notices``, and the other sensors' frames keep
coming. Before, sensor 1 turning from a quad into an 8x8 grid ended the subscription for every
board after 1610 frames: its converter asked GET http://127.0.0.1:8000/sensors, an unrelated
address (connection refused; a local service there would have shaped the remote board)."""
import threading
import time

import numpy as np
import orjson
import pytest

from service.client import SHAPES_RETRY_S, TactileClient, TactileError
from service.client_zenoh import ZenohClient
from service.net.zenoh_config import frame_key, open_session, sensors_key, session_config
from service.net.zenoh_publisher import encode
from service.readings import SensorInfo
from service.reconstruct import ForceFrame
from tests.conftest import free_port

BOARD, INSTANCE = "arm", "lab-pc:4711:3b3e8d"
QUAD = {"kind": "quad", "rows": 2, "cols": 2}
GRID = {"kind": "grid", "rows": 8, "cols": 8}
PERIOD_S = 0.005  # 200 frames/s of each sensor, as the tester's emulated boards


class Service:
    """A made-up service of ``BOARD`` listening on loopback: answers its sensors
    query with ``listed`` (id → shape, changeable), counts the queries, puts frames."""

    def __init__(self, endpoint: str, listed: dict[int, dict]) -> None:
        self.listed, self.asked = listed, 0
        self.session = open_session(session_config(listen=[endpoint], multicast=False))
        self.queryable = self.session.declare_queryable(sensors_key(BOARD), self._answer)

    def _answer(self, query) -> None:
        self.asked += 1
        sensors = [{"id": sid, **shape} for sid, shape in sorted(self.listed.items())]
        document = {"board": BOARD, "instance": INSTANCE, "info": {}, "sensors": sensors}
        query.reply(sensors_key(BOARD), orjson.dumps(document))

    def put(self, sensor: int, kind: str, seq: int) -> np.ndarray:
        """One frame of ``sensor`` (a quad's 3 forces or an 8x8 grid's 64), forces
        seq + i/100 N; what it put, as float32 (the encoding's)."""
        n = 3 if kind == "quad" else 64
        forces = seq + np.arange(n) / 100
        info = SensorInfo(sensor, kind, 2 if kind == "quad" else 8, 2 if kind == "quad" else 8, board=BOARD)
        frame = ForceFrame(info, seq, 1000 * seq, time.time(), forces, np.zeros(n), [], "full", calibration="c",
                           sigma_N=np.full(n, 0.05), t_host_scan=time.time())
        self.session.put(frame_key(BOARD, sensor), encode([frame]), attachment=INSTANCE.encode())
        return forces.astype(np.float32)


@pytest.fixture
def no_http(monkeypatch):
    """Every HTTP request a TactileClient (the Zenoh client's converters are ones) would make, refused and kept."""
    asked = []

    def refused(self, method, path, body=None, replied=None):
        asked.append(f"{method} {self.base_url}{path}")
        raise AssertionError(f"an HTTP request from a Zenoh client: {method} {self.base_url}{path}")

    monkeypatch.setattr(TactileClient, "_request", refused)
    return asked


@pytest.fixture
def endpoint():
    return f"tcp/127.0.0.1:{free_port()}"


def publish(service: Service, ready: threading.Event, stop: threading.Event, schedule, published: list) -> None:
    """Sensor 0 alone until the client has a frame (its subscription is live), then
    each tick of ``schedule`` (a list of (sensor 1's kind or None, a change to
    ``listed`` or None)): sensor 1's frame and sensor 0's quad; ``published`` gets
    (sensor, seq, kind, forces, time.monotonic()). Until ``stop``."""
    seq = 0
    while not ready.wait(PERIOD_S) and not stop.is_set():
        service.put(0, "quad", seq)
        seq += 1
    for kind, change in schedule:
        if stop.is_set():
            return
        seq += 1
        if change is not None:
            service.listed.update(change)
        if kind is not None:
            published.append((1, seq, kind, service.put(1, kind, seq), time.monotonic()))
        published.append((0, seq, "quad", service.put(0, "quad", seq), time.monotonic()))  # the last of a tick
        time.sleep(PERIOD_S)


def collect(client: ZenohClient, ready: threading.Event, published: list, ticks: int) -> list[tuple[dict, float]]:
    """(frame, time.monotonic()) of every frame until sensor 0's last one of the schedule
    (the tick's last: one session's samples arrive in the order put)."""
    got = []
    for frame in client.subscribe(board=BOARD, timeout=3.0):
        got.append((frame, time.monotonic()))
        ready.set()
        header = frame["header"]
        if len(published) and header["sensor_id"] == 0 and header["seq"] == published[0][1] + ticks - 1:
            return got
    raise AssertionError("the subscription ended")


def stream(endpoint: str, service: Service, schedule) -> tuple[ZenohClient, list, list, float]:
    """(the client, its frames as ``collect`` gives them, what ``publish`` put, seconds
    from the publisher's start to the last frame): ``service`` publishing ``schedule``
    to a ZenohClient subscribed to every sensor of the board."""
    published: list = []
    ready, stop = threading.Event(), threading.Event()
    publisher = threading.Thread(target=publish, args=(service, ready, stop, schedule, published), daemon=True)
    try:
        with ZenohClient([endpoint], timeout=3.0) as client:
            publisher.start()
            started = time.monotonic()
            got = collect(client, ready, published, len(schedule))
            return client, got, published, time.monotonic() - started
    finally:
        stop.set()
        if publisher.ident is not None:
            publisher.join(5)
        service.session.close()


def test_a_sensor_turning_from_quad_to_8x8_grid_keeps_the_others_frames_and_is_shaped_over_zenoh(endpoint, no_http):
    """Sensor 1 turns into an 8x8 grid 0.5 s in; its service's sensors document
    says so 0.3 s later (until then a 64-force record misfits the quad listed)."""
    service = Service(endpoint, {0: QUAD, 1: QUAD})
    lag_ticks = round(0.3 / PERIOD_S)
    schedule = [("quad", None)] * 100 + [("grid", None)] * lag_ticks + [("grid", {1: GRID})] + [("grid", None)] * 500
    client, got, published, _ = stream(endpoint, service, schedule)
    assert no_http == []
    first = published[0][1]
    ours = {(f["header"]["sensor_id"], f["header"]["seq"]): (f, t) for f, t in got if f["header"]["seq"] >= first}
    sent = {(sid, seq): (kind, forces, t) for sid, seq, kind, forces, t in published}
    # Sensor 0: every frame of the schedule, through the change.
    assert sorted(seq for sid, seq in ours if sid == 0) == list(range(first, first + len(schedule)))
    # Every frame given is what was published, in the shape it was published in.
    for key, (frame, _) in ours.items():
        kind, forces, _ = sent[key]
        assert frame["header"]["kind"] == kind
        np.testing.assert_array_equal(frame["force_N"], forces)
        if kind == "grid":
            assert (frame["rows"], frame["cols"]) == (8, 8)
    quads = [seq for (sid, seq), (kind, _, _) in sent.items() if sid == 1 and kind == "quad"]
    grids = [seq for (sid, seq), (kind, _, _) in sent.items() if sid == 1 and kind == "grid"]
    assert all((1, seq) in ours for seq in quads)
    # Each grid record either given with its 8x8 shape or skipped and counted: none given as a quad's.
    given = [seq for seq in grids if (1, seq) in ours]
    assert len(given) + client.unshaped == len(grids) and client.unshaped >= lag_ticks
    # The new shape is used once the service says it, after at most one retry interval (1 s) more.
    listed_at = next(t for sid, seq, kind, _, t in published if seq == first + 100 + lag_ticks)
    late = [seq for seq in grids if sent[(1, seq)][2] > listed_at + SHAPES_RETRY_S + 0.1]
    assert len(late) > 150 and all((1, seq) in ours for seq in late)
    assert len(client.notices) == 1 and "arm/1" in client.notices[0] and "64 forces" in client.notices[0]


def test_a_sensor_its_service_does_not_list_is_skipped_and_counted_and_asked_about_once_a_second(endpoint, no_http):
    """Sensor 1 publishes for 2 s without ever being listed."""
    service = Service(endpoint, {0: QUAD})
    schedule = [("quad", None)] * 400
    client, got, published, elapsed = stream(endpoint, service, schedule)
    assert no_http == []
    first = published[0][1]
    assert sorted(f["header"]["seq"] for f, _ in got if f["header"]["seq"] >= first) == \
        list(range(first, first + len(schedule)))
    assert {f["header"]["sensor_id"] for f, _ in got} == {0}
    assert client.unshaped == len(schedule)  # each of sensor 1's records, all after the subscription was live
    assert service.asked <= 2 + elapsed / SHAPES_RETRY_S  # the first frame's, then at most once a second
    assert len(client.notices) == 1 and "arm/1" in client.notices[0] and "not listed" in client.notices[0]


def test_a_subscription_whose_every_frame_is_skipped_raises_after_its_timeout_naming_why(endpoint, no_http):
    """Sensor 1 alone, never listed, 200 frames/s: no frame is given, and a
    controller must not wait on that stream for ever."""
    service = Service(endpoint, {0: QUAD})
    stop = threading.Event()

    def put():
        seq = 0
        while not stop.wait(PERIOD_S):
            service.put(1, "quad", seq)
            seq += 1

    publisher = threading.Thread(target=put, daemon=True)
    try:
        with ZenohClient([endpoint], timeout=3.0) as client:
            publisher.start()
            started = time.monotonic()
            with pytest.raises(TactileError, match=r"no frame on tactile/arm/1/frame within 0.5 s \(records skipped: "
                                                   r"sensor arm/1: not listed by its service\)"):
                next(client.subscribe(board=BOARD, sensors=[1], timeout=0.5))
            elapsed = time.monotonic() - started
    finally:
        stop.set()
        if publisher.ident is not None:
            publisher.join(5)
        service.session.close()
    assert 0.5 < elapsed < 1.5 and client.unshaped > 20

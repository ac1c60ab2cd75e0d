"""ZenohClient given a sample that does not decode (bytes that are no records, a record cut
short): the sample is dropped, counted in ``undecodable`` (and per board in
``undecodable_by_board``), told once per board in ``notices``, and the subscription goes on.
Before, the first such sample raised TactileError out of ``subscribe``, which ended the
stream of every board the subscription followed."""
import threading
import time

import numpy as np
import pytest

from service.client import TactileError
from service.client_zenoh import ZenohClient
from service.fanout.encoding import decode_binary
from service.net.zenoh_config import frame_key
from service.net.zenoh_publisher import encode
from service.readings import SensorInfo
from service.reconstruct import ForceFrame
from tests.conftest import free_port
from tests.test_zenoh_client_shapes import BOARD, INSTANCE, PERIOD_S, QUAD, Service

GARBAGE = b"\xff" * 7  # a u16 count of 65535 and too few bytes for one record header


def quad_sample(seq: int) -> bytes:
    """One sample of sensor 0 (a quad): one record, forces seq + [0, 0.01, 0.02] N."""
    info = SensorInfo(0, "quad", 2, 2, board=BOARD)
    frame = ForceFrame(info, seq, 1000 * seq, time.time(), seq + np.arange(3) / 100, np.zeros(3), [], "full",
                       calibration="c", sigma_N=np.full(3, 0.05), t_host_scan=time.time())
    return encode([frame])


def put(service: Service, payload: bytes) -> None:
    service.session.put(frame_key(BOARD, 0), payload, attachment=INSTANCE.encode())


FIRST = 1000  # the good frames' first seq; those below are put until the subscription is live


def forty_good_frames_around(endpoint: str, bad_after: dict[int, bytes]) -> ZenohClient:
    """A subscription to BOARD while 40 good quad frames (seqs FIRST ...)
    are put, ``bad_after[k]`` right after the k-th; asserts all 40 came, in
    order, with their forces; the client, closed, for its counters."""
    service = Service(endpoint, {0: QUAD})
    ready, stop = threading.Event(), threading.Event()

    def publish():
        seq = 0
        while not ready.wait(PERIOD_S) and not stop.is_set():
            put(service, quad_sample(seq))
            seq += 1
        for k in range(40):
            put(service, quad_sample(FIRST + k))
            if k in bad_after:
                put(service, bad_after[k])
            time.sleep(PERIOD_S)

    publisher = threading.Thread(target=publish, daemon=True)
    got = []
    try:
        with ZenohClient([endpoint], timeout=3.0) as client:
            publisher.start()
            for frame in client.subscribe(board=BOARD, timeout=3.0):
                ready.set()
                got.append((frame["header"]["seq"], frame["force_N"]))
                if frame["header"]["seq"] == FIRST + 39:
                    break
    finally:
        stop.set()
        if publisher.ident is not None:
            publisher.join(5)
        service.session.close()
    ours = [(seq, forces) for seq, forces in got if seq >= FIRST]
    assert [seq for seq, _ in ours] == list(range(FIRST, FIRST + 40))
    for seq, forces in ours:
        np.testing.assert_allclose(forces, seq + np.array([0, 0.01, 0.02]), rtol=1e-6)
    return client


@pytest.fixture
def endpoint():
    return f"tcp/127.0.0.1:{free_port()}"


def test_samples_that_do_not_decode_are_dropped_counted_and_told_once_and_the_good_frames_go_on(endpoint):
    """40 good frames, a garbage sample after the 10th and a record cut short
    (its last 20 bytes, into sigma) after the 25th."""
    truncated = quad_sample(10_000)[:-20]
    for bad in (GARBAGE, truncated):  # independently: neither is a sample decode_binary reads
        with pytest.raises(Exception):
            decode_binary(bad)
    client = forty_good_frames_around(endpoint, {9: GARBAGE, 24: truncated})
    assert client.undecodable == 2 and client.undecodable_by_board == {BOARD: 2}
    assert len(client.notices) == 1
    assert client.notices[0].startswith(f"board {BOARD}: a zenoh sample on {frame_key(BOARD, 0)} does not decode (")
    assert "dropped (counted in undecodable)" in client.notices[0]


def test_a_subscription_whose_every_sample_does_not_decode_raises_after_its_timeout_naming_why(endpoint):
    """Garbage alone at 200 samples/s: no frame is given within 0.5 s, and the error says why."""
    service = Service(endpoint, {0: QUAD})
    stop = threading.Event()

    def publish():
        while not stop.wait(PERIOD_S):
            put(service, GARBAGE)

    publisher = threading.Thread(target=publish, daemon=True)
    try:
        with ZenohClient([endpoint], timeout=3.0) as client:
            publisher.start()
            with pytest.raises(TactileError, match=r"no frame on tactile/arm/\*/frame within 0.5 s \(\d+ samples did "
                                                   r"not decode; the last: board arm: a zenoh sample on "
                                                   r"tactile/arm/0/frame does not decode \(.*\)\)$"):
                next(client.subscribe(board=BOARD, timeout=0.5))
    finally:
        stop.set()
        if publisher.ident is not None:
            publisher.join(5)
        service.session.close()
    assert client.undecodable > 20 and len(client.notices) == 1

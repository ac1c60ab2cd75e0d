"""ZenohClient against what unauthenticated peers may send: a sample larger
than the gateway's bound (zenoh_feed.MAX_SAMPLE_BYTES, 1 MiB) is dropped
undecoded and counted as one that does not decode, and a flood of made-up
board names leaves the client's per-board state at its bound while a real
board's frames go on. Before, the client decoded samples of any size and
kept state for every name it was sent."""
import copy
import pickle
import threading
import time

import numpy as np
import orjson
import pytest

from service import client_zenoh
from service.client import TactileError
from service.client_zenoh import KEPT_BOARDS, KEPT_NOTICES, KEPT_SENSORS, ZenohClient
from service.fanout.encoding import decode_binary
from service.net.zenoh_config import frame_key, latest_key, sensors_key
from service.net.zenoh_publisher import encode
from service.readings import SensorInfo
from service.recent import MostRecent
from service.reconstruct import ForceFrame
from tests.conftest import free_port
from tests.test_zenoh_client_shapes import BOARD, INSTANCE, PERIOD_S, QUAD, Service
from tests.test_zenoh_client_undecodable import forty_good_frames_around

BOUND = 1 << 20  # the gateway's MAX_SAMPLE_BYTES, 1 MiB, written out: the test's own reference
MADE_UP = 10_000


def quad_sample(seq: int, board: str = BOARD) -> bytes:
    """One sample of ``board``'s sensor 0 (a quad): one record, forces seq + [0, 0.01, 0.02] N."""
    info = SensorInfo(0, "quad", 2, 2, board=board)
    frame = ForceFrame(info, seq, 1000 * seq, time.time(), seq + np.arange(3) / 100, np.zeros(3), [], "full",
                       calibration="c", sigma_N=np.full(3, 0.05), t_host_scan=time.time())
    return encode([frame])


@pytest.fixture
def endpoint():
    return f"tcp/127.0.0.1:{free_port()}"


@pytest.fixture
def decoded_sizes(monkeypatch):
    """The size of every payload the client decodes; one over BOUND fails the test where it is decoded."""
    sizes = []

    def decode(payload: bytes) -> list[dict]:
        sizes.append(len(payload))
        assert len(payload) <= BOUND, f"a {len(payload)}-byte sample decoded"
        return decode_binary(payload)

    monkeypatch.setattr(client_zenoh, "decode_binary", decode)
    return sizes


def test_most_recent_forgets_the_least_recently_set_or_read_beyond_its_limit():
    kept = MostRecent(3)
    for key in "abc":
        kept[key] = key.upper()
    assert kept["a"] == "A"  # read: a is now the most recent
    kept["d"] = "D"  # b, the least recent, goes
    assert list(kept.items()) == [("c", "C"), ("a", "A"), ("d", "D")]
    assert kept.get("b") is None and kept.get("c") == "C"  # c read: now the most recent
    kept["e"] = "E"  # a goes
    assert list(kept.items()) == [("d", "D"), ("c", "C"), ("e", "E")]
    for copied in (copy.copy(kept), copy.deepcopy(kept), pickle.loads(pickle.dumps(kept))):
        assert list(copied.items()) == [("d", "D"), ("c", "C"), ("e", "E")] and copied.limit == 3


def test_a_sample_over_the_bound_is_dropped_undecoded_counted_and_told_once_and_the_good_frames_go_on(
        endpoint, decoded_sizes):
    """40 good frames; after the 10th, a valid record padded to BOUND + 1 bytes
    (decoded, it would be a frame of seq 9 999); after the 25th, another."""
    oversized = quad_sample(9_999)
    oversized += bytes(BOUND + 1 - len(oversized))
    assert len(oversized) == 1_048_577 and decode_binary(oversized)[0]["seq"] == 9_999
    client = forty_good_frames_around(endpoint, {9: oversized, 24: oversized})
    assert max(decoded_sizes) < 100  # a quad sample is ~60 bytes; the padded ones never reached the decoder
    assert client.undecodable == 2 and client.undecodable_by_board == {BOARD: 2}
    assert len(client.notices) == 1
    assert client.notices[0].startswith(f"board {BOARD}: a zenoh sample on {frame_key(BOARD, 0)} of 1048577 bytes "
                                        f"is over the 1048576-byte bound")


def test_a_latest_answer_over_the_bound_is_an_error_naming_its_size_not_decoded(endpoint, decoded_sizes):
    service = Service(endpoint, {0: QUAD})
    oversized = quad_sample(7) + bytes(BOUND)
    queryable = service.session.declare_queryable(
        latest_key(BOARD, 0), lambda query: query.reply(latest_key(BOARD, 0), oversized,
                                                        attachment=INSTANCE.encode()))
    try:
        with ZenohClient([endpoint], timeout=2.0, one_service_per_board=False) as client:
            with pytest.raises(TactileError, match=rf"a zenoh sample on {latest_key(BOARD, 0)} of "
                                                   rf"{len(oversized)} bytes is over the 1048576-byte bound"):
                client.latest(BOARD, 0)
    finally:
        queryable.undeclare()
        service.session.close()
    assert decoded_sizes == []


def test_ten_thousand_made_up_board_names_leave_per_board_state_at_its_bound_and_the_real_board_goes_on(endpoint):
    """A peer answers every board's sensors query (an even name: a quad 0; an odd
    one: no sensors, so its frames are skipped) and puts, under each of 10 000
    made-up names, one frame and one sample that does not decode; the real board
    puts a frame every 100 names. Every structure kept per board or sensor stays
    at its bound, and every frame of the real board arrives, its forces exact."""
    service = Service(endpoint, {0: QUAD})
    attacker = service.session

    def answer(query) -> None:
        board = str(query.key_expr).split("/")[1]
        sensors = [{"id": 0, **QUAD}] if board == BOARD or int(board[4:]) % 2 == 0 else []
        query.reply(sensors_key(board), orjson.dumps({"board": board, "instance": INSTANCE, "sensors": sensors}))

    service.queryable.undeclare()
    queryable = attacker.declare_queryable(sensors_key("*"), answer)
    real = list(range(1000, 1000 + MADE_UP // 100))
    ready = threading.Event()

    def publish():
        seq = 0
        while not ready.wait(PERIOD_S):
            attacker.put(frame_key(BOARD, 0), quad_sample(seq), attachment=INSTANCE.encode())
            seq += 1
        for i in range(MADE_UP):
            name = f"fake{i}"
            attacker.put(frame_key(name, 0), quad_sample(i, name), attachment=INSTANCE.encode())
            attacker.put(frame_key(name, 0), b"\xff" * 7, attachment=INSTANCE.encode())
            if i % 100 == 99:
                attacker.put(frame_key(BOARD, 0), quad_sample(real[i // 100]), attachment=INSTANCE.encode())

    publisher = threading.Thread(target=publish, daemon=True)
    got, boards = [], set()
    try:
        with ZenohClient([endpoint], timeout=5.0) as client:
            publisher.start()
            for frame in client.subscribe(board="*", timeout=5.0, queue_samples=3 * MADE_UP):
                ready.set()
                board = frame["header"]["board"]
                boards.add(board)
                if board == BOARD:
                    got.append((frame["header"]["seq"], frame["force_N"]))
                    if frame["header"]["seq"] == real[-1]:
                        break
    finally:
        publisher.join(60)
        queryable.undeclare()
        service.session.close()
    assert client.dropped == 0  # every sample was taken: the flood reached the client's state
    assert len(boards) > MADE_UP // 2  # the even names' frames came, made up as they are
    assert client.undecodable == MADE_UP and client.unshaped == MADE_UP // 2
    assert len(client.undecodable_by_board) == KEPT_BOARDS == 64
    assert len(client._converters) <= KEPT_BOARDS and len(client._shapes) <= KEPT_BOARDS
    assert len(client._skipping) <= KEPT_SENSORS == 256
    assert len(client.notices) == KEPT_NOTICES == 64
    ours = [(seq, forces) for seq, forces in got if seq >= real[0]]
    assert [seq for seq, _ in ours] == real
    for seq, forces in ours:
        np.testing.assert_allclose(forces, seq + np.array([0, 0.01, 0.02]), rtol=1e-6)

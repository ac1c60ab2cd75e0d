"""The Python client against a real server on loopback."""
import itertools
import time

import numpy as np
import pytest

from service.client import TactileClient, TactileError


def history_by_seq(client, sensor_id):
    """The service's own record of the sensor's last 5 s: seq → (board time, forces)."""
    out = {}
    for m in client.history(sensor_id, seconds=5, max_points=5000):
        force = m["force_N"] if "force_N" in m else [m["wrench"]["force"][axis] for axis in "xyz"]
        out[m["header"]["seq"]] = m["header"]["board_time_us"], np.array(force, dtype=float)  # None → NaN
    return out


def test_client_rest_and_subscriptions(served):
    client = TactileClient(served[0])
    assert [s["kind"] for s in client.sensors()] == ["grid", "quad", "grid"]
    assert len(client.latest(0)["force_N"]) == 64
    with pytest.raises(TactileError, match="404 unknown sensor id 7"):
        client.latest(7)
    stream = client.subscribe(sensors=[1], binary=True)
    frames = list(itertools.islice(stream, 50))
    mine = [c for c in client.clients() if c["sensors"] == [1]]
    produced = history_by_seq(client, 1)
    stream.close()
    assert len(mine) == 1 and mine[0]["encoding"] == "binary" and mine[0]["dropped_frames"] == 0
    assert {f["sensor_id"] for f in frames} == {1} and frames[0]["force_N"].shape == (3,)
    seqs = [f["seq"] for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + 50))  # unbatched, undecimated: every frame
    # Every frame the service produced for the sensor meanwhile, as it produced it (f32 on the wire) ...
    for frame in frames:
        board_time_us, force = produced[frame["seq"]]
        assert frame["board_time_us"] == board_time_us
        np.testing.assert_array_equal(frame["force_N"], force.astype(np.float32))
    # ... in one message per frame, or fewer when merged (a client behind), each timed when sent.
    since = sum(1 for seq in produced if seq >= seqs[0])
    assert 50 <= since and -(-50 // 32) <= mine[0]["latency"]["samples"] <= since
    json_frames = list(itertools.islice(client.subscribe(sensors=[0], fields=["force"], max_rate=50), 5))
    assert all(set(f) == {"header", "rows", "cols", "force_N"} for f in json_frames)
    produced, latest = history_by_seq(client, 0), client.latest(0)
    for frame in json_frames:  # shaped as /latest, less the fields not asked for
        assert frame["header"].keys() == latest["header"].keys()
        assert (frame["rows"], frame["cols"]) == (latest["rows"], latest["cols"])
    for frame in json_frames:  # exactly as the service holds them
        board_time_us, force = produced[frame["header"]["seq"]]
        assert frame["header"]["board_time_us"] == board_time_us
        np.testing.assert_array_equal(np.array(frame["force_N"], dtype=float), force)
    with pytest.raises(TactileError, match="max_rate"):
        next(client.subscribe(max_rate=-5))


def test_a_silent_stream_raises_and_the_server_forgets_the_client(served):
    client = TactileClient(served[0])
    with pytest.raises(TactileError, match="no message .* within 0.3 s"):
        next(client.subscribe(sensors=[99], timeout=0.3))  # no such sensor: nothing ever comes
    # Nothing was ever sent to it, yet the server notices that it left.
    deadline = time.monotonic() + 5
    while client.health()["websocket_clients"] and time.monotonic() < deadline:
        time.sleep(0.02)
    assert client.health()["websocket_clients"] == 0

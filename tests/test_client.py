"""The Python client against a real server on loopback."""
import itertools
import time

import pytest

from service.client import TactileClient, TactileError


def test_client_rest_and_subscriptions(served):
    client = TactileClient(served[0])
    assert [s["kind"] for s in client.sensors()] == ["grid", "quad", "grid"]
    assert len(client.latest(0)["force_N"]) == 64
    with pytest.raises(TactileError, match="404 unknown sensor id 7"):
        client.latest(7)
    stream = client.subscribe(sensors=[1], binary=True)
    frames = list(itertools.islice(stream, 50))
    mine = [c for c in client.clients() if c["sensors"] == [1]]
    assert len(mine) == 1 and mine[0]["encoding"] == "binary" and mine[0]["latency"]["samples"] >= 50 // 32  # merged when behind
    stream.close()
    assert {f["sensor_id"] for f in frames} == {1} and frames[0]["force_N"].shape == (3,)
    seqs = [f["seq"] for f in frames]
    assert seqs == list(range(seqs[0], seqs[0] + 50))  # unbatched, undecimated: every frame
    json_frames = list(itertools.islice(client.subscribe(sensors=[0], fields=["force"], max_rate=50), 5))
    assert all(set(f) == {"header", "rows", "cols", "force_N"} for f in json_frames)
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

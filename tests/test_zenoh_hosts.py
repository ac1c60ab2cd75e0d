"""Two `tactile serve --zenoh` processes, different HTTP ports, Zenoh endpoints and board names, and
one ZenohClient connected to both; then one of them killed."""
import itertools
import subprocess
import sys
import threading
import time

import numpy as np

from service.client import TactileClient
from service.client_zenoh import ZenohClient
from tests.conftest import free_port

SOURCE = "sim://?scene=press&sensors=grid,quad"  # 1 kHz: 2 000 frames/s


def serve(tmp_path, name: str) -> tuple[subprocess.Popen, str, str]:
    """(process, HTTP URL, Zenoh endpoint) of `tactile serve --zenoh` reading the simulator."""
    http, endpoint = free_port(), f"tcp/127.0.0.1:{free_port()}"
    with open(tmp_path / f"{name}.err", "w") as err:  # the child keeps its own descriptor
        process = subprocess.Popen(
            [sys.executable, "-m", "service.cli", "serve", "--source", SOURCE, "--port", str(http), "--zenoh",
             "--zenoh-listen", endpoint, "--no-multicast", "--board-name", name],
            stdout=subprocess.PIPE, stderr=err, text=True)
    return process, f"http://127.0.0.1:{http}", endpoint


def collect(client: ZenohClient, stop: threading.Event, into: list) -> None:
    """(arrival, frame) of every frame of every board, until ``stop``."""
    for frame in client.subscribe("*"):
        into.append((time.monotonic(), frame))
        if stop.is_set():
            return


def same_frame(ours: dict, theirs: dict) -> bool:
    """A Zenoh frame equals a WebSocket binary frame, key for key, the board in the header included;
    the Zenoh one's header also names the service instance that published it."""
    header = {k: v for k, v in ours["header"].items() if k != "instance"}
    return ours.keys() == theirs.keys() and header == theirs["header"] and ours["header"]["instance"] and all(
        np.array_equal(ours[k], theirs[k], equal_nan=True) if isinstance(ours[k], np.ndarray) else ours[k] == theirs[k]
        for k in ours if k != "header")


def test_two_services_one_subscriber_and_one_of_them_killed(tmp_path):
    services = {name: serve(tmp_path, name) for name in ("arm-a", "arm-b")}
    received: list = []
    stop = threading.Event()
    try:
        for name, (process, _, _) in services.items():
            assert "dashboard at" in process.stdout.readline(), (tmp_path / f"{name}.err").read_text()
        with ZenohClient([endpoint for _, _, endpoint in services.values()]) as client:
            thread = threading.Thread(target=collect, args=(client, stop, received), daemon=True)
            thread.start()
            deadline = time.monotonic() + 10
            while len({f["header"]["board"] for _, f in received[-100:]}) < 2 and time.monotonic() < deadline:
                time.sleep(0.05)  # both boards flowing, then the WebSocket
            stream = TactileClient(services["arm-a"][1]).subscribe(binary=True)
            websocket = list(itertools.islice(stream, 20))
            stream.close()
            time.sleep(1.0)
            services["arm-b"][0].kill()
            killed = time.monotonic()
            time.sleep(2.2)
            ages = {name: client.last_health_age_s(name) for name in services}
            stop.set()
            thread.join(10)
    finally:
        for process, _, _ in services.values():
            process.kill()
            process.communicate(timeout=10)
    before = [(t, f) for t, f in received if t < killed]
    assert {f["header"]["board"] for _, f in before} == {"arm-a", "arm-b"}
    by_key = {(f["header"]["board"], f["header"]["sensor_id"], f["header"]["seq"]): f for _, f in received}
    assert all(same_frame(by_key[("arm-a", f["header"]["sensor_id"], f["header"]["seq"])], f) for f in websocket)
    assert not [f for t, f in received if f["header"]["board"] == "arm-b" and t > killed + 0.1]
    for sensor in (0, 1):
        seqs = {f["header"]["seq"] for t, f in received if killed <= t < killed + 1.0
                and f["header"]["board"] == "arm-a" and f["header"]["sensor_id"] == sensor}
        assert len(seqs) > 900 and len(seqs) >= 0.999 * (max(seqs) - min(seqs) + 1)
    assert ages["arm-a"] < 1.3 and ages["arm-b"] > 2.0

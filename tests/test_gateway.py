"""`tactile gateway`: two `tactile serve --zenoh` processes (different simulated
boards) and one gateway on 127.0.0.1 with explicit endpoints, multicast off:
every frame of both reaches a gateway WebSocket client, the REST API answers
for both boards, and a killed service is reported lost within 1 s while the
other keeps flowing."""
import json
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import numpy as np

from service.client import TactileClient
from tests.conftest import free_port

SOURCES = {"arm-a": "sim://?scene=press&sensors=grid,quad", "arm-b": "sim://?scene=press&sensors=quad&seed=5"}


def start(tmp_path, name: str, *args: str) -> subprocess.Popen:
    with open(tmp_path / f"{name}.err", "w") as err:
        process = subprocess.Popen([sys.executable, "-m", "service.cli", *args], stdout=subprocess.PIPE, stderr=err,
                                   text=True)
    assert "dashboard at" in process.stdout.readline(), (tmp_path / f"{name}.err").read_text()
    return process


def get(url: str):
    try:
        with urllib.request.urlopen(url, timeout=5) as response:
            return response.status, json.load(response)
    except urllib.error.HTTPError as exc:
        return exc.code, json.load(exc)


def test_a_gateway_serves_every_board_of_two_services_and_reports_one_lost(tmp_path):
    endpoints = {name: f"tcp/127.0.0.1:{free_port()}" for name in SOURCES}
    http = free_port()
    processes = {}
    received: list = []
    stop = threading.Event()
    try:
        for name, source in SOURCES.items():
            processes[name] = start(tmp_path, name, "serve", "--source", f"{name}={source}", "--port",
                                    str(free_port()), "--zenoh", "--zenoh-listen", endpoints[name], "--no-multicast")
        connect = [arg for endpoint in endpoints.values() for arg in ("--zenoh-endpoint", endpoint)]
        processes["gateway"] = start(tmp_path, "gateway", "gateway", "--port", str(http), "--no-multicast", *connect)
        url = f"http://127.0.0.1:{http}"
        client = TactileClient(url)
        deadline = time.monotonic() + 15
        while len(get(url + "/sensors")[1]["sensors"]) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)

        def collect():
            for frame in client.subscribe(binary=True, timeout=5):
                received.append((time.monotonic(), frame["header"]))
                if stop.is_set():
                    return

        thread = threading.Thread(target=collect, daemon=True)
        thread.start()
        time.sleep(3.0)
        sensors = get(url + "/sensors")[1]
        latest = get(url + "/sensors/arm-b/0/latest")[1]
        request = urllib.request.Request(url + "/sensors/arm-a/0/tare", method="POST")
        try:
            urllib.request.urlopen(request, timeout=5)
            tare = 200
        except urllib.error.HTTPError as exc:
            tare = (exc.code, json.load(exc)["detail"])
        processes["arm-b"].kill()
        killed = time.monotonic()
        lost_after = None
        while time.monotonic() < killed + 3:
            health = get(url + "/health")[1]
            if health["boards"]["arm-b"]["remote"]["lost"]:
                lost_after = time.monotonic() - killed
                break
            time.sleep(0.02)
        time.sleep(1.0)
        health = get(url + "/health")[1]
        stop.set()
        thread.join(10)
    finally:
        for process in processes.values():
            process.kill()
            process.communicate(timeout=10)
    assert [s["address"] for s in sensors["sensors"]] == ["arm-a/0", "arm-a/1", "arm-b/0"]
    assert latest["header"]["board"] == "arm-b" and latest["header"]["kind"] == "quad"
    assert tare[0] == 409 and "arm-a" in tare[1] and "another host" in tare[1]
    print(f"\ngateway: arm-b reported lost {lost_after:.3f} s after its kill")
    assert lost_after is not None and lost_after < 1.0, lost_after
    assert health["boards"]["arm-a"]["status"] == "ok" and health["boards"]["arm-b"]["status"] == "degraded"
    assert any("arm-b" in problem and "lost" in problem for problem in health["problems"])
    assert "lost: the service of board arm-b (" in health["boards"]["arm-b"]["problems"][0]  # named on its own too
    assert health["boards"]["arm-b"]["link"]["state"] == "down" and health["boards"]["arm-a"]["link"]["state"] == "up"
    before = [h for t, h in received if t < killed]
    for address in ("arm-a/0", "arm-a/1", "arm-b/0"):
        board, sid = address.split("/")
        seqs = np.unique(np.array([h["seq"] for h in before if h["board"] == board and h["sensor_id"] == int(sid)]))
        print(f"gateway: {address}: {len(seqs)} of {seqs.max() - seqs.min() + 1} frames")
        assert len(seqs) > 2000 and len(seqs) >= 0.999 * (seqs.max() - seqs.min() + 1), address
    after = [h for t, h in received if killed + 0.2 <= t < killed + 1.0 and h["board"] == "arm-a"]
    assert len(after) > 0.8 * 2 * 1000 * 0.8  # both arm-a sensors at ~1 kHz kept flowing
    assert not [h for t, h in received if t > killed + 0.2 and h["board"] == "arm-b"]

"""Three `tactile serve --zenoh` processes that all name their board `arm`, and
one gateway: it serves one of them (one sensor's frames at 1 kHz, its seq
never going back), names the clash with every instance in /health, and
reports both the refused one's death and the served one's loss while a
same-named service still lives. Before, it merged them (3 000 frames/s under
arm/0, seq going back, and a death never reported)."""
import subprocess
import threading
import time

from service.client import TactileClient, TactileError
from tests.conftest import free_port
from tests.test_gateway import get, start


def remote(url: str) -> dict:
    return get(url + "/health")[1]["boards"].get("arm", {}).get("remote", {})


def wait_for(condition, seconds: float):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.02)
    return None


def test_a_gateway_serves_one_of_three_services_of_one_name_and_reports_each_death(tmp_path):
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(3)]
    http = free_port()
    url = f"http://127.0.0.1:{http}"
    processes: dict[str, subprocess.Popen] = {}
    received: list = []
    stop = threading.Event()
    try:
        for i, endpoint in enumerate(endpoints):
            processes[f"s{i}"] = start(tmp_path, f"s{i}", "serve", "--source", f"arm=sim://?sensors=quad&seed={i}",
                                       "--port", str(free_port()), "--zenoh", "--zenoh-listen", endpoint,
                                       "--no-multicast")
        connect = [arg for endpoint in endpoints for arg in ("--zenoh-endpoint", endpoint)]
        processes["gateway"] = start(tmp_path, "gateway", "gateway", "--port", str(http), "--no-multicast", *connect)
        publishers = wait_for(lambda: len(remote(url).get("publishers", [])) == 3 and remote(url)["publishers"], 15)
        assert publishers, f"the gateway does not tell the three publishers of arm apart: {remote(url)}"
        by_pid = {str(p.pid): name for name, p in processes.items()}
        served = [by_pid[p["instance"].split(":")[1]] for p in publishers if p["served"]]
        refused = [(by_pid[p["instance"].split(":")[1]], p["instance"]) for p in publishers if not p["served"]]
        instance = {name: p["instance"] for p in publishers for name in [by_pid[p["instance"].split(":")[1]]]}
        problems = get(url + "/health")[1]["problems"]

        def collect():
            try:
                for frame in TactileClient(url).subscribe(binary=True, timeout=2):
                    received.append((time.monotonic(), frame["header"]))
                    if stop.is_set():
                        return
            except TactileError:
                return  # no frame for 2 s: the served service is dead, and the others are not served

        thread = threading.Thread(target=collect, daemon=True)
        thread.start()
        time.sleep(2.0)
        processes[refused[0][0]].kill()
        killed_refused = time.monotonic()
        gone = wait_for(lambda: [p for p in remote(url)["publishers"] if p["instance"] == refused[0][1]
                                 and p["alive"] is False], 3)
        gone_after = time.monotonic() - killed_refused
        after_refused = get(url + "/health")[1]
        processes[served[0]].kill()
        killed_served = time.monotonic()
        lost = wait_for(lambda: remote(url)["lost"], 3)
        lost_after = time.monotonic() - killed_served
        time.sleep(0.8)
        after_served = remote(url)
        stop.set()
        thread.join(10)
    finally:
        for process in processes.values():
            process.kill()
            process.communicate(timeout=10)
    assert len(served) == 1 and len(refused) == 2
    clashes = [p for p in problems if "name clash" in p]
    assert len(clashes) == 2 and all(instance[served[0]] in p and "--source NAME=URL" in p for p in clashes)
    assert all(any(i in p for p in clashes) for _, i in refused)
    window = [h for t, h in received if killed_refused - 1.5 <= t < killed_refused and h["sensor_id"] == 0]
    seqs = [h["seq"] for h in window]
    backwards = sum((b - a) % 65536 > 32768 for a, b in zip(seqs, seqs[1:]))
    print(f"\ngateway: arm/0 {len(window) / 1.5:.0f} frames/s, seq back {backwards} times; refused one's death "
          f"seen {gone_after:.3f} s, served one's loss {lost_after:.3f} s after the kill")
    assert 800 < len(window) / 1.5 < 1150 and backwards == 0  # one quad at 1 kHz, not three interleaved
    assert gone and gone_after < 1.0
    assert not after_refused["boards"]["arm"]["remote"]["lost"] and any(refused[0][1] in p and "is gone" in p
                                                  for p in after_refused["problems"])
    assert lost and lost_after < 1.0  # although the third `arm` still lives
    assert [p["alive"] for p in after_served["publishers"] if p["instance"] == refused[1][1]] == [True]
    assert not [h for t, h in received if t > killed_served + 0.2]  # the third's frames are not served

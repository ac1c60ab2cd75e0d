"""How many boards × sensors one service and one gateway carry at 1 kHz (a script, not a unit test; docs/scale.md).

    python scripts/scale.py service --boards 1 2 4 8 --sensors 2 4 [--seconds 10] [--nice -10] [--in-process]
    python scripts/scale.py gateway --services 1 2 4 [--sensors 2] [--seconds 10]

``service``: one `tactile serve` reading ``boards`` simulated boards of
``sensors`` sensors each (half grids 8×8, half quads, all at 1 kHz) and no
client. Each board is a `tactile sim --tcp` process at nice 19, read over
``socket://``: a real board costs the host nothing to make its bytes, and
the simulator's forward model costs more than the service (run inside the
service, ``--in-process``, it is counted in the service's CPU). Reported per set-up: the service's published latency
(receive stamp → reconstructed and handed to the listeners, /health over its
last 2 000 frames: p50, p99, max), the frames per second it published and
its CPU (user + system over the window, /proc/PID/stat).

``gateway``: ``services`` `tactile serve --zenoh` processes (one board of
``sensors`` sensors each) and one `tactile gateway` connected to all; a
binary WebSocket client of the gateway measures receive stamp (the service's)
→ arrival, and the gateway's /health its own share (stamp → handed to its
listeners). All on this host (one clock), loopback, explicit endpoints,
multicast off. Every process is stopped at the end, whatever happened.
"""
from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import numpy as np

from service.client import TactileClient


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sensors_url(count: int, seed: int) -> str:
    kinds = ",".join("grid" if i % 2 == 0 else "quad" for i in range(count))
    return f"sim://?scene=press&rate=1000&sensors={kinds}&seed={seed}"


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as stat:
        fields = stat.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def health(port: int) -> dict:
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=30) as response:
        return json.load(response)


def start(args: list[str], nice: int) -> subprocess.Popen:
    prefix = ["nice", "-n", str(nice)] if nice else []
    process = subprocess.Popen([*prefix, sys.executable, "-m", "service.cli", *args], stdout=subprocess.PIPE,
                               stderr=subprocess.DEVNULL, text=True)
    line = process.stdout.readline()
    if "dashboard at" not in line:
        process.kill()
        raise SystemExit(f"did not start: {' '.join(args)}: {line!r}")
    return process


def stop(processes) -> None:
    for process in processes:
        process.terminate()
    for process in processes:
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


def simulator(sensors: int, seed: int) -> tuple[subprocess.Popen, str]:
    """A `tactile sim --tcp` process at nice 19 and its socket:// URL."""
    kinds = ",".join("grid" if i % 2 == 0 else "quad" for i in range(sensors))
    process = subprocess.Popen(["nice", "-n", "19", sys.executable, "-m", "service.cli", "sim", "--tcp", "0",
                                "--rate", "1000", "--sensors", kinds, "--scene", "press", "--seed", str(seed)],
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    line = process.stdout.readline()
    if "socket://" not in line:
        process.kill()
        raise SystemExit(f"the simulator did not start: {line!r}")
    return process, line.split(" on ", 1)[1].split()[0]


def one_service(boards: int, sensors: int, seconds: float, nice: int, in_process: bool) -> dict:
    port = free_port()
    sims = [] if in_process else [simulator(sensors, b) for b in range(boards)]
    urls = [sensors_url(sensors, b) for b in range(boards)] if in_process else [url for _, url in sims]
    sources = [arg for b, url in enumerate(urls) for arg in ("--source", f"b{b}={url}")]
    try:
        process = start(["serve", *sources, "--port", str(port)], nice)
    except BaseException:
        stop([p for p, _ in sims])
        raise
    try:
        time.sleep(3.0)  # tared, rates settled
        before, frames_before, t0 = cpu_s(process.pid), health(port)["frames_published"], time.monotonic()
        time.sleep(seconds)
        report = health(port)
        elapsed = time.monotonic() - t0
        cpu = (cpu_s(process.pid) - before) / elapsed
    finally:
        stop([process, *(p for p, _ in sims)])
    latency = report["latency"]["published"]
    return {"boards": boards, "sensors": sensors, "frames_per_s": round((report["frames_published"] - frames_before) / elapsed),
            "p50_ms": latency["p50_ms"], "p99_ms": latency["p99_ms"], "max_ms": latency["max_ms"],
            "cpu_pct": round(100 * cpu, 1), "status": report["status"]}


def one_gateway(services: int, sensors: int, seconds: float, nice: int) -> dict:
    endpoints = [f"tcp/127.0.0.1:{free_port()}" for _ in range(services)]
    processes = []
    try:
        for i, endpoint in enumerate(endpoints):
            processes.append(start(["serve", "--source", f"s{i}={sensors_url(sensors, i)}", "--port", str(free_port()),
                                    "--zenoh", "--zenoh-listen", endpoint, "--no-multicast"], nice))
        port = free_port()
        connect = [arg for endpoint in endpoints for arg in ("--zenoh-endpoint", endpoint)]
        gateway = start(["gateway", "--port", str(port), "--no-multicast", *connect], nice)
        processes.append(gateway)
        time.sleep(3.0)
        latencies: list[float] = []
        done = threading.Event()

        def collect() -> None:
            for frame in TactileClient(f"http://127.0.0.1:{port}").subscribe(binary=True, timeout=5):
                latencies.append(time.time() - frame["header"]["stamp"])
                if done.is_set():
                    return

        thread = threading.Thread(target=collect, daemon=True)
        thread.start()
        before, t0 = cpu_s(gateway.pid), time.monotonic()
        time.sleep(seconds)
        report = health(port)
        elapsed = time.monotonic() - t0
        cpu = (cpu_s(gateway.pid) - before) / elapsed
        done.set()
        thread.join(10)
    finally:
        stop(processes)
    arrival = np.array(latencies[len(latencies) // 10:]) * 1e3  # the first tenth: the client catching up
    own = report["latency"]["published"]
    return {"services": services, "sensors": sensors, "frames_per_s": round(len(latencies) / seconds),
            "gateway_p50_ms": own["p50_ms"], "gateway_p99_ms": own["p99_ms"],
            "client_p50_ms": round(float(np.percentile(arrival, 50)), 2),
            "client_p99_ms": round(float(np.percentile(arrival, 99)), 2),
            "gateway_cpu_pct": round(100 * cpu, 1), "lost": [n for n, b in report["boards"].items() if b["remote"]["lost"]]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="mode", required=True)
    service = sub.add_parser("service")
    service.add_argument("--boards", type=int, nargs="+", default=[1, 2, 4, 8])
    service.add_argument("--sensors", type=int, nargs="+", default=[2, 4])
    service.add_argument("--in-process", action="store_true", help="the simulators inside the service (sim://)")
    gateway = sub.add_parser("gateway")
    gateway.add_argument("--services", type=int, nargs="+", default=[1, 2, 4])
    gateway.add_argument("--sensors", type=int, default=2)
    for each in (service, gateway):
        each.add_argument("--seconds", type=float, default=10.0)
        each.add_argument("--nice", type=int, default=0, help="run the services at this niceness (negative: root)")
    args = parser.parse_args()
    if args.mode == "service":
        for boards in args.boards:
            for sensors in args.sensors:
                print(json.dumps(one_service(boards, sensors, args.seconds, args.nice, args.in_process)), flush=True)
    else:
        for services in args.services:
            print(json.dumps(one_gateway(services, args.sensors, args.seconds, args.nice)), flush=True)


if __name__ == "__main__":
    main()

"""Figures of `tactile serve --zenoh` on loopback (a script, not a unit test; docs/scale.md).

    python scripts/zenohlatency.py latency [--seconds 10]   # receive stamp → arrival: Zenoh subscriber vs WebSocket
    python scripts/zenohlatency.py cpu [--seconds 20]       # service CPU with and without --zenoh, a subscriber attached

The service runs as `tactile serve` in a process of its own, reading the
simulator (`sim://?rate=1000&sensors=grid,quad`: 2 000 frames/s). Latency is
from a frame's `header.stamp` (the service's receive stamp) to the moment the
subscriber's callback sees it, one sample per frame; the service's own share
(stamp → handed to its listeners, `latency.published` in /health) is printed
beside it, so the hop is the difference. CPU is the service process's
user+system time over the window (/proc/PID/stat), per second of wall time.
"""
from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import time

import numpy as np

from service.client import TactileClient
from service.client_zenoh import ZenohClient
from service.fanout.encoding import decode_binary
from service.net.zenoh_config import frame_key

SOURCE = "sim://?scene=press&rate=1000&sensors=grid,quad"
BOARD = "latency"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """`tactile serve` in a subprocess, with or without --zenoh."""

    def __init__(self, zenoh: bool) -> None:
        self.http = free_port()
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        command = [sys.executable, "-m", "service.cli", "serve", "--source", SOURCE, "--port", str(self.http)]
        if zenoh:
            command += ["--zenoh", "--zenoh-listen", self.endpoint, "--no-multicast", "--board-name", BOARD]
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        line = self.process.stdout.readline()  # "tactile: reading …; dashboard at …" once it listens
        if "dashboard at" not in line:
            raise SystemExit(f"tactile serve did not start: {line!r}")
        self.client = TactileClient(f"http://127.0.0.1:{self.http}")

    def cpu_s(self) -> float:
        """User + system CPU seconds of the service process so far."""
        with open(f"/proc/{self.process.pid}/stat") as stat:
            fields = stat.read().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def close(self) -> None:
        self.process.terminate()
        self.process.wait(10)
        self.process.stdout.close()


def percentiles(latencies_s: list[float]) -> str:
    p50, p99, top = np.percentile(np.array(latencies_s) * 1000.0, [50, 99, 100])
    return f"p50 {p50:.3f} ms, p99 {p99:.3f} ms, max {top:.3f} ms over {len(latencies_s)} frames"


def zenoh_latencies(endpoint: str, seconds: float) -> list[float]:
    """Stamp → arrival of every frame a plain Zenoh subscriber gets in ``seconds``."""
    arrivals: list[tuple[float, bytes]] = []
    with ZenohClient([endpoint]) as client:
        subscriber = client.session.declare_subscriber(frame_key(BOARD, "*"),
                                                       lambda s: arrivals.append((time.time(), s.payload.to_bytes())))
        time.sleep(seconds)
        subscriber.undeclare()
    return [arrived - record["stamp"] for arrived, payload in arrivals for record in decode_binary(payload)]


def websocket_latencies(client: TactileClient, seconds: float) -> list[float]:
    """The same for the service's WebSocket stream (binary, unbatched)."""
    out: list[float] = []
    deadline = time.time() + seconds
    for frame in client.subscribe(binary=True):
        now = time.time()
        out.append(now - frame["header"]["stamp"])
        if now > deadline:
            return out
    return out


def latency(seconds: float) -> None:
    service = Service(zenoh=True)
    try:
        time.sleep(2.0)  # past the auto-tare and the first INFO
        zenoh = zenoh_latencies(service.endpoint, seconds)
        published = service.client.health()["latency"]["published"]
        websocket = websocket_latencies(service.client, seconds)
        health = service.client.health()
    finally:
        service.close()
    print(f"service, stamp → published (its /health):  p50 {published['p50_ms']} ms, p99 {published['p99_ms']} ms")
    print(f"zenoh subscriber, stamp → arrival:         {percentiles(zenoh)}")
    print(f"websocket client (binary), stamp → arrival: {percentiles(websocket)}")
    print(f"zenoh publisher: {health['zenoh']['frames_published']} frames in {health['zenoh']['samples_published']} "
          f"samples, {health['zenoh']['frames_dropped']} dropped")


def cpu(seconds: float) -> None:
    for zenoh in (False, True):
        service = Service(zenoh)
        subscriber, frames = None, [0]
        try:
            if zenoh:
                client = ZenohClient([service.endpoint])
                subscriber = client.session.declare_subscriber(  # a sample's first u16 counts its frames
                    frame_key(BOARD, "*"),
                    lambda s: frames.__setitem__(0, frames[0] + int.from_bytes(s.payload.to_bytes()[:2], "little")))
            time.sleep(2.0)
            before, start, frames[0] = service.cpu_s(), time.monotonic(), 0
            time.sleep(seconds)
            used, wall = service.cpu_s() - before, time.monotonic() - start
            rate = sum(s["rate_hz"] for s in service.client.health()["sensors"].values())
            received = f", the subscriber got {frames[0] / (time.monotonic() - start):.0f} frames/s" if zenoh else ""
        finally:
            if subscriber is not None:
                subscriber.undeclare()
                client.close()
            service.close()
        print(f"{'with' if zenoh else 'without'} --zenoh: {100 * used / wall:.1f} % of a core at {rate:.0f} frames/s "
              f"({1000 * 100 * used / wall / rate:.1f} % per 1 000 frames/s){received}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["latency", "cpu"])
    parser.add_argument("--seconds", type=float, help="measuring window (default: 10 for latency, 20 for cpu)")
    args = parser.parse_args()
    if args.what == "latency":
        latency(args.seconds or 10.0)
    else:
        cpu(args.seconds or 20.0)


if __name__ == "__main__":
    main()

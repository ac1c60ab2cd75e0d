"""History storm: many clients polling /history while the 1 kHz path runs (a script, not a unit test).

    python scripts/historystorm.py --clients 20 --hz 5 --seconds 20 [--nice -10]

Starts `tactile serve` on loopback (built-in simulator: one 8x8 grid and one
quad at 1 kHz) from the current directory's ``service`` package (run it from
another checkout to measure that code), lets it settle, then runs
``--clients`` threads each asking ``GET /sensors/0/history?seconds=5&max_points=5000``
``--hz`` times a second for ``--seconds``. Reports the service's own
published latency (receive stamp → reconstructed and handed to the
listeners; /health, its last 10 000 published reads, ~10 s) before the storm
(start-up included) and 2 s before its end, how the reads were answered, and
the niceness the service really runs at (``nice_running``: ``--nice`` below 0
needs root or CAP_SYS_NICE, and without it ``nice`` runs the service at 0).
Only loopback is used; every loop is bounded in time.
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
import urllib.error
import urllib.request
from collections import Counter


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def get(url: str, timeout: float = 10.0) -> tuple[int, bytes]:
    try:
        with urllib.request.urlopen(url, timeout=timeout) as response:
            return response.status, response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()


def published(base: str) -> dict:
    return json.loads(get(f"{base}/health")[1])["latency"]["published"]


def poll(base: str, hz: float, until: float, answers: Counter, lock: threading.Lock, max_points: int) -> None:
    url = f"{base}/sensors/0/history?seconds=5&max_points={max_points}"
    next_due = time.monotonic()
    while next_due < until:
        status, _ = get(url)
        with lock:
            answers[status] += 1
        next_due += 1.0 / hz
        time.sleep(max(0.0, next_due - time.monotonic()))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clients", type=int, default=20)
    parser.add_argument("--hz", type=float, default=5.0)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--max-points", type=int, default=5000, help="frames per answer (5000: 5 s of an 8x8 grid, ~6 MB)")
    parser.add_argument("--nice", type=int, default=0, help="the service's niceness (the deployed set-up: -10; needs root)")
    args = parser.parse_args()
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen(["nice", "-n", str(args.nice), sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        time.sleep(0.5)  # nice has made itself the service by then
        running = os.getpriority(os.PRIO_PROCESS, server.pid)
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:
            try:
                if published(base)["samples"] > 6000:  # 3 s of frames: the window is full and tared
                    break
            except (OSError, KeyError, ValueError):
                pass
            time.sleep(0.2)
        quiet = published(base)
        answers: Counter = Counter()
        lock = threading.Lock()
        until = time.monotonic() + args.seconds
        threads = [threading.Thread(target=poll, args=(base, args.hz, until, answers, lock, args.max_points), daemon=True)
                   for _ in range(args.clients)]
        for thread in threads:
            thread.start()
        time.sleep(args.seconds - 2.0)  # the last 2 000 frames (2 s at 1 kHz of the grid) fall inside the storm
        storm = published(base)
        for thread in threads:
            thread.join(30)
    finally:
        server.terminate()
        server.wait(10)
    print(json.dumps({"quiet_published": quiet, "storm_published": storm, "answers": dict(answers),
                      "clients": args.clients, "hz": args.hz, "max_points": args.max_points, "seconds": args.seconds, "nice": args.nice, "nice_running": running}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())

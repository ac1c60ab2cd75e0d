"""One board's latency while another board of the same service floods (a script, not a unit test; docs/scale.md).

    python scripts/floodlatency.py [--seconds 4]

A service (in this process, as tests/test_boards.py runs it) reads a
simulated 1 kHz board (`sim://`, a grid and a quad) and a misbehaving TCP
board (firmware_sim/misbehaving.py), which streams, then floods, then
streams again, ``--seconds`` each. Printed per phase: the good board's
quad, receive stamp → handed to the listeners (p50, p99, max), and the
frames it published.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
from fastapi.testclient import TestClient

from firmware_sim.misbehaving import MisbehavingBoard
from service.api.app import create_app
from service.board import BoardSpec
from service.live_service import TactileService


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=4.0)
    args = parser.parse_args()
    bad = MisbehavingBoard()
    service = TactileService(boards=[BoardSpec("sim://?scene=press&sensors=grid,quad", "good"),
                                     BoardSpec(f"socket://127.0.0.1:{bad.port}", "bad")], silence_s=1.0)
    samples: list[tuple[float, float]] = []
    marks = {}
    with TestClient(create_app(service), base_url="http://localhost"):
        good = service.board("good").pipeline
        good.listeners = [*good.listeners, lambda frames: samples.extend(
            (time.time(), time.time() - f.t_host) for f in frames if f.sensor.kind == "quad")]
        deadline = time.monotonic() + 10
        while len(service.board("bad").pipeline.latest) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        for phase in ("stream", "flood", "stream again"):
            bad.phase = "flood" if phase == "flood" else "stream"
            start = time.time()
            time.sleep(args.seconds)
            marks[phase] = (start + 0.5, time.time())  # after the phase settled
        bad.stop.set()
    stamps = np.array(samples)
    for phase, (start, end) in marks.items():
        ms = stamps[(stamps[:, 0] >= start) & (stamps[:, 0] < end), 1] * 1e3
        print(f"{phase:>12}: {len(ms)} frames, p50 {np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
              f"max {ms.max():.2f} ms")


if __name__ == "__main__":
    main()

"""Per-read cost of the live pipeline, in process: 4 grids + 4 quads at 1 kHz
cut into ~1 ms reads and fed as the live path does (``Pipeline.feed_reads``,
grids reconstructed at once); prints µs per read (median, p99, p99.9, max).

    python scripts/perread.py [TREE]     # TREE: another checkout to measure (its service/ and firmware_sim/)

Alternate runs of two trees on a quiet host to compare them.
"""
import argparse
import sys
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("tree", nargs="?", default=None, help="checkout to import service/ from (default: this one)")
    parser.add_argument("--seconds", type=float, default=6.0)
    args = parser.parse_args()
    if args.tree:
        sys.path.insert(0, args.tree)
    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.sensors import SimGrid, SimQuad
    from service.pipeline import Pipeline

    sensors = [SimGrid(i) for i in range(4)] + [SimQuad(4 + i) for i in range(4)]
    data, _ = capture(BoardConfig(sensors=sensors, scene="demo", rate_hz=1000), args.seconds)
    step = int(len(data) / (args.seconds * 1000))  # one read a millisecond
    pipeline = Pipeline()
    times = []
    for k, start in enumerate(range(0, len(data), step)):
        began = time.perf_counter()
        pipeline.feed_reads([(data[start:start + step], 1000.0 + k * 1e-3)], lambda f: f())
        times.append(time.perf_counter() - began)
    us = np.array(times[1000:]) * 1e6  # after the tare and the first adoption
    print(f"{args.tree or 'this tree'}: µs per read median {np.median(us):.0f}, p99 {np.percentile(us, 99):.0f}, "
          f"p99.9 {np.percentile(us, 99.9):.0f}, max {us.max():.0f}")


if __name__ == "__main__":
    main()

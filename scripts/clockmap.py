"""Two simulated boards, one event: how far apart does the host see it?

    python scripts/clockmap.py [--seeds 20] [--seconds 10] [--jitter-ms 5]

Per rate (1000 and 200 Hz) and seed: two boards with clocks at +200 and
−200 ppm and offsets far apart (one wraps during the run), their scans
delivered late by up to ``--jitter-ms`` (one-sided, a late scan holding up
the next: several per read), decoded by service.protocol_decoder.Decoder and mapped
by one service.clock_map.ClockMap per board. After ``--seconds`` it maps the
true times of 500 events in the last second to each board's clock and back
to the host's, and prints the max and p99 over seeds of the two boards'
disagreement, each board's worst error against the truth, and µs per
``observe`` call (best of the runs, the simulator and decoder not counted).
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from firmware_sim.board import BoardConfig
from firmware_sim.delivery import deliveries
from firmware_sim.sensors import SimQuad
from service.clock_map import ClockMap
from service.protocol import DATA_TYPES
from service.protocol_decoder import Decoder

WRAP = 1 << 32
BOARDS = [(200.0, 123_456_789), (-200.0, WRAP - 4_000_000)]


def one_board(rate_hz: float, seed: int, ppm: float, offset: int, seconds: float, jitter_ms: float):
    config = BoardConfig(sensors=[SimQuad(0)], scene="idle", rate_hz=rate_hz, seed=seed, noise_fF=0.0,
                         clock_ppm=ppm, clock_offset_us=offset, jitter_ms=jitter_ms)
    decoder = Decoder()
    fed = []
    for t_recv, data in deliveries(config, seconds):
        t_us = np.array([f.t_us for f in decoder.feed(data) if f.type in DATA_TYPES], dtype=np.int64)
        if t_us.size:
            fed.append((t_us, t_recv))
    clock = ClockMap()
    start = time.perf_counter()
    for t_us, t_recv in fed:
        clock.observe(t_us, t_recv)
    us_per_call = (time.perf_counter() - start) / len(fed) * 1e6
    events = np.linspace(seconds - 1.0, seconds, 500)
    seen = clock.to_host((np.rint(events * (1 + ppm * 1e-6) * 1e6).astype(np.int64) + offset) % WRAP)
    return seen, float(np.abs(seen - events).max()), us_per_call, clock.status()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--jitter-ms", type=float, default=5.0)
    args = parser.parse_args()
    for rate_hz in (1000.0, 200.0):
        apart, worst, speed, rate_err = [], [], [], []
        for seed in range(args.seeds):
            runs = [one_board(rate_hz, 2 * seed + b, ppm, offset, args.seconds, args.jitter_ms)
                    for b, (ppm, offset) in enumerate(BOARDS)]
            apart.append(float(np.abs(runs[0][0] - runs[1][0]).max()))
            worst += [r[1] for r in runs]
            speed += [r[2] for r in runs]
            rate_err += [abs(r[3]["rate_error_ppm"] - ppm) for r, (ppm, _) in zip(runs, BOARDS)]
        print(f"{rate_hz:6.0f} Hz, {args.seeds} seeds, {args.jitter_ms} ms jitter, after {args.seconds} s: "
              f"disagreement max {max(apart) * 1e3:.3f} ms, p99 {np.percentile(apart, 99) * 1e3:.3f} ms; "
              f"error vs truth max {max(worst) * 1e3:.3f} ms; rate error max {max(rate_err):.2f} ppm; "
              f"observe {min(speed):.1f} µs/call (median {np.median(speed):.1f})")


if __name__ == "__main__":
    main()

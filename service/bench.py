"""`tactile bench`: decoder throughput and level-0 reconstruction cost.

Data: a simulator capture (default board: one 8x8 grid + one quad, 1 kHz,
scene demo) made on a virtual clock. Timings are wall-clock on this machine,
best of a few repeats, one core.
"""
from __future__ import annotations

import platform
import time

import numpy as np

from .calibration import table1
from .pipeline import Pipeline
from .protocol import Decoder
from .readings import Interpreter
from .reconstruct import Reconstructor, level0

REPEATS = 3


def _best(fn) -> float:
    best = float("inf")
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def run(seconds: float = 10.0) -> dict:
    from firmware_sim.board import BoardConfig, capture

    data, board = capture(BoardConfig(scene="demo"), seconds, keep_truth=True)
    frames = Decoder().feed(data)
    n = len(frames)

    batch_s = _best(lambda: Decoder().feed(data))

    def streaming():
        decoder = Decoder()
        for i in range(0, len(data), 4096):
            decoder.feed(data[i : i + 4096])

    stream_s = _best(streaming)

    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [r for r in (interpreter.interpret(f, 0.0) for f in frames) if r is not None]

    def per_frame():
        reconstructor = Reconstructor(tare_frames=1)
        for reading in readings:
            reconstructor.process(reading)

    per_frame_s = _best(per_frame)

    grid = np.stack([r.capacitance_pF for r in readings if r.sensor.kind == "grid"])
    baseline = grid[:100].mean(axis=0)
    calibration = table1()
    batch_grid_s = _best(lambda: level0.grid_forces(grid, baseline, calibration))

    def end_to_end():
        pipeline = Pipeline(Reconstructor(hold_until_tared=True), clock=lambda: 0.0)
        pipeline.feed(data, 0.0)
        pipeline.finish(0.0)

    end_to_end_s = _best(end_to_end)

    report = {
        "machine": f"{platform.machine()} {platform.processor() or ''} python {platform.python_version()}".strip(),
        "capture": {"seconds": seconds, "bytes": len(data), "frames": n},
        "decoder_batch_frames_per_s": n / batch_s,
        "decoder_stream_4k_chunks_frames_per_s": n / stream_s,
        "level0_per_frame_us": per_frame_s / len(readings) * 1e6,
        "level0_grid_batch_us_per_frame": batch_grid_s / len(grid) * 1e6,
        "pipeline_end_to_end_frames_per_s": n / end_to_end_s,
    }
    report["text"] = "\n".join(
        [
            f"machine: {report['machine']}",
            f"capture: {seconds:g} s, {len(data)} bytes, {n} frames (8x8 grid + quad at 1 kHz)",
            f"decoder, whole capture in one feed: {report['decoder_batch_frames_per_s']:,.0f} frames/s",
            f"decoder, 4 KiB chunks:               {report['decoder_stream_4k_chunks_frames_per_s']:,.0f} frames/s",
            f"level-0 reconstruction, per frame:   {report['level0_per_frame_us']:.1f} µs (interpret excluded)",
            f"level-0 grid forces, batched:        {report['level0_grid_batch_us_per_frame']:.3f} µs/frame",
            f"bytes → forces, whole pipeline:      {report['pipeline_end_to_end_frames_per_s']:,.0f} frames/s",
        ]
    )
    return report

"""Whole-process figures for `tactile bench`: what a user runs, timed as the
operating system counts it (user + sys CPU of the child process, imports
and start-up included), against a naive reference decoder
(naive_decoder.py) measured in the same run on the same file.

The capture is the simulator's 8×8 grid alone (scene press, 1 kHz); the
MCAP recording is the same bytes recorded through a live pipeline in 50 ms
reads. Commands run in turn, ``repeats`` rounds; each figure is the median
of its rounds, each ratio the naive decoder's median CPU over the command's
(> 1: faster than the naive decoder). ``start-up`` is the replay of a 0.1 s
capture: the cost of a run that does no work.
"""
from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Callable

RATE_HZ = 1000
REPEATS = 3
READ_S = 0.05


def cpu_seconds(command: list[str]) -> float:
    """User + sys CPU of one run of ``command`` (RuntimeError if it fails)."""
    child = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(child.pid, 0)
    child.returncode = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    if child.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed (exit {child.returncode})")
    return usage.ru_utime + usage.ru_stime


def _captures(directory: Path, seconds: float) -> tuple[Path, Path, Path]:
    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.sensors import SimGrid

    from ..pipeline import Pipeline
    from ..reconstruct import Reconstructor
    from ..record.recorder import Recorder

    config = BoardConfig(sensors=[SimGrid(0)], scene="press", rate_hz=RATE_HZ)
    data, _ = capture(config, seconds)
    raw, tiny, mcap = directory / "grid.bin", directory / "tiny.bin", directory / "grid.mcap"
    raw.write_bytes(data)
    tiny.write_bytes(capture(config, 0.1)[0])
    pipeline = Pipeline(Reconstructor())
    recorder = Recorder(mcap)
    recorder.attach(pipeline)
    step = max(1, int(len(data) / seconds * READ_S))
    for i, pos in enumerate(range(0, len(data), step)):
        pipeline.feed(data[pos : pos + step], 1000.0 + i * READ_S)
    recorder.stop()
    return raw, tiny, mcap


def commands(raw: Path, tiny: Path, mcap: Path, out: Path) -> dict[str, list[str]]:
    python = [sys.executable, "-m"]
    replay = [*python, "service.cli", "replay"]
    return {
        "naive decoder → jsonl": [*python, "service.reports.naive_decoder", str(raw), str(out / "naive.jsonl")],
        "replay --raw → jsonl": [*replay, "--raw", str(raw), "--export", str(out / "replay.jsonl")],
        "replay --raw → parquet": [*replay, "--raw", str(raw), "--export", str(out / "replay.parquet")],
        "replay .mcap --speed max → jsonl": [*replay, str(mcap), "--speed", "max", "--export", str(out / "mcap.jsonl")],
        "start-up (0.1 s capture)": [*replay, "--raw", str(tiny), "--export", str(out / "tiny.jsonl")],
    }


def whole_process(seconds: float = 60.0, repeats: int = REPEATS,
                  progress: Callable[[str], None] = lambda what: None) -> dict:
    """Median CPU s, grid frames/s and ratio to the naive decoder per command."""
    with tempfile.TemporaryDirectory(prefix="tactile-bench-") as tmp:
        raw, tiny, mcap = _captures(Path(tmp), seconds)
        runs = commands(raw, tiny, mcap, Path(tmp))
        cpu: dict[str, list[float]] = {name: [] for name in runs}
        for round_ in range(repeats):
            for name, command in runs.items():
                cpu[name].append(cpu_seconds(command))
            progress(f"whole process, round {round_ + 1} of {repeats}")
        size = raw.stat().st_size
    frames = int(seconds * RATE_HZ)
    naive = statistics.median(cpu["naive decoder → jsonl"])
    rows = []
    for name, times in cpu.items():
        median = statistics.median(times)
        count = frames if "start-up" not in name else None
        rows.append({"command": name, "cpu_s": median, "runs_s": times,
                     "grid_frames_per_s": count / median if count else None,
                     "ratio_to_naive": naive / median if count else None})
    return {"frames": frames, "capture_bytes": size, "repeats": repeats, "rows": rows}


def render(figures: dict) -> list[str]:
    lines = [f"whole process (user + sys CPU of the command, median of {figures['repeats']}; "
             f"{figures['frames']:,} 8×8 grid frames, {figures['capture_bytes'] / 1e6:.1f} MB):", "",
             "| command | CPU s | grid frames/s | × naive decoder |", "|---|---|---|---|"]
    for row in figures["rows"]:
        rate = f"{row['grid_frames_per_s']:,.0f}" if row["grid_frames_per_s"] else "–"
        ratio = f"{row['ratio_to_naive']:.2f}" if row["ratio_to_naive"] else "–"
        lines.append(f"| {row['command']} | {row['cpu_s']:.2f} | {rate} | {ratio} |")
    return lines

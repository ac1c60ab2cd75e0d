"""`tactile bench`: speed against error of every fidelity level.

For each scenario the simulator (1 kHz, 1 fF noise, the paper's mechanical
crosstalk) records a capture with its ground truth; each level then
reconstructs it in batch (all grid frames at once, one core) and streaming
(frame by frame through the Reconstructor, flags and contact summary
included). Errors are against the truth: grid taxels split into loaded
(truth > 0.05 N) and unloaded, quad per axis. The decoder's throughput is
measured on the same bytes. ``--out DIR`` writes bench.md and bench.png
(matplotlib, the docs extra, is required for that: see plotting.py).
"""
from __future__ import annotations

import itertools
import platform
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from ..protocol_decoder import Decoder
from ..interpreter import Interpreter
from ..reconstruct import Reconstructor
from ..reconstruct.baseline import DEFAULT_TARE_FRAMES
from ..reconstruct.calibration_upload import processor_for
from ..reconstruct.levels import GRID_LEVELS
from ..reconstruct.sensor_calibration import builtin
from . import bench_process, plotting

REPEATS = 3
LOADED_N = 0.05
TARGET_GRID_FRAMES_PER_S = 37_000


@dataclass(frozen=True)
class Scenario:
    name: str
    scene: str
    grid_options: dict = field(default_factory=dict)


SCENARIOS = (
    Scenario("press", "press"),
    Scenario("slide", "slide"),
    Scenario("press + 1 % mux leakage", "press", {"electrical_leakage": 0.01}),
    # 0.47 %/min at its fastest: a physical drift (drift.py tracks up to 1 %/min; 20 s periods made 5.7)
    Scenario("slide + common-mode drift", "slide", {"drift": ("drift", 0.003, 240.0)}),
    Scenario("shear (quad)", "shear"),
)


def _best(fn) -> float:
    best = float("inf")
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def _capture(scenario: Scenario, seconds: float):
    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.sensors import Drift, SimGrid, SimQuad

    options = dict(scenario.grid_options)
    if "drift" in options:
        _, amplitude, period = options.pop("drift")
        options["drift"] = Drift(amplitude, period)
    config = BoardConfig(sensors=[SimGrid(0, **options), SimQuad(1)], scene=scenario.scene)
    return capture(config, seconds, keep_truth=True)


def noise_floor_N(noise_fF: float = 1.0) -> float:
    """The force noise floor of the 8×8 grid: the RMS over the 64 table-1
    taxels of the force that ``noise_fF`` of white capacitance noise reads as.

    A taxel reads ΔC/C0 = s · F, so a capacitance error σ_C is a force error
    σ_C / (C0 · s), with σ_C in pF (1 fF = 1e-3 pF), C0 the taxel's rest
    capacitance (pF) and s its sensitivity (per N). With the simulator's
    1 fF, C0 ≈ 10 pF and s ≈ 1.25 %/N this is ≈ 0.0076 N. The bench and the
    fidelity tests state errors against it.
    """
    from ..physics.paper_data import table1

    cal = table1()
    return float(np.sqrt(np.mean((noise_fF * 1e-3 / (cal.c0_pF * cal.sensitivity_per_N)) ** 2)))


def _errors(forces: np.ndarray, truth: np.ndarray) -> dict:
    err = forces - truth
    loaded = truth > LOADED_N
    out = {}
    for name, mask in (("loaded", loaded), ("unloaded", ~loaded)):
        e = np.abs(err[mask])
        out[f"rms_{name}_N"] = float(np.sqrt(np.mean(e**2))) if e.size else float("nan")
        out[f"p99_{name}_N"] = float(np.percentile(e, 99)) if e.size else float("nan")
    return out


def run_scenario(scenario: Scenario, seconds: float) -> list[dict]:
    data, board = _capture(scenario, seconds)
    frames = Decoder().feed(data)
    interpreter = Interpreter(clock=lambda: 0.0)
    readings = [r for r in (interpreter.interpret(f, 0.0) for f in frames) if r is not None]
    truth = {(t.sensor, t.seq): t.values for t in board.truth}
    grid = [r for r in readings if r.sensor.kind == "grid"]
    quad = [r for r in readings if r.sensor.kind == "quad"]
    grid_c = np.stack([r.capacitance_pF for r in grid])
    grid_t = np.array([r.t_us * 1e-6 for r in grid])
    grid_truth = np.stack([truth[(0, r.seq)] for r in grid])
    quad_truth = np.stack([truth[(1, r.seq)] for r in quad])
    tare = slice(0, DEFAULT_TARE_FRAMES)
    baseline, baseline_std = grid_c[tare].mean(axis=0), grid_c[tare].std(axis=0)
    rows = []
    for level in GRID_LEVELS:
        processor = processor_for(grid[0].sensor, level, "flat", builtin(grid[0].sensor))
        batch_s = _best(lambda: processor.process(grid_c, baseline, baseline_std, grid_t))

        def streaming():
            rec = Reconstructor(level=level, hold_until_tared=True)
            out = []
            for reading in readings:
                out.extend(rec.process(reading))
            return out

        def chunked():
            # As the live path gets them: one read of the port is ~50 ms of frames.
            rec = Reconstructor(level=level, hold_until_tared=True)
            for i in range(0, len(readings), 100):
                rec.process_many(readings[i : i + 100])

        t0 = time.perf_counter()
        streamed = streaming()
        stream_s = time.perf_counter() - t0
        chunk_s = _best(chunked)
        by_sensor = {0: [], 1: []}
        for frame in streamed:
            by_sensor[frame.sensor.id].append(frame.forces_N)
        row = {
            "scenario": scenario.name,
            "level": level,
            "batch_us_per_grid_frame": batch_s / len(grid) * 1e6,
            "batch_grid_frames_per_s": len(grid) / batch_s,
            "stream_us_per_frame": stream_s / len(readings) * 1e6,
            "chunked_us_per_frame": chunk_s / len(readings) * 1e6,
            **_errors(np.stack(by_sensor[0]), grid_truth),
        }
        quad_err = np.stack(by_sensor[1]) - quad_truth
        for axis, name in enumerate(("x", "y", "z")):
            row[f"quad_rms_{name}_N"] = float(np.sqrt(np.mean(quad_err[:, axis] ** 2)))
        rows.append(row)
    return rows


def decoder_figures(seconds: float) -> dict:
    data, _ = _capture(SCENARIOS[1], seconds)
    n = len(Decoder().feed(data))

    def streaming():
        decoder = Decoder()
        for i in range(0, len(data), 4096):
            decoder.feed(data[i : i + 4096])

    return {
        "frames": n,
        "decoder_batch_frames_per_s": n / _best(lambda: Decoder().feed(data)),
        "decoder_stream_4k_frames_per_s": n / _best(streaming),
    }


def live_path_figures(seconds: float, level: str = "full") -> dict:
    """The live data path as the service runs it: a board of 4 grids and 4
    quads at 1 kHz, fed to the pipeline one 1 ms read at a time (decode,
    readings, reconstruction, history, publish; no API clients). Best of
    REPEATS over the last two thirds (after the tare)."""
    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.sensors import SimGrid, SimQuad

    from ..pipeline import Pipeline

    config = BoardConfig(sensors=[SimGrid(i) for i in range(4)] + [SimQuad(i) for i in range(4, 8)], scene="demo")
    data, _ = capture(config, seconds)
    scan = len(data) / (seconds * config.rate_hz)
    reads = [data[int(i * scan) : int((i + 1) * scan)] for i in range(int(seconds * config.rate_hz))]
    warm = len(reads) // 3
    best = float("inf")
    for _ in range(REPEATS):
        pipeline = Pipeline(Reconstructor(level=level))
        for chunk in reads[:warm]:
            pipeline.feed(chunk, 0.0)
        t0 = time.perf_counter()
        for chunk in reads[warm:]:
            pipeline.feed(chunk, 0.0)
        best = min(best, (time.perf_counter() - t0) / (len(reads) - warm))
    return {"level": level, "us_per_1ms_read": best * 1e6, "share_of_one_core_at_1kHz": best * config.rate_hz}


def _no_progress(done: int, total: int, what: str) -> None:
    pass


def run(seconds: float = 10.0, progress: Callable[[int, int, str], None] = _no_progress,
        process_seconds: float = 60.0) -> dict:
    """The whole bench; ``progress(done, total, what)`` after each of its steps
    (a scenario, the decoder, the live path at one level, a round of the
    whole-process figures on a ``process_seconds`` capture; 0: none)."""
    rounds = bench_process.REPEATS if process_seconds else 0
    total = len(SCENARIOS) + 1 + len(GRID_LEVELS) + rounds
    rows = []
    for i, scenario in enumerate(SCENARIOS, 1):
        rows += run_scenario(scenario, seconds)
        progress(i, total, scenario.name)
    decoder = decoder_figures(seconds)
    progress(len(SCENARIOS) + 1, total, "decoder")
    live = []
    for level in GRID_LEVELS:
        live.append(live_path_figures(min(seconds, 6.0), level))
        progress(len(SCENARIOS) + 1 + len(live), total, f"live path, {level}")
    steps = itertools.count(len(SCENARIOS) + 2 + len(live))
    process = bench_process.whole_process(process_seconds, rounds, lambda what: progress(next(steps), total, what)) \
        if rounds else None
    report = {
        "machine": f"{platform.machine()} python {platform.python_version()}",
        "process": process,
        "seconds": seconds,
        "noise_floor_N": noise_floor_N(),
        "decoder": decoder,
        "live": live,
        "rows": rows,
    }
    report["text"] = render_text(report)
    return report


def render_text(report: dict) -> str:
    floor = report["noise_floor_N"]
    dec = report["decoder"]
    lines = [
        f"machine: {report['machine']}; {report['seconds']:g} s per scenario at 1 kHz; noise floor σ = {floor:.4f} N per taxel",
        f"decoder: {dec['decoder_batch_frames_per_s']:,.0f} frames/s in one feed, {dec['decoder_stream_4k_frames_per_s']:,.0f} frames/s in 4 KiB chunks",
        "live path, 4 grids + 4 quads at 1 kHz read 1 ms at a time: "
        + "; ".join(f"{live['level']} {live['us_per_1ms_read']:.0f} µs per read ({100 * live['share_of_one_core_at_1kHz']:.0f} % of a core)"
                    for live in report["live"]),
        "",
        *(bench_process.render(report["process"]) + [""] if report.get("process") else []),
        "| scenario | level | batch µs/grid frame | grid frames/s | stream µs/frame | live chunks µs/frame | RMS loaded N | p99 loaded N | RMS unloaded N | p99 unloaded N | quad RMS x/y/z N |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in report["rows"]:
        lines.append(
            f"| {r['scenario']} | {r['level']} | {r['batch_us_per_grid_frame']:.2f} | {r['batch_grid_frames_per_s']:,.0f} | "
            f"{r['stream_us_per_frame']:.1f} | {r['chunked_us_per_frame']:.1f} | {r['rms_loaded_N']:.4f} | {r['p99_loaded_N']:.4f} | {r['rms_unloaded_N']:.4f} | "
            f"{r['p99_unloaded_N']:.4f} | {r['quad_rms_x_N']:.3f}/{r['quad_rms_y_N']:.3f}/{r['quad_rms_z_N']:.3f} |"
        )
    return "\n".join(lines)


def write_docs(report: dict, out_dir: Path) -> list[Path]:
    """Write bench.md and bench.png to ``out_dir``. Without matplotlib this
    raises plotting.PlottingUnavailable before writing either, so the docs
    never hold a new table beside a stale figure."""
    plotting.require("bench.png")
    out_dir.mkdir(parents=True, exist_ok=True)
    md = out_dir / "bench.md"
    md.write_text(
        "# Speed against error\n\nProduced by `tactile bench --out docs` (see service/reports/bench.py for what is measured).\n"
        f"Target: full fidelity at ≥ {TARGET_GRID_FRAMES_PER_S:,} grid frames/s in batch on one core, "
        "error within 2× the noise floor.\n\n" + report["text"] + "\n"
    )
    return [md, plot(report, out_dir / "bench.png")]


def plot(report: dict, path: Path) -> Path:
    """RMS error on loaded taxels against batch cost, one marker per level,
    one line per scenario, with the 2× noise floor and the speed target."""
    fig, (ax,) = plotting.figure(
        plotting.Panel("batch cost per grid frame (µs)", "RMS error on loaded taxels (N)", xscale="log", yscale="log"),
        size_in=(7, 4.5),
    )
    markers = {"level0": "o", "table": "s", "full": "^"}
    for scenario in dict.fromkeys(r["scenario"] for r in report["rows"]):
        rows = [r for r in report["rows"] if r["scenario"] == scenario]
        ax.plot([r["batch_us_per_grid_frame"] for r in rows], [r["rms_loaded_N"] for r in rows], "-", alpha=0.4)
        for r in rows:
            ax.scatter(r["batch_us_per_grid_frame"], r["rms_loaded_N"], marker=markers[r["level"]], label=f"{scenario}: {r['level']}")
    ax.axhline(2 * report["noise_floor_N"], color="k", ls="--", lw=1, label="2× noise floor")
    ax.axvline(1e6 / TARGET_GRID_FRAMES_PER_S, color="r", ls=":", lw=1, label=f"{TARGET_GRID_FRAMES_PER_S:,} frames/s".replace(",", " "))
    ax.legend(fontsize=6, ncol=2)
    return plotting.save_png(fig, path)

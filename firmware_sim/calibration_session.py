"""A reference-load calibration session of a grid that is not table 1.

What a user's calibration run produces, simulated on the board's own
physics (``SimGrid`` with its own ``GridCalibration``): a probe presses one
taxel at a time, 0 → ~90 % of full scale → 0 as a raised-cosine ramp (about
1 s each way), each taxel twice, with at least ``gap_s`` unloaded between
presses; the board streams its raw bytes, and a reference instrument logs the
applied force on its own clock (``t_ref = offset_s + t_board·(1 + ppm·1e-6)``)
at its own rate, with noise and a few blank or garbage lines, as a CSV
``t_s,force_N``. The pauses are jittered (a person or a randomised robot
never presses with a perfect period; a perfectly periodic session can only be
aligned by its ends, see service/calibration/alignment.py).

Imports only the simulator and service.physics, like the rest of firmware_sim.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from service.physics.paper_data import GridCalibration, table1

from .board import BoardConfig, capture
from .sensors import SimGrid

FULL_SCALE_N = 10.0  # the paper's calibrated range, 0–10 N
QUIET_S = 1.5  # unloaded before the first press and after the last


@dataclass(frozen=True)
class Press:
    """One probe press: taxel (row-major index), start (board s), peak (N), ramp (s each way)."""

    taxel: int
    start_s: float
    peak_N: float
    ramp_s: float = 1.0

    @property
    def end_s(self) -> float:
        return self.start_s + 2.0 * self.ramp_s


def user_grid_calibration(seed: int = 1, gain_spread: float = 0.15, c0_spread: float = 0.05) -> GridCalibration:
    """An 8x8 grid that is not table 1: sensitivities table 1's mean × U(1 ± gain_spread),
    C0 table 1's × U(1 ± c0_spread); arrays of shape (64,)."""
    rng = np.random.default_rng(seed)
    base = table1()
    n = base.rows * base.cols
    sensitivity = float(base.sensitivity_per_N.mean()) * rng.uniform(1 - gain_spread, 1 + gain_spread, n)
    c0 = np.asarray(base.c0_pF) * rng.uniform(1 - c0_spread, 1 + c0_spread, n)
    return GridCalibration(base.rows, base.cols, c0, sensitivity)


def probe_schedule(taxels=range(64), repeats: int = 2, peak_N: float = 0.9 * FULL_SCALE_N, ramp_s: float = 1.0,
                   gap_s: float = 0.6, gap_jitter_s: float = 0.4, peak_jitter: float = 0.05,
                   seed: int = 0, start_s: float = QUIET_S) -> list[Press]:
    """Each taxel of ``taxels`` pressed ``repeats`` times in a row; pauses of
    gap_s + U(0, gap_jitter_s), peaks peak_N·U(1 ± peak_jitter)."""
    rng = np.random.default_rng(seed)
    presses, t = [], start_s
    for taxel in taxels:
        for _ in range(repeats):
            peak = peak_N * rng.uniform(1 - peak_jitter, 1 + peak_jitter)
            presses.append(Press(int(taxel), t, float(peak), ramp_s))
            t = presses[-1].end_s + gap_s + rng.uniform(0.0, gap_jitter_s)
    return presses


class ScheduleScene:
    """A scene (``BoardConfig.scene``) that plays a list of presses on one grid.

    ``forces(t)`` gives the probe's force (N) at board times ``t`` (k,)."""

    def __init__(self, presses: list[Press], sensor_id: int = 0) -> None:
        self.presses = sorted(presses, key=lambda p: p.start_s)
        self.sensor_id = sensor_id
        self._starts = np.array([p.start_s for p in self.presses])
        self._index = 0

    @property
    def end_s(self) -> float:
        return max((p.end_s for p in self.presses), default=0.0) + QUIET_S

    def _active(self, t: float) -> Press | None:
        i = int(np.searchsorted(self._starts, t, side="right")) - 1
        if i >= 0 and t < self.presses[i].end_s:
            return self.presses[i]
        return None

    def __call__(self, sensor, t: float) -> np.ndarray:
        truth = np.zeros(sensor.channels if sensor.kind == "grid" else 3)
        press = self._active(t) if sensor.id == self.sensor_id else None
        if press is not None:
            phase = (t - press.start_s) / (2.0 * press.ramp_s)
            truth[press.taxel] = press.peak_N * 0.5 * (1.0 - math.cos(2.0 * math.pi * phase))
        return truth

    def forces(self, t: np.ndarray) -> np.ndarray:
        out = np.zeros(len(t))
        for p in self.presses:
            inside = (t >= p.start_s) & (t < p.end_s)
            out[inside] = p.peak_N * 0.5 * (1.0 - np.cos(np.pi * (t[inside] - p.start_s) / p.ramp_s))
        return out


@dataclass
class Session:
    """A simulated session: the board's bytes, the reference CSV text and the truth."""

    raw: bytes
    reference_csv: str
    calibration: GridCalibration  # the sensor's true C0 and sensitivity (LS with intercept, 0–10 N)
    gain: np.ndarray  # (64,) true compliance gains κ
    presses: list[Press]
    offset_s: float
    rate_ppm: float
    garbage_lines: int
    truth_t_us: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (frames,) board times of the truth
    truth_N: np.ndarray = field(default_factory=lambda: np.zeros((0, 64)))  # (frames, 64) true forces


GARBAGE = ("", "ERR overload?", "   ", "t_s,force_N", "nan,oops", "# instrument paused")


def reference_csv(scene: ScheduleScene, board_end_s: float, rate_hz: float = 100.0, offset_s: float = 12.3,
                  rate_ppm: float = 150.0, noise_N: float = 0.01, garbage: int = 4, seed: int = 0,
                  head_s: float = 0.4, tail_s: float = 0.3) -> tuple[str, int]:
    """The instrument's log: samples uniform on its own clock from ``head_s``
    after the board starts to ``tail_s`` before it stops, ``garbage`` junk lines
    scattered in. Returns (text, number of junk lines)."""
    rng = np.random.default_rng(seed)
    scale = 1.0 + rate_ppm * 1e-6
    t_ref = np.arange(offset_s + head_s * scale, offset_s + (board_end_s - tail_s) * scale, 1.0 / rate_hz)
    force = scene.forces((t_ref - offset_s) / scale) + rng.normal(0.0, noise_N, t_ref.size)
    lines = [f"{t:.6f},{f:.5f}" for t, f in zip(t_ref, force)]
    for k, where in enumerate(sorted(rng.integers(1, len(lines), garbage))[::-1]):
        lines.insert(int(where), GARBAGE[k % len(GARBAGE)])
    return "t_s,force_N\n" + "\n".join(lines) + "\n", garbage


def run_presses(calibration: GridCalibration, presses: list[Press], rate_hz: float = 500.0, noise_fF: float = 1.0,
                seed: int = 0, keep_truth: bool = False, **board) -> tuple[bytes, ScheduleScene, object]:
    """The board's bytes for ``presses`` on a grid of ``calibration`` (sensor 0)."""
    scene = ScheduleScene(presses)
    grid = SimGrid(0, calibration=calibration, serial=board.pop("sensor_serial", None),
                   electrical_leakage=board.pop("leakage", 0.0))
    config = BoardConfig(sensors=[grid], rate_hz=rate_hz, scene=scene, noise_fF=noise_fF, seed=seed,
                         name=board.pop("name", "tactile-sim-8x8"), **board)
    raw, sim = capture(config, scene.end_s, keep_truth=keep_truth)
    return raw, scene, sim


def session(calibration: GridCalibration | None = None, presses: list[Press] | None = None, rate_hz: float = 500.0,
            noise_fF: float = 1.0, seed: int = 0, reference: dict | None = None, **board) -> Session:
    """A whole calibration session (defaults: every taxel twice, 500 Hz, the
    reference at 100 Hz, 12.3 s ahead, 150 ppm fast, 0.01 N noise)."""
    calibration = calibration or user_grid_calibration(seed + 1)
    presses = probe_schedule(seed=seed) if presses is None else presses
    raw, scene, _ = run_presses(calibration, presses, rate_hz, noise_fF, seed, **board)
    options = {"seed": seed, **(reference or {})}
    text, garbage = reference_csv(scene, scene.end_s, **options)
    gain = SimGrid(0, calibration=calibration).response.gain
    return Session(raw, text, calibration, gain, presses, options.get("offset_s", 12.3),
                   options.get("rate_ppm", 150.0), garbage)


def validation_presses(seed: int = 7, count: int = 12) -> list[Press]:
    """A separate press sequence: ``count`` random taxels, peaks 2–8 N, ramps 0.6–1.2 s."""
    rng = np.random.default_rng(seed)
    presses, t = [], QUIET_S
    for taxel in rng.choice(64, count, replace=False):
        ramp = float(rng.uniform(0.6, 1.2))
        presses.append(Press(int(taxel), t, float(rng.uniform(2.0, 8.0)), ramp))
        t = presses[-1].end_s + 0.5
    return presses


def validation_capture(calibration: GridCalibration, seed: int = 7, rate_hz: float = 500.0,
                       noise_fF: float = 1.0, presses: list[Press] | None = None, **board) -> Session:
    """The same sensor under a separate press sequence (default
    validation_presses(seed)), with the truth per frame; ``board`` as for
    run_presses (serials, name)."""
    presses = validation_presses(seed) if presses is None else presses
    raw, _, sim = run_presses(calibration, presses, rate_hz, noise_fF, seed, keep_truth=True, **board)
    truth_t = np.array([t.t_us for t in sim.truth])
    truth = np.stack([t.values for t in sim.truth])
    gain = SimGrid(0, calibration=calibration).response.gain
    return Session(raw, "", calibration, gain, presses, 0.0, 0.0, 0, truth_t, truth)


def main(argv: list[str] | None = None) -> int:
    """``python -m firmware_sim.calibration_session OUT_DIR [--rate HZ] [--seed N]``: writes
    session.bin, reference.csv, validation.bin and truth.json (gains, sensitivities, C0, clocks)."""
    import argparse
    import json
    from pathlib import Path

    parser = argparse.ArgumentParser(prog="python -m firmware_sim.calibration_session")
    parser.add_argument("out")
    parser.add_argument("--rate", type=float, default=500.0, help="board scans per second (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    sim = session(rate_hz=args.rate, seed=args.seed)
    (out / "session.bin").write_bytes(sim.raw)
    (out / "reference.csv").write_text(sim.reference_csv)
    (out / "validation.bin").write_bytes(validation_capture(sim.calibration, rate_hz=args.rate).raw)
    truth = {"offset_s": sim.offset_s, "rate_ppm": sim.rate_ppm, "gain": sim.gain.tolist(),
             "sensitivity_pct_per_N": (100 * sim.calibration.sensitivity_per_N).tolist(),
             "c0_pF": sim.calibration.c0_pF.tolist(), "garbage_lines": sim.garbage_lines,
             "session_s": max(p.end_s for p in sim.presses) + QUIET_S}
    (out / "truth.json").write_text(json.dumps(truth, indent=1))
    print(f"{out}: session.bin ({len(sim.raw)} bytes, {truth['session_s']:.0f} s at {args.rate:g} Hz), reference.csv, "
          "validation.bin, truth.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

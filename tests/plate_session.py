"""Drift-free and drifting sessions of an 8×8 under slow plates, from paper
000's physics, as bytes a board sends (an independent generator: not the
simulator the service was tuned on).

A taxel's PDMS is confined, so a force F compresses its gap by k·F·d0 and
C = C0/(1 − kF): ΔC/C0 = kF/(1 − kF). k = 0.0112 /N puts 5.21 N at the
paper's 6.1 % (U44) and the 0–10 N least-squares slope near its 1.24 %/N;
each taxel's k is spread ±20 % (a sensitivity the service was not told).
A pressed taxel pulls each of its eight neighbours by −0.28 % of its own
ΔC/C0 (paper 000: 0.015–0.019 % at U44's 6.1 %). C0 is table 1's; the
converter adds 2 fF of white noise; a common-mode drift multiplies every C0
by 1 + drift(t)."""
from __future__ import annotations

import numpy as np
import orjson

from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.reconstruct import Reconstructor

C0_PF = np.array([
    [9.76, 9.74, 10.56, 10.54, 10.87, 10.64, 10.65, 10.63],
    [8.45, 8.24, 7.82, 9.15, 10.77, 11.66, 11.14, 10.65],
    [9.35, 9.40, 10.07, 9.59, 10.13, 10.30, 9.62, 9.76],
    [9.49, 10.01, 9.65, 9.68, 10.40, 10.52, 9.95, 9.95],
    [9.47, 9.95, 10.67, 10.94, 11.09, 10.93, 10.33, 10.49],
    [11.22, 11.64, 11.43, 11.15, 11.55, 11.28, 11.63, 11.28],
    [10.92, 10.92, 11.12, 11.61, 12.04, 11.70, 10.60, 11.29],
    [11.03, 12.36, 12.20, 12.03, 12.63, 12.34, 12.35, 11.99]]).ravel()  # paper 000 table 1
K_PER_N = 0.0112
COUPLING = -0.0028
NOISE_PF = 0.002
RATE_HZ = 500


def neighbours() -> np.ndarray:
    """(64, 64): 1 where two taxels of the 8×8 touch (sides or corners)."""
    r, c = np.divmod(np.arange(64), 8)
    near = (np.abs(r[:, None] - r[None, :]) <= 1) & (np.abs(c[:, None] - c[None, :]) <= 1)
    return (near & ~np.eye(64, dtype=bool)).astype(float)


def plate(start_s: float, ramp_s: float, hold_s: float, peak_n: float):
    """Force per taxel at t: 0 until ``start_s``, up over ``ramp_s``, held ``hold_s``, down over ``ramp_s``."""
    def force(t: np.ndarray) -> np.ndarray:
        up = (t - start_s) / ramp_s
        down = (start_s + 2 * ramp_s + hold_s - t) / ramp_s
        return peak_n * np.clip(np.minimum(up, down), 0.0, 1.0)
    return force


def capacitance(force_n: np.ndarray, drift: np.ndarray, seed: int, noise_pf: float = NOISE_PF) -> np.ndarray:
    """(N, 64) pF for forces (N, 64) N and a common-mode drift (N,) ΔC/C0, ``noise_pf`` of white noise."""
    rng = np.random.default_rng(seed)
    x = K_PER_N * (1 + rng.uniform(-0.2, 0.2, 64)) * force_n
    own = x / (1 - x)
    relative = own + COUPLING * own @ neighbours()
    noise = rng.normal(0.0, noise_pf, force_n.shape)
    return C0_PF * (1 + drift)[:, None] * (1 + relative) + noise


def session(seconds: float, force, covered: np.ndarray, drift_per_s: float = 0.0, seed: int = 1,
            noise_pf: float = NOISE_PF, drift=None, reconstructor: Reconstructor | None = None):
    """(t (N,), truth (N, 64) N, frames) of ``seconds`` at RATE_HZ through the
    Pipeline at the full level: ``force(t)`` on the ``covered`` taxels, C0
    drifting linearly by ``drift_per_s`` ΔC/C0 a second (from the first
    frame) or by ``drift(t)`` if given, ``noise_pf`` of noise; the first
    frames tare. ``reconstructor``: one to inspect afterwards (a new one if None)."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    truth = np.zeros((len(t), 64))
    truth[:, covered] = force(t)[:, None]
    common = drift_per_s * t if drift is None else drift(t)
    attofarads = np.rint(capacitance(truth, common, seed, noise_pf) * 1e6).astype("<u4")
    info = {"board": "plate-gen", "fw": "1.0.0", "rate_hz": RATE_HZ,
            "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]}
    data = [encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(info))]
    data += [encode_frame(FrameType.GRID, 0, k, int(round(s * 1e6)) + 500, row.tobytes())
             for k, (s, row) in enumerate(zip(t, attofarads))]
    pipeline = Pipeline(reconstructor or Reconstructor(level="full"), clock=lambda: 0.0)
    frames = []
    for i in range(0, len(data), 50):  # reads of 50 scans, as a port delivers them
        frames += pipeline.feed(b"".join(data[i:i + 50]), 0.0)
    frames += pipeline.finish(0.0)
    return t, truth, frames

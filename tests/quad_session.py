"""Quad sessions with presses, creep and a temperature drift, from paper
001's quad model, as bytes a board sends (an independent generator: not the
simulator the service was tuned on).

Electrode ij (sx, sy = ±1 on the +X/+Y side) reads

    ΔC/C0 = s·(n(Fz) + sx·t(Fx) + sy·t(Fy)) + creep

with n(F) = 0.0343 F − 0.0009 F² (fit 34 without its offset), t(F) =
0.0077 F − 0.0004 F|F| (fit 35, odd), s = 1 − 0.22·(1 − exp(−cycles/1000))
what the presses so far left of the sensitivity (paper 001 §5.2: 3 N ten
thousand times, −22 %), counted here per press above 1 N. PDMS creeps under
a held load: ``creep`` follows CREEP_SHARE of the normal response with
CREEP_TAU_S (a Kelvin–Voigt element: up under the load, back after it).
A temperature drift multiplies every electrode's C0 by 1 + drift(t); the
converter adds NOISE_RELATIVE of C0 of white noise. One INFO, then a QUAD
frame a millisecond per quad, fed to ``service.pipeline.Pipeline`` 50 scans
a read."""
from __future__ import annotations

import numpy as np
import orjson

from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.reconstruct import Reconstructor

C0_PF = np.array([2.21, 2.18, 2.24, 2.20])
NORMAL = (0.0343, -0.0009)  # ΔC/C0 = a F + b F², paper 001 fit (34)
SHEAR = (0.0077, -0.0004)  # fit (35)
SIDES = np.array([[-1.0, 1.0, -1.0, 1.0], [-1.0, -1.0, 1.0, 1.0]])  # C11, C12, C21, C22 on the ±X, ±Y sides
NOISE_RELATIVE = 1e-4
RATE_HZ = 1000
READ_SCANS = 50
CREEP_SHARE = 0.04
CREEP_TAU_S = 20.0


def press(start_s: float, ramp_s: float, hold_s: float, fz_n: float, fx_n: float = 0.0):
    """(Fx, Fy, Fz) at times t: 0 until ``start_s``, up over ``ramp_s``, held ``hold_s``, down over ``ramp_s``."""
    def force(t: np.ndarray) -> np.ndarray:
        up = (t - start_s) / ramp_s
        down = (start_s + 2 * ramp_s + hold_s - t) / ramp_s
        share = np.clip(np.minimum(up, down), 0.0, 1.0)
        return np.stack([fx_n * share, 0.0 * share, fz_n * share], axis=-1)
    return force


def presses(until_s: float, seed: int = 0, hold_s: tuple = (2.0, 20.0)) -> list:
    """Presses of 1–8 N held ``hold_s`` (2–20 s), 3–10 s apart, from 5 s until ``until_s``: ramps of 0.2 s, every
    fourth brought on and off at a robot's slow 0.2 N/s (up to 3 N, 15 s each way), every third with a
    shear of a third of its normal force."""
    rng = np.random.default_rng(seed)
    out, start = [], 5.0
    while True:
        k = len(out)
        fz = rng.uniform(1.0, 3.0 if k % 4 == 3 else 8.0)
        ramp, hold = (fz / 0.2 if k % 4 == 3 else 0.2), rng.uniform(*hold_s)
        if start + 2 * ramp + hold > until_s:
            return out
        out.append(press(start, ramp, hold, fz, fz / 3 if k % 3 == 2 else 0.0))
        start += 2 * ramp + hold + rng.uniform(3.0, 10.0)


def forces(t: np.ndarray, loads) -> np.ndarray:
    total = np.zeros((len(t), 3))
    for load in loads:
        total += load(t)
    return total


def _odd(f: np.ndarray, coefficients) -> np.ndarray:
    a, b = coefficients
    return a * f + b * f * np.abs(f)


def relative(f: np.ndarray, t: np.ndarray, creep: bool) -> np.ndarray:
    """(N, 4) electrode ΔC/C0 for forces (N, 3) at times t (N,) from rest."""
    normal = _odd(np.maximum(f[:, 2], 0.0), NORMAL)
    above = f[:, 2] > 1.0
    cycles = np.cumsum(np.concatenate([[False], above[:-1] & ~above[1:]]))  # presses let go before each frame
    sensitivity = 1.0 - 0.22 * -np.expm1(-cycles / 1000.0)
    r = sensitivity[:, None] * (normal[:, None] + _odd(f[:, :2], SHEAR) @ SIDES)
    if creep:  # dc/dt = (share·n − c)/τ, stepped exactly per frame
        decay = np.exp(-np.diff(t, prepend=t[0]) / CREEP_TAU_S)
        c, out = 0.0, np.empty(len(t))
        for k, (target, keep) in enumerate(zip((CREEP_SHARE * sensitivity * normal).tolist(), decay.tolist())):
            c = target + (c - target) * keep
            out[k] = c
        r = r + out[:, None]
    return r


def session(seconds: float, loads, drift=lambda t: 0.0 * t, creep: bool = False, seed: int = 1, quads: int = 1):
    """(t (N,), true forces (N, 3), counts (quads, N, 4) aF): every quad under the same loads and drift."""
    t = np.arange(1, int(seconds * RATE_HZ) + 1) / RATE_HZ
    f = forces(t, loads)
    pf = C0_PF * (1.0 + drift(t))[:, None] * (1.0 + relative(f, t, creep))
    rng = np.random.default_rng(seed)
    counts = np.round(1e6 * (pf + rng.normal(0.0, NOISE_RELATIVE, (quads,) + pf.shape) * C0_PF)).astype("<u4")
    return t, f, counts


def feed(t: np.ndarray, counts: np.ndarray, read_scans: int = READ_SCANS) -> dict:
    """{sensor: (forces (N, 3), σ (N, 3), flags list)} of every scan, through a Pipeline at the full level,
    ``read_scans`` scans a read."""
    pipeline = Pipeline(Reconstructor(level="full"), map_clock=False)
    quads = len(counts)
    info = {"board": "quad-drift", "sensors": [{"id": q, "kind": "quad"} for q in range(quads)]}
    frames = {q: [] for q in range(quads)}
    for frame in pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(info)), 0.0):
        frames[frame.sensor.id].append(frame)
    t_us = np.round(t * 1e6).astype(np.int64).tolist()
    for start in range(0, len(t), read_scans):
        data = b"".join(encode_frame(FrameType.QUAD, q, k, t_us[k], counts[q, k].tobytes())
                        for k in range(start, min(start + read_scans, len(t))) for q in range(quads))
        for frame in pipeline.feed(data, t[start]):
            frames[frame.sensor.id].append(frame)
    return {q: (np.array([f.forces_N for f in fs], dtype=float),
                np.array([np.full(3, np.nan) if f.sigma_N is None else f.sigma_N for f in fs], dtype=float),
                [f.flags for f in fs]) for q, fs in frames.items()}

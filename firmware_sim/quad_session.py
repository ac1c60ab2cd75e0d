"""A reference-load calibration session of a quad sensor that is not paper 001's.

A force/torque instrument logs (Fx, Fy, Fz) on its own clock while a probe
loads the sensor: normal presses 0 → ~15 N → 0, then shear along +X, −X,
+Y, −Y under a normal preload (shear needs grip), then shear under a
heavier preload (where paper 001 §5.3's coupling shows: normal load
reduces the shear response), each with unloaded pauses of jittered
length. The sensor has its own curves (``user_quad_model``: slopes ±15 %
off fits 34/35, a coupling) and its own C0. The CSV is
``t_s,fx_N,fy_N,fz_N`` with ``t_ref = offset_s + t_board·(1 + ppm·1e-6)``,
noise and a few junk lines, like the grid's (calibration_session.py).

Imports only the simulator and service.physics, like the rest of firmware_sim.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.physics.paper_data import FIT34, FIT35
from service.physics.quad_model import QuadModel

from .board import BoardConfig, capture
from .calibration_session import GARBAGE, QUIET_S
from .sensors import SimQuad


def user_quad_model(seed: int = 1, spread: float = 0.15, coupling: float = 1.0) -> QuadModel:
    """Fits 34/35 with c1 and a scaled by U(1 ± spread), the curvatures with them, and a normal–shear coupling."""
    rng = np.random.default_rng(seed)
    k_n, k_s = rng.uniform(1 - spread, 1 + spread, 2)
    return QuadModel((FIT34[0] * k_n, FIT34[1] * k_n, 0.0), FIT35[1] * k_s, -FIT35[0] * k_s, coupling=coupling)


@dataclass(frozen=True)
class Load:
    """A raised-cosine load: peak (Fx, Fy, Fz) N reached at start + ramp, back to 0 at start + 2 ramp;
    ``preload_N`` of normal force held around it (ramped in and out over ``ramp_s``)."""

    start_s: float
    peak: tuple[float, float, float]
    ramp_s: float = 1.2
    preload_N: float = 0.0

    @property
    def end_s(self) -> float:
        return self.start_s + 2.0 * self.ramp_s + (2.0 * self.ramp_s if self.preload_N else 0.0)


def _bump(t: np.ndarray, start: float, ramp: float) -> np.ndarray:
    inside = (t >= start) & (t < start + 2 * ramp)
    return np.where(inside, 0.5 * (1 - np.cos(np.pi * (t - start) / ramp)), 0.0)


def forces(loads: list[Load], t: np.ndarray) -> np.ndarray:
    """(k, 3) applied forces at board times ``t`` (k,)."""
    out = np.zeros((len(t), 3))
    for load in loads:
        if load.preload_N:  # preload up, hold, down; the shear bump in the middle
            hold = (t >= load.start_s + load.ramp_s) & (t < load.end_s - load.ramp_s)
            up = _bump(t, load.start_s, load.ramp_s) * (t < load.start_s + load.ramp_s)
            down = _bump(t, load.end_s - 2 * load.ramp_s, load.ramp_s) * (t >= load.end_s - load.ramp_s)
            out[:, 2] += load.preload_N * (hold + up + down)
            out += np.outer(_bump(t, load.start_s + load.ramp_s, load.ramp_s), load.peak)
        else:
            out += np.outer(_bump(t, load.start_s, load.ramp_s), load.peak)
    return out


def quad_schedule(seed: int = 0, normal_peak_N: float = 15.0, shear_peak_N: float = 4.0, preloads=(3.0, 9.0),
                  repeats: int = 2) -> list[Load]:
    """Normal presses, then ±X and ±Y shear under each preload, ``repeats`` times each, jittered pauses."""
    rng = np.random.default_rng(seed)
    plan = [(0.0, 0.0, normal_peak_N, 0.0)] * (2 * repeats)
    for preload in preloads:
        for direction in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            plan += [(direction[0] * shear_peak_N, direction[1] * shear_peak_N, 0.0, preload)] * repeats
    loads, t = [], QUIET_S
    for fx, fy, fz, preload in plan:
        scale = rng.uniform(0.9, 1.05)
        loads.append(Load(t, (fx * scale, fy * scale, fz * scale), float(rng.uniform(0.9, 1.3)), preload))
        t = loads[-1].end_s + 0.6 + rng.uniform(0.0, 0.5)
    return loads


class QuadScene:
    """``BoardConfig.scene`` playing ``loads`` on the quad ``sensor_id``."""

    def __init__(self, loads: list[Load], sensor_id: int = 0) -> None:
        self.loads = sorted(loads, key=lambda load: load.start_s)
        self.sensor_id = sensor_id
        self._starts = np.array([load.start_s for load in self.loads])

    @property
    def end_s(self) -> float:
        return max(load.end_s for load in self.loads) + QUIET_S

    def __call__(self, sensor, t: float) -> np.ndarray:
        if sensor.id != self.sensor_id:
            return np.zeros(sensor.channels if sensor.kind == "grid" else 3)
        i = int(np.searchsorted(self._starts, t, side="right")) - 1  # loads do not overlap: only this one acts
        if i < 0 or t >= self.loads[i].end_s:
            return np.zeros(3)
        return forces(self.loads[i:i + 1], np.array([t]))[0]


@dataclass
class QuadSession:
    raw: bytes
    reference_csv: str
    model: QuadModel
    c0_pF: tuple
    loads: list[Load]
    truth_t_us: np.ndarray
    truth_N: np.ndarray  # (frames, 3)


def quad_session(model: QuadModel | None = None, loads: list[Load] | None = None, rate_hz: float = 500.0,
                 seed: int = 0, offset_s: float = 7.5, rate_ppm: float = -120.0, ref_rate_hz: float = 200.0,
                 noise_N: float = 0.01, c0_pF=(2.31, 2.12, 2.27, 2.19), **board) -> QuadSession:
    """The board's bytes, the F/T reference CSV and the truth (defaults: user_quad_model(seed + 1))."""
    model = model or user_quad_model(seed + 1)
    loads = quad_schedule(seed) if loads is None else loads
    scene = QuadScene(loads)
    sensor = SimQuad(0, c0_pF=tuple(c0_pF), model=model)
    config = BoardConfig(sensors=[sensor], rate_hz=rate_hz, scene=scene, seed=seed,
                         name=board.pop("name", "tactile-sim-quad"), **board)
    raw, sim = capture(config, scene.end_s, keep_truth=True)
    rng = np.random.default_rng(seed + 100)
    scale = 1.0 + rate_ppm * 1e-6
    t_ref = np.arange(offset_s + 0.4 * scale, offset_s + (scene.end_s - 0.3) * scale, 1.0 / ref_rate_hz)
    f = forces(loads, (t_ref - offset_s) / scale) + rng.normal(0.0, noise_N, (t_ref.size, 3))
    lines = [f"{t:.6f},{x:.5f},{y:.5f},{z:.5f}" for t, (x, y, z) in zip(t_ref, f)]
    for k, where in enumerate(sorted(rng.integers(1, len(lines), 3))[::-1]):
        lines.insert(int(where), GARBAGE[k % len(GARBAGE)])
    truth_t = np.array([t.t_us for t in sim.truth])
    truth = np.stack([t.values for t in sim.truth])
    return QuadSession(raw, "t_s,fx_N,fy_N,fz_N\n" + "\n".join(lines) + "\n", model, tuple(c0_pF), loads,
                       truth_t, truth)


def validation_loads(seed: int = 9) -> list[Load]:
    """A separate sequence: combined loads at random peaks and preloads."""
    rng = np.random.default_rng(seed)
    loads, t = [], QUIET_S
    for _ in range(10):
        angle = rng.uniform(0, 2 * math.pi)
        shear = rng.uniform(1.0, 3.5)
        loads.append(Load(t, (shear * math.cos(angle), shear * math.sin(angle), 0.0), float(rng.uniform(0.8, 1.2)),
                          float(rng.uniform(2.0, 10.0))))
        t = loads[-1].end_s + 0.6
    return loads

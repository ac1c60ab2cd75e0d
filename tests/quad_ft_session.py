"""A quad's calibration session with a force/torque reference, as arrays,
from paper 001's quad model written out here (not the simulator's):
electrode ij (sx, sy = ±1 on the +X/+Y side)

    ΔC/C0 = n(Fz) + (sx·t(Fx) + sy·t(Fy))·(1 − c·n(Fz)),
    n(F) = c1·F + c2·F²,   t(F) = sign(F)·(a|F| − b·F²),

with converter noise of 1e-4 of C0 per electrode, C0 optionally drifting
linearly over the session (temperature), and the reference's forces at the
board's frames (the clocks aligned) with 0.01 N of noise per axis, in N or
another unit. The loads: two normal presses to 15 N, then shear 4 N along
±X, ±Y twice each under every preload (ramped in and out), 0.6–1.1 s apart."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.calibration.calibrate_quad import fit_document
from service.calibration.quad_fit import QuadFit, fit_quad
from service.readings import SensorInfo
from service.reconstruct.calibration_upload import processor_for
from service.reconstruct.sensor_calibration import from_document

RATE_HZ = 200.0
C0_PF = np.array([2.31, 2.12, 2.27, 2.19])
NORMAL = (0.0400, -0.0010)  # c1, c2: 17 % steeper than fit 34
SHEAR = (0.0090, 0.00045)  # a, b: 17 % steeper than fit 35
SIDES = np.array([[-1.0, 1.0, -1.0, 1.0], [-1.0, -1.0, 1.0, 1.0]])  # C11, C12, C21, C22 on the ±X, ±Y sides
NOISE_RELATIVE = 1e-4
REFERENCE_NOISE_N = 0.01
QUAD = SensorInfo(0, "quad", 2, 2)
BOTH_WAYS = ((1, 0), (-1, 0), (0, 1), (0, -1))


@dataclass
class Session:
    t_s: np.ndarray  # (N,) board seconds
    capacitance_pF: np.ndarray  # (N, 4)
    reference: np.ndarray  # (N, 3) the reference's forces at the frames, in its unit
    truth_N: np.ndarray  # (N, 3)

    def fit(self) -> QuadFit:
        return fit_quad(self.t_s, self.capacitance_pF, self.reference, np.zeros(len(self.t_s), bool), 1.0)


def normal_response(fz):
    return NORMAL[0] * fz + NORMAL[1] * fz * fz


def odd(f, a, b):
    return np.sign(f) * (a * np.abs(f) - b * f * f)


def _bump(t, start, ramp):
    """A raised cosine 0 → 1 → 0 over [start, start + 2 ramp)."""
    inside = (t >= start) & (t < start + 2 * ramp)
    return np.where(inside, 0.5 * (1 - np.cos(np.pi * (t - start) / ramp)), 0.0)


def schedule(preloads, seed, shear_N=4.0, normal_N=15.0, directions=BOTH_WAYS):
    """(loads: (start, ramp, (Fx, Fy, Fz) peak, preload), end s)."""
    rng = np.random.default_rng(seed)
    plan = [((0.0, 0.0, normal_N), 0.0)] * 2
    for preload in preloads:
        for fx, fy in directions:
            plan += [((fx * shear_N, fy * shear_N, 0.0), preload)] * 2
    loads, t = [], 1.5
    for peak, preload in plan:
        ramp = float(rng.uniform(0.9, 1.3))
        loads.append((t, ramp, np.array(peak) * rng.uniform(0.9, 1.05), preload))
        t += (4 if preload else 2) * ramp + rng.uniform(0.6, 1.1)
    return loads, t + 1.5


def forces(t, loads):
    """(N, 3) N at times t (N,)."""
    out = np.zeros((t.size, 3))
    for start, ramp, peak, preload in loads:
        if preload:  # preload up over a ramp, held while the shear bump passes, down over a ramp
            held = np.clip(np.minimum(t - start, start + 4 * ramp - t) / ramp, 0.0, 1.0)
            out[:, 2] += preload * 0.5 * (1 - np.cos(np.pi * held))
            out += np.outer(_bump(t, start + ramp, ramp), peak)
        else:
            out += np.outer(_bump(t, start, ramp), peak)
    return out


def capacitance(f, coupling, rng, c0=C0_PF):
    """Electrode capacitances (N, 4) pF under forces (N, 3), C0 (4,) or (N, 4)."""
    n = normal_response(f[:, 2])
    shear = odd(f[:, 0], *SHEAR)[:, None] * SIDES[0] + odd(f[:, 1], *SHEAR)[:, None] * SIDES[1]
    relative = n[:, None] + shear * (1.0 - coupling * n)[:, None]
    return c0 * (1.0 + relative + rng.normal(0.0, NOISE_RELATIVE, relative.shape))


def session(preloads=(3.0, 9.0), coupling=1.0, seed=0, drift=0.0, unit_N=1.0, **loads) -> Session:
    """A calibration session: C0 moves by ``drift`` (relative) linearly over
    it; the reference logs force / ``unit_N`` (4.448 for lbf)."""
    plan, end = schedule(preloads, seed, **loads)
    t = np.arange(0.0, end, 1.0 / RATE_HZ)
    f = forces(t, plan)
    rng = np.random.default_rng(seed + 100)
    c0 = C0_PF * (1.0 + drift * t / end)[:, None]
    return Session(t, capacitance(f, coupling, rng, c0), f / unit_N + rng.normal(0.0, REFERENCE_NOISE_N, f.shape), f)


def validation(coupling, seed=9):
    """(true forces (N, 3), capacitance (N, 4)) of combined loads: shear 1–3.5 N at any angle under 2–10 N."""
    rng = np.random.default_rng(seed)
    plan, t0 = [], 1.0
    for _ in range(12):
        angle, shear = rng.uniform(0, 2 * np.pi), rng.uniform(1.0, 3.5)
        ramp = float(rng.uniform(0.8, 1.2))
        plan.append((t0, ramp, np.array([shear * np.cos(angle), shear * np.sin(angle), 0.0]), rng.uniform(2.0, 10.0)))
        t0 += 4 * ramp + 0.6
    t = np.arange(0.0, t0 + 1.0, 1.0 / RATE_HZ)
    f = forces(t, plan)
    return f, capacitance(f, coupling, np.random.default_rng(seed + 1))


def read_back(fit: QuadFit, coupling: float):
    """(true forces, forces, σ) (k, 3) of the validation sequence through the
    stored calibration's fields, at the full level: loaded frames with σ."""
    document = {**fit_document(fit), "id": "test-quad", "kind": "quad"}
    processor = processor_for(QUAD, "full", "flat", from_document(document, QUAD))
    truth, measured = validation(coupling)
    noise = processor.noise(C0_PF, C0_PF * NOISE_RELATIVE)
    got, _ = processor.process(measured, C0_PF, noise)
    sigma = processor.sigma(got, noise)
    loaded = (np.linalg.norm(truth, axis=1) > 0.1) & np.isfinite(sigma).all(axis=1)
    return truth[loaded], got[loaded], sigma[loaded]

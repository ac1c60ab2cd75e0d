"""A quad under presses and a temperature drift: Fz's error, σ's coverage, flags.

    python scripts/quaddrift.py [free ramp05 ramp1 sine creep light]

Each case through the Pipeline at 1 kHz from tests/quad_session.py (paper
001's quad model, noise 1e-4 ΔC/C0): presses of 1–8 N held 2–20 s (every
fourth at 0.2 N/s, every third with shear) under no drift (free, 240 s), a
0.5 or 1 %/min ramp of C0 (240 s), a ±1 % sine of 5 min (300 s); a 3 N
(creep) or 0.2 N (light) press held 60 s, creeping +4 % of its ΔC/C0 under
a 20 s time constant, under no drift (120 s). Prints Fz's RMS error against
the truth, on all frames and on the unloaded ones, the share of frames
within 1σ and 2σ, frames flagged drift_suspect, unloaded frames flagged
normal_out_of_range, and for the held presses Fz after the release.
"""
from __future__ import annotations

import sys

import numpy as np

from tests import quad_session as qs


def case(name: str):
    seconds, drift, creep = 240.0, (lambda t: 0.0 * t), False
    loads = qs.presses(seconds - 10, seed=3)
    if name in ("ramp05", "ramp1"):
        rate = (0.005 if name == "ramp05" else 0.01) / 60
        drift = lambda t: rate * t  # noqa: E731
    elif name == "sine":
        seconds = 300.0
        loads, drift = qs.presses(seconds - 10, seed=3), (lambda t: 0.01 * np.sin(2 * np.pi * t / 300.0))
    elif name in ("creep", "light"):
        seconds, creep = 120.0, True
        loads = [qs.press(10.0, 0.3, 60.0, 3.0 if name == "creep" else 0.2)]
    return seconds, loads, drift, creep


def main(names: list[str]) -> None:
    for name in names or ["free", "ramp05", "ramp1", "sine", "creep", "light"]:
        seconds, loads, drift, creep = case(name)
        t, f, counts = qs.session(seconds, loads, drift, creep=creep)
        forces, sigma, flags = qs.feed(t, counts)[0]
        fz, sz = forces[:, 2], sigma[:, 2]
        live = np.isfinite(fz) & (t > 1.0)
        error = fz[live] - f[live, 2]
        z = np.abs(error / sz[live])
        unloaded = live & (f[:, 2] == 0)
        below = sum("normal_out_of_range" in flags[i] for i in np.flatnonzero(unloaded))
        print(f"{name}: Fz error RMS {np.sqrt(np.mean(error ** 2)):.4f} N (unloaded {np.sqrt(np.mean(fz[unloaded] ** 2)):.4f}),"
              f" within 1σ {np.mean(z <= 1):.3f}, 2σ {np.mean(z <= 2):.3f}; drift_suspect"
              f" {sum('drift_suspect' in fl for fl in flags)} of {len(flags)} frames; unloaded normal_out_of_range {below}")
        if creep:
            after = t > 72.0
            print(f"  after the release: Fz mean {np.mean(fz[after]):+.4f} N, min {np.min(fz[after]):+.4f} N,"
                  f" mean σ {np.mean(sz[after]):.4f} N")


if __name__ == "__main__":
    main(sys.argv[1:])

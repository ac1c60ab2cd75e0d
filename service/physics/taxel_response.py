"""Per-taxel force ↔ ΔC/C0 from a model table and the taxel's own calibration.

What a per-taxel gain scales. Table 1 of the 8x8 paper shows C0 varying
±10 % across the array while the sensitivity varies ±1 %. C0 = εr ε0 A/d0
carries the electrode area A and the PDMS thickness d0; but the PDMS is
confined, so its compression under a pressure q is q·d0/M (M the confined
modulus) and ΔC/C0 ≈ compression/d0 = q/M: neither A nor d0 enters the
relative change. Table 1 agrees (C0 and sensitivity are uncorrelated). So C0
is only the normalisation, and we take it from the taxel's own tared
baseline; what differs from taxel to taxel in ΔC/C0(F) is the mechanical
compliance (PDMS modulus, bump bonding), which scales the *force*: a taxel
with compliance gain κ responds as r(F) = R(κ F), R the model table. The
gap nonlinearity 1/(d0 − w) stays where the physics puts it. κ is solved so
that the least-squares slope of R(κ F) over 0–10 N equals the taxel's
measured sensitivity, the way the paper measured it.

The inverse F = R⁻¹(r)/κ is monotone interpolation (PCHIP resampled to a
dense grid). Above the table's top (gap closure) the force is held at the
top and flagged saturated; a compressive sensor cannot pull, so a negative
ΔC/C0 gives zero force, flagged out of range when it exceeds 5× the noise.

An uploaded calibration (per-taxel sensitivity, %/N) must be finite and
within SENSITIVITY_RANGE_PCT_PER_N = (0.1, 10) %/N (table 1: 1.22–1.27), and
the response built from it must pass ``check``: the forward model on a dense
grid over [0, max_force_N] finite and strictly increasing per taxel, and the
inverse giving those forces back within ROUND_TRIP_TOLERANCE_N = 0.002 N
(a quarter of the noise floor; the PCHIP inverse of the linear-interpolated
table differs from it by < 0.0004 N).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from .mountings import MOUNTINGS
from .paper_data import GridCalibration

DENSE_POINTS = 4096
OUT_OF_RANGE_SIGMAS = 5.0  # 3σ would flag ~1 taxel-frame in 700 on noise alone
SENSITIVITY_FORCES_N = np.arange(0.0, 11.0)
SENSITIVITY_RANGE_PCT_PER_N = (0.1, 10.0)  # plausible per-taxel sensitivity of an upload
ROUND_TRIP_TOLERANCE_N = 0.002
CHECK_POINTS = 1025


def _ls_slope(forces: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least-squares slope along the last axis of ``values`` against ``forces``."""
    f = forces - forces.mean()
    return ((values - values.mean(axis=-1, keepdims=True)) * f).sum(axis=-1) / (f * f).sum()


def _origin_slope(forces: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least-squares slope through the origin along the last axis."""
    return (values * forces).sum(axis=-1) / (forces * forces).sum()


SENSITIVITY_READINGS = ("intercept", "origin")


@dataclass(frozen=True)
class TaxelResponse:
    """ΔC/C0 ↔ force for ``n`` taxels sharing one model curve.

    ``gain`` has shape (n,); the curve is tabulated on ``force_N`` (m,)."""

    force_N: np.ndarray
    relative: np.ndarray
    gain: np.ndarray
    dense: tuple[np.ndarray, np.ndarray] | None = field(default=None, compare=False, repr=False)  # dense_inverse's

    @classmethod
    def from_table(cls, force_N: np.ndarray, relative: np.ndarray, sensitivity_per_N: np.ndarray,
                   dense: tuple[np.ndarray, np.ndarray] | None = None, reading: str = "intercept") -> TaxelResponse:
        """Gains whose curves have ``sensitivity_per_N`` (n,) as their slope
        over 0–10 N in ``reading``: "intercept" (least squares with an
        intercept, table 1's) or "origin" (through the origin, ~2.5 %
        lower on this curve, so the same number needs a higher gain)."""
        if reading not in SENSITIVITY_READINGS:
            raise ValueError(f"sensitivity reading {reading!r}: one of {', '.join(SENSITIVITY_READINGS)}")
        slope = _ls_slope if reading == "intercept" else _origin_slope
        force_N, relative = np.asarray(force_N, float), np.asarray(relative, float)
        if np.any(np.diff(relative) <= 0) or np.any(np.diff(force_N) <= 0):
            raise ValueError("a taxel table must be strictly increasing in force and ΔC/C0")
        sensitivity = np.asarray(sensitivity_per_N, float)
        if np.any(sensitivity <= 0):
            raise ValueError(f"sensitivities must be positive, got min {sensitivity.min()}")
        model_slope = slope(SENSITIVITY_FORCES_N, np.interp(SENSITIVITY_FORCES_N, force_N, relative))
        gain = sensitivity / model_slope
        for _ in range(20):  # fixed point: the curve is nearly linear, so this converges in a few steps
            scaled = np.interp(np.outer(gain, SENSITIVITY_FORCES_N), force_N, relative)
            gain = gain * sensitivity / slope(SENSITIVITY_FORCES_N, scaled)
        return cls(force_N, relative, gain, dense)

    def check(self) -> None:
        """ValueError unless every taxel's forward model is finite and
        strictly increasing over [0, max_force_N] and the inverse gives the
        forces back within ROUND_TRIP_TOLERANCE_N."""
        with np.errstate(all="ignore"):
            limit = self.max_force_N
            force = np.linspace(0.0, 1.0, CHECK_POINTS)[:, None] * limit[None, :]
            relative = self.forward(force)
            monotone = np.isfinite(limit) & np.isfinite(relative).all(axis=0) & np.all(np.diff(relative, axis=0) > 0, axis=0)
            back, _, _ = self.inverse(relative)
            error = np.abs(back - force)
            exact = np.all(error <= ROUND_TRIP_TOLERANCE_N, axis=0)
        if not monotone.all():
            bad = int(np.flatnonzero(~monotone)[0])
            raise ValueError(f"taxel {bad}: the response is not finite and strictly increasing over its range")
        if not exact.all():
            bad = int(np.flatnonzero(~exact)[0])
            raise ValueError(f"taxel {bad}: the inverse does not give the forces back "
                             f"(error {np.nanmax(error[:, bad], initial=np.inf):.3g} N)")

    @property
    def top(self) -> float:
        return float(self.relative[-1])

    @property
    def max_force_N(self) -> np.ndarray:
        """Largest force each taxel's table covers, shape (n,)."""
        return self.force_N[-1] / self.gain

    def forward(self, forces_N: np.ndarray) -> np.ndarray:
        """ΔC/C0 for forces of shape (..., n); held at the top past the table."""
        return np.interp(np.asarray(forces_N) * self.gain, self.force_N, self.relative)

    def inverse_slope(self, relative: np.ndarray, gain: np.ndarray | None = None) -> np.ndarray:
        """dF/d(ΔC/C0) at ``relative`` (..., n): how a ΔC/C0 error becomes a
        force error (the curve's end slope outside the table)."""
        dense_r, _ = self._dense
        return np.interp(relative, dense_r, self._dense_slope) / (self.gain if gain is None else gain)

    def shares_curve(self, other: TaxelResponse) -> bool:
        """Whether both were built on the same model table (gains may differ)."""
        return self.force_N is other.force_N and self.relative is other.relative

    def inverse(self, relative: np.ndarray, noise: np.ndarray | float = 0.0,
                gain: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Forces (..., n) from ΔC/C0 (..., n).

        Returns (force, saturated, out_of_range): saturated where ΔC/C0 is
        above the table (force held at the table's top), out_of_range where
        it is below −5·noise (force 0). NaN stays NaN. ``gain`` (..., n)
        replaces this response's own, for rows of several sensors that share
        the curve.
        """
        dense_r, dense_f = self._dense
        force = np.interp(relative, dense_r, dense_f) / (self.gain if gain is None else gain)
        saturated = relative > self.top
        out_of_range = relative < -OUT_OF_RANGE_SIGMAS * np.asarray(noise)
        return force, saturated, out_of_range

    @property
    def _dense(self) -> tuple[np.ndarray, np.ndarray]:
        cached = self.__dict__.get("_dense_cache")
        if cached is None:
            cached = self.dense if self.dense is not None else dense_inverse(self.force_N, self.relative)
            object.__setattr__(self, "_dense_cache", cached)
            object.__setattr__(self, "_dense_slope", np.gradient(cached[1], cached[0]))
        return cached


def dense_inverse(force_N: np.ndarray, relative: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(ΔC/C0, force) at DENSE_POINTS equally spaced ΔC/C0 over [0, top]:
    the table's PCHIP inverse, sampled for np.interp (shipped with each
    table, tables.ForceTable.dense)."""
    from scipy.interpolate import PchipInterpolator  # building tables, or a table without its dense inverse

    dense_r = np.linspace(0.0, float(relative[-1]), DENSE_POINTS)
    return dense_r, PchipInterpolator(relative, force_N)(dense_r)


@lru_cache(maxsize=8)
def _table(shape: str):
    from .table_files import TableSpec, load

    return load(TableSpec(shape))


def model_table(mounting: str = "flat"):
    """The mounting's model table (physics/tables.py): force_N and relative_change."""
    if mounting not in MOUNTINGS:
        raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
    return _table(MOUNTINGS[mounting])


def table_top(mounting: str = "flat") -> float:
    """ΔC/C0 at the end of the mounting's model table (where the gap would
    close by half): the largest change the model explains."""
    if mounting not in MOUNTINGS:
        raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
    return float(_table(MOUNTINGS[mounting]).relative_change[-1])


def taxel_response(calibration: GridCalibration, mounting: str = "flat") -> TaxelResponse:
    """The per-taxel response of a grid from the shipped model table."""
    if mounting not in MOUNTINGS:
        raise ValueError(f"unknown mounting {mounting!r}; known: {', '.join(MOUNTINGS)}")
    table = _table(MOUNTINGS[mounting])
    return TaxelResponse.from_table(table.force_N, table.relative_change, calibration.sensitivity_per_N, table.dense)

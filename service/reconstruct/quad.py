"""Quad reconstruction: (Fx, Fy, Fz) from four electrodes per frame or batch.

The model and its closed-form inverse are physics (physics/quad_model.py);
here each frame's flags come on top: out of the calibrated range, and an
electrode fault when the redundant combination R (which the model says is
0) stands beyond its noise.

An electrode outside its plausible range (level0.py: ΔC/C0 against its own
baseline outside [−0.5, (1 + r_top)·1.5 − 1], r_top = QuadModel.top_relative
= 0.360 with the paper's fits, so an upper bound of 1.04) leaves the frame without forces (all three
null: every axis combines all four electrodes), flagged ``out_of_range``, at
every level — the same rule and flag as a grid taxel's; so is a frame with an
electrode the tare gave no zero (no plausible reading in its window). ``electrode_fault``
keeps its meaning: plausible electrodes that disagree with the model (the
redundant combination R); it and the range flags are not raised on a frame
without forces. A frame with a stale electrode (stuck.py: its converter
repeated one count STUCK_FRAMES frames running on a board that shows noise)
is also without forces, flagged ``stale``, not its last forces held.

``normal_out_of_range`` marks Z beyond the curve's usable top (Fz held
there) and, as a grid taxel's ``out_of_range``, Z more than
OUT_OF_RANGE_SIGMAS noise σ below its zero (Fz 0): no compression reads
so, a tare made under a load since removed does.
"""
from __future__ import annotations

from dataclasses import astuple, dataclass, field

import numpy as np

from ..physics.paper_data import QUAD_NORMAL_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N
from ..physics.quad_model import QuadModel
from ..physics.taxel_response import OUT_OF_RANGE_SIGMAS
from .baseline import NOISE_FLOOR_PF
from .sigma import TARE_FACTOR
from .level0 import bounds, implausible, plausible_relative, quad_axes, relative_change

QUAD_LEVELS = ("level0", "table", "full")
FAULT_SIGMAS = 8.0
FAULT_RELATIVE = 0.05  # model mismatch allowed in R, as a share of |Z|
# The fatigue compensation is paper 001's one sensor's loss (fatigue.py); another sensor's may differ
# by half of it either way: its σ, so a quad that does not fatigue is not read 25 % high at ±3 %.
FATIGUE_SIGMA_SHARE = 0.5
_LEVEL0_SLOPES = np.array([QUAD_SHEAR_SLOPE_PER_N, QUAD_SHEAR_SLOPE_PER_N, QUAD_NORMAL_SLOPE_PER_N])


@dataclass
class QuadProcessor:
    level: str
    model: QuadModel = field(default_factory=QuadModel)
    relative_se: tuple[float, float] = (0.0, 0.0)  # σ/value of the normal and shear slopes (sigma.py)
    model_sigma_N: tuple[float, float, float] = (0.0, 0.0, 0.0)  # Fx, Fy, Fz: what the calibration's fit leaves unexplained
    electrode_gain_se: float = 0.0  # σ/value of each electrode's gain about the others' (sensor_calibration.py)
    # (σ of a coupling c left out of the model, the normal ΔC/C0 n_ref its shear slope was measured under):
    # shear read under another normal load is off by c·(n(Fz) − n_ref) of itself (sensor_calibration.py)
    coupling_sigma: tuple[float, float] | None = None
    _noise_for: tuple | None = None
    _noisy_for: tuple | None = field(default=None, repr=False, compare=False)
    # (last reading (4,) pF, its electrodes' run lengths (4,)) that the next frames continue (stuck.py).
    # Written in place only: a QuadPlan's stacked arrays hold them as rows (quad_batch.py).
    runs: tuple | None = field(default=None, repr=False, compare=False)
    # (the zero it is tracked on, its DriftTracker): the common-mode drift (quad_drift.py), the full level's.
    drift: tuple | None = field(default=None, repr=False, compare=False)
    # (the zero (4,) pF kept at a loaded tare, its σ (4,) ΔC/C0: loaded_tare.kept_zero_sigma): quad_batch.zero_sigmas
    kept_zero: tuple | None = field(default=None, repr=False, compare=False)
    # Processors with equal keys give the same result on the same input, so
    # their sensors' frames can go through one call.
    batch_key: tuple = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.level not in QUAD_LEVELS:
            raise ValueError(f"unknown quad level {self.level!r}; known: {', '.join(QUAD_LEVELS)}")
        self.batch_key = (self.level, astuple(self.model), self.relative_se, self.model_sigma_N, self.electrode_gain_se,
                          self.coupling_sigma)
        self.plausible = plausible_relative(self.model.top_relative)
        self._bounds = bounds(*self.plausible)
        # sigma's per-axis constants, made once: at 1 kHz a call's small arrays are its cost
        self._se = np.array([self.relative_se[1], self.relative_se[1], self.relative_se[0]])
        self._model_variance = np.square(self.model_sigma_N) if any(self.model_sigma_N) else None
        self._held_at = np.array([self.model.shear_usable_N, self.model.shear_usable_N, self.model.normal_usable_N])
        # mismatch's: each axis's curve r = F·(slope − bend·|F|), and σ_g²/4 on X and Y only
        if self.level == "level0":
            self._curves = (_LEVEL0_SLOPES, np.zeros(3))
        else:
            model = self.model
            c2, c1, _ = model.normal_fit
            self._curves = (np.array([model.shear_a, model.shear_a, c1]), np.array([model.shear_b, model.shear_b, -c2]))
        self._mismatch = 0.25 * self.electrode_gain_se ** 2 * np.array([1.0, 1.0, 0.0]) if self.electrode_gain_se else None

    def noise(self, baseline: np.ndarray, baseline_std: np.ndarray) -> float:
        """Noise of the combinations' ΔC/C0 from the tare spread (once per tare)."""
        if self._noise_for is None or self._noise_for[0] is not baseline_std:
            self._noise_for = (baseline_std, float(np.sqrt(np.sum((np.fmax(baseline_std, NOISE_FLOOR_PF) / baseline) ** 2)) / 4.0))
        return self._noise_for[1]

    def noisy(self, baseline_std: np.ndarray) -> bool:
        """Whether the converter shows noise at all (else equal counts in a
        row are normal and a stuck electrode cannot be told). Once per tare."""
        if self._noisy_for is None or self._noisy_for[0] is not baseline_std:
            self._noisy_for = (baseline_std, bool(np.nanmax(baseline_std, initial=0.0) > NOISE_FLOOR_PF))
        return self._noisy_for[1]

    def runs_before(self) -> tuple[np.ndarray, np.ndarray]:
        """(last reading (4,) pF, run lengths (4,)) the next frames continue;
        a NaN reading and no runs before the first."""
        if self.runs is None:
            self.runs = (np.full(4, np.nan), np.zeros(4, dtype=np.int64))
        return self.runs

    @property
    def stale_runs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(last reading (4,) pF, run lengths (4,)) of the stale-electrode count, None before a frame."""
        return self.runs

    def restore_stale_runs(self, last_pF, runs) -> None:
        """Continue another processor's (or a recording's) stale-electrode count, in new arrays."""
        self.runs = (np.array(last_pF, dtype=float), np.array(runs, dtype=np.int64))

    def sigma(self, forces: np.ndarray, noise: np.ndarray | float,
              sensitivity: np.ndarray | float = 1.0, drift: np.ndarray | None = None) -> np.ndarray:
        """1-σ (N, 3) of forces (N, 3) (sigma.py's terms): each axis's
        combination noise through the curve's slope at that force (Z's with
        ``drift`` (N,) in ΔC/C0, the drift estimate's own σ (quad_drift.py)
        and a zero kept at a loaded tare's (quad_batch.zero_sigmas);
        X's and Y's with the electrodes' gain mismatch, ``mismatch``), the
        force times its slope's relative error, what the calibration's fit
        left unexplained (``model_sigma_N``), a shear force times what a
        coupling left out may change its slope by at this normal load
        (``coupling_sigma``: σ_c·|n(Fz) − n_ref|), and FATIGUE_SIGMA_SHARE of
        the fatigue compensation (``sensitivity``, scalar or (N,), as
        ``process``). Frames without forces, and an axis held at its usable
        end (a lower bound, as a grid's saturated force): NaN."""
        noise = TARE_FACTOR * np.asarray(noise, dtype=float)
        if noise.ndim:
            noise = noise[:, None]
        if self._mismatch is not None:
            noise = np.sqrt(noise * noise + self.mismatch(forces))
        if self.level == "level0":
            reading = noise / _LEVEL0_SLOPES
            if drift is not None:
                reading[:, 2] = np.hypot(reading[:, 2], drift / _LEVEL0_SLOPES[2])
        else:
            model = self.model
            c2, c1, _ = model.normal_fit
            fz = forces[:, 2:3]
            shear_slope = (model.shear_a - 2.0 * model.shear_b * np.abs(forces[:, :2]))
            if model.coupling:
                shear_slope = shear_slope * (1.0 - model.coupling * model.normal_response(fz))
            slopes = np.concatenate([shear_slope, c1 + 2.0 * c2 * fz], axis=1)
            reading = noise / np.maximum(slopes, 1e-9)
            if drift is not None:
                reading[:, 2] = np.hypot(reading[:, 2], drift / np.maximum(slopes[:, 2], 1e-9))
        variance = reading * reading + (forces * self._se) ** 2
        if self.coupling_sigma is not None and self.level != "level0":
            sigma_c, n_ref = self.coupling_sigma
            variance[:, :2] += (forces[:, :2] * (sigma_c * (self.model.normal_response(forces[:, 2:3]) - n_ref))) ** 2
        if self._model_variance is not None:
            variance += self._model_variance
        s = np.asarray(sensitivity, dtype=float)
        if (s != 1.0).any():
            compensated = forces * (FATIGUE_SIGMA_SHARE * (1.0 / (s[:, None] if s.ndim else s) - 1.0))
            variance += compensated * compensated
        sigma = np.sqrt(variance)
        if self.level != "level0":
            held = np.abs(forces) >= self._held_at
            if np.count_nonzero(held):
                sigma[held] = np.nan
        return sigma

    def mismatch(self, forces: np.ndarray) -> np.ndarray:
        """Variance (N, 3) of the combinations X, Y (Z: 0) in ΔC/C0 at
        forces (N, 3) from each electrode's gain off by an independent
        ``electrode_gain_se`` σ_g (relative): X = Σ c_i g_i r_i with
        c_i = ±1/4 varies by Σ c_i² σ_g² r_i² = σ_g² (n² + t_x² + t_y²)/4
        (the cross terms cancel over the four sides), Y alike; n, t the
        level's curves (a tared curve: no offset). Under a normal load
        alone that is σ_g·n/2 in X, and a ±p pattern between the X sides
        reads X = −p·n: 2p/σ_g of it. Z's share is within the slope's
        relative error (``relative_se``)."""
        slope, bend = self._curves
        responses = forces * (slope - bend * np.abs(forces))
        if self.level != "level0" and self.model.coupling:
            responses[:, :2] *= 1.0 - self.model.coupling * responses[:, 2:3]
        return self._mismatch * np.square(responses).sum(axis=1, keepdims=True)

    def process(self, capacitance: np.ndarray, baseline: np.ndarray, noise: np.ndarray | float,
                sensitivity: np.ndarray | float = 1.0, stale: np.ndarray | None = None) -> tuple[np.ndarray, list[list[str]]]:
        """Capacitances (N, 4) pF against baselines (4,) or (N, 4) with the
        combinations' noise (scalar or (N,)) → forces (N, 3) and each frame's
        flags. ``sensitivity`` (scalar or (N,)): what load cycles left of it
        (fatigue.py); ΔC/C0 is divided by it before inversion. ``stale``
        (N, 4) or None: the electrodes found stale (quad_batch.stale_runs)."""
        relative = relative_change(capacitance, baseline)
        if not np.isscalar(sensitivity) or sensitivity != 1.0:
            relative = relative / (np.asarray(sensitivity)[:, None] if np.ndim(sensitivity) else sensitivity)
        bad = implausible(relative, *self._bounds)
        if np.isnan(baseline).any():  # an electrode the tare gave no zero reads nothing usable either
            unzeroed = np.isnan(baseline) & ~np.isnan(capacitance)
            bad = unzeroed if bad is None else bad | unzeroed
        # A frame with an implausible or stale electrode has no force.
        lost = {name: mask.any(axis=-1) for name, mask in (("out_of_range", bad), ("stale", stale)) if mask is not None}
        if lost:
            relative = np.where(np.logical_or.reduce(list(lost.values()))[..., None], np.nan, relative)
        if self.level == "level0":  # level0.quad_forces, on the checked ΔC/C0
            forces = quad_axes(relative) / _LEVEL0_SLOPES
            if not lost:
                return forces, [[] for _ in range(len(capacitance))]
            masks = lost
        else:
            forces, masks = self.model.inverse(relative)
            combinations = masks.pop("combinations")
            masks["electrode_fault"] = np.abs(combinations[..., 3]) > FAULT_SIGMAS * noise + FAULT_RELATIVE * np.abs(combinations[..., 2])
            # Z well below its zero: Fz 0, flagged (module docstring).
            below = combinations[..., 2] < -OUT_OF_RANGE_SIGMAS * noise
            if np.count_nonzero(below):
                masks["normal_out_of_range"] = masks["normal_out_of_range"] | below
            masks.update(lost)
            if not lost and not any(np.count_nonzero(mask) for mask in masks.values()):  # the usual case: no flag on any frame
                return forces, [[] for _ in range(len(forces))]
        names = list(masks)
        table = np.stack([masks[name] for name in names], axis=-1)
        return forces, [[name for name, hit in zip(names, row) if hit] for row in table.tolist()]

"""Grid reconstruction at every fidelity level, per frame or in batches (the
full level's batches of several sensors at once: grid_full.py).

Levels (cheapest first):

``level0``  F = (ΔC/C0)/s, linear, signed (see level0.py).
``table``   per-taxel inversion of the model table (taxel.py): the gap
            nonlinearity, saturation at the table's top, no negative forces.
``full``    table + multiplexer leakage and mechanical crosstalk
            compensation (crosstalk.py) + common-mode drift tracking
            (drift.py) + crosstalk detection.

Every level flags per taxel: no reading, saturated, out of range; ``full``
adds crosstalk-corrected and drift-suspect; a channel stuck at the same
count for STUCK_FRAMES frames is flagged stale. Inputs are capacitances in
pF, shape (n,) per frame or (N, n) per batch, and the sensor's baseline (n,).
The flag bits, and the flags a reading earns before any force, are in
taxel_flags.py; what the full level carries from batch to batch (crosstalk
estimation, checkpoints) in grid_state.py.

``out_of_range`` has two meanings, told apart by the value: force 0 for a
ΔC/C0 below −5σ (a compressive taxel cannot pull; noise or drift), force
null (NaN) for an implausible reading, at every level — one outside

    0.5·C0 ≤ C ≤ (1 + r_top)·1.5·C0

with C0 the taxel's tared baseline and r_top the model table's top ΔC/C0
(0.785, where the gap would close by half): ΔC/C0 outside [−0.5, 1.68].
See level0.py for the reasoning and the figures. At ``full`` an implausible
channel is treated like a missing one before any compensation: the
leakage filter takes its baseline in its place and mechanical unmixing 0,
so it moves none of its neighbours.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..physics.crosstalk_model import PAPER_MECHANICAL_COUPLING, neighbour_matrix
from ..physics.paper_data import GridCalibration
from ..physics.taxel_response import OUT_OF_RANGE_SIGMAS, TaxelResponse, table_top
from . import level0
from .baseline import NOISE_FLOOR_PF
from .crosstalk import Crosstalk, CrosstalkEstimator
from .drift import MIN_REFERENCE_TAXELS, DriftTracker
from .grid_state import GridState
from .levels import GRID_LEVELS
from .sigma import empirical_forces, level0_sigma, table_sigma, zero_sigma_for
from .taxel_flags import OUT_OF_RANGE, SATURATED, STALE, ReadingFlags


@dataclass
class GridResult:
    forces_N: np.ndarray  # (N, n), NaN = no reading
    taxel_flags: np.ndarray  # (N, n) uint8 bit set, see TAXEL_FLAG_NAMES
    sigma_N: np.ndarray | None = None  # (N, n) 1-σ of each force (sigma.py), NaN where the force is or saturated


@dataclass
class GridProcessor(ReadingFlags, GridState):
    """Reconstruction of one grid sensor at one level."""

    level: str
    calibration: GridCalibration
    response: TaxelResponse | None = None
    top_relative: float | None = None  # largest ΔC/C0 the model explains; default: the response's table top
    crosstalk: Crosstalk | None = None
    drift: DriftTracker = field(default_factory=DriftTracker)
    estimator: CrosstalkEstimator | None = None
    gain_relative_se: np.ndarray | None = None  # (n,) σ(κ)/κ of the calibration; None: 0
    model_sigma_N: np.ndarray | None = None  # (n,) what the calibration's curve leaves unexplained; None: 0
    calibrated_to_N: np.ndarray | None = None  # (n,) the largest force the calibration pressed; None: inf (unknown)
    curves: dict = field(default_factory=dict)  # taxel → (relative, force): empirical inverses (sensor_calibration.py)
    _last_raw: np.ndarray | None = None
    _same_count: np.ndarray | None = None
    _noise_for: tuple | None = None
    _noisy_for: tuple | None = None
    _low_flagged_for: tuple | None = None
    _reference_for: tuple | None = None
    _parameters_for: tuple | None = None
    _stacked_for: tuple | None = None
    adopted_events: int = 0
    _frames_seen: int = 0
    _sampled: list = field(default_factory=list)  # (ΔC/C0 rows, noise, baseline) awaiting the estimator
    tare_window: tuple[np.ndarray, np.ndarray] | None = None  # (n,) low, high pF a tare accepts (level0.py)
    _zero_missing_for: tuple | None = None
    _fill_for: tuple | None = None
    _neighbours: np.ndarray | None = None  # (n, n) eight-neighbourhood, for the table level's crosstalk margin
    # (the zero (n,) pF kept at a loaded tare, its σ (n,) ΔC/C0: loaded_tare.kept_zero_sigma), sigma.zero_sigma_for
    kept_zero: tuple | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.level not in GRID_LEVELS:
            raise ValueError(f"unknown grid level {self.level!r}; known: {', '.join(GRID_LEVELS)}")
        if self.level != "level0" and self.response is None:
            raise ValueError(f"level {self.level!r} needs a taxel response table")
        if self.top_relative is None:
            self.top_relative = self.response.top if self.response is not None else table_top()
        self.plausible = level0.plausible_relative(self.top_relative)
        self._bounds = level0.bounds(*self.plausible)
        self._ratio_bounds = level0.bounds(self.plausible[0] + 1.0, self.plausible[1] + 1.0)
        n = self.calibration.rows * self.calibration.cols
        if n < MIN_REFERENCE_TAXELS:  # never a drift reference (drift.py): untracked, as at the table level, not
            self.drift.suspect_after_s = math.inf  # a drift_suspect on every frame that would say nothing,
            self.drift.max_rate_per_s = 0.0  # nor the bound's reach since the tare in σ (it never follows a drift)
        self.gain_relative_se = np.zeros(n) if self.gain_relative_se is None else self.gain_relative_se
        self.model_sigma_N = np.zeros(n) if self.model_sigma_N is None else self.model_sigma_N
        self.calibrated_to_N = np.full(n, np.inf) if self.calibrated_to_N is None else self.calibrated_to_N
        if self.level == "full":
            self.crosstalk = self.crosstalk or Crosstalk(self.calibration.rows, self.calibration.cols)
            self.estimator = self.estimator or CrosstalkEstimator(self.calibration.rows, self.calibration.cols)

    def reset(self) -> None:
        """Forget tracked state (after a tare)."""
        self.drift.reset()

    def noise(self, baseline_pF: np.ndarray, baseline_std_pF: np.ndarray) -> np.ndarray:
        """Noise of ΔC/C0 per taxel from the tare window's spread. The
        converter's noise is one figure for all channels, and 100 frames give
        each channel's spread only to ±7 %, so the median over channels is
        used (in pF), divided by each taxel's baseline."""
        if self._noise_for is None or self._noise_for[0] is not baseline_std_pF:
            pooled = np.nanmedian(baseline_std_pF) if np.isfinite(baseline_std_pF).any() else 0.0
            self._noise_for = (baseline_std_pF, max(pooled, NOISE_FLOOR_PF) / baseline_pF)
        return self._noise_for[1]

    def process(self, capacitance: np.ndarray, baseline: np.ndarray, baseline_std: np.ndarray, t_s: np.ndarray,
                clipped: np.ndarray | None = None) -> GridResult:
        """Frames (N, n) pF at board times (N,) s → forces (N, n) N and
        per-taxel flags (N, n). A single frame is a batch of one.
        ``clipped`` (N, n): channels at the converter's top (level0.clipped):
        saturated, no σ, never stale."""
        if self.level == "full":
            from .grid_full import GridJob, process_full  # grid_full builds on this module

            return process_full([GridJob(self, capacitance, baseline, baseline_std, t_s, clipped)])[0]
        flags, stale = self._reading_flags(capacitance, baseline, baseline_std)
        if stale is not None and clipped is not None:
            flags[clipped & stale] &= ~np.uint8(STALE)
            stale = stale & ~clipped
            if not np.count_nonzero(stale):
                stale = None
        relative = level0.relative_change(capacitance, baseline)
        if self.level == "level0":  # level0.grid_forces, on the checked ΔC/C0
            implausible = level0.implausible(relative, *self._bounds)
            if implausible is not None:  # no force, flagged
                relative = np.where(implausible, np.nan, relative)
                np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=implausible)
            if stale is not None:
                relative = np.where(stale, np.nan, relative)
            # Past the model's top (the gap half closed) a line says nothing: held there, saturated, as the
            # table level does (a true 56 N read 124 N ± 9 N unflagged).
            over = relative > self.top_relative
            if np.count_nonzero(over):
                relative = np.where(over, self.top_relative, relative)
            forces = relative / self.calibration.sensitivity_per_N
            noise = self.noise(baseline, baseline_std)
            sigma = level0_sigma(self, forces, noise, relative, zero_sigma_for(self.kept_zero, baseline))
            held = over if clipped is None else over | (clipped & (forces == forces))
            if np.count_nonzero(held):
                np.bitwise_or(flags, SATURATED, out=flags, where=held)
                sigma[held] = np.nan
            return GridResult(forces, flags, sigma)
        noise = self.noise(baseline, baseline_std)
        forces, saturated, out_of_range = self.response.inverse(relative, noise)
        if self.curves:
            empirical_forces(self.curves, relative, forces, saturated)
        if clipped is not None:  # a lower bound where there is a force: held as read, no σ
            saturated |= clipped & (forces == forces)
        # Taxel by taxel, so an implausible reading is set aside afterwards.
        # It lies above the table's top (saturated) or below −5σ (out of
        # range) — unless the tare was absurdly noisy — so a frame with
        # neither needs no test: the usual frame costs two counts.
        if np.count_nonzero(saturated) or np.count_nonzero(out_of_range) or not self._low_flagged(noise):
            if self.crosstalk is None and np.count_nonzero(out_of_range):
                out_of_range &= ~self._crosstalk_explains(relative, noise)
            np.bitwise_or(flags, SATURATED, out=flags, where=saturated)
            np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=out_of_range)
            implausible = level0.implausible(relative, *self._bounds)
            if implausible is not None:  # no force, flagged out of range (not saturated)
                forces[implausible] = np.nan
                flags[implausible] = (flags[implausible] & ~np.uint8(SATURATED)) | OUT_OF_RANGE
        if stale is not None:
            forces[stale] = np.nan
        sigma = table_sigma(self.response, relative, forces, noise, self.response.gain, self.gain_relative_se,
                            self.model_sigma_N, self.calibrated_to_N, saturated,
                            zero=zero_sigma_for(self.kept_zero, baseline))
        return GridResult(forces, flags, sigma)

    def _crosstalk_explains(self, relative: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """(N, n): readings below −5σ by no more than the paper's mechanical
        coupling takes from a taxel beside pressed ones (the table level does
        not unmix it: a 30 N press left its healthy neighbours flagged
        out_of_range). Their force is 0 either way."""
        if self._neighbours is None:
            self._neighbours = neighbour_matrix(self.calibration.rows, self.calibration.cols)
        pressed = np.nan_to_num(np.clip(relative, 0.0, None))
        return relative >= -(OUT_OF_RANGE_SIGMAS * noise + abs(PAPER_MECHANICAL_COUPLING) * (pressed @ self._neighbours))

    def _low_flagged(self, noise: np.ndarray) -> bool:
        """Whether every implausibly low ΔC/C0 is also below −5σ (flagged out
        of range by the inversion); once per tare."""
        if self._low_flagged_for is None or self._low_flagged_for[0] is not noise:
            self._low_flagged_for = (noise, bool(np.all(OUT_OF_RANGE_SIGMAS * noise < -self.plausible[0])))
        return self._low_flagged_for[1]


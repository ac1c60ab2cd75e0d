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
from .levels import GRID_LEVELS
from .sigma import empirical_forces, level0_sigma, table_sigma
from .stuck import STUCK_FRAMES, run_lengths

NO_READING, SATURATED, OUT_OF_RANGE, CROSSTALK_CORRECTED, DRIFT_SUSPECT, STALE, LOADED_AT_TARE = (1 << i for i in range(7))
TAXEL_FLAG_NAMES = {
    NO_READING: "no_reading",
    SATURATED: "saturated",
    OUT_OF_RANGE: "out_of_range",
    CROSSTALK_CORRECTED: "crosstalk_corrected",
    DRIFT_SUSPECT: "drift_suspect",
    STALE: "stale",
    LOADED_AT_TARE: "loaded_at_tare",  # zero from the calibration's C0 (loaded_tare.py)
}
ADOPT_AFTER_EVENTS = 10  # isolated loads needed before a detected coefficient replaces the prior (within the first press)
SIGNIFICANT_SIGMAS = 3.0  # a leakage residual is added only when it stands this far above its own error
ADOPT_PERIOD_FRAMES = 64  # estimates are adopted only at multiples of this frame count
ESTIMATE_EVERY = 4


# The names of every combination of taxel flags, looked up per frame rather than built.
FLAG_NAMES_BY_BITS = tuple(tuple(name for bit, name in TAXEL_FLAG_NAMES.items() if bits & bit)
                           for bits in range(2 ** len(TAXEL_FLAG_NAMES)))


@dataclass
class GridResult:
    forces_N: np.ndarray  # (N, n), NaN = no reading
    taxel_flags: np.ndarray  # (N, n) uint8 bit set, see TAXEL_FLAG_NAMES
    sigma_N: np.ndarray | None = None  # (N, n) 1-σ of each force (sigma.py), NaN where the force is or saturated


@dataclass
class GridProcessor:
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
            self.drift.suspect_after_s = math.inf  # a drift_suspect on every frame that would say nothing
        self.gain_relative_se = np.zeros(n) if self.gain_relative_se is None else self.gain_relative_se
        self.model_sigma_N = np.zeros(n) if self.model_sigma_N is None else self.model_sigma_N
        self.calibrated_to_N = np.full(n, np.inf) if self.calibrated_to_N is None else self.calibrated_to_N
        if self.level == "full":
            self.crosstalk = self.crosstalk or Crosstalk(self.calibration.rows, self.calibration.cols)
            self.estimator = self.estimator or CrosstalkEstimator(self.calibration.rows, self.calibration.cols)

    def reset(self) -> None:
        """Forget tracked state (after a tare)."""
        self.drift.reset()

    def checkpoint(self) -> tuple:
        """What processing a batch advances (stuck counters, drift, frame
        count, sampled frames, estimator sums, adopted coefficients), for
        ``rollback`` after a failed call of several sensors. References and
        scalars only: every array here is replaced when it changes, never
        written in place, so this costs a few attribute reads."""
        estimator, crosstalk = self.estimator, self.crosstalk
        state = (self._last_raw, self._same_count, self._frames_seen, self._sampled, len(self._sampled),
                 self.adopted_events, self.drift.state())
        if estimator is None:
            return state
        m, e = estimator.mechanical, estimator.electrical
        slopes = ((m, m.xy, m.xx, m.events, m.yy), (e, e.xy, e.xx, e.events, e.yy))
        return state + (slopes, crosstalk.electrical, crosstalk.mechanical, crosstalk._unmix)

    def rollback(self, checkpoint: tuple) -> None:
        """Back to a ``checkpoint`` taken before a batch."""
        (self._last_raw, self._same_count, self._frames_seen, sampled, length, self.adopted_events,
         drift) = checkpoint[:7]
        self.drift.restore(drift)
        del sampled[length:]
        self._sampled = sampled
        if len(checkpoint) > 7:
            slopes, self.crosstalk.electrical, self.crosstalk.mechanical, self.crosstalk._unmix = checkpoint[7:]
            for slope, xy, xx, events, yy in slopes:
                slope.xy, slope.xx, slope.events, slope.yy = xy, xx, events, yy
            self.estimator.mechanical, self.estimator.electrical = (slope for slope, *_ in slopes)

    def noise(self, baseline_pF: np.ndarray, baseline_std_pF: np.ndarray) -> np.ndarray:
        """Noise of ΔC/C0 per taxel from the tare window's spread. The
        converter's noise is one figure for all channels, and 100 frames give
        each channel's spread only to ±7 %, so the median over channels is
        used (in pF), divided by each taxel's baseline."""
        if self._noise_for is None or self._noise_for[0] is not baseline_std_pF:
            pooled = np.nanmedian(baseline_std_pF) if np.isfinite(baseline_std_pF).any() else 0.0
            self._noise_for = (baseline_std_pF, max(pooled, NOISE_FLOOR_PF) / baseline_pF)
        return self._noise_for[1]

    def _runs_before(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(last frame (n,) pF, its run lengths (n,)) that this sensor's next
        frames continue (stuck.py); a NaN frame and no runs before the first."""
        if self._last_raw is None or self._last_raw.shape != (n,):
            return np.full(n, np.nan), np.zeros(n, dtype=np.int64)
        return self._last_raw, self._same_count

    @property
    def stale_runs(self) -> tuple[np.ndarray, np.ndarray] | None:
        """(last reading (n,) pF, run lengths (n,)) of the stale-channel count, None before a frame."""
        return None if self._last_raw is None else (self._last_raw, self._same_count)

    def restore_stale_runs(self, last_pF, runs) -> None:
        """Continue another processor's (or a recording's) stale-channel count."""
        self._last_raw, self._same_count = np.array(last_pF, dtype=float), np.array(runs, dtype=np.int64)

    def _stuck(self, capacitance: np.ndarray, counted: tuple | None = None) -> np.ndarray:
        """Run lengths (N, n) of repeated counts in frames (N, n), continuing
        this sensor's runs (stuck.py); ``counted``: (run lengths, last frame)
        already found with other sensors' frames (stuck.stale_rows), only kept."""
        if counted is None:
            previous, prior = self._runs_before(capacitance.shape[1])
            counted = run_lengths(previous[None], prior[None], capacitance[None])[0], capacitance[-1].copy()
        runs, self._last_raw = counted
        self._same_count = runs[-1]
        return runs

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
            sigma = level0_sigma(self, forces, noise, relative)
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
                            self.model_sigma_N, self.calibrated_to_N, saturated)
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

    def _reading_flags(self, capacitance: np.ndarray, baseline: np.ndarray,
                       baseline_std: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """(no-reading, stale and no-zero bits of (N, n) frames, the stale
        readings' mask or None). A stale reading (a converter that stopped
        converting repeats an old count) gives no force of now: null, as
        a missing one. Flags are set with ``where=`` masks: at 1 kHz the
        number of numpy calls, not their arithmetic, is the cost."""
        flags = np.isnan(capacitance).astype(np.uint8)  # NO_READING is bit 0
        stale = None
        if self._noisy_board(baseline_std):
            stale = self._stuck(capacitance) >= STUCK_FRAMES
            if np.count_nonzero(stale):
                np.bitwise_or(flags, STALE, out=flags, where=stale)
            else:
                stale = None
        self.flag_missing_zero(flags, capacitance, baseline)
        return flags, stale

    def flag_missing_zero(self, flags: np.ndarray, capacitance: np.ndarray, baseline: np.ndarray) -> None:
        """A channel the tare gave no zero (baseline NaN: no plausible
        reading in its window) has no force. Where it reads, say why: a
        reading outside the tare window (level0.py; e.g. a channel stuck at
        the converter's top since power-up) is ``out_of_range``, a
        plausible one still waiting for its late zero (baseline.py)
        ``no_reading``. Once per tare the usual answer is that every
        channel has its zero."""
        if self._zero_missing_for is None or self._zero_missing_for[0] is not baseline:
            missing = np.isnan(baseline)
            self._zero_missing_for = (baseline, missing if missing.any() else None)
        missing = self._zero_missing_for[1]
        if missing is None:
            return
        reads = missing & ~np.isnan(capacitance)
        if self.tare_window is None:
            outside = reads
        else:
            outside = reads & ((capacitance < self.tare_window[0]) | (capacitance > self.tare_window[1]))
        np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=outside)
        np.bitwise_or(flags, NO_READING, out=flags, where=reads & ~outside)

    def _noisy_board(self, baseline_std_pF: np.ndarray) -> bool:
        """Whether the converter shows noise at all (else equal counts in a
        row are normal and stuck channels cannot be told). Once per tare."""
        if self._noisy_for is None or self._noisy_for[0] is not baseline_std_pF:
            self._noisy_for = (baseline_std_pF, bool(np.nanmax(baseline_std_pF, initial=0.0) > NOISE_FLOOR_PF))
        return self._noisy_for[1]

    def frames_to_adoption(self) -> int:
        """Frames left before the next adoption point. Refined coefficients
        take effect only at multiples of ADOPT_PERIOD_FRAMES frames, so the
        result does not depend on how the stream was cut into batches (a
        replay equals the live run)."""
        return ADOPT_PERIOD_FRAMES - self._frames_seen % ADOPT_PERIOD_FRAMES

    def _sample(self, relative: np.ndarray, noise: np.ndarray, baseline: np.ndarray) -> None:
        """Keep every ESTIMATE_EVERY-th frame (by frame count, so batching does
        not matter) for the estimator: plenty for coefficients that change over
        hours; they are observed together once per adoption period."""
        first = -self._frames_seen % ESTIMATE_EVERY
        if first < len(relative):
            self._sampled.append((relative[first::ESTIMATE_EVERY], noise, baseline))

    def _advance(self, frames: int) -> None:
        self._frames_seen += frames
        if self._frames_seen % ADOPT_PERIOD_FRAMES == 0:
            self._observe_sampled()
            self._adopt_estimates()

    def _row_parameters(self, baseline: np.ndarray, baseline_std: np.ndarray) -> tuple:
        """(baseline, noise, un-leaked reference, drift band, gain, gain's
        relative error, model σ, largest force calibrated), each (n,):
        what the full level needs per row; the same tuple until a tare or a
        new leakage fraction, so stacks of it can be kept."""
        cached = self._parameters_for
        if cached is None or cached[0] is not baseline or cached[1] is not baseline_std or cached[2] != self.crosstalk.electrical:
            noise = self.noise(baseline, baseline_std)
            self.drift.noise = float(np.nanmedian(noise)) if np.isfinite(noise).any() else 0.0  # what a load departs from (drift.py)
            values = (baseline, noise, self._reference(baseline), self.drift.band * noise, self.response.gain,
                      self.gain_relative_se, self.model_sigma_N, self.calibrated_to_N)
            cached = self._parameters_for = (baseline, baseline_std, self.crosstalk.electrical, values)
        return cached[3]

    def _stacked(self, parameters: list[tuple]) -> tuple:
        """Several sensors' ``_row_parameters`` stacked field by field, (S, n)
        each; rebuilt only when one sensor's tuple changes."""
        cached = self._stacked_for
        if cached is None or len(cached[0]) != len(parameters) or any(a is not b for a, b in zip(cached[0], parameters)):
            cached = self._stacked_for = (tuple(parameters), tuple(np.array(field) for field in zip(*parameters)))
        return cached[1]

    def _reference(self, baseline: np.ndarray) -> np.ndarray:
        """The baseline as the multiplexer would read it without leakage;
        recomputed only after a tare or a new leakage fraction."""
        electrical = self.crosstalk.electrical
        cached = self._reference_for
        if cached is None or cached[0] is not baseline or cached[1] != electrical:
            cached = self._reference_for = (baseline, electrical, self.crosstalk.unleak(baseline, self.leak_fill(baseline)))
        return cached[2]

    def leak_fill(self, baseline: np.ndarray) -> np.ndarray:
        """What an unread channel is taken to leak into the one scanned after
        it (Crosstalk.unleak): its baseline, or where the tare gave it none
        the calibration's C0 (a NaN there ran through the inverse filter: with
        a leakage in use the whole grid was null, its other taxels unflagged).
        Once per tare."""
        if self._fill_for is None or self._fill_for[0] is not baseline:
            missing = np.isnan(baseline)
            self._fill_for = (baseline, np.where(missing, self.calibration.c0_pF, baseline) if missing.any() else baseline)
        return self._fill_for[1]

    def _observe_sampled(self) -> None:
        """Feed the estimator the frames sampled this period, one call per tare."""
        sampled, self._sampled = self._sampled, []
        while sampled:
            _, noise, baseline = sampled[0]
            same = 0
            while same < len(sampled) and sampled[same][1] is noise and sampled[same][2] is baseline:
                same += 1
            self.estimator.observe(np.concatenate([rows for rows, _, _ in sampled[:same]]), noise, baseline)
            sampled = sampled[same:]

    def _adopt_estimates(self) -> None:
        """Refine the coefficients from the data once enough isolated loads
        were seen. The mechanical slope is measured before unmixing, so it is
        the coupling itself and keeps accumulating; the electrical one is
        measured after the leakage already compensated, so it is a residual:
        added to the fraction in use when it is significant (else the
        fraction would wander with the noise of every few events), then
        measured afresh."""
        estimator, crosstalk = self.estimator, self.crosstalk
        if estimator.electrical.events < ADOPT_AFTER_EVENTS:
            return
        report = estimator.report()
        residual = report["electrical"]["estimate"]
        if abs(residual) > SIGNIFICANT_SIGMAS * estimator.electrical.standard_error():
            crosstalk.electrical = float(np.clip(crosstalk.electrical + residual, 0.0, 0.3))
        crosstalk.set_mechanical(float(np.clip(report["mechanical"]["estimate"], -0.02, 0.0)))
        self.adopted_events += estimator.electrical.events
        estimator.electrical = type(estimator.electrical)()

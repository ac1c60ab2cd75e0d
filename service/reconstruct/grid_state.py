"""What a grid processor carries from batch to batch at the full level
(grid_full.py): the frames sampled for the crosstalk estimator, the
adoption of its estimates at fixed frame counts, each tare's row
parameters, and checkpoints of it all for a batch of several sensors that
fails (isolation.py).
"""
from __future__ import annotations

import numpy as np

from .sigma import zero_sigma_for

ADOPT_AFTER_EVENTS = 10  # isolated loads needed before a detected coefficient replaces the prior (within the first press)
SIGNIFICANT_SIGMAS = 3.0  # a leakage residual is added only when it stands this far above its own error
ADOPT_PERIOD_FRAMES = 64  # estimates are adopted only at multiples of this frame count
ESTIMATE_EVERY = 4


class GridState:
    """GridProcessor's state across batches (its fields: ``crosstalk``,
    ``estimator``, ``drift``, ``_sampled``, ``_frames_seen`` and the caches
    named ``_*_for``)."""

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
        relative error, model σ, largest force calibrated, the σ of a zero
        kept at a loaded tare in ΔC/C0: sigma.zero_sigma_for, 0 where tared), each (n,):
        what the full level needs per row; the same tuple until a tare or a
        new leakage fraction, so stacks of it can be kept."""
        cached = self._parameters_for
        if cached is None or cached[0] is not baseline or cached[1] is not baseline_std or cached[2] != self.crosstalk.electrical:
            noise = self.noise(baseline, baseline_std)
            self.drift.noise = float(np.nanmedian(noise)) if np.isfinite(noise).any() else 0.0  # what a load departs from (drift.py)
            values = (baseline, noise, self._reference(baseline), self.drift.band * noise, self.response.gain,
                      self.gain_relative_se, self.model_sigma_N, self.calibrated_to_N, self._zero_sigma(baseline))
            cached = self._parameters_for = (baseline, baseline_std, self.crosstalk.electrical, values)
        return cached[3]

    def _zero_sigma(self, baseline: np.ndarray) -> np.ndarray:
        """The σ (n,) ΔC/C0 of each taxel's zero, kept at a loaded tare (sigma.zero_sigma_for); 0 where tared."""
        sigma = zero_sigma_for(self.kept_zero, baseline)
        return np.zeros(baseline.shape) if sigma is None else sigma

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

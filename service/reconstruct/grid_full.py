"""The full grid level for several sensors at once, row by row.

Leakage → drift → mechanical unmixing → table inversion (grid.py describes
the levels and the flags; GridProcessor keeps each sensor's state: grid_state.py). Every
step except the drift's exponential average and the estimator's
bookkeeping works row by row, so the frames of all sensors go through one
call per step: at 1 kHz the per-call cost, not the per-frame arithmetic,
dominates.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import level0
from .drift import quiet_medians
from .sigma import empirical_forces, table_sigma
from .stuck import stale_rows
from .grid import GridProcessor, GridResult
from .taxel_flags import CROSSTALK_CORRECTED, DRIFT_SUSPECT, NO_READING, OUT_OF_RANGE, SATURATED, STALE

CORRECTION_SIGMAS = 3.0

# One sensor's rows in a pass: its processor, its job, and which of the job's frames.
Piece = tuple[GridProcessor, "GridJob", slice]


@dataclass
class GridJob:
    """One grid sensor's share of a batch: frames (N, n) pF at board times
    (N,) s, with the sensor's tare baseline and spread (n,); ``clipped``
    (N, n): channels at the converter's top (level0.clipped), None: none."""

    processor: GridProcessor
    capacitance: np.ndarray
    baseline: np.ndarray
    baseline_std: np.ndarray
    t_s: np.ndarray
    clipped: np.ndarray | None = None


def process_full(jobs: list[GridJob]) -> list[GridResult]:
    """The full level for several grid sensors at once (each result equals,
    bit for bit, what the sensor's frames would give alone).

    A sensor whose batch crosses its adoption point is split there and the
    rest goes through the next round, with the adopted coefficients.
    """
    shapes: dict[tuple[int, int], list[int]] = {}
    for k, job in enumerate(jobs):
        shapes.setdefault((job.processor.calibration.rows, job.processor.calibration.cols), []).append(k)
    if len(shapes) > 1:  # rows of one pass must have one length
        results: list[GridResult | None] = [None] * len(jobs)
        for ks in shapes.values():
            for k, result in zip(ks, process_full([jobs[k] for k in ks])):
                results[k] = result
        return results
    spans = [(job, 0, min(len(job.capacitance), job.processor.frames_to_adoption())) for job in jobs]
    results = _full_rows(spans)
    for job, start, end in spans:
        job.processor._advance(end - start)
    if all(end == len(job.capacitance) for job, _, end in spans):  # the usual batch: no adoption point inside
        return results
    parts = [[result] for result in results]
    pending = [(k, end) for k, (job, _, end) in enumerate(spans) if end < len(job.capacitance)]
    while pending:
        spans = [(jobs[k], start, min(len(jobs[k].capacitance), start + jobs[k].processor.frames_to_adoption()))
                 for k, start in pending]
        for (k, _), (job, start, end), result in zip(pending, spans, _full_rows(spans)):
            parts[k].append(result)
            job.processor._advance(end - start)
        pending = [(k, end) for (k, _), (job, _, end) in zip(pending, spans) if end < len(job.capacitance)]
    return [part[0] if len(part) == 1 else GridResult(*(np.concatenate([getattr(r, name) for r in part])
                                                        for name in ("forces_N", "taxel_flags", "sigma_N")))
            for part in parts]


def _full_rows(spans: list[tuple[GridJob, int, int]]) -> list[GridResult]:
    """One pass over rows ``start:end`` of each job (none crossing an adoption point)."""
    pieces, counts, rows, params = [], [], [], []
    row = 0
    for job, start, end in spans:  # each sensor's share, in one loop: per-sensor Python is what a pass costs
        p = job.processor
        pieces.append((p, job, slice(start, end)))
        counts.append(end - start)
        rows.append(slice(row, row + end - start))
        row += end - start
        params.append(p._row_parameters(job.baseline, job.baseline_std))
    capacitance, t_s, (baseline, noise, reference, band, gain, relative_se, model_sigma, calibrated_to, zero) = \
        _stacked_rows(pieces, counts, params)
    clipped = _clipped(pieces, capacitance.shape)
    flags, stale = _reading_flags(pieces, rows, capacitance, clipped)
    capacitance, ratio = _plausible_ratio(pieces, rows, counts, capacitance, baseline, reference, flags, stale)
    medians, quiet = quiet_medians(ratio - 1.0, band)
    drift, suspect, unseen = _drift(pieces, rows, t_s, quiet, medians)
    scale = 1.0 + drift[:, None]
    relative = ratio / scale - 1.0  # drift removed: (1 + r)/(1 + d) − 1
    for (p, job, _), r, (_, n, *_) in zip(pieces, rows, params):
        p._sample(relative[r], n, job.baseline)
    compensated = _unmixed(pieces, rows, relative)
    uncompensated = capacitance / (baseline * scale) - 1.0
    np.bitwise_or(flags, CROSSTALK_CORRECTED, out=flags, where=np.abs(compensated - uncompensated) > CORRECTION_SIGMAS * noise)
    if np.count_nonzero(suspect):
        np.bitwise_or(flags, DRIFT_SUSPECT, out=flags, where=suspect[:, None] & (flags & (NO_READING | OUT_OF_RANGE) == 0))
    first = pieces[0][0].response
    shared = all(p.response.shares_curve(first) for p, _, _ in pieces)  # one table: one call for all rows
    forces, saturated, out_of_range = _inverted(pieces, rows, params, compensated, noise, gain, shared)
    for (p, _, _), r in zip(pieces, rows):
        if p.curves:
            empirical_forces(p.curves, compensated[r], forces[r], saturated[r])
    if clipped is not None:  # a lower bound: held as read, no σ
        saturated |= clipped & (forces == forces)
    sigma = _sigma(pieces, rows, compensated, forces, (noise, gain, relative_se, model_sigma, calibrated_to), saturated,
                   shared, unseen, zero)
    np.bitwise_or(flags, SATURATED, out=flags, where=saturated)
    np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=out_of_range)
    return [GridResult(forces[r], flags[r], sigma[r]) for r in rows]


def _drift(pieces: list[Piece], rows: list[slice], t_s: np.ndarray, quiet: np.ndarray,
           medians: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(drift, drift-suspect, the drift it cannot have seen) (R,) of the
    stacked rows, each sensor's tracker stepped through its own rows
    (``quiet``: how many taxels each median is of, 0: too few)."""
    t_s, quiet, medians = t_s.tolist(), quiet.tolist(), medians.tolist()
    steps = []
    for (p, _, _), r in zip(pieces, rows):
        steps += p.drift.follow(t_s[r], quiet[r], medians[r])
    steps = np.array(steps, dtype=float).reshape(-1, 3)
    return steps[:, 0], steps[:, 1] != 0.0, steps[:, 2]


def _stacked_rows(pieces: list[Piece], counts: list[int], params: list[tuple]) -> tuple:
    """(capacitance (R, n), times (R,), row parameters): the pieces' frames
    one after the other, and (baseline, noise, reference, band, gain) per row."""
    if len(pieces) == 1:
        _, job, sl = pieces[0]
        return job.capacitance[sl], job.t_s[sl], params[0]
    capacitance = np.concatenate([job.capacitance[sl] for _, job, sl in pieces])
    t_s = np.concatenate([job.t_s[sl] for _, job, sl in pieces])
    stacked = pieces[0][0]._stacked(params)
    return capacitance, t_s, stacked if max(counts) == 1 else tuple(np.repeat(a, counts, axis=0) for a in stacked)


def _clipped(pieces: list[Piece], shape: tuple[int, int]) -> np.ndarray | None:
    """The stacked rows' channels at the converter's top (GridJob.clipped), None where no job has any."""
    if all(job.clipped is None for _, job, _ in pieces):
        return None
    return np.concatenate([np.zeros((sl.stop - sl.start, shape[1]), dtype=bool) if job.clipped is None
                           else job.clipped[sl] for _, job, sl in pieces])


def _reading_flags(pieces: list[Piece], rows: list[slice], capacitance: np.ndarray,
                   clipped: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """(no-reading, stale and no-zero bits of the stacked rows, the stale
    readings' mask or None); a channel at the converter's top (``clipped``)
    repeats its count without being stale."""
    flags = np.isnan(capacitance).astype(np.uint8)  # NO_READING is bit 0
    stale = stale_rows(pieces, rows, capacitance)
    if stale is not None and clipped is not None:
        stale &= ~clipped
    if stale is not None:
        if np.count_nonzero(stale):
            np.bitwise_or(flags, STALE, out=flags, where=stale)
        else:
            stale = None
    for (p, job, _), r in zip(pieces, rows):
        p.flag_missing_zero(flags[r], capacitance[r], job.baseline)
    return flags, stale


def _plausible_ratio(pieces: list[Piece], rows: list[slice], counts: list[int], capacitance: np.ndarray,
                     baseline: np.ndarray, reference: np.ndarray, flags: np.ndarray,
                     stale: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """(capacitance, ratio to the un-leaked reference), implausible readings
    (level0.py) made missing and flagged out of range before any
    compensation, so they move none of their neighbours; so are ``stale``
    ones (a converter that stopped converting repeats an old count: no
    force of now). Without leakage the reference is the baseline itself
    and the test reuses the ratio."""
    if len(pieces) == 1 or len({p.plausible for p, _, _ in pieces}) == 1:
        low, high = pieces[0][0]._ratio_bounds
    else:
        low, high = (np.repeat([p.plausible[i] + 1.0 for p, _, _ in pieces], counts)[:, None] for i in (0, 1))
    leaky = any(p.crosstalk.electrical for p, _, _ in pieces)
    if leaky:
        implausible = level0.implausible(capacitance / baseline, low, high)
    else:
        ratio = capacitance / reference
        implausible = level0.implausible(ratio, low, high)
    if implausible is not None:
        np.bitwise_or(flags, OUT_OF_RANGE, out=flags, where=implausible)
    missing = implausible if stale is None else stale if implausible is None else implausible | stale
    if missing is not None:
        capacitance = np.where(missing, np.nan, capacitance)
        if not leaky:
            ratio = np.where(missing, np.nan, ratio)
    if leaky:
        if missing is None:
            unleaked = [p.crosstalk.unleak(job.capacitance[sl], p.leak_fill(job.baseline)) for p, job, sl in pieces]
        else:
            unleaked = [p.crosstalk.unleak(capacitance[r], p.leak_fill(job.baseline))
                        for (p, job, _), r in zip(pieces, rows)]
        ratio = (unleaked[0] if len(unleaked) == 1 else np.concatenate(unleaked)) / reference
    return capacitance, ratio


def _unmixed(pieces: list[Piece], rows: list[slice], relative: np.ndarray) -> np.ndarray:
    """Mechanical unmixing; sensors with the same coupling share the matrix,
    so their rows go through one call."""
    first = pieces[0][0]
    if all(p.crosstalk.mechanical == first.crosstalk.mechanical for p, _, _ in pieces):
        return first.crosstalk.unmix_mechanical(relative)
    return np.concatenate([p.crosstalk.unmix_mechanical(relative[r]) for (p, _, _), r in zip(pieces, rows)])


def _inverted(pieces: list[Piece], rows: list[slice], params: list[tuple], compensated: np.ndarray,
              noise: np.ndarray, gain: np.ndarray, shared: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(forces, saturated, out of range) from the model tables; sensors on
    the same table (``shared``) share the inversion, so their rows go through one call."""
    if shared:
        return pieces[0][0].response.inverse(compensated, noise, gain)
    inverted = [p.response.inverse(compensated[r], n) for (p, _, _), r, (_, n, *_) in zip(pieces, rows, params)]
    return tuple(np.concatenate(arrays) for arrays in zip(*inverted))


def _sigma(pieces: list[Piece], rows: list[slice], compensated: np.ndarray, forces: np.ndarray,
           per_row: tuple, saturated: np.ndarray, shared: bool, unseen: np.ndarray, zero: np.ndarray) -> np.ndarray:
    """σ of every force (sigma.py), with the drift each row's tracker cannot
    have seen (R,) ΔC/C0 and the σ of a zero kept at a loaded tare (n,) or
    (R, n) ΔC/C0; sensors on the same table in one call."""
    if shared:
        return table_sigma(pieces[0][0].response, compensated, forces, *per_row, saturated, unseen, zero)
    return np.concatenate([table_sigma(p.response, compensated[r], forces[r], *(a[r] if a.ndim == 2 else a for a in per_row),
                                       saturated[r], unseen[r], zero[r] if zero.ndim == 2 else zero)
                           for (p, _, _), r in zip(pieces, rows)])

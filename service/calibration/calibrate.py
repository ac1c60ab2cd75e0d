"""A whole calibration run: session + reference → per-taxel fits → a registry document.

``calibrate`` reads both files, aligns the clocks, segments the presses,
fits every taxel that was pressed and returns a ``Calibration`` (with the
timings of each step). ``document`` turns it into the registry's immutable
record: taxels not pressed keep the previous calibration's values (the
active one of that sensor, or table 1) and are listed as carried.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from . import registry
from .alignment import Alignment, align, board_response
from .crosstalk_session import session_crosstalk, unleaked
from .fit import MIN_RANGE_FRACTION, TaxelError, TaxelFit, fit_taxel, table_cells, unit_response
from .reference import Reference, flat_top_said, read_reference, unit_hint
from .reference_zero import with_zero_hint, zero_said, zeroed
from .segmentation import Press, noise_sigma, segment, taxel_samples, unloaded
from .session import BoardSession, file_sha256, load_session

FULL_SCALE_N = 10.0


@dataclass
class Calibration:
    """What one run found. ``fits`` by taxel (row-major); ``problems`` by
    taxel (why it could not be fitted); ``samples`` the data fitted;
    ``timings_s`` per step."""

    session: BoardSession
    reference: Reference
    alignment: Alignment
    presses: list[Press]
    fits: dict[int, TaxelFit]
    problems: dict[int, str]
    reference_noise_N: float
    mounting: str
    full_scale_N: float
    samples: dict = field(default_factory=dict)  # taxel → segmentation.TaxelSamples
    timings_s: dict[str, float] = field(default_factory=dict)
    crosstalk: dict | None = None  # {mechanical, electrical, events} measured in the session (crosstalk_session.py)

    @property
    def flagged_presses(self) -> list[Press]:
        return [p for p in self.presses if p.problem is not None]


OVER_FULL_SCALE = 1.5  # presses this far past the full scale can spoil the clock alignment (its note)


def calibrate(session_path, reference_path, sensor_id: int | None = None, full_scale_N: float = FULL_SCALE_N,
              mounting: str = "flat", allow_partial: bool = False, board: str | None = None,
              zero_reference: bool = False) -> Calibration:
    """Calibrate one grid; ValueError naming every bad taxel unless
    ``allow_partial`` (then they keep their previous calibration).
    ``board``: the board's name in the service (session.load_session);
    ``zero_reference``: subtract the reference's rest level (reference_zero.py)."""
    clock, timings = time.perf_counter(), {}

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name], clock = now - clock, now

    session = load_session(session_path, sensor_id, board=board)
    reference = zeroed(read_reference(reference_path), zero_reference)
    lap("read")
    try:  # a refusal says whether the reference's rest level may be why
        rows, cols = session.info.rows, session.info.cols
        crosstalk = session_crosstalk(session.capacitance_pF, rows, cols)
        if crosstalk is not None:
            session.capacitance_pF = unleaked(session.capacitance_pF, rows, cols, crosstalk["electrical"])
        lap("crosstalk")
        dead = {t: str(TaxelError(t, cols, why)) for t, why in sorted(session.dead.items())}
        # dead columns are all NaN: alignment's medians would warn about them, and they add nothing to the sum
        capacitance = np.delete(session.capacitance_pF, list(dead), axis=1) if dead else session.capacitance_pF
        try:
            alignment = align(session.t_s, board_response(session.t_s, capacitance), reference.t_s, reference.force_N)
        except ValueError as exc:
            notes = []
            if dead:  # the reference shows their presses and the board does not: it may be why they match badly
                notes.append(f"presses on dead taxels show on no channel ({'; '.join(dead.values())})")
            top = float(np.max(reference.force_N))
            if top > OVER_FULL_SCALE * full_scale_N:  # the response flattens there: no longer like the reference's
                notes.append(f"the reference reaches {top:.1f} N, past {OVER_FULL_SCALE:g}× the full scale "
                             f"({full_scale_N:g} N), where a taxel's response is far from proportional: press within "
                             "it, or give --full-scale")
            if not notes:
                raise
            raise ValueError(f"{exc}; note: {'; '.join(notes)}") from None
        lap("align")
        t_ref_board = alignment.to_board(reference.t_s)
        presses = segment(session.t_s, session.capacitance_pF, t_ref_board, reference.force_N)
        samples = taxel_samples(presses, session.t_s, session.capacitance_pF, session.saturated, t_ref_board, reference.force_N)
        lap("segment")
        noise = noise_sigma(reference.force_N[unloaded(presses, t_ref_board)])  # pauses: pure instrument noise
        fits = {}
        problems = dict(dead)
        for taxel, data in samples.items():
            try:
                fits[taxel] = fit_taxel(data, noise, full_scale_N, mounting, session.info.cols,
                                        reference.rate_hz / session.rate_hz)
            except TaxelError as exc:
                problems[taxel] = str(exc)
        lap("fit")
        if problems and not allow_partial:
            reach = float(np.max(reference.force_N))
            hint = unit_hint(_force_ratio(samples, mounting), "the board's response gives through the model curve "
                             "at gain 1 (the median taxel's)")
            units = (f"; note: the reference never exceeds {reach:.2f} N: if it logs another unit than N (lbf: 4.45 N "
                     "each, kgf: 9.81), convert it, or press to the full scale (--full-scale)"
                     if reach < MIN_RANGE_FRACTION * full_scale_N and not hint else "")
            # the unit first: every taxel is refused by it, and the list of them would hide it
            raise ValueError("cannot calibrate: " + (f"{hint}; " if hint else "")
                             + "; ".join(problems[t] for t in sorted(problems)) + units)
        if not fits:
            raise ValueError(f"{session.path}: no taxel could be calibrated ({len(presses)} presses found)")
        return Calibration(session, reference, alignment, presses, fits, problems, noise, mounting, full_scale_N, samples,
                           timings, crosstalk)
    except ValueError as exc:
        raise with_zero_hint(reference, exc) from None


def _force_ratio(samples: dict, mounting: str) -> float:
    """The reference's force over the force a taxel's ΔC/C0 gives on the
    mounting's model curve at gain 1 (table 1's taxels are within ±15 % of
    it), per taxel the median over its samples loaded past half its largest
    such force, then the median over the taxels (``samples``: taxel →
    segmentation.TaxelSamples); NaN without any."""
    unit = unit_response(mounting)
    ratios = []
    for data in samples.values():
        board = unit.inverse(data.relative[:, None])[0][:, 0]
        loaded = board > 0.5 * np.nanmax(board, initial=0.0)
        if loaded.any():
            ratios.append(np.median(data.force_N[loaded] / board[loaded]))
    return float(np.median(ratios)) if ratios else float("nan")


def identity(session: BoardSession) -> dict:
    """The sensor's identity (protocol.md): its own serial, else the board's serial (or name) and its id."""
    return registry.sensor_identity(session.board, session.info)


def document(result: Calibration, previous: dict | None = None, created: str | None = None) -> dict:
    """The registry record (without id) of ``result``; taxels not fitted keep
    ``previous``'s values (a registry document; table 1's by default)."""
    info = result.session.info
    n = info.channels
    previous = previous or registry.builtin_document(info.rows, info.cols)
    old = previous["taxels"]
    fields = ("c0_pF", "gain", "gain_se", "sensitivity_pct_per_N", "sensitivity_origin_pct_per_N",
              "residual_rms_N", "presses", "max_force_N", "model", "source")
    taxels = {name: list(old.get(name, [None] * n)) for name in fields}
    taxels["source"] = [previous["id"] if previous.get("id") else "previous"] * n
    taxels["curves"] = dict(old.get("curves", {}))
    for t, fit in result.fits.items():
        values = {"c0_pF": fit.c0_pF, "gain": fit.gain, "gain_se": fit.gain_se,
                  "sensitivity_pct_per_N": 100 * fit.sensitivity_per_N,
                  "sensitivity_origin_pct_per_N": 100 * fit.sensitivity_origin_per_N,
                  "residual_rms_N": fit.residual_rms_N, "presses": fit.presses, "max_force_N": fit.max_force_N,
                  "model": fit.model, "source": "this session"}
        for name, value in values.items():
            taxels[name][t] = value
        taxels["curves"].pop(str(t), None)
        if fit.model == "empirical":
            taxels["curves"][str(t)] = {"force_N": fit.curve_force_N, "relative": fit.curve_relative}
    a = result.alignment
    return {
        "schema": registry.SCHEMA,
        "kind": "grid",
        "rows": info.rows,
        "cols": info.cols,
        "sensor": identity(result.session),
        "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "mounting": result.mounting,
        "full_scale_N": result.full_scale_N,
        "previous": previous.get("id"),
        "sources": [{"role": "session", "name": str(result.session.path), "sha256": result.session.sha256},
                    {"role": "reference", "name": result.reference.path, "sha256": file_sha256(result.reference.path)}],
        "alignment": a.as_dict(),
        **({"crosstalk": result.crosstalk} if result.crosstalk is not None else {}),
        "statistics": {"presses": len(result.presses), "flagged_presses": len(result.flagged_presses),
                       "reference_noise_N": result.reference_noise_N, "reference_rest_N": None if result.reference.zero_N is None else result.reference.zero_N[-1],
                       "reference_rest_subtracted": result.reference.zero_subtracted,
                       "reference_rest_warning": result.reference.zero_warning,
                       "reference_flat_top_warning": flat_top_said(result.reference),
                       "reference_skipped_lines": result.reference.skipped,
                       "taxels_fitted": sorted(result.fits), "taxels_failed": {str(t): m for t, m in result.problems.items()},
                       "taxels_not_pressed": not_pressed(result),
                       "residual_rms_N_median": float(np.median([f.residual_rms_N for f in result.fits.values()]))},
        "taxels": taxels,
    }


def not_pressed(result: Calibration) -> list[int]:
    """Taxels (row-major) that no press of the session was credited to (none within the reference's span, or
    none at all): neither fitted nor failed, they keep their previous values, and are named as such."""
    return [t for t in range(result.session.info.channels) if t not in result.fits and t not in result.problems]


def summary_lines(result: Calibration) -> list[str]:
    """What ``tactile calibrate`` prints: alignment, then one line per fitted taxel."""
    a, cols = result.alignment, result.session.info.cols
    lines = [f"session {result.session.path}: {len(result.session.t_s)} frames at {result.session.rate_hz:.1f} Hz; "
             f"reference {result.reference.path}: {len(result.reference.t_s)} samples at {result.reference.rate_hz:.1f} Hz, "
             f"{result.reference.skipped} lines skipped",
             f"alignment: t_ref = t_board·(1 {a.rate_ppm:+.1f} ppm) {a.offset_s:+.4f} s; match {a.quality:.4f} "
             f"(runner-up lag {a.runner_up_lag_s:+.2f} s: {a.runner_up:.3f} against {a.coarse_best:.3f})",
             f"presses: {len(result.presses)} ({len(result.flagged_presses)} set aside), reference noise "
             f"{result.reference_noise_N:.4f} N, {zero_said(result.reference)}",
             "crosstalk: " + ("too few isolated presses to measure" if result.crosstalk is None else
                              f"mechanical {result.crosstalk['mechanical']:+.4f}, multiplexer leakage "
                              f"{result.crosstalk['electrical']:.4f} ({result.crosstalk['events']} isolated frames)"),
             *filter(None, [flat_top_said(result.reference)]),
             "taxel     C0 pF   sens %/N (LS) (origin)   gain ± se          RMS N   presses  max N  model"]
    for t in sorted(result.fits):
        name, c0, sens, origin, gain, rms, presses, max_n, model = table_cells(t, cols, result.fits[t])
        lines.append(f"{name:<9}{c0:>7}   {sens:>7}  {origin:>7}    {gain}   {rms}   {presses:>5}  {max_n:>5}  {model}")
    for t, why in sorted(result.problems.items()):
        lines.append(f"not calibrated: {why}")
    missed = not_pressed(result)
    if missed:
        lines.append(f"not pressed, so not calibrated (they keep their previous values): taxels {missed}")
    for p in result.flagged_presses:
        lines.append(f"press at {p.start_s:.2f} s set aside: {p.problem}")
    return lines



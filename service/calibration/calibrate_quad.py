"""A whole quad calibration: session + 3-axis reference → curves and coupling → a registry document."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from datetime import datetime, timezone

import numpy as np

from ..physics.quad_fits import invert_fit
from ..physics.quad_model import QuadModel
from ..reconstruct.fatigue import PAPER_001
from ..reconstruct.sensor_calibration import undetermined_coupling_se
from . import registry
from .alignment import Alignment, align, board_response
from .quad_fit import COUPLING_MIN_SPREAD_N, COUPLING_SIGMAS, REST_MIN_S, QuadFit, fit_quad
from .reference import Reference, flat_top_said, read_reference, unit_hint
from .reference_zero import with_zero_hint, zero_said, zeroed
from .session import BoardSession, file_sha256, load_session


@dataclass
class QuadCalibration:
    session: BoardSession
    reference: Reference
    alignment: Alignment
    fit: QuadFit
    timings_s: dict[str, float] = field(default_factory=dict)


def calibrate_quad(session_path, reference_path, sensor_id: int | None = None,
                   board: str | None = None, zero_reference: bool = False) -> QuadCalibration:
    """Align the clocks on the normal force (the electrodes' summed response
    is the normal curve: shear cancels in it), then fit (quad_fit.py).
    ``board``: the board's name in the service (session.load_session)."""
    started = time.perf_counter()
    session = load_session(session_path, sensor_id, kind="quad", board=board)
    reference = read_reference(reference_path)
    if reference.fxyz_N is None:
        raise ValueError(f"{reference.path}: a quad calibration needs a 3-axis reference 't_s,fx_N,fy_N,fz_N'")
    reference = zeroed(reference, zero_reference)
    read = time.perf_counter()
    response = board_response(session.t_s, session.capacitance_pF, normalise=False)  # shear cancels in the plain sum
    alignment = align(session.t_s, response, reference.t_s, reference.force_N)
    t_ref_board = alignment.to_board(reference.t_s)
    inside = (session.t_s >= t_ref_board[0]) & (session.t_s <= t_ref_board[-1])
    fxyz = np.stack([np.interp(session.t_s[inside], t_ref_board, reference.fxyz_N[:, k]) for k in range(3)], axis=1)
    aligned = time.perf_counter()
    try:  # a refusal says whether the reference's rest level, or its unit, may be why
        fit = fit_quad(session.t_s[inside], session.capacitance_pF[inside], fxyz, session.saturated[inside],
                       session.rate_hz / reference.rate_hz)
    except ValueError as exc:
        hint = unit_hint(_normal_ratio(response[inside], fxyz[:, 2]), "the board's response gives through paper "
                         "001's fit 34")
        raise with_zero_hint(reference, ValueError(f"{exc}; note: {hint}") if hint else exc) from None
    done = time.perf_counter()
    return QuadCalibration(session, reference, alignment, fit,
                           {"read": read - started, "align": aligned - read, "fit": done - aligned})


def fit_document(fit: QuadFit) -> dict:
    """The fit's fields of the registry record (sensor_calibration.py reads
    them): curves, coupling (``coupling_se`` null: not determined), the
    normal force the shear was measured under, C0, usable ends and the
    fit's statistics."""
    return {
        "normal_fit": list(fit.normal), "normal_fit_se": list(fit.normal_se),
        "shear_fit": list(fit.shear), "shear_fit_se": list(fit.shear_se),
        "coupling": fit.coupling, "coupling_se": fit.coupling_se, "coupling_shown_by_data": fit.coupling_kept,
        "shear_preload_N": fit.shear_preload_N[0],
        "normal_usable_N": fit.usable_N[0], "shear_usable_N": fit.usable_N[1],
        "c0_pF": fit.c0_pF.tolist(),
        "statistics": {"frames_fitted": fit.frames, "loads": fit.loads, "rms_N": dict(zip("xyz", fit.rms_N)),
                       "flat_above_N": {"normal": fit.flat_N[0], "shear": fit.flat_N[1]},
                       "shear_reach_N": fit.shear_reach_N, "shear_preload_spread_N": fit.shear_preload_N[1],
                       "c0_moved": fit.c0_moved, "c0_rests": fit.c0_rests},
    }


def _normal_ratio(response: np.ndarray, fz: np.ndarray) -> float:
    """The reference's Fz (k,) over the normal force the board's summed
    response (k,) (alignment.board_response: four times Z above its rest)
    gives through fit 34, the median over the frames loaded past half the
    largest such force: ~1 for a reference in N, whatever its thresholds
    make of another unit; NaN without loads."""
    board, _ = invert_fit(QuadModel().normal_fit, response / 4.0)
    loaded = board > 0.5 * board.max()
    return float(np.median(fz[loaded] / board[loaded])) if board.max() > 0 else float("nan")


def quad_document(result: QuadCalibration, created: str | None = None, fatigue: str = "paper") -> dict:
    """The registry record (without id). ``fatigue``: "paper" (paper 001's
    loss from this calibration's count 0: a new sensor) or "none" (a sensor
    whose loss has settled: cycled long before the session)."""
    fitted = fit_document(result.fit)
    return {
        "schema": registry.SCHEMA, "kind": "quad",
        "sensor": registry.sensor_identity(result.session.board, result.session.info),
        "created": created or datetime.now(timezone.utc).isoformat(timespec="seconds"),
        **fitted,
        "fatigue": {"drop": PAPER_001.drop if fatigue == "paper" else 0.0, "tau_cycles": PAPER_001.tau_cycles},
        "sources": [{"role": "session", "name": str(result.session.path), "sha256": result.session.sha256},
                    {"role": "reference", "name": result.reference.path, "sha256": file_sha256(result.reference.path)}],
        "alignment": result.alignment.as_dict(),
        "statistics": {**fitted["statistics"],
                       "reference_skipped_lines": result.reference.skipped,
                       "reference_rest_N": dict(zip("xyz", result.reference.zero_N or (None,) * 3)),
                       "reference_rest_subtracted": result.reference.zero_subtracted,
                       "reference_rest_warning": result.reference.zero_warning,
                       "reference_flat_top_warning": flat_top_said(result.reference)},
    }


def quad_summary(result: QuadCalibration) -> list[str]:
    a, fit = result.alignment, result.fit
    c2, c1 = fit.normal
    return [f"session {result.session.path}: {len(result.session.t_s)} frames of quad {result.session.info.id}; "
            f"reference {result.reference.path}: {len(result.reference.t_s)} samples, {result.reference.skipped} lines skipped; "
            f"{zero_said(result.reference)}",
            *filter(None, [flat_top_said(result.reference)]),
            f"alignment: t_ref = t_board·(1 {a.rate_ppm:+.1f} ppm) {a.offset_s:+.4f} s; match {a.quality:.4f}",
            c0_said(fit),
            f"normal: ΔC/C0 = {c2:.6f}·F² + {c1:.5f}·F  (± {fit.normal_se[0]:.1e}, {fit.normal_se[1]:.1e})",
            f"shear:  ΔC/C0 = {fit.shear[0]:.5f}·F − {fit.shear[1]:.6f}·F²  (± {fit.shear_se[0]:.1e}, {fit.shear_se[1]:.1e})",
            coupling_said(fit),
            f"residual RMS through the model: Fx {fit.rms_N[0]:.4f}, Fy {fit.rms_N[1]:.4f}, Fz {fit.rms_N[2]:.4f} N "
            f"over {fit.frames} loaded frames; loads {fit.loads}"] + [
            f"{axis} response flat above {flat:.1f} N (the session pressed on without it rising): fitted where it "
            f"rises, usable to {usable:.1f} N; past that the force is held there and flagged {flag} (σ null)"
            for axis, flat, usable, flag in (("Fz", fit.flat_N[0], fit.usable_N[0], "normal_out_of_range"),
                                             ("shear", fit.flat_N[1], fit.usable_N[1], "shear_out_of_range"))
            if flat is not None] + (
            [f"shear usable to {fit.usable_N[1]:.1f} N, the largest shear the session pressed: past it the curve "
             "is not measured and may turn (a larger force would read smaller), so the force is held there and "
             "flagged shear_out_of_range (σ null)"] if fit.flat_N[1] is None and fit.usable_N[1] == fit.shear_reach_N else [])


def coupling_said(fit: QuadFit) -> str:
    """The summary's line on the coupling c: fitted, not shown, or not
    determined (shear under one normal load) and how to measure it."""
    if fit.coupling_kept:
        return f"coupling: c = {fit.coupling:.3f} ± {fit.coupling_se:.3f} (normal load reduces the shear response)"
    if fit.coupling_fitted is not None and fit.coupling_fitted[0] < -COUPLING_SIGMAS * fit.coupling_fitted[1]:
        c, se = fit.coupling_fitted
        return (f"coupling: the data gave c = {c:.2f} ± {se:.2f}, normal load raising the shear response, which the "
                "model does not hold (c ≥ 0): fitted without it, the shear curve is the one under "
                f"{fit.shear_preload_N[0]:.1f} N (the mean normal load under the shear), and shear read under other "
                f"normal loads carries c = 0 ± {fit.coupling_se:.2f} in its σ")
    if fit.coupling_fitted is not None:
        c, se = fit.coupling_fitted
        return (f"coupling: not shown by the data: c = {c:.3f} ± {se:.3f} (within {COUPLING_SIGMAS:g}σ of 0), "
                f"fitted without it (c = 0 ± {fit.coupling_se:.3f}, in the shear's σ away from "
                f"{fit.shear_preload_N[0]:.1f} N, the mean normal load under the shear)")
    preload, spread = fit.shear_preload_N
    model = QuadModel.from_fits(fit.normal, fit.shear, 0.0, fit.usable_N[0], fit.usable_N[1])
    return (f"coupling: not determined: the shear was pressed under one normal load ({preload:.1f} N, spread "
            f"{spread:.2f} N, need ≥ {COUPLING_MIN_SPREAD_N:g} N), where a coupling c (normal load reducing the shear "
            "response) and the shear slope change the response alike; c = 0 (the model's default), the shear curve "
            f"is the one under {preload:.1f} N, and shear read under other normal loads carries in its σ what c may "
            f"make of it (c taken as 0 ± {undetermined_coupling_se(model):.2f}, a third of the largest the model holds)"
            f"; to measure c, press shear under two preloads at least {2 * COUPLING_MIN_SPREAD_N:g} N apart "
            "(e.g. 3 and 9 N)")


def c0_said(fit: QuadFit) -> str:
    """The summary's line on C0: how far it moved over the session (the
    most of an electrode's, and as Fz on the fitted curve's small-force
    slope) and between how many rests it was followed."""
    moved = f"C0 moved {100 * fit.c0_moved:.1f} % during the session (as much as {fit.c0_moved / fit.normal[1]:.2f} N of Fz)"
    if fit.c0_rests < 2:
        return f"{moved}; fewer than two rest stretches of {REST_MIN_S:g} s: one C0 (the unloaded frames' mean) throughout"
    return f"{moved}, followed linearly between its {fit.c0_rests} rest stretches"

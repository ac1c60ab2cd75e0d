"""Each sensor's calibration and what it gives.

A sensor is reconstructed with the papers' calibration (table 1 for a grid,
fits 34/35 for a quad) unless one was uploaded for it; ``validated_upload``
checks an upload and names the bad field and why (the API answers 422).
``processor_for`` builds the sensor's processor from its calibration,
``tare_window`` the readings a tare may take.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import GridCalibration, grid_calibration
from ..physics.quad_model import NOMINAL_C0_PF, QuadModel
from ..physics.taxel_response import SENSITIVITY_RANGE_PCT_PER_N, table_top, taxel_response
from ..readings import SensorInfo
from .grid import GridProcessor
from .level0 import tare_window_pF
from .quad import QuadProcessor


def processor_for(info: SensorInfo, level: str, mounting: str,
                  uploaded: GridCalibration | QuadModel | None) -> GridProcessor | QuadProcessor:
    """The sensor's processor at ``level``, on its uploaded calibration if
    there is one of its kind."""
    if info.kind == "quad":
        return QuadProcessor(level, uploaded) if isinstance(uploaded, QuadModel) else QuadProcessor(level)
    calibration = uploaded if isinstance(uploaded, GridCalibration) else grid_calibration(info.rows, info.cols)
    response = None if level == "level0" else taxel_response(calibration, mounting)
    return GridProcessor(level, calibration, response, table_top(mounting))


def tare_window(info: SensorInfo, mounting: str,
                uploaded: GridCalibration | QuadModel | None) -> tuple[np.ndarray, np.ndarray]:
    """Readings a tare may take (level0.py): the plausible window around
    the nominal C0 (table 1's; a quad's NOMINAL_C0_PF), widened."""
    if info.kind == "quad":
        model = uploaded if isinstance(uploaded, QuadModel) else QuadModel()
        return tare_window_pF(np.full(info.channels, NOMINAL_C0_PF), model.top_relative)
    return tare_window_pF(grid_calibration(info.rows, info.cols).c0_pF, table_top(mounting))


def validated_upload(info: SensorInfo, upload: dict, mounting: str) -> tuple[GridCalibration | QuadModel, dict]:
    """(calibration, what is applied) of an uploaded calibration; ValueError
    names the bad field and why.

    Grid: ``sensitivity_pct_per_N``, one per taxel (rows*cols), each
    finite and within (0.1, 10) %/N (table 1: 1.22–1.27 %/N); the
    per-taxel response built from them must be finite and strictly
    increasing over each taxel's range and its inverse must give the
    forces back within 0.002 N (TaxelResponse.check).

    Quad: ``normal_fit`` [c2, c1] of ΔC/C0 = c2 F² + c1 F and
    ``shear_fit`` [a, b] of ΔC/C0 = a F − b F² (QuadModel.from_fits):
    all finite; c1 and a within (0.001, 1) per N (fits 34/35: 0.0343,
    0.0077); c2 ≤ 0 and b ≥ 0, each small enough that the curve stays
    usable (slope ≥ 10 % of its initial value) to at least 1 N, i.e.
    |c2| ≤ 0.45·c1 and b ≤ 0.45·a; the usable range is 0.9·c1/(2|c2|)
    (0.9·a/(2b)) capped at 50 N, and 50 N for a linear curve (c2 = 0 or
    b = 0, accepted). The model's forward must be finite and strictly
    increasing over the usable ranges and its inverse give the forces
    back (within 1e-6 N + 1e-6 relative).
    """
    if info.kind == "grid":
        return _grid_upload(info, upload, mounting)
    return _quad_upload(upload)


def _grid_upload(info: SensorInfo, upload: dict, mounting: str) -> tuple[GridCalibration, dict]:
    try:
        values = np.asarray(upload.get("sensitivity_pct_per_N", []), dtype=float)
    except (TypeError, ValueError):
        raise ValueError("sensitivity_pct_per_N: expected a list of numbers") from None
    if values.shape != (info.channels,):
        raise ValueError(f"sensitivity_pct_per_N: expected {info.channels} values (rows*cols), got {values.size}")
    low, high = SENSITIVITY_RANGE_PCT_PER_N
    bad = np.flatnonzero(~((values > low) & (values < high)))  # NaN fails both
    if bad.size:
        raise ValueError(f"sensitivity_pct_per_N[{bad[0]}] = {values[bad[0]]} is outside ({low:g}, {high:g}) %/N")
    base = grid_calibration(info.rows, info.cols)
    calibration = GridCalibration(info.rows, info.cols, base.c0_pF, values / 100.0)
    try:
        taxel_response(calibration, mounting).check()
    except ValueError as exc:
        raise ValueError(f"sensitivity_pct_per_N: {exc}") from None
    return calibration, {"sensitivity_pct_per_N": values.tolist()}


def _quad_upload(upload: dict) -> tuple[QuadModel, dict]:
    if "normal_fit" not in upload or "shear_fit" not in upload:
        raise ValueError("a quad calibration needs normal_fit [c2, c1] and shear_fit [a, b]")
    model = QuadModel.from_fits(upload["normal_fit"], upload["shear_fit"])
    c2, c1, _ = model.normal_fit
    return model, {"normal_fit": [c2, c1], "shear_fit": [model.shear_a, model.shear_b],
                   "normal_usable_N": model.normal_usable_N, "shear_usable_N": model.shear_usable_N}

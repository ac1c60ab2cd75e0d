"""Each sensor's calibration and what it gives; an upload made a calibration document.

A sensor is reconstructed with its SensorCalibration (sensor_calibration.py:
its own from the registry or a recording, else the papers' built-in one).
``upload_document`` turns what ``PUT /sensors/{id}/calibration`` accepts into
a registry document and checks it, naming the bad field and why (the API
answers 422). ``processor_for`` builds the sensor's processor from its
calibration, ``tare_window`` the readings a tare may take: around the C0
the calibration expects (``expected_c0``), the sensor's own where it was
measured, else the papers' nominal one.
"""
from __future__ import annotations

from datetime import datetime, timezone
from functools import partial

import numpy as np

from ..physics.paper_data import GridCalibration, grid_calibration
from ..physics.quad_model import NOMINAL_C0_PF, QuadModel
from ..physics.taxel_response import SENSITIVITY_RANGE_PCT_PER_N, table_top, taxel_response
from ..readings import SensorInfo
from .crosstalk import Crosstalk
from .grid import GridProcessor
from .level0 import own_level_window, tare_window_pF
from .quad import QuadProcessor
from .sensor_calibration import SCHEMA, SensorCalibration, calibration_id, check_c0, from_document, quad_c0


def processor_for(info: SensorInfo, level: str, mounting: str,
                  calibration: SensorCalibration) -> GridProcessor | QuadProcessor:
    """The sensor's processor at ``level`` on ``calibration``; crosstalk
    measured in a calibration session is the full level's starting point."""
    if info.kind == "quad":
        return QuadProcessor(level, calibration.quad, calibration.quad_relative_se, calibration.quad_model_sigma_N,
                             calibration.quad_electrode_gain_se, calibration.quad_coupling_sigma)
    crosstalk = None
    if level == "full" and calibration.crosstalk is not None:
        crosstalk = Crosstalk(info.rows, info.cols, *calibration.crosstalk)
    return GridProcessor(level, calibration.grid, None if level == "level0" else calibration.response,
                         table_top(mounting), crosstalk, gain_relative_se=calibration.gain_relative_se,
                         model_sigma_N=calibration.model_sigma_N, calibrated_to_N=calibration.calibrated_to_N,
                         curves=calibration.curves,
                         tare_window=tare_window(info, mounting, calibration))


def tare_window(info: SensorInfo, mounting: str, calibration: SensorCalibration) -> tuple[np.ndarray, np.ndarray]:
    """Readings (n,) low, high pF a tare may take (level0.py): the plausible
    window around the C0 the calibration expects (``expected_c0``), widened."""
    return tare_window_pF(expected_c0(info, calibration), _top(info, mounting, calibration))


def own_level(info: SensorInfo, mounting: str, calibration: SensorCalibration):
    """The window around a finished tare's own level (level0.own_level_window), for the sensor's Baseline:
    against the calibration's C0 pattern (a sensor whose taxels' C0 differ 2.5× is not faulty)."""
    nominal = calibration.grid.c0_pF if info.kind == "grid" else expected_c0(info, calibration)
    return partial(own_level_window, nominal_c0_pF=nominal, top_relative=_top(info, mounting, calibration))


def expected_c0(info: SensorInfo, calibration: SensorCalibration) -> np.ndarray:
    """The C0 (n,) pF a tare expects: the calibration's measured C0 where it
    has one (a sensor's own, which may be 0.4 pF taxels or 17 pF electrodes),
    else the papers' nominal (table 1's; a quad's NOMINAL_C0_PF) — on a
    partly measured sensor scaled by the measured channels' median ratio
    to it, the sensor's own level."""
    if info.kind == "quad":
        nominal = np.full(info.channels, NOMINAL_C0_PF)
    else:
        nominal = grid_calibration(info.rows, info.cols).c0_pF
    measured = calibration.measured_c0_pF
    if measured is None:
        return nominal
    level = float(np.nanmedian(measured / nominal))
    return np.where(np.isnan(measured), nominal * level, measured)


def _top(info: SensorInfo, mounting: str, calibration: SensorCalibration) -> float:
    """The largest ΔC/C0 the sensor's model explains (level0.py's r_top)."""
    return calibration.quad.top_relative if info.kind == "quad" else table_top(mounting)


def upload_document(info: SensorInfo, upload: dict, mounting: str, sensor: dict | None = None) -> dict:
    """The registry document (with its id) of an upload, checked by building
    the calibration from it; ValueError names the bad field and why.

    An upload is a whole calibration document (``tactile calibrations
    export``; it has ``schema``), or the short forms:

    Grid: ``sensitivity_pct_per_N``, one per taxel (rows*cols), each
    finite and within (0.1, 10) %/N (table 1: 1.22–1.27 %/N); the
    per-taxel response built from them must be finite and strictly
    increasing over each taxel's range and its inverse must give the
    forces back within 0.002 N (TaxelResponse.check). Optional ``c0_pF``
    (rows*cols, measured unloaded capacitances) lets a tare tell a load.

    Quad: ``normal_fit`` [c2, c1] of ΔC/C0 = c2 F² + c1 F and
    ``shear_fit`` [a, b] of ΔC/C0 = a F − b F², checked by
    QuadModel.from_fits (physics/quad_model.py lists the ranges); optional
    ``c0_pF`` (4, measured unloaded capacitances) sets the window a tare takes
    and lets a tare tell a load.

    ``sensor`` (the registry's identity of the sensor) is stored in the
    document, so the same numbers on two sensors are two calibrations.
    """
    if "schema" in upload:
        document = {k: v for k, v in upload.items() if k != "id"}
        given = upload.get("id")
        if given is not None and given != calibration_id(document):
            raise ValueError(f"id: {given} does not match the document's content (which gives "
                             f"{calibration_id(document)}): edited or corrupt")
        named = (document.get("sensor") or {}).get("key") if isinstance(document.get("sensor"), dict) else None
        if sensor is not None and named != sensor["key"]:  # the registry would file it under another sensor
            raise ValueError(f"sensor: this document calibrates {named or 'no named sensor'}, not this sensor "
                             f"({sensor['key']}); export the document of this sensor, or upload its numbers "
                             f"in the short form")
    elif info.kind == "grid":
        document = _grid_document(info, upload, mounting)
    else:
        document = _quad_document(upload)
    if sensor is not None and "schema" not in upload:
        document["sensor"] = sensor
    document["id"] = calibration_id(document)
    from_document(document, info, mounting)  # the checks
    return document


def _grid_document(info: SensorInfo, upload: dict, mounting: str) -> dict:
    values = _values(upload, "sensitivity_pct_per_N", info.channels)
    low, high = SENSITIVITY_RANGE_PCT_PER_N
    bad = np.flatnonzero(~((values > low) & (values < high)))  # NaN fails both
    if bad.size:
        raise ValueError(f"sensitivity_pct_per_N[{bad[0]}] = {values[bad[0]]} is outside ({low:g}, {high:g}) %/N")
    measured = upload.get("c0_pF") is not None
    c0 = _values(upload, "c0_pF", info.channels) if measured else grid_calibration(info.rows, info.cols).c0_pF
    check_c0("c0_pF", c0)
    try:
        response = taxel_response(GridCalibration(info.rows, info.cols, c0, values / 100.0), mounting)
        response.check()
    except ValueError as exc:
        raise ValueError(f"sensitivity_pct_per_N: {exc}") from None
    n = info.channels
    return {"schema": SCHEMA, "kind": "grid", "rows": info.rows, "cols": info.cols, "mounting": mounting,
            "created": _now(), "c0_measured": measured, "note": "uploaded sensitivities",
            "taxels": {"gain": response.gain.tolist(), "gain_se": [None] * n, "c0_pF": c0.tolist(),
                       "sensitivity_pct_per_N": values.tolist(), "model": ["table"] * n, "source": ["upload"] * n,
                       "curves": {}}}


def _quad_document(upload: dict) -> dict:
    if "normal_fit" not in upload or "shear_fit" not in upload:
        raise ValueError("a quad calibration needs normal_fit [c2, c1] and shear_fit [a, b]")
    model = QuadModel.from_fits(upload["normal_fit"], upload["shear_fit"])
    c0 = quad_c0(upload.get("c0_pF"))
    return {"schema": SCHEMA, "kind": "quad", "created": _now(), "note": "uploaded fits",
            "normal_fit": [model.normal_fit[0], model.normal_fit[1]], "shear_fit": [model.shear_a, model.shear_b],
            "normal_usable_N": model.normal_usable_N, "shear_usable_N": model.shear_usable_N,
            **({} if c0 is None else {"c0_pF": c0.tolist()})}


def _values(upload: dict, name: str, n: int) -> np.ndarray:
    if isinstance(upload.get(name), list) and any(isinstance(v, bool) for v in upload[name]):
        raise ValueError(f"{name}: expected a list of numbers, not true/false")
    try:
        values = np.asarray(upload.get(name, []), dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a list of numbers") from None
    if values.shape != (n,):
        raise ValueError(f"{name}: expected {n} values (rows*cols), got {values.size}")
    return values


def _now() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")

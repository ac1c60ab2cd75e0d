"""A sensor's calibration as the reconstruction uses it, built from a registry document.

A document (docs/calibration.md; ``tactile calibrate`` and the registry make
them) is JSON; ``from_document`` checks it against the sensor it is applied
to and names the bad field. What it carries, per kind:

grid  ``taxels``: ``gain`` (n,) compliance gains of the model curve (κ in
      physics/taxel_response.py), ``gain_se`` (n,) their standard errors
      (null: unknown; 0 to the gain), ``c0_pF`` (n,) unloaded capacitances,
      ``curves`` {taxel: {force_N, relative}} monotone empirical curves that
      replace the model for those taxels (forces 0 to force_max_N, 471 N;
      ΔC/C0 what taxels of GAIN_RANGE read there, ±CURVE_TOLERANCE),
      ``residual_rms_N`` (n,) (0 to 471 N); optional ``sensitivity_pct_per_N`` (n,)
      (level0's slopes, 0.1–10 %/N as an upload's; null: the curve's),
      ``max_force_N`` (n,) the largest force pressed (up to 471 N), and
      ``crosstalk`` {mechanical, electrical} measured in the session.
quad  ``normal_fit`` [c2, c1], ``shear_fit`` [a, b] (QuadModel.from_fits),
      optional ``normal_fit_se``/``shear_fit_se`` (the standard errors of
      the two coefficients, not negative; c1's and a's are used, at most c1
      and a), ``statistics.rms_N`` {x, y, z} (0 to the axis's usable force), and
      ``normal_usable_N``/``shear_usable_N``: where the session's response
      stopped rising (past them a force is held and flagged); optional
      ``c0_pF`` (4,) the electrodes' unloaded capacitances its session
      measured (``tactile calibrate``), which set the window a tare takes
      and judge it (loaded_tare.judge_quad); optional ``coupling`` c,
      ``coupling_se`` (null: not determined) and ``shear_preload_N``, the
      normal force the shear slope was measured under: with c = 0 (not
      fitted) shear read under another normal load may be off by
      c·(n(Fz) − n(preload)) of itself, which σ carries
      (``quad_coupling_sigma``), with c's σ a third of the largest coupling
      the model holds when not determined (the session pressed shear under
      one normal load: nothing tells c; the paper gives no figure, the
      model's bound is c·n(top) ≤ 0.9, 2.4 on a quad like fits 34/35).
both  ``created``: an ISO 8601 string (absent: not known).

``builtin`` is what a sensor without a calibration of its own uses: table 1
(8x8; the table's mean for other shapes) or fits 34/35. Its gain error is
not a fit's: it is how far a sensor that is not the paper's may be from it —
the issue's measured array differed from table 1 by up to ±12 % in
sensitivity (uniform: σ = 12 %/√3 ≈ 7 %), so 7 % per taxel, and likewise
for the quad's two slopes; and each quad electrode's gain about the
others', which reads as shear (ELECTRODE_GAIN_SE: table 1's within-array
spread; also a quad document's whose fit did not measure its shear
residual). Its C0 was not measured on this sensor, so it cannot tell a
loaded tare (``measured`` False for every taxel).
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field

import numpy as np

from ..physics.mountings import MOUNTINGS
from ..physics.paper_data import (BUILTIN_GRID_ID, BUILTIN_QUAD_ID, TABLE1_COLS, TABLE1_ROWS, GridCalibration,
                                  grid_calibration)
from ..physics.quad_model import QuadModel, max_coupling
from ..physics.taxel_response import SENSITIVITY_RANGE_PCT_PER_N, TaxelResponse, model_table, taxel_response
from ..readings import SensorInfo
from .crosstalk import Crosstalk
from .fatigue import PAPER_001, FatigueModel

ID_HEX = 16
SCHEMA = 1  # the calibration document's format (registry documents, uploads, exports)
BUILTIN_RELATIVE_SE = 0.07
# A quad's four electrodes are made together, so each one's gain about the others is assumed to spread as
# the taxels of one array do: table 1's 64 sensitivities, std/mean = 0.0106/1.247 %/N = 0.85 %. Unlike the
# common gain (BUILTIN_RELATIVE_SE) it reads as shear: ±2 % between the X sides read 12 N as Fx = −0.79 N.
ELECTRODE_GAIN_SE = 0.0085
# Plausible gains: those of the uploadable sensitivities (0.1–10 %/N) on the
# flat table, whose slope at gain 1 is ~1.25 %/N.
GAIN_RANGE = (SENSITIVITY_RANGE_PCT_PER_N[0] / 1.25, SENSITIVITY_RANGE_PCT_PER_N[1] / 1.25)
# A flexible sensor's unloaded taxel: tens of fF to a nF (table 1: 10–11 pF; the quad's electrodes 2.2 pF).
# Outside, a C0 is a unit slip (F for pF) or garbage: 1e-300 pF made every taxel "loaded", no tare possible.
C0_RANGE_PF = (0.01, 1000.0)
# How far an empirical curve's ΔC/C0 may stray from what taxels of a plausible gain read at its
# forces (its start's noise and offset): 25× a table-1 taxel's reading noise (2 fF on 10 pF), ~0.4 N at gain 1.
CURVE_TOLERANCE = 0.005


def canonical(document: dict) -> bytes:
    """The document without ``id`` as canonical JSON (sorted keys, compact,
    UTF-8, no NaN); ValueError naming the first field that is not a JSON number."""
    body = {k: v for k, v in document.items() if k != "id"}
    try:
        return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()
    except ValueError:
        found = _non_finite(body)
        if found is None:
            raise
        raise ValueError(f"{found[0]} = {found[1]} is not a JSON number (a calibration document holds no NaN "
                         "or Infinity)") from None


def _non_finite(value, where: str = "") -> tuple[str, float] | None:
    """(path, value) of the first NaN or infinite float in a JSON-like value, None if none."""
    if isinstance(value, float) and not math.isfinite(value):
        return where, value
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list | tuple) else ()
    for key, item in items:
        found = _non_finite(item, f"{where}[{key}]" if isinstance(key, int) else f"{where}.{key}" if where else key)
        if found:
            return found
    return None


def calibration_id(document: dict) -> str:
    """A calibration's id: the first ID_HEX hex digits of the sha256 of its
    canonical JSON, so the same content always has the same id."""
    return hashlib.sha256(canonical(document)).hexdigest()[:ID_HEX]


@dataclass(frozen=True)
class SensorCalibration:
    """What one sensor is reconstructed with. Grid arrays have shape (n,),
    n = rows*cols, row-major."""

    id: str
    kind: str  # "grid" | "quad"
    created: str | None  # ISO 8601, None for the built-in
    measured: np.ndarray | None  # grid (n,) bool: C0 measured on this sensor (a loaded tare can be told there)
    grid: GridCalibration | None = None  # C0 and LS sensitivity (level0 uses it)
    response: TaxelResponse | None = None  # the model curve with each taxel's gain
    gain_relative_se: np.ndarray | None = None  # (n,) σ(κ)/κ
    model_sigma_N: np.ndarray | None = None  # (n,) what an empirical curve leaves (its residual RMS), else 0
    curves: dict = field(default_factory=dict)  # taxel → (relative (m,), force (m,)) of an empirical inverse
    crosstalk: tuple[float, float] | None = None  # (mechanical, electrical) measured in the session
    quad: QuadModel | None = None
    quad_relative_se: tuple[float, float] = (BUILTIN_RELATIVE_SE, BUILTIN_RELATIVE_SE)  # normal, shear slopes
    quad_model_sigma_N: tuple[float, float, float] = (0.0, 0.0, 0.0)  # Fx, Fy, Fz residual RMS of a quad's fit
    quad_electrode_gain_se: float = ELECTRODE_GAIN_SE  # σ/value of each electrode's gain about the others'
    # (σ of a coupling left out of the model, the normal ΔC/C0 the shear slope was measured under); None: none
    quad_coupling_sigma: tuple[float, float] | None = None
    fatigue: FatigueModel | None = None  # sensitivity lost to load cycles (fatigue.py); None: not compensated
    tare_c0_pF: np.ndarray | None = None  # grid (n,): C0 as the multiplexer reads it (leakage applied), what a tare sees
    calibrated_to_N: np.ndarray | None = None  # grid (n,): the largest force its session pressed; None: unknown
    quad_c0_pF: np.ndarray | None = None  # quad (4,): C0 its session measured; None: not measured
    document: dict | None = field(default=None, compare=False, repr=False)

    @property
    def builtin(self) -> bool:
        return self.id.startswith("builtin")

    @property
    def measured_c0_pF(self) -> np.ndarray | None:
        """(n,) pF: the C0 measured on this sensor as a tare reads it (a grid's
        leakage applied), NaN where not measured; None when none was."""
        if self.quad_c0_pF is not None:
            return self.quad_c0_pF
        if self.measured is None or not self.measured.any():
            return None
        return np.where(self.measured, self.tare_c0_pF, np.nan)


def builtin(info: SensorInfo, mounting: str = "flat") -> SensorCalibration:
    """Table 1 (or its mean) for a grid, fits 34/35 for a quad."""
    if info.kind == "quad":
        return SensorCalibration(BUILTIN_QUAD_ID, "quad", None, None, quad=QuadModel(), fatigue=PAPER_001)
    base = grid_calibration(info.rows, info.cols)
    n = info.channels
    cid = BUILTIN_GRID_ID if (info.rows, info.cols) == (TABLE1_ROWS, TABLE1_COLS) else f"builtin-mean-{info.rows}x{info.cols}"
    return SensorCalibration(cid, "grid", None, np.zeros(n, dtype=bool), base, taxel_response(base, mounting),
                             np.full(n, BUILTIN_RELATIVE_SE), np.zeros(n))


def from_document(document: dict, info: SensorInfo, mounting: str = "flat") -> SensorCalibration:
    """The calibration a registry document describes, for ``info``;
    ValueError naming the field and why."""
    if not isinstance(document, dict):
        raise ValueError("a calibration document is a JSON object")
    cid = document.get("id")
    if not isinstance(cid, str) or not cid:
        raise ValueError("id: a calibration document needs its id")
    if document.get("kind") != info.kind:
        raise ValueError(f"kind: calibration {cid} is for a {document.get('kind')!r} sensor, sensor {info.id} is a {info.kind}")
    if info.kind == "quad":
        return _quad(document, cid)
    if (document.get("rows"), document.get("cols")) != (info.rows, info.cols):
        raise ValueError(f"rows, cols: calibration {cid} is for a {document.get('rows')}x{document.get('cols')} grid, "
                         f"sensor {info.id} is {info.rows}x{info.cols}")
    return _grid(document, cid, info, _mounting(document, mounting))


def _mounting(document: dict, mounting: str) -> str:
    """The document's ``mounting`` (absent: ``mounting``, the service's);
    ValueError unless one of MOUNTINGS: a list was a TypeError (unhashable),
    {}, 0 and null were stored and the service's taken in their place."""
    if "mounting" not in document:
        return mounting
    given = document["mounting"]
    if not isinstance(given, str) or given not in MOUNTINGS:
        raise ValueError(f"mounting: {given!r} is not one of {', '.join(MOUNTINGS)}")
    return given


def _created(document: dict) -> str | None:
    """The document's ``created`` (ISO 8601; absent: not known); ValueError
    unless a string: /health tells its age and the registry files it as text
    (created = 1 was stored and /health answered 500 at every start)."""
    if "created" not in document:
        return None
    created = document["created"]
    if not isinstance(created, str):
        raise ValueError(f"created: expected an ISO 8601 time as a string, got {created!r}")
    return created


def force_max_N(mounting: str) -> float:
    """The largest force (N) a taxel of ``mounting`` can be calibrated to:
    where the model table's gap closes at the lowest plausible gain (37.7 N
    at gain 1 on both mountings, so 471 N at 0.08, i.e. 0.1 %/N). An
    empirical curve's or a session's force past it is a unit slip (g, mN)
    or garbage: a curve to 1e9 N read a 5 N load as 1.1e8 N, unflagged."""
    return float(model_table(mounting).force_N[-1]) / GAIN_RANGE[0]


def check_for_its_sensor(document: dict) -> None:
    """ValueError naming the field when the service could not use ``document``
    on a sensor of the kind and shape it declares (from_document's own checks):
    stored anyway, it would only be refused at use, the built-in taken instead."""
    kind, rows, cols = document.get("kind"), document.get("rows"), document.get("cols")
    if kind == "quad":
        info = SensorInfo(0, "quad", 2, 2)
    elif kind == "grid":
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (rows, cols)):
            raise ValueError(f"rows, cols: {rows!r}, {cols!r} is not a grid's shape (two positive integers)")
        info = SensorInfo(0, "grid", rows, cols)
    else:
        raise ValueError(f"kind: {kind!r} is neither 'grid' nor 'quad'")
    from_document({**document, "id": calibration_id(document)}, info)


def check_c0(name: str, c0: np.ndarray) -> None:
    """ValueError naming the first C0 outside C0_RANGE_PF."""
    low, high = C0_RANGE_PF
    bad = np.flatnonzero(~((c0 >= low) & (c0 <= high)))  # NaN fails both
    if bad.size:
        raise ValueError(f"{name}[{bad[0]}] = {c0[bad[0]]:g} pF is outside [{low:g}, {high:g}] pF")


def _numbers(taxels: dict, name: str, n: int, missing_ok: bool = False) -> np.ndarray:
    values = taxels.get(name)
    if values is None and missing_ok:
        return np.full(n, np.nan)
    if isinstance(values, list) and len(values) != n:
        raise ValueError(f"taxels.{name}: {len(values)} values for the {n} taxels")
    if not _number_list(values):
        raise ValueError(f"taxels.{name}: expected a list of {n} numbers")
    if not missing_ok and None in values:  # float(None) would pass as NaN
        raise ValueError(f"taxels.{name}[{values.index(None)}] is null: expected a number")
    try:
        out = np.array([np.nan if v is None and missing_ok else v for v in values], dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"taxels.{name}: expected a list of {n} numbers") from None
    bad = np.flatnonzero(~np.isfinite(out) & ~(missing_ok & np.isnan(out)))
    if bad.size:
        raise ValueError(f"taxels.{name}[{bad[0]}] = {out[bad[0]]} is not finite")
    return out


def _check_within(name: str, values: np.ndarray, low: float, high: float, unit: str, high_in: bool = False,
                  low_in: bool = False) -> None:
    """ValueError naming the first of ``values`` (n,) outside (low, high), the
    ends included with ``low_in``, ``high_in``; NaN (a null: not known) passes."""
    above = values > high if high_in else values >= high
    below = values < low if low_in else values <= low
    bad = np.flatnonzero(below | above)
    if bad.size:
        raise ValueError(f"taxels.{name}[{bad[0]}] = {values[bad[0]]:g} is outside "
                         f"{'[' if low_in else '('}{low:.3g}, {high:.3g}{']' if high_in else ')'} {unit}")


def _gain_relative_se(se: np.ndarray, gain: np.ndarray) -> np.ndarray:
    """σ(κ)/κ (n,) of standard errors ``se`` (n,), NaN where not known (the
    built-in's then); ValueError naming the first outside [0, its gain]
    (_check_standard_error). Fits give ~0.5 % (tactile calibrate), the
    built-in 7 %. -1e150 gave σ 1e150 N, 1e300 an infinite σ (null:
    saturated) beside a force, unflagged."""
    bad = np.flatnonzero((se < 0) | (se > gain))
    if bad.size:
        _check_standard_error(f"taxels.gain_se[{bad[0]}]", float(se[bad[0]]), "the taxel's gain", float(gain[bad[0]]))
    return np.where(np.isnan(se), BUILTIN_RELATIVE_SE, se / gain)


def _check_standard_error(field: str, error: float, of: str, value: float = math.inf) -> None:
    """ValueError naming ``field`` unless the standard ``error`` of ``of`` lies within [0, ``value``], ``of``'s
    value (inf: nothing bounds it): a standard error is not negative, and one past the value leaves that
    value undetermined (its 1-σ interval reaches 0: no sensitivity at all)."""
    if not 0.0 <= error <= value:
        bound = f"[0, {value:.4g}]" if math.isfinite(value) else "[0, inf)"
        raise ValueError(f"{field} = {error:g} is outside {bound}, {of}: a standard error is not negative, nor past "
                         "the value it is of (that is then undetermined)")


def _number_list(values) -> bool:
    """Whether ``values`` is a list with no true/false or string in it (numpy takes true and "1" as 1.0)."""
    return isinstance(values, list) and not any(isinstance(v, bool | str) for v in values)


def _grid(document: dict, cid: str, info: SensorInfo, mounting: str) -> SensorCalibration:
    if mounting not in MOUNTINGS:
        raise ValueError(f"mounting: {mounting!r} is not one of {', '.join(MOUNTINGS)}")
    taxels = document.get("taxels")
    if not isinstance(taxels, dict):
        raise ValueError("taxels: expected an object of per-taxel lists")
    n = info.channels
    gain = _numbers(taxels, "gain", n)
    low, high = GAIN_RANGE
    bad = np.flatnonzero(~((gain > low) & (gain < high)))
    if bad.size:
        raise ValueError(f"taxels.gain[{bad[0]}] = {gain[bad[0]]} is outside ({low:g}, {high:g})")
    c0 = _numbers(taxels, "c0_pF", n)
    check_c0("taxels.c0_pF", c0)
    relative_se = _gain_relative_se(_numbers(taxels, "gain_se", n, missing_ok=True), gain)
    table = model_table(mounting)
    response = TaxelResponse(table.force_N, table.relative_change, gain, table.dense)
    response.check()
    force_max = force_max_N(mounting)
    # an RMS residual in N: none past the largest force a taxel can be calibrated to (1e300 made σ infinite)
    residual = _numbers(taxels, "residual_rms_N", n, missing_ok=True)
    _check_within("residual_rms_N", residual, 0.0, force_max, "N", high_in=True, low_in=True)
    curves, model_sigma = _curves(taxels.get("curves"), n, residual, force_max, table)
    reach = _numbers(taxels, "max_force_N", n, missing_ok=True) if "max_force_N" in taxels else np.full(n, np.nan)
    _check_within("max_force_N", reach, 0.0, force_max, "N", high_in=True)
    # level0 divides by it: 0.0001 %/N read a 5 N load as 5.5e4 N, -1.25 as -4.4 N, with a small σ
    sensitivity = _numbers(taxels, "sensitivity_pct_per_N", n, missing_ok=True)
    _check_within("sensitivity_pct_per_N", sensitivity, *SENSITIVITY_RANGE_PCT_PER_N, "%/N")
    sensitivity = np.where(np.isnan(sensitivity), _ls_sensitivity(response), sensitivity / 100.0)
    coupling = _coupling(document.get("crosstalk"))
    # C0 is this sensor's where the document says so (an upload without c0_pF
    # carries table 1's) and the taxel's values are not carried from a built-in.
    sources = taxels.get("source") if isinstance(taxels.get("source"), list) else [None] * n
    measured = np.array([bool(document.get("c0_measured", True)) and not str(src).startswith("builtin")
                         for src in sources[:n]] + [False] * (n - len(sources[:n])))
    tare_c0 = c0 if coupling is None else Crosstalk(info.rows, info.cols, *coupling).leak(c0)
    return SensorCalibration(cid, "grid", _created(document), measured,
                             GridCalibration(info.rows, info.cols, c0, sensitivity), response, relative_se, model_sigma,
                             curves, coupling, fatigue=FatigueModel.from_document(document.get("fatigue"), None),
                             tare_c0_pF=tare_c0, document=document, calibrated_to_N=np.where(reach > 0, reach, np.inf))


def _coupling(crosstalk: dict | None) -> tuple[float, float] | None:
    """(mechanical, electrical) of a document's ``crosstalk``, checked."""
    if crosstalk is None:
        return None
    try:
        coupling = (float(crosstalk.get("mechanical", 0.0)), float(crosstalk.get("electrical", 0.0)))
    except (AttributeError, TypeError, ValueError):
        raise ValueError("crosstalk: expected {mechanical: number, electrical: number}") from None
    if not (-0.05 <= coupling[0] <= 0.0 and 0.0 <= coupling[1] <= 0.3):
        raise ValueError(f"crosstalk: mechanical {coupling[0]} must be in [-0.05, 0], electrical {coupling[1]} in [0, 0.3]")
    return coupling


def _ls_sensitivity(response: TaxelResponse) -> np.ndarray:
    """The least-squares slope of each taxel's curve over 0–10 N (table 1's reading)."""
    forces = np.arange(0.0, 11.0)
    r = response.forward(forces[:, None] * np.ones(response.gain.shape))
    f = forces - forces.mean()
    return ((r - r.mean(axis=0)) * f[:, None]).sum(axis=0) / (f * f).sum()


def _curves(raw: dict | None, n: int, residual: np.ndarray, force_max: float, table) -> tuple[dict, np.ndarray]:
    """Empirical inverses {taxel: (relative, force)} and the model σ per taxel;
    a curve's forces within [0, ``force_max``] N (a compressive taxel reads no
    pull: -100..-99 N read a 5 N load as -99.9 ± 0.018 N, unflagged), its
    ΔC/C0 what a plausible taxel reads there (_check_curve_reading on the
    mounting's model ``table``)."""
    if raw is None:
        raw = {}
    if not isinstance(raw, dict):
        raise ValueError(f"taxels.curves: expected an object {{taxel: {{force_N, relative}}}}, got {raw!r}")
    curves, model_sigma = {}, np.zeros(n)
    for key, curve in raw.items():
        try:
            taxel = int(key)
            force, relative = _curve_numbers(curve["force_N"]), _curve_numbers(curve["relative"])
        except (TypeError, ValueError, KeyError):
            raise ValueError(f"taxels.curves[{key!r}]: expected {{force_N: [...], relative: [...]}}") from None
        if not 0 <= taxel < n:
            raise ValueError(f"taxels.curves[{key!r}]: taxel {taxel} is outside 0..{n - 1}")
        if force.shape != relative.shape or force.ndim != 1:
            raise ValueError(f"taxels.curves[{key!r}]: force_N ({force.size} values) and relative "
                             f"({relative.size}) are not two lists of one length")
        if force.size < 2:
            raise ValueError(f"taxels.curves[{key!r}]: {force.size} points (a curve needs at least 2)")
        if not (np.isfinite(force).all() and np.isfinite(relative).all()
                and np.all(np.diff(force) > 0) and np.all(np.diff(relative) > 0)):
            raise ValueError(f"taxels.curves[{key!r}]: must be finite and strictly increasing")
        if force[0] < 0:
            raise ValueError(f"taxels.curves[{key!r}]: force_N starts at {force[0]:g} N, below 0")
        if force[-1] > force_max:
            raise ValueError(f"taxels.curves[{key!r}]: force_N reaches {force[-1]:g} N, past {force_max:.3g} N "
                             "(where the gap of the stiffest plausible taxel closes)")
        _check_curve_reading(key, relative, force, table)
        curves[taxel] = (relative, force)
        model_sigma[taxel] = 0.0 if math.isnan(residual[taxel]) else residual[taxel]
    return curves, model_sigma


def _curve_numbers(values) -> np.ndarray:
    """A curve's list of numbers as floats; TypeError for anything else (_number_list)."""
    if not _number_list(values):
        raise TypeError(f"expected a list of numbers, got {values!r}")
    return np.asarray(values, float)


def _check_curve_reading(key: str, relative: np.ndarray, force: np.ndarray, table) -> None:
    """ValueError unless each point of an empirical curve (relative, force (m,))
    reads what a taxel of a plausible gain (GAIN_RANGE on the model ``table``)
    reads at its force, within CURVE_TOLERANCE. Outside, its inverse gives
    forces no sensor reads, with the small σ of a fit: relative [0, 1e300]
    read the press scene's 5 N as 5e-301 N ± 0.013 N, [0.5, 0.6] as 0 N,
    [-1e300, 1e300] every load as 5 N, unflagged."""
    low = np.interp(GAIN_RANGE[0] * force, table.force_N, table.relative_change) - CURVE_TOLERANCE
    high = np.interp(GAIN_RANGE[1] * force, table.force_N, table.relative_change) + CURVE_TOLERANCE
    bad = np.flatnonzero((relative < low) | (relative > high))
    if bad.size:
        i = bad[0]
        raise ValueError(f"taxels.curves[{key!r}]: relative[{i}] = {relative[i]:g} at {force[i]:g} N is outside "
                         f"[{low[i]:.3g}, {high[i]:.3g}], what taxels of gain {GAIN_RANGE[0]:g} to {GAIN_RANGE[1]:g} "
                         "read there")


def _quad_residual(document: dict, model: QuadModel) -> tuple[float, float, float]:
    """The fit's residual RMS (Fx, Fy, Fz) through the model (statistics.rms_N of a calibrated quad;
    zeros where absent: an upload of fits alone); ValueError naming a bad one, or one past its axis's
    usable force (a fit that misses by more than the range it covers explains nothing: 999 N was taken)."""
    statistics = document.get("statistics")
    if statistics is not None and not isinstance(statistics, dict):
        raise ValueError(f"statistics: expected an object, got {statistics!r}")
    rms = (statistics or {}).get("rms_N") or {}
    out = []
    for axis, usable in zip("xyz", (model.shear_usable_N, model.shear_usable_N, model.normal_usable_N)):
        value = rms.get(axis, 0.0) if isinstance(rms, dict) else None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ValueError(f"statistics.rms_N.{axis}: {value!r} is not a residual in N")
        if not 0.0 <= value <= usable:
            raise ValueError(f"statistics.rms_N.{axis}: {value:g} is outside [0, {usable:.4g}] N, the axis's "
                             "usable force")
        out.append(float(value))
    return out[0], out[1], out[2]


def _shear_residual_measured(document: dict) -> bool:
    """Whether the document's fit measured its shear residual (statistics.rms_N has x and y; checked
    by _quad_residual)."""
    rms = (document.get("statistics") or {}).get("rms_N")
    return isinstance(rms, dict) and "x" in rms and "y" in rms


def _slope_relative_se(document: dict, name: str, coefficients: tuple[str, str], slope: str, value: float) -> float:
    """σ/value of the fit's ``slope`` coefficient (of ``value``) from ``name``
    (the standard errors of its two ``coefficients``), the built-in's where
    absent; ValueError naming a bad one (_check_standard_error, as a grid
    taxel's gain_se): not negative, and the slope's at most the slope (fits
    give 0.004–0.08 %: 1e300 gave σ 3e301 N)."""
    errors = document.get(name)
    if errors is None:
        return BUILTIN_RELATIVE_SE
    if not (isinstance(errors, list) and len(errors) == 2
            and all(isinstance(e, (int, float)) and not isinstance(e, bool) for e in errors)):
        raise ValueError(f"{name}: expected the standard errors [{', '.join(coefficients)}] of {name[:-3]}, "
                         f"got {errors!r}")
    for i, (coefficient, error) in enumerate(zip(coefficients, errors)):
        _check_standard_error(f"{name}[{i}]", error, coefficient, value if coefficient == slope else math.inf)
    return float(errors[coefficients.index(slope)]) / value


def quad_c0(values) -> np.ndarray | None:
    """A quad's measured C0 (4,) pF from a document's or an upload's ``c0_pF``
    (None: not measured); ValueError naming the bad value."""
    if values is None:
        return None
    if not isinstance(values, list | tuple) or any(isinstance(v, bool) for v in values):
        raise ValueError("c0_pF: expected a list of numbers, one per electrode (C11, C12, C21, C22)")
    try:
        c0 = np.asarray(values, dtype=float)
    except (TypeError, ValueError):
        raise ValueError("c0_pF: expected a list of numbers, one per electrode (C11, C12, C21, C22)") from None
    if c0.shape != (4,):
        raise ValueError(f"c0_pF: expected 4 values (C11, C12, C21, C22), got {c0.size}")
    check_c0("c0_pF", c0)
    return c0


UNDETERMINED_COUPLING_SHARE = 1.0 / 3.0  # of the model's largest coupling: c's σ when the session could not tell it


def undetermined_coupling_se(model: QuadModel) -> float:
    """σ of a coupling the calibration session could not tell: the model's
    bound (c·n(normal usable end) ≤ 0.9) taken as its 3σ."""
    return UNDETERMINED_COUPLING_SHARE * max_coupling(model.normal_fit[:2], model.normal_usable_N)


def _coupling_sigma(document: dict, model: QuadModel) -> tuple[float, float] | None:
    """(σ of c, the normal curve's ΔC/C0 at ``shear_preload_N``) for a
    model without a coupling whose document says under which normal load its
    shear slope was measured; None otherwise (c in the model, or an older
    document); ValueError naming a bad field."""
    preload = document.get("shear_preload_N")
    if preload is None or model.coupling:
        return None
    if isinstance(preload, bool) or not isinstance(preload, (int, float)) or not 0.0 <= preload <= 1e3:
        raise ValueError(f"shear_preload_N: {preload!r} is not a normal force in N")
    se = document.get("coupling_se")
    if se is not None and (isinstance(se, bool) or not isinstance(se, (int, float)) or not 0.0 <= se < 1e3):
        raise ValueError(f"coupling_se: {se!r} is not a standard error (null: not determined)")
    return (undetermined_coupling_se(model) if se is None else float(se),
            float(model.normal_response(float(preload))))


def _quad(document: dict, cid: str) -> SensorCalibration:
    coupling = document.get("coupling")
    model = QuadModel.from_fits(document.get("normal_fit"), document.get("shear_fit"),
                                0.0 if coupling is None else coupling,
                                document.get("normal_usable_N"), document.get("shear_usable_N"))
    se = (_slope_relative_se(document, "normal_fit_se", ("c2", "c1"), "c1", model.normal_fit[1]),
          _slope_relative_se(document, "shear_fit_se", ("a", "b"), "a", model.shear_a))
    residual = _quad_residual(document, model)
    # A session's normal presses show the electrodes' mismatch as shear in its fit's residual (rms_N.x, .y),
    # which σ then carries; fits alone (an upload) measured none of it.
    mismatch = 0.0 if _shear_residual_measured(document) else ELECTRODE_GAIN_SE
    return SensorCalibration(cid, "quad", _created(document), None, quad=model, quad_relative_se=se,
                             quad_model_sigma_N=residual, quad_electrode_gain_se=mismatch,
                             quad_coupling_sigma=_coupling_sigma(document, model),
                             quad_c0_pF=quad_c0(document.get("c0_pF")),
                             fatigue=FatigueModel.from_document(document.get("fatigue"), PAPER_001), document=document)

"""Calibrating a quad sensor from a force/torque reference (paper 001's curves and §5.3 coupling).

The electrodes' ΔC/C0 combine into Z (normal), X and Y (shear) and the
redundant R (physics/quad_model.py), each electrode against its C0 where
the frame is: the mean of each rest stretch between loads, followed
linearly between them (``rest_c0``; the grid takes each taxel's C0 from the
pauses around its own presses, segmentation.py). Temperature moves C0
during a session: one C0 for all of it (the unloaded frames' mean) left a
tester's quad, warming 2 % over 100 s, at 0.20 N of Fz residual (0.012 N
without), and the drift in the noise figure made its rising curve look flat
from 13.3 N ("usable to 11.4 N"; it rose to ~19 N). The stored C0 is still
the unloaded frames' mean; how far it moved is said (``c0_moved``).
The model is

    Z = c2·Fz² + c1·Fz,     X = t(Fx)·(1 − c·n(Fz)),   Y = t(Fy)·(1 − c·n(Fz)),
    t(F) = sign(F)·(a|F| − b·F²),   n = the normal curve,

so the normal curve is a linear least-squares fit of Z on (Fz², Fz) over the
loaded frames, and the shear curve and the coupling c a nonlinear one of X
and Y on the same frames (scipy's least_squares, Jacobian-scaled), standard
errors s²(JᵀJ)⁻¹ widened by √(frames per reference sample) when the board
is faster than the reference (they share its noise). The coupling is fitted
only where the session can tell it: under one normal load n(Fz) is a
constant, and c scales the shear response exactly as a smaller a and b do
(the Jacobian's c column is a combination of a's and b's: JᵀJ is singular,
and its pseudo-inverse showed no error along that line — a tester's shear
under 2 N alone gave c = 1.921 ± 0.208, truth 1.0, what the reference's
noise on the zero-shear frames pulled it to). So c is fitted only when the
normal force under the shear (``shear_preload``: its mean and spread,
frames weighted by Fx² + Fy², their share in the slope) spreads at least
COUPLING_MIN_SPREAD_N: two preloads 2 N apart or more. A held preload
spreads by the reference's noise alone (~0.03 N), and the simulator's 3 and
9 N (spread 3 N) give c to ±0.002: at 1 N, ±0.005 there, still clear at ten
times its noise. Otherwise c is not determined: it stays 0 (the model's
default), the shear curve is the one under that preload, and the
reconstruction widens σ for what a coupling would make of shear read under
other normal loads (sensor_calibration.py). A determined c is kept only
where the data shows it: c > 3 standard errors, else the shear curve is
refitted without it — also when c < 0, which the model does not hold
(normal load raising the shear response): stored as 0 beside the slope
fitted with it, that slope was another c's (a tester's −3.75 left a at half
the sensor's, 0.44 N residual). A c left out keeps what the data said of
it as the σ of the 0 stored, √(c² + se²) (it was stored as 0 ± 0), which
the reconstruction carries as an undetermined one's. Residuals are
reported in newtons through the fitted model's inverse. The reference
(interpolated to the board's frame times through the alignment) is smooth
at the loads' pace, so interpolation adds nothing the noise does not.

A sensor's response can stop rising before the fits' turns (a dielectric
compressed solid, an overlap that cannot grow further): pressed past it,
the flat part pulled the quadratic off the rising part (a tester's quad,
flat above 14.6 N and pressed to 18 N, was fitted to 0.66 N RMS and read
22 and 30 N as 13.1 N, unflagged). So each axis's response is binned
against its force first (``flat_from``): where it comes within FLAT_SIGMAS
noise σ of its highest level and the session pressed FLAT_MIN_N further,
it is flat there; the curve is fitted below that only (reported: where the
fitted curve reaches the flat level, 14.6 N on that quad), and the axis is
usable (``normal_usable_N``/``shear_usable_N``) up to where the fitted
curve is FLAT_SIGMAS noise σ below the flat level, so a reading on the flat
part is held and flagged rather than read as a force below it. The
residual RMS (the fit's share of σ in the reconstruction) is taken over the
usable range only. A response that turns and falls past its top (a shear
curve past a/2b) is worse than flat: a larger force reads back as a smaller
one, which no single reading shows. So where the response came back down
past its top by more than FLAT_SIGMAS noise σ, the axis is usable only up to
where the fitted curve is FLAT_SIGMAS σ under the lowest level it fell to:
the session's forces past the turn read above it, held and flagged. And the
shear axis is usable no further than the largest shear the session pressed
(``shear_reach_N``): past it the curve is an extrapolation that may turn
anywhere (a sensor turning at 9.6 N, calibrated to 4.2 N, read a true 12 N
as 7.2 N and 14 N as 5.3 N unflagged); now such forces, up to the mirror of
the reach about the turn (15 N there), read at the reach, flagged
``shear_out_of_range``, σ null. The normal axis is pressed to at least half
its full scale and keeps its curve's own end. The grid refuses a non-monotone taxel instead (fit.py):
its table's shape is fixed, a quad's curves are the sensor's own, and
pressing less would not make the sensor's range any longer.

Refused, naming the reason: no unloaded stretch to take C0 from, saturated
frames, a normal range under half of NORMAL_FULL_SCALE_N or a shear range
under MIN_SHEAR_N, fewer than two loads on an axis.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..physics.quad_model import QuadModel, combinations
from ..physics.shear import shear_force
from ..physics.taxel_response import OUT_OF_RANGE_SIGMAS
from .segmentation import GUARD_S, find_runs

UNLOADED_N = 0.05
LOADED_N = 0.1
NORMAL_FULL_SCALE_N = 20.0  # fit (34)'s range
MIN_SHEAR_N = 1.0
COUPLING_SIGMAS = 3.0
COUPLING_MIN_SPREAD_N = 1.0  # the normal force under the shear spreads this far (weighted σ) for c to be fitted
REST_MIN_S = 0.1  # a rest stretch, GUARD_S clear of the loads on either side, lasts this long for a C0 of its own
FLAT_BIN_N = 0.25
FLAT_SIGMAS = OUT_OF_RANGE_SIGMAS  # a reading at the flat level is flagged as a grid's out-of-range one is
FLAT_MIN_N = 1.0  # pressed at least this far on without the response rising: a session that ends near a
# turn (its curve within noise of its top over the last few tenths of a newton) is not flat


@dataclass
class QuadFit:
    c0_pF: np.ndarray  # (4,) the unloaded frames' mean
    c0_moved: float  # the most an electrode's C0 moved over the session's rest stretches, relative
    c0_rests: int  # the rest stretches C0 was followed between (rest_c0)
    normal: tuple[float, float]  # c2, c1
    normal_se: tuple[float, float]
    shear: tuple[float, float]  # a, b
    shear_se: tuple[float, float]
    coupling: float
    coupling_se: float | None  # None: not determined (shear under one normal load); left out: √(c² + se²) as fitted
    coupling_kept: bool
    coupling_fitted: tuple[float, float] | None  # c and its standard error as fitted (None: not determined)
    shear_preload_N: tuple[float, float]  # the normal force under the shear: mean, spread (shear_preload)
    rms_N: tuple[float, float, float]  # Fx, Fy, Fz through the fitted model's inverse, within the usable ranges
    usable_N: tuple[float, float]  # normal, shear: the model's usable ends
    flat_N: tuple[float | None, float | None]  # normal, shear: where the fitted curve reaches the flat level (None: none)
    shear_reach_N: float  # the largest |Fx|, |Fy| the session pressed: the shear axis's usable end at most
    frames: int
    loads: dict  # axis → number of loads seen


def _loads(force: np.ndarray) -> int:
    return len(find_runs(np.abs(force), LOADED_N, 0.5 * np.abs(force).max())) if force.size and np.abs(force).max() > 0 else 0


def check(fxyz: np.ndarray, saturated: np.ndarray, unloaded: np.ndarray) -> dict:
    """The loads per axis; ValueError for data a fit must not be made from."""
    if unloaded.sum() < 100:
        raise ValueError(f"only {int(unloaded.sum())} unloaded frames (|F| < {UNLOADED_N} N): C0 needs an unloaded "
                         "stretch, e.g. 1 s before the first load")
    if saturated.any():
        raise ValueError(f"{int(saturated.sum())} saturated frames (the board's flag): load less")
    loads = {axis: _loads(fxyz[:, k]) for k, axis in enumerate("xyz")}
    if fxyz[:, 2].max() < 0.5 * NORMAL_FULL_SCALE_N:
        raise ValueError(f"normal force range 0–{fxyz[:, 2].max():.2f} N is under half of full scale "
                         f"({NORMAL_FULL_SCALE_N:g} N)")
    for k, axis in enumerate("xy"):  # each way: the shear curve is taken as odd, so both must be seen
        if min(fxyz[:, k].max(), -fxyz[:, k].min()) < MIN_SHEAR_N:
            raise ValueError(f"shear along {axis.upper()} reaches {fxyz[:, k].max():+.2f} N and "
                             f"−{abs(fxyz[:, k].min()):.2f} N (need ≥ {MIN_SHEAR_N:g} N both ways)")
    thin = [axis for axis, n in loads.items() if n < 2]
    if thin:
        raise ValueError(f"fewer than 2 loads along {', '.join(a.upper() for a in thin)} (need at least 2 each)")
    return loads


def rest_c0(t_s: np.ndarray, capacitance_pF: np.ndarray, unloaded: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(C0 (N, 4) pF at each frame, the rest stretches' C0 (m, 4)) from
    frames at ``t_s`` (N,) s, (N, 4) pF and the unloaded mask (N,): each rest
    stretch's mean (a run of unloaded frames, GUARD_S clear of the loads on
    either side, at least REST_MIN_S long), followed linearly between the
    stretches' mean times and held before the first and after the last. With
    fewer than two stretches, the unloaded frames' mean throughout."""
    times, levels = [], []
    for a, b in find_runs(unloaded.astype(float), 0.5, 0.5):
        t = t_s[a:b]
        inner = (t >= t[0] + GUARD_S) & (t <= t[-1] - GUARD_S)
        if inner.any() and t[inner][-1] - t[inner][0] >= REST_MIN_S:
            times.append(t[inner].mean())
            levels.append(np.nanmean(capacitance_pF[a:b][inner], axis=0))
    if len(times) < 2:
        return np.broadcast_to(np.nanmean(capacitance_pF[unloaded], axis=0), capacitance_pF.shape), np.array(levels)
    levels = np.array(levels)
    return np.stack([np.interp(t_s, times, levels[:, k]) for k in range(levels.shape[1])], axis=1), levels


def _shear_residual(params: np.ndarray, fxy: np.ndarray, normal: np.ndarray, xy: np.ndarray) -> np.ndarray:
    a, b, c = params
    t = np.sign(fxy) * (a * np.abs(fxy) - b * fxy * fxy)
    return (t * (1.0 - c * normal)[:, None] - xy).ravel()


def _shear(fxy, normal, xy, with_coupling: bool, widen: float):
    from scipy.optimize import least_squares  # offline only

    start = np.array([0.0077, 0.0004, 0.0])
    fun = (lambda p: _shear_residual(p, fxy, normal, xy)) if with_coupling else \
        (lambda p: _shear_residual(np.r_[p, 0.0], fxy, normal, xy))
    result = least_squares(fun, start if with_coupling else start[:2], x_scale="jac")
    dof = max(result.fun.size - result.x.size, 1)
    cov = np.linalg.pinv(result.jac.T @ result.jac) * float(result.fun @ result.fun) / dof * widen
    return result.x, np.sqrt(np.diag(cov))


def flat_from(force: np.ndarray, response: np.ndarray, noise: float) -> tuple[float, float, float] | None:
    """(force, level, held) where a response (k,) against its force (k,) ≥ 0
    stops rising: the lowest FLAT_BIN_N bin whose mean is within
    FLAT_SIGMAS·``noise`` (one frame's σ) of the highest bin's, the level
    that highest mean; None unless the force went FLAT_MIN_N past it.
    ``held``: the level the axis is held from, the flat level, or where
    the response fell back to past its top by more than FLAT_SIGMAS·noise
    (a turn: the lowest bin mean from there on)."""
    which = (force / FLAT_BIN_N).astype(int)
    counts = np.bincount(which)
    used = np.flatnonzero(counts >= 3)  # a bin of one or two frames is a ramp passing through, noisy
    means = np.bincount(which, weights=response)[used] / counts[used]
    level = float(means.max())
    first = int(np.argmax(means >= level - FLAT_SIGMAS * noise))
    start = float(used[first] * FLAT_BIN_N)
    fell_to = float(means[first:].min())
    held = fell_to if fell_to < level - FLAT_SIGMAS * noise else level
    return (start, level, held) if force.max() - start >= FLAT_MIN_N else None


def _flat_ends(flat: tuple[float, float, float] | None, slope: float, bend: float, noise: float) -> tuple:
    """(where the fitted curve slope·F − bend·F² (both axes' form) reaches the
    flat level, where it is FLAT_SIGMAS noise σ under the level it is held
    from); Nones without one."""
    if flat is None:
        return None, None
    ends, _ = shear_force(np.array([flat[1], flat[2] - FLAT_SIGMAS * noise]), slope, bend)
    return float(ends[0]), float(ends[1])


def shear_preload(fxyz: np.ndarray) -> tuple[float, float]:
    """(mean, spread) N of the normal force under the shear of frames (k, 3):
    Fz's mean and standard deviation, each frame weighted by Fx² + Fy² (its
    share in the shear slope's fit)."""
    weights = fxyz[:, 0] ** 2 + fxyz[:, 1] ** 2
    mean = float(np.average(fxyz[:, 2], weights=weights))
    return mean, float(np.sqrt(np.average((fxyz[:, 2] - mean) ** 2, weights=weights)))


def _fit_shear(fxy, normal, xy, widen, determined: bool):
    """(a, b, c), their standard errors (c's NaN when not ``determined``: not
    fitted), whether c was kept and (c, its standard error) as fitted (None:
    not determined) (module docstring)."""
    fitted = None
    if determined:
        params, se = _shear(fxy, normal, xy, True, widen)
        fitted = (float(params[2]), float(se[2]))
        if params[2] > COUPLING_SIGMAS * se[2]:
            return params, se, True, fitted
    params, se = _shear(fxy, normal, xy, False, widen)
    # the 0 stored is off the data's c by c ± its error: σ √(c² + se²) (0 was stored, and read as exact)
    return np.r_[params, 0.0], np.r_[se, np.hypot(*fitted) if determined else np.nan], False, fitted


def fit_quad(t_s: np.ndarray, capacitance_pF: np.ndarray, fxyz: np.ndarray, saturated: np.ndarray,
             per_frame: float) -> QuadFit:
    """Fit frames at ``t_s`` (N,) s, (N, 4) pF against the reference forces at their times (N, 3)."""
    unloaded = np.linalg.norm(fxyz, axis=1) < UNLOADED_N
    loads = check(fxyz, saturated, unloaded)
    c0 = np.nanmean(capacitance_pF[unloaded], axis=0)
    followed, rests = rest_c0(t_s, capacitance_pF, unloaded)
    moved = float(np.max(np.ptp(rests, axis=0) / np.mean(rests, axis=0))) if len(rests) > 1 else 0.0
    axes = combinations(capacitance_pF / followed - 1.0)
    noise = np.nanstd(axes[unloaded], axis=0)  # one frame's σ of X, Y, Z
    loaded = (np.linalg.norm(fxyz, axis=1) > LOADED_N) & np.isfinite(axes).all(axis=1)
    fxyz, axes = fxyz[loaded], axes[loaded]
    # Z is the normal curve alone (shear cancels in it): its flat part is found before any fit.
    normal_flat = flat_from(np.maximum(fxyz[:, 2], 0.0), axes[:, 2], noise[2])
    kept = fxyz[:, 2] <= normal_flat[0] if normal_flat else np.ones(len(fxyz), bool)
    fz, z = fxyz[kept, 2], axes[kept, 2]
    design = np.stack([fz * fz, fz], axis=1)
    (c2, c1), *_ = np.linalg.lstsq(design, z, rcond=None)
    residual = z - design @ np.array([c2, c1])
    widen = max(per_frame, 1.0)
    cov = np.linalg.inv(design.T @ design) * float(residual @ residual) / max(z.size - 2, 1) * widen
    normal = (c2 * fxyz[:, 2] + c1) * fxyz[:, 2]
    preload = shear_preload(fxyz[kept])
    params, se, coupled, fitted = _fit_shear(fxyz[kept, :2], normal[kept], axes[kept, :2], widen,
                                             preload[1] >= COUPLING_MIN_SPREAD_N)
    # The shear curve t shows only through the coupling: X, Y divided by 1 − c·n, both axes pooled by sign.
    t = axes[kept, :2] / (1.0 - params[2] * normal[kept])[:, None]
    shear_noise = float(np.hypot(*noise[:2]) / np.sqrt(2))
    shear_flat = flat_from(np.abs(fxyz[kept, :2]).ravel(), (np.sign(fxyz[kept, :2]) * t).ravel(), shear_noise)
    if shear_flat:
        kept &= (np.abs(fxyz[:, :2]) <= shear_flat[0]).all(axis=1)
        preload = shear_preload(fxyz[kept])
        params, se, coupled, fitted = _fit_shear(fxyz[kept, :2], normal[kept], axes[kept, :2], widen,
                                                 preload[1] >= COUPLING_MIN_SPREAD_N)
    normal_ends = _flat_ends(normal_flat, c1, -c2, noise[2])
    shear_ends = _flat_ends(shear_flat, params[0], params[1], shear_noise)
    reach = float(np.abs(fxyz[:, :2]).max())
    model = QuadModel.from_fits([c2, c1], [params[0], params[1]], params[2], normal_ends[1],
                                reach if shear_ends[1] is None else min(reach, shear_ends[1]))
    usable = (fxyz[:, 2] <= model.normal_usable_N) & (np.abs(fxyz[:, :2]) <= model.shear_usable_N).all(axis=1)
    forces, _ = model.inverse(capacitance_pF[loaded][usable] / followed[loaded][usable] - 1.0)
    rms = tuple(float(np.sqrt(np.mean((forces[:, k] - fxyz[usable, k]) ** 2))) for k in range(3))
    return QuadFit(c0, moved, len(rests), (float(c2), float(c1)), tuple(float(v) for v in np.sqrt(np.diag(cov))),
                   (float(params[0]), float(params[1])), (float(se[0]), float(se[1])), float(params[2]),
                   None if np.isnan(se[2]) else float(se[2]), coupled, fitted, preload,
                   rms, (model.normal_usable_N, model.shear_usable_N),
                   (normal_ends[0], shear_ends[0]), reach, int(kept.sum()), loads)

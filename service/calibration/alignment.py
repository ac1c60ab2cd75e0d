"""Reference clock → board clock, from the data alone.

Model: ``t_ref = offset_s + t_board·(1 + rate_ppm·1e-6)``. The reference force
is matched with the board's response (``board_response``): each channel's
ΔC/C0 above its rest level, summed over the channels. The rest level is the
lowest 0.1 s mean within REST_WINDOW_S (every window holds a pause), so a slow
C0 drift is removed: it is common to the channels, and 64 taxels × 0.1 % of
drift wander as much as a press. On a grid each taxel is scaled by its largest
response, so taxels of gains 0.5–2× weigh alike (the force on one taxel at a
time is what the reference sees), and taxels that never stand out of their
noise are left out; a quad's electrodes are summed alike (shear cancels in
their sum). The response is monotone and nearly linear in the force, so the
two signals correlate best when the clocks are aligned.

1. Coarse: both signals on a 100 Hz grid of their own clocks, FFT
   cross-correlation normalised over the overlap at each lag (a Pearson
   correlation of the overlapping stretches, at least MIN_OVERLAP of the
   shorter signal), best lag. Over the overlap, because a reference that
   covers part of the board's log (or the other way round) would otherwise
   be judged on zero padding: the peak shrinks with the share covered, and
   the padding stands for the session's mean level (on a quad, mostly loaded).
2. Refine: the same correlation on each quarter of the reference
   separately, at the board's finer resolution around the coarse lag, each
   peak interpolated by a parabola: a line through the four (time, lag)
   points gives offset and rate. The parts are cut where the reference is
   lowest (between loads), never through a load. (Maximising the Pearson correlation over
   (offset, rate) directly was tried: its optimum is flat along the
   offset–rate valley and the response's curvature biases it, ~1 ms and
   5 ppm off on the simulator against 0.1 ms and 1 ppm for the lag line.)

Refused (ValueError naming why): a rate past ±MAX_RATE_PPM that matches (the
search reaches ~2.5 times as far, to say so), a match quality (Pearson
correlation at the alignment) below MIN_QUALITY, or a runner-up lag — a local
maximum of the coarse correlation at least MIN_SEPARATION_S away — that leaves
less than AMBIGUITY_RATIO times the best's unexplained share (1 − correlation):
the data cannot tell the two apart. A strictly periodic schedule on taxels of
equal response whose reference covers only the middle of the board's log is
such a case (shifted by one press it matches as well); irregular pauses and
the taxels' own differences normally separate them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import minimum_filter1d, uniform_filter1d
from scipy.signal import fftconvolve

COARSE_HZ = 100.0
FINE_HZ = 1000.0
MIN_QUALITY = 0.9
AMBIGUITY_RATIO = 2.0
MIN_SEPARATION_S = 1.0
MAX_RATE_PPM = 1000.0
SEGMENTS = 4
MIN_OVERLAP = 0.5  # of the shorter signal: a few presses alone match almost anywhere
BLOCK_S = 0.1  # the board's response is averaged over this for its rest level and peaks
REST_WINDOW_S = 20.0
RESPONSIVE_SIGMA = 20.0  # a taxel whose largest response is under this many noise σ was not pressed
WEIGHT_FLOOR = 0.1  # of the median taxel's peak: a lightly pressed taxel is not scaled past 10 times that


@dataclass(frozen=True)
class Alignment:
    """``t_ref = offset_s + t_board·(1 + rate_ppm·1e-6)``; ``quality`` the
    normalised correlation at the alignment, ``coarse_best`` and
    ``runner_up`` the coarse correlation at the best lag and at the best
    other one, ``overlap_s`` the common span."""

    offset_s: float
    rate_ppm: float
    quality: float
    coarse_best: float
    runner_up: float
    runner_up_lag_s: float
    overlap_s: float

    def to_board(self, t_ref: np.ndarray) -> np.ndarray:
        """Board seconds of reference times (k,)."""
        return (np.asarray(t_ref) - self.offset_s) / (1.0 + self.rate_ppm * 1e-6)

    def as_dict(self) -> dict:
        return {"offset_s": self.offset_s, "rate_ppm": self.rate_ppm, "quality": self.quality,
                "coarse_best": self.coarse_best, "runner_up": self.runner_up, "runner_up_lag_s": self.runner_up_lag_s,
                "overlap_s": self.overlap_s}


def board_response(t_s: np.ndarray, capacitance_pF: np.ndarray, normalise: bool = True) -> np.ndarray:
    """The signal the reference is aligned with, (n,), from frame times (n,)
    and capacitances (n, channels): each channel's ΔC/C0 above its rest
    level, summed; ``normalise`` (a grid) scales each taxel by its largest
    response and leaves out those within their noise. NaN counts as at rest."""
    t_s = np.asarray(t_s, float)
    relative, means, centres = _relative(t_s, np.asarray(capacitance_pF, float))
    weights = _weights(means - _rest(means)) if normalise else np.ones(means.shape[1])
    # the rest of the sum, not of each channel: a taxel's rest would follow its dips as its neighbours are
    # pressed (mechanical coupling), a slope under their presses that moves their lag ~0.3 ms
    return relative @ weights - np.interp(t_s, centres, _rest(means @ weights))


def _rest(means: np.ndarray) -> np.ndarray:
    """Rest level of BLOCK_S means (blocks, ...) along axis 0: the lowest
    within REST_WINDOW_S (every window holds a pause), smoothed over as long
    (so it never lies above the signal)."""
    window = int(round(REST_WINDOW_S / BLOCK_S))
    return uniform_filter1d(minimum_filter1d(means, window, axis=0, mode="nearest"), window, axis=0, mode="nearest")


def _relative(t_s: np.ndarray, capacitance_pF: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ΔC/C0 against each channel's median (n, channels), 0 where not
    finite; its BLOCK_S means (blocks, channels); the blocks' mean times (blocks,))."""
    sample = capacitance_pF[:: max(1, len(capacitance_pF) // 5000)]
    live = np.isfinite(sample).any(axis=0)  # a dead channel's median would warn
    baseline = np.full(capacitance_pF.shape[1], np.nan)
    baseline[live] = np.nanmedian(sample[:, live], axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        relative = capacitance_pF / baseline - 1.0
    relative[~np.isfinite(relative)] = 0.0
    block = np.floor((t_s - t_s[0]) / BLOCK_S).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(block) > 0])
    counts = np.diff(np.r_[starts, len(t_s)])
    return relative, np.add.reduceat(relative, starts, axis=0) / counts[:, None], np.add.reduceat(t_s, starts) / counts


def _weights(blocks: np.ndarray) -> np.ndarray:
    """Each taxel's weight (channels,) from its block means above rest
    (blocks, channels): 1 / its largest response (at least WEIGHT_FLOOR of
    the median responsive taxel's), 0 where that stays within RESPONSIVE_SIGMA
    noise σ (a taxel not pressed would add only its noise, scaled up)."""
    peak = blocks.max(axis=0)
    sigma = 1.4826 * np.median(np.abs(np.diff(blocks, axis=0)), axis=0) / np.sqrt(2.0)  # robust: presses are rare
    responsive = peak > RESPONSIVE_SIGMA * sigma  # strict: a constant channel has both 0
    weights = np.zeros(peak.size)
    if responsive.any():
        floor = WEIGHT_FLOOR * np.median(peak[responsive])
        weights[responsive] = 1.0 / np.maximum(peak[responsive], floor)
    return weights


def _resample(t: np.ndarray, y: np.ndarray, rate_hz: float) -> tuple[float, np.ndarray]:
    """(start, samples) of ``y`` (k,) on a uniform grid of ``rate_hz`` from t[0]."""
    grid = np.arange(t[0], t[-1], 1.0 / rate_hz)
    return float(t[0]), np.interp(grid, t, y)


def _xcorr(a: np.ndarray, b: np.ndarray, min_overlap: float) -> np.ndarray:
    """Pearson correlation of a (p,) and b (q,) over their overlap at every
    shift (p + q − 1,): index i pairs a[j] with b[j − i + q − 1]; −inf where
    the overlap is under ``min_overlap`` samples or either side is flat."""
    a, b = a - a.mean(), b - b.mean()  # conditioning only: each lag's own means are removed below
    p, q = a.size, b.size
    k = np.arange(p + q - 1) - (q - 1)
    lo, hi = np.maximum(k, 0), np.minimum(p, q + k)  # a's overlapping indices; b's are these − k
    n = hi - lo

    def window_sums(x, first, last):
        cum = np.r_[0.0, np.cumsum(x)]
        return cum[last] - cum[first]

    sa, saa = window_sums(a, lo, hi), window_sums(a * a, lo, hi)
    sb, sbb = window_sums(b, lo - k, hi - k), window_sums(b * b, lo - k, hi - k)
    cov = fftconvolve(a, b[::-1], mode="full") - sa * sb / n
    va, vb = saa - sa * sa / n, sbb - sb * sb / n
    ok = (n >= min_overlap) & (va > 1e-9 * (a @ a)) & (vb > 1e-9 * (b @ b))
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(ok, cov / np.sqrt(va * vb), -np.inf)


def _peaks(c: np.ndarray, rate_hz: float) -> tuple[int, float, float, int]:
    """(best index, best value, runner-up value, runner-up index) of a correlation."""
    best = int(np.argmax(c))
    far = np.abs(np.arange(c.size) - best) >= MIN_SEPARATION_S * rate_hz
    local = np.r_[False, (c[1:-1] >= c[:-2]) & (c[1:-1] >= c[2:]), False] & far & np.isfinite(c)
    if not local.any():
        return best, float(c[best]), 0.0, best
    second = int(np.flatnonzero(local)[np.argmax(c[local])])
    return best, float(c[best]), float(c[second]), second


def _lag(t_b, s_b, t_r, f_r, rate_hz, around: float | None = None, span_s: float = 0.5) -> tuple[float, np.ndarray, float]:
    """Lag (s) such that t_r ≈ t_b + lag, the correlation and its step; peak by a parabola."""
    b0, b = _resample(t_b, s_b, rate_hz)
    r0, r = _resample(t_r, f_r, rate_hz)
    c = _xcorr(r, b, MIN_OVERLAP * min(r.size, b.size))  # index i ↔ r shifted by i − (len(b) − 1) samples against b
    lags = (np.arange(c.size) - (b.size - 1)) / rate_hz + (r0 - b0)
    if around is not None:
        c = np.where(np.abs(lags - around) <= span_s, c, -np.inf)
    i = int(np.argmax(c))
    if 0 < i < c.size - 1 and np.isfinite(c[i - 1]) and np.isfinite(c[i + 1]):
        den = c[i - 1] - 2 * c[i] + c[i + 1]
        shift = 0.5 * (c[i - 1] - c[i + 1]) / den if den < 0 else 0.0
    else:
        shift = 0.0
    return float(lags[i] + shift / rate_hz), c, float(lags[1] - lags[0])


def quality(offset_s: float, rate_ppm: float, t_b, s_b, t_r, f_r) -> tuple[float, float]:
    """(Pearson correlation, overlap in s) of the reference against the board
    response interpolated at the aligned reference times; 0 where undefined."""
    tb = (t_r - offset_s) / (1.0 + rate_ppm * 1e-6)
    inside = (tb >= t_b[0]) & (tb <= t_b[-1])
    if inside.sum() < 10:
        return 0.0, 0.0
    x, y = f_r[inside], np.interp(tb[inside], t_b, s_b)
    with np.errstate(divide="ignore", invalid="ignore"):
        q = float(np.corrcoef(x, y)[0, 1])
    return (q if np.isfinite(q) else 0.0), float(tb[inside][-1] - tb[inside][0])


def _quiet_split(force: np.ndarray, parts: int) -> list[np.ndarray]:
    """Index ranges of ``parts`` consecutive parts of the reference (k,),
    each boundary moved to the lowest force within an eighth of a part of
    where an even split puts it, and the two ends inwards as far: a part cut
    in the middle of a load would correlate best where the board's response
    has more of that load in the window, not at the true lag (a few ms off on
    long flat loads; ~1.4 ms on a press cut by where the reference starts)."""
    size = force.size
    reach = max(size // (8 * parts), 1)
    cuts = [int(np.argmin(force[:reach]))]
    for k in range(1, parts):
        nominal = k * size // parts
        window = force[nominal - reach:nominal + reach]
        cuts.append(nominal - reach + int(np.argmin(window)) if window.size else nominal)
    cuts.append(size - int(np.argmin(force[::-1][:reach])))
    return [np.arange(a, b) for a, b in zip(cuts[:-1], cuts[1:])]


def _refine(t_b, s_b, t_r, f_r, coarse_lag: float) -> tuple[float, float]:
    """(offset_s, rate_ppm): a line through the lags of SEGMENTS consecutive
    parts of the reference where the board's log covers it (each against the
    board's response at FINE_HZ), twice: the second time on the reference
    with the first line taken out. A part's lag is that of where its presses
    lie, not of its middle: −230 ppm shifts it by 0.23 ms per second between
    them (~0.3 ms a part, 20 ppm on a 2-minute session); with the rate taken
    out it no longer matters. The search reaches 0.2 s + MAX_RATE_PPM over the
    span each way: the outer parts' centres are ~3/8 of it from the middle, so
    rates to ~2.5 times the limit are found (and named)."""
    covered = np.flatnonzero((t_r - coarse_lag >= t_b[0]) & (t_r - coarse_lag <= t_b[-1]))
    t_r, f_r = t_r[covered], f_r[covered]
    span_s = 0.2 + MAX_RATE_PPM * 1e-6 * (t_r[-1] - t_r[0])
    parts = _quiet_split(f_r, SEGMENTS)
    offset, scale = coarse_lag, 1.0  # t_ref = offset + scale·t_board
    for _ in range(2):
        u = (t_r - offset) / scale  # the reference on the board's clock as estimated so far
        points = []
        for part in parts:
            near = (t_b >= u[part[0]] - span_s - 1.0) & (t_b <= u[part[-1]] + span_s + 1.0)
            lag, _, _ = _lag(t_b[near], s_b[near], u[part], f_r[part], FINE_HZ, around=0.0, span_s=span_s)
            points.append((0.5 * (u[part[0]] + u[part[-1]]) - lag, lag))  # (board time, lag left)
        tb, lags = np.array(points).T
        slope, intercept = np.polyfit(tb, lags, 1)  # u = t_board·(1 + slope) + intercept
        offset, scale = offset + scale * intercept, scale * (1.0 + slope)
    return float(offset), float((scale - 1.0) * 1e6)


def align(t_board: np.ndarray, response: np.ndarray, t_ref: np.ndarray, force_N: np.ndarray) -> Alignment:
    """Align a reference (t_ref, force_N) (k,) with the board's response
    (t_board, response) (n,) (``board_response``); ValueError when the rate
    is past the limit, or the match low or ambiguous."""
    coarse_lag, c, step = _lag(t_board, response, t_ref, force_N, COARSE_HZ)
    best, top, second, second_i = _peaks(c, COARSE_HZ)
    offset, rate = _refine(t_board, response, t_ref, force_N, coarse_lag)
    q, overlap = quality(offset, rate, t_board, response, t_ref, force_N)
    runner_lag = (second_i - best) * step
    if abs(rate) > MAX_RATE_PPM and q >= MIN_QUALITY:
        raise ValueError(f"the reference's clock runs {rate:+.0f} ppm against the board's (correlation {q:.3f} at that "
                         f"rate), past the ±{MAX_RATE_PPM:.0f} ppm the calibration takes: is its time column in seconds "
                         "of one steady clock?")
    if q < MIN_QUALITY:
        raise ValueError(f"the reference does not match the board's response: correlation {q:.3f} at the best "
                         f"alignment over {overlap:.0f} s (need ≥ {MIN_QUALITY}); is it the same session and the same "
                         "sensor?")
    if 1.0 - second < AMBIGUITY_RATIO * (1.0 - top):
        raise ValueError(f"ambiguous alignment: a lag {runner_lag:+.2f} s away matches almost as well "
                         f"(coarse correlation {second:.3f} against {top:.3f}); a strictly periodic schedule "
                         "cannot be aligned — vary the pauses between presses")
    return Alignment(float(offset), float(rate), q, top, second, runner_lag, overlap)

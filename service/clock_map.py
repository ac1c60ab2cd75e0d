"""Board clock → host clock, per board, estimated online from when frames arrive.

Model. A board stamps every scan with ``t_us``, a u32 microsecond counter that
wraps every 2**32 µs (71.6 min) and starts anywhere. Unwrapped, in seconds
since the first frame of the current run, call it x. The host reads a frame at

    t_recv = r0 + c + (1 + m)·x + d,        d >= 0,

where r0 is the receive time of the run's first frame (a reference, to keep
the float arithmetic small), r0 + c + (1 + m)·x is the scan's time on the
host clock plus the link's least latency, 1 + m the host seconds per board
second (a crystal off by p ppm gives m ≈ −p·1e-6), and d the delivery
jitter: queueing, USB polling, a reader that was late, and chunking (every
frame of one read carries the read's time). d is one-sided: a frame never
arrives before it was scanned. So in the plane (x, y = t_recv − r0 − x) every
frame lies on or above the line y = c + m·x, and the line is the lower
envelope of the points, not a least-squares fit through them (the mean of d
is neither zero nor constant: it follows the host's load).

Algorithm. Of the frames of one read only the newest can touch the envelope
(the others lie on a slope −1 above it), so each read adds one point. Points
are kept per 0.1 s bin of board time (the lowest, after the current slope)
over a sliding window (30 s). Every ``refit_s`` of host time the line is the
supporting line of the points' lower convex hull at their mean x̄: of all
lines below every point it is the one with the least summed distance to them
(the linear programme of the convex-hull clock-sync literature, solved
exactly: the hull's height at x̄ is the least interpolation at x̄ over all
pairs straddling x̄, its slope the right-hand derivative there).

Until ``lock_s`` of board time is seen the map is the naive one: receive time
minus the least delay seen (with the previous run's rate, when there was one).
A restart — ``restart()``, the board clock stepping back by more than
``restart_jump_s``, a frame arriving ``step_s`` before its envelope says it
was scanned, ``step_bins`` bins in a row late by more than ``step_s`` and not
shrinking, or ``gap_s`` without a frame (the wrap count is then unknown) —
starts a new run and keeps the last locked rate as the prior. Late is not a
new clock: a stalled link or reader that then hands on its backlog faster than
real time makes reads late, then less and less; a host clock stepped on (a
board clock stepped back), late by a constant. So a late bin ``drain_s`` less
late than the first of its streak starts the streak again, and late bins stay
out of the fit. A read late by more than ``step_s`` before its streak was seen
to shrink is ``suspect``: a stall (scans right) or a step (off by ``late_s``)?
"""
from __future__ import annotations

import math

import numpy as np

_WRAP = 1 << 32
_HALF = 1 << 31
_MASK = _WRAP - 1
_QUARTER = 1 << 30  # a read spans far less: above this no frame of it can lie before the wrap
_NEAREST = 8  # the residual of the 8th-nearest point measures how tightly the points hug the envelope
_TICK_S = 1e-6  # t_us resolution: no estimate is better than this


class ClockMap:
    """Board time → host time for one board.

    Parameters
    ----------
    window_s : board seconds of points the line is fitted to
    bin_s : board seconds per bin (one candidate point per bin for the fit)
    refit_s : host seconds between refits
    lock_s : board seconds of data before the fitted line replaces the naive map
    step_s, step_bins, restart_jump_s, gap_s : when to start a new run (module docstring)
    drain_s : lateness a streak of late bins must lose to be a draining backlog, not a clock step
    late_s, suspect (attributes) : of the last read (module docstring)
    """

    def __init__(self, window_s: float = 30.0, *, bin_s: float = 0.1, refit_s: float = 0.25, lock_s: float = 1.0,
                 step_s: float = 0.05, step_bins: int = 5, restart_jump_s: float = 1.0, gap_s: float = 600.0,
                 drain_s: float = 0.02) -> None:
        if not 0 < bin_s < lock_s <= window_s:
            raise ValueError(f"need 0 < bin_s < lock_s <= window_s, got {bin_s}, {lock_s}, {window_s}")
        if refit_s <= 0 or step_s <= 0 or step_bins < 1 or restart_jump_s <= 0 or not 0 < gap_s < _HALF * 1e-6:
            raise ValueError(f"refit_s, step_s, step_bins, restart_jump_s must be positive, gap_s within (0, 2147 s); "
                             f"got {refit_s}, {step_s}, {step_bins}, {restart_jump_s}, {gap_s}")
        if not 0 < drain_s < step_s:
            raise ValueError(f"need 0 < drain_s < step_s, got {drain_s}, {step_s}")
        self.window_s, self.bin_s, self.refit_s, self.lock_s = window_s, bin_s, refit_s, lock_s
        self.step_s, self.step_bins, self.gap_s, self.drain_s = step_s, step_bins, gap_s, drain_s
        self._jump_us = int(restart_jump_s * 1e6)
        self._bin_cap = int(math.ceil(window_s / bin_s)) + 2
        self._read_cap = 1 << 15  # reads kept for status(): 30 s at 1 kHz
        self._prior = 0.0  # slope of the last locked run
        self.restarts = 0
        self._new_run()

    def _new_run(self) -> None:
        self._empty = True
        self._raw = 0  # t_us of the newest frame, and its unwrapped µs since the run's first
        self._x_us = 0
        self._r0 = self._t_last = 0.0
        self._c, self._m, self._locked = math.inf, self._prior, False
        self._naive = math.inf  # least y − prior·x: the naive map's c
        self._bin, self._bin_x, self._bin_y, self._bin_res = -1, 0.0, 0.0, math.inf
        self._late_bins, self._late_ref, self._draining, self.late_s, self.suspect = 0, 0.0, False, 0.0, False
        self._bx, self._by, self._nb = np.empty(self._bin_cap), np.empty(self._bin_cap), 0
        self._rx, self._ry, self._nr = np.empty(self._read_cap), np.empty(self._read_cap), 0
        self._next_refit = -math.inf

    def restart(self) -> None:
        """The board restarted: forget this run, keep its rate (if locked) as the next run's prior."""
        if self._locked:
            self._prior = self._m
        self.restarts += 1
        self._new_run()

    def observe(self, t_us: np.ndarray, t_recv: float) -> np.ndarray:
        """Take the frames of one read; return their scan times on the host clock.

        ``t_us`` : (k,) board times (u32 values, any integer dtype) of the frames
        of one read, in arrival order (the last is the newest); ``t_recv`` :
        the read's host time, seconds. Returns (k,) float64 host seconds, never
        later than ``t_recv``.
        """
        t = np.asarray(t_us, dtype=np.int64)
        newest = int(t[-1])
        scale, base = self._take(newest, t_recv)
        # µs relative to the newest frame; the modular form only when the counter may have wrapped within the read.
        d_us = t - newest if newest >= _QUARTER else ((t - newest + _HALF) & _MASK) - _HALF
        out = d_us * scale
        out += base
        return np.minimum(out, t_recv, out=out)

    def scan_times(self, t_us: list[int], t_recv: float) -> list[float]:
        """``observe`` for a read's board times as a list, in plain Python
        (the same float operations, so the same values): for one read's few
        dozen frames numpy's per-call cost outweighs the arithmetic."""
        newest = t_us[-1]
        scale, base = self._take(newest, t_recv)
        if newest >= _QUARTER:
            times = [(t - newest) * scale + base for t in t_us]
        else:
            times = [(((t - newest + _HALF) & _MASK) - _HALF) * scale + base for t in t_us]
        return [t if t < t_recv else t_recv for t in times]

    def _take(self, newest: int, t_recv: float) -> tuple[float, float]:
        """Take a read whose newest frame has board time ``newest``; return
        the map (µs from the newest → host seconds) as (scale, base)."""
        if self._empty or t_recv - self._t_last > self.gap_s or self._step_us(newest) < -self._jump_us:
            self._begin(newest, t_recv)
        x_us = self._x_us + self._step_us(newest)
        x = x_us * 1e-6
        y = (t_recv - self._r0) - x
        late = y - (self._c + self._m * x) if self._c < math.inf else 0.0
        if late < -self.step_s:  # before its scan: the clock stepped on
            self._begin(newest, t_recv)
            x_us, x, y, late = 0, 0.0, 0.0, 0.0
        self._raw, self._x_us, self._t_last = newest, x_us, t_recv
        self._add(x, y)
        if self._late_bins >= self.step_bins:  # late by a constant for a while: the clock stepped back
            self._begin(newest, t_recv)
            self._add(0.0, 0.0)
            late = 0.0  # this read starts the new run
        self.late_s, self.suspect = late, late > self.step_s and not self._draining
        if t_recv >= self._next_refit:
            self._refit(t_recv)
        return (1.0 + self._m) * 1e-6, self._r0 + self._c + (1.0 + self._m) * (self._x_us * 1e-6)

    def _begin(self, newest: int, t_recv: float) -> None:
        if not self._empty:
            self.restart()
        self._empty = False
        self._raw, self._x_us, self._r0, self._t_last = newest, 0, t_recv, t_recv

    def _step_us(self, raw: int) -> int:
        """Signed µs from the newest frame to ``raw``, the nearer way round the wrap."""
        return ((raw - self._raw + _HALF) & _MASK) - _HALF

    def _add(self, x: float, y: float) -> None:
        i = self._nr % self._read_cap
        self._rx[i], self._ry[i] = x, y
        self._nr += 1
        if not self._locked and y - self._prior * x < self._naive:
            self._naive = self._c = y - self._prior * x
        b = int(x // self.bin_s)
        if b != self._bin:
            if self._bin >= 0:
                self._close_bin()
            self._bin, self._bin_x, self._bin_y, self._bin_res = b, x, y, math.inf
        elif y - self._m * x < self._bin_y - self._m * self._bin_x:
            self._bin_x, self._bin_y = x, y
        self._bin_res = min(self._bin_res, y - (self._c + self._m * x))

    def _close_bin(self) -> None:
        late = self._bin_res
        if late <= self.step_s:
            i = self._nb % self._bin_cap
            self._bx[i], self._by[i] = self._bin_x, self._bin_y
            self._nb += 1
            self._late_bins, self._draining = 0, False
        elif not self._late_bins:
            self._late_bins, self._late_ref = 1, late
        elif late < self._late_ref - self.drain_s:  # shrinking: a backlog draining, not a clock step
            self._late_bins, self._late_ref, self._draining = 1, late, True
        else:
            self._late_bins += 1

    def _window(self, xs: np.ndarray, ys: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The ring's points within the window ending at the newest frame."""
        xs, ys = xs[: min(n, xs.size)], ys[: min(n, ys.size)]
        keep = xs >= self._x_us * 1e-6 - self.window_s
        return xs[keep], ys[keep]

    def _fit_points(self) -> tuple[np.ndarray, np.ndarray]:
        xs, ys = self._window(self._bx, self._by, self._nb)
        late = self._bin_res > self.step_s  # the open bin is late: out of the fit, as when closed
        return (xs, ys) if late else (np.append(xs, self._bin_x), np.append(ys, self._bin_y))

    def _refit(self, t_recv: float) -> None:
        self._next_refit = t_recv + self.refit_s
        xs, ys = self._fit_points()
        if xs.size < 3 or xs.max() - xs.min() < self.lock_s:
            return
        h, m, xbar = envelope(xs, ys)
        self._c, self._m, self._locked = h - m * xbar, m, True

    def to_host(self, t_us):
        """Host seconds of board time(s) ``t_us`` (u32, scalar or (k,)) under the
        current estimate, unwrapped next to the newest frame; NaN before any frame."""
        t = np.asarray(t_us, dtype=np.int64)
        if self._empty:
            out = np.full(t.shape, np.nan)
        else:
            x = (self._x_us + (((t - self._raw + _HALF) & _MASK) - _HALF)) * 1e-6
            out = self._r0 + self._c + (1.0 + self._m) * x
        return float(out) if out.ndim == 0 else out

    def status(self) -> dict:
        """The estimate and how far to trust it.

        rate_error_ppm : how fast the board clock runs against the host's, ppm
        offset_uncertainty_ms : likely error of the map at the newest frame
        jitter_ms : p99 − min of the reads' delay above the envelope over the window
        samples : reads in the window; window_s : board seconds they span
        locked : the fitted line is in use (else the naive map)
        restarts : runs started again (by restart() or a detected clock step)
        late_ms, suspect : of the last read (module docstring); if suspect, the uncertainty includes late_ms
        """
        xs, ys = self._window(self._rx, self._ry, self._nr)
        doc = {"rate_error_ppm": (1.0 / (1.0 + self._m) - 1.0) * 1e6, "offset_uncertainty_ms": None,
               "jitter_ms": None, "samples": int(xs.size), "window_s": 0.0, "locked": self._locked,
               "restarts": self.restarts, "late_ms": self.late_s * 1e3, "suspect": self.suspect}
        if xs.size == 0:
            return doc
        res = ys - (self._c + self._m * xs)
        span = float(xs.max() - xs.min())
        jitter = float(np.percentile(res, 99) - res.min())
        uncertainty = self._uncertainty(xs, res, span, jitter) + (self.late_s if self.suspect else 0.0)
        doc.update(jitter_ms=jitter * 1e3, window_s=span, offset_uncertainty_ms=uncertainty * 1e3)
        return doc

    def _uncertainty(self, xs: np.ndarray, res: np.ndarray, span: float, jitter: float) -> float:
        """Seconds. Locked: the residual of the 8th-nearest point, δ, is how far
        the envelope may sit above the true one where the points are (fewer
        points near the line, looser line); the slope is then good to about
        4δ/span, so at the newest frame, |x − x̄| from the centre, δ·(1 + 4|x − x̄|/span).
        Naive: the least delay may itself be up to the jitter late, and the rate
        unknown to 1000 ppm without a prior."""
        if not self._locked:
            return jitter + (1e-3 if self.restarts == 0 else 0.0) * span + _TICK_S
        k = min(_NEAREST, res.size - 1)
        delta = float(np.partition(res, k)[k]) - float(res.min())
        lever = abs(self._x_us * 1e-6 - float(xs.mean())) / max(span, self.lock_s)
        return delta * (1.0 + 4.0 * lever) + _TICK_S


def envelope(xs: np.ndarray, ys: np.ndarray) -> tuple[float, float, float]:
    """Supporting line of the lower convex hull of the points (xs, ys), (n,) each
    with at least two distinct xs, at their mean x̄: returns (h, m, x̄), the
    line y = h + m·(x − x̄). Exact (no iteration to converge)."""
    xbar = float(xs.mean())
    order = np.argsort(xs, kind="stable")
    xs, ys = _hull_candidates(xs[order], ys[order])
    left, right = xs <= xbar, xs > xbar
    xl, yl = xs[left, None], ys[left, None]
    xr, yr = xs[right], ys[right]
    # The hull's height at x̄ is the least height at x̄ of a segment from a point left of it to one right of it.
    h = float(np.min(yl + (yr - yl) * ((xbar - xl) / (xr - xl))))
    # Its slope: the least slope from (x̄, h) to a point on the right keeps every point on or above the line.
    m = float(np.min((yr - h) / (xr - xbar)))
    return h, m, xbar


def _hull_candidates(xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Of points sorted by x, drop those above the chord of their neighbours
    (never a lower-hull vertex) until none is, so the O(n²) step above sees
    the hull's few vertices, not the window's hundreds of bins."""
    while xs.size > 2:
        cross = (xs[1:-1] - xs[:-2]) * (ys[2:] - ys[:-2]) - (ys[1:-1] - ys[:-2]) * (xs[2:] - xs[:-2])
        above = np.flatnonzero(cross < 0) + 1  # the middle point lies above its neighbours' chord
        if above.size == 0:
            break
        keep = np.ones(xs.size, bool)
        keep[above] = False
        xs, ys = xs[keep], ys[keep]
    return xs, ys

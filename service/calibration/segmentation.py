"""Presses from the aligned reference force, each attributed to a taxel.

A press is a run of reference samples above LOW (noise-scaled) that reaches
HIGH somewhere (hysteresis: noise around the low threshold does not split or
invent presses). It belongs to the taxel whose ΔC/C0 rises most at the
press's top (force above TOP_FRACTION of its peak), against the unloaded
window just before it; a press where that rise is within RESPONSE_SIGMAS of
the taxel's noise is flagged (no live taxel answered: the pressed one is
dead), and one where the runner-up taxel rises by more than COMPARABLE of
the first (the probe straddled two taxels); flagged presses are not used. Each taxel's C0 is the mean of its capacitance over the unloaded
windows around its own presses (robust to slow drift across the session).
The fit's samples are the reference samples of the taxel's presses (padded
by PAD_S of unloaded reference on each side, so that which samples are
used is decided by time, not by their force: selecting on the force near a
threshold would bias the fit), with the taxel's ΔC/C0
interpolated at their board times: one sample per reference reading, so
their errors are independent.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LOW_SIGMAS, HIGH_SIGMAS = 5.0, 20.0
LOW_MIN_N, HIGH_MIN_N = 0.05, 0.5
TOP_FRACTION = 0.8
COMPARABLE = 0.3
RESPONSE_SIGMAS = 5.0  # a press's taxel rises this far above its noise (thousands of σ at a few N)
PAD_S = 0.25  # the pauses are ≥ 0.5 s: unloaded samples, and the ramps' feet below the threshold
GUARD_S = 0.15  # unloaded windows keep this far from any press
WINDOW_S = 0.5  # longest unloaded window used for a baseline


@dataclass
class Press:
    """One press on the board clock: [start_s, end_s], its peak force, the
    taxel (row-major) that responded most and its ΔC/C0 at the top, the
    runner-up and its share, and why it was set aside (None: used)."""

    start_s: float
    end_s: float
    peak_N: float
    taxel: int
    response: float
    runner_up: int
    runner_up_share: float
    problem: str | None = None


@dataclass
class TaxelSamples:
    """One taxel's data: ``force_N`` and ``relative`` (k,) paired samples,
    ``c0_pF`` its unloaded mean, ``noise_relative`` the σ of its unloaded
    ΔC/C0 per frame, ``saturated`` how many samples the board flagged or
    lost (sentinel), ``presses`` indices into the session's press list."""

    taxel: int
    force_N: np.ndarray
    relative: np.ndarray
    c0_pF: float
    noise_relative: float
    saturated: int
    presses: list[int] = field(default_factory=list)


def noise_sigma(values: np.ndarray) -> float:
    """Robust white-noise σ of a signal (k,) from its second differences
    (MAD; σ√6 for white noise): smooth ramps barely enter, where first
    differences of 1 s presses read 6× the noise."""
    d = np.diff(values, 2)
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(6.0)) if d.size else 0.0


def threshold_sigma(values: np.ndarray, block: int = 8) -> float:
    """σ of the noise of a signal (k,) with loaded stretches: the MAD
    estimate of its second differences per block of ``block``, lower
    quartile over blocks (pauses are pure noise; at 10 Hz a press's ramps
    are not smooth on the sample scale and would inflate a global MAD)."""
    d = np.abs(np.diff(values, 2))
    if d.size < 4 * block:
        return noise_sigma(values)
    medians = np.median(d[: d.size // block * block].reshape(-1, block), axis=1)
    return float(1.4826 * np.percentile(medians, 25) / np.sqrt(6.0))


def unloaded(presses: list, t_ref_board: np.ndarray) -> np.ndarray:
    """Mask (k,) of the reference samples outside every press (padded by GUARD_S)."""
    mask = np.ones(t_ref_board.size, bool)
    for p in presses:
        mask &= ~((t_ref_board >= p.start_s - GUARD_S) & (t_ref_board <= p.end_s + GUARD_S))
    return mask


def find_runs(force_N: np.ndarray, low: float, high: float) -> list[tuple[int, int]]:
    """[start, end) index runs of ``force_N`` (k,) above ``low`` that reach ``high``."""
    above = np.r_[False, force_N > low, False]
    edges = np.flatnonzero(np.diff(above.astype(np.int8)))
    runs = zip(edges[::2], edges[1::2])
    return [(int(a), int(b)) for a, b in runs if force_N[a:b].max() > high]


def _window(t_s: np.ndarray, capacitance: np.ndarray, a: float, b: float) -> np.ndarray | None:
    """The frames (k, taxels) with a ≤ t < b, None if there are fewer than 5."""
    i, j = np.searchsorted(t_s, [a, b])
    return capacitance[i:j] if j - i >= 5 else None


def _quiet_windows(presses: list[Press], k: int, t_first: float, t_last: float) -> list[tuple[float, float]]:
    """The unloaded windows (≤ WINDOW_S) just before and just after press ``k``."""
    before = presses[k - 1].end_s if k > 0 else t_first - GUARD_S
    after = presses[k + 1].start_s if k + 1 < len(presses) else t_last + GUARD_S
    p = presses[k]
    out = [(max(before + GUARD_S, p.start_s - GUARD_S - WINDOW_S), p.start_s - GUARD_S),
           (p.end_s + GUARD_S, min(after - GUARD_S, p.end_s + GUARD_S + WINDOW_S))]
    return [(a, b) for a, b in out if b - a > 0.05]


def segment(t_board: np.ndarray, capacitance_pF: np.ndarray, t_ref_board: np.ndarray, force_N: np.ndarray) -> list[Press]:
    """Presses of a session: board frames (n,), (n, taxels); the reference's
    samples on the board clock (k,) and forces (k,)."""
    sigma = threshold_sigma(force_N)
    low, high = max(LOW_MIN_N, LOW_SIGMAS * sigma), max(HIGH_MIN_N, HIGH_SIGMAS * sigma)
    presses = []
    for a, b in find_runs(force_N, low, high):
        presses.append(Press(float(t_ref_board[a]), float(t_ref_board[b - 1]), float(force_N[a:b].max()), -1, 0.0, -1, 0.0))
    for k, press in enumerate(presses):
        _attribute(press, k, presses, t_board, capacitance_pF, t_ref_board, force_N)
    return presses


def _attribute(press: Press, k: int, presses: list[Press], t_board, capacitance_pF, t_ref_board, force_N) -> None:
    windows = _quiet_windows(presses, k, float(t_board[0]), float(t_board[-1]))
    quiet = next((w for a, b in windows if (w := _window(t_board, capacitance_pF, a, b)) is not None), None)
    top = (t_ref_board >= press.start_s) & (t_ref_board <= press.end_s) & (force_N >= TOP_FRACTION * press.peak_N)
    loaded = _window(t_board, capacitance_pF, float(t_ref_board[top].min()), float(t_ref_board[top].max()) + 1e-6)
    if quiet is None or loaded is None:
        press.problem = "no unloaded window or no board frames around it"
        return
    baseline = quiet.mean(axis=0)
    rise = np.nan_to_num(loaded.mean(axis=0) / baseline - 1.0, nan=-np.inf)
    # σ of that rise from the taxel's own unloaded noise: a noisy taxel's
    # chance rise must not take a press whose taxel answered on no channel
    sigma = quiet.std(axis=0, ddof=1) * np.sqrt(1 / len(quiet) + 1 / len(loaded)) / baseline
    order = np.argsort(rise)[::-1]
    press.taxel, press.runner_up = int(order[0]), int(order[1])
    press.response = float(rise[order[0]])
    press.runner_up_share = float(rise[order[1]] / rise[order[0]]) if rise[order[0]] > 0 else 1.0
    with np.errstate(divide="ignore", invalid="ignore"):  # noiseless (synthetic) frames: σ 0
        sigmas = float(rise[order[0]] / sigma[order[0]])
    if not sigmas > RESPONSE_SIGMAS:
        press.problem = (f"no taxel responded (largest rise: ΔC/C0 {press.response:.5f} on taxel {press.taxel}, "
                         f"{sigmas:.1f} σ of its noise)")
    elif press.runner_up_share > COMPARABLE:
        press.problem = (f"taxels {press.taxel} and {press.runner_up} responded comparably "
                         f"({100 * press.runner_up_share:.0f} %)")


def _padded(presses: list[Press], k: int) -> tuple[float, float]:
    """Press ``k`` widened by PAD_S each side, never past half the pause to a neighbour."""
    p = presses[k]
    a = p.start_s - PAD_S if k == 0 else max(p.start_s - PAD_S, 0.5 * (presses[k - 1].end_s + p.start_s))
    b = p.end_s + PAD_S if k + 1 == len(presses) else min(p.end_s + PAD_S, 0.5 * (p.end_s + presses[k + 1].start_s))
    return a, b


def taxel_samples(presses: list[Press], t_board, capacitance_pF, saturated_frames, t_ref_board, force_N) -> dict[int, TaxelSamples]:
    """Per taxel, its paired (force, ΔC/C0) samples over the presses attributed to it (unflagged)."""
    t_first, t_last = float(t_board[0]), float(t_board[-1])
    out: dict[int, TaxelSamples] = {}
    for taxel in sorted({p.taxel for p in presses if p.problem is None}):
        mine = [k for k, p in enumerate(presses) if p.taxel == taxel and p.problem is None]
        quiet = np.concatenate([np.arange(*np.searchsorted(t_board, [a, b]))
                                for k in mine for a, b in _quiet_windows(presses, k, t_first, t_last)] or [np.zeros(0, int)])
        column = capacitance_pF[:, taxel]
        c0 = float(np.nanmean(column[quiet])) if quiet.size else float(np.nanmedian(column))
        relative = column / c0 - 1.0
        keep = np.zeros(t_ref_board.size, bool)
        for k in mine:
            a, b = _padded(presses, k)
            keep |= (t_ref_board >= a) & (t_ref_board <= b)
        keep &= (t_ref_board >= t_first) & (t_ref_board <= t_last)
        frames = np.searchsorted(t_board, t_ref_board[keep])
        bad = ~np.isfinite(column) | saturated_frames
        lost = bad[np.clip(frames, 0, len(bad) - 1)] | bad[np.clip(frames - 1, 0, len(bad) - 1)]
        r = np.interp(t_ref_board[keep], t_board, np.nan_to_num(relative, nan=0.0))
        out[taxel] = TaxelSamples(taxel, force_N[keep][~lost], r[~lost], c0,
                                  noise_sigma(relative[quiet]) if quiet.size > 2 else 0.0, int(lost.sum()), mine)
    return out

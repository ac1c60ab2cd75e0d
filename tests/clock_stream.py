"""A board's reads as a host receives them, with stalls, load and clock steps,
and each scan's true host time: the reference the clock-map tests measure against."""
import numpy as np

WRAP = 1 << 32
LATENCY = 0.5e-3  # the link's least delay: part of the envelope


def reads(seconds, ppm, *, rate_hz=1000, jitter_ms=5.0, reader_ms=0.0, stalls=(), host_step=None, restart_at=None,
          start=100.0, offset_us=123_456_789, seed=0):
    """[(t_us (k,), t_recv, true scan times (k,))] per read.

    Scans every 1/rate of board time from a crystal ``ppm`` fast: a scan at
    true time t has t_us = offset_us + (t − start)·(1 + ppm·1e-6)·1e6 (u32).
    Frames leave in chunks of 1-4 scans, each chunk LATENCY + U(0, jitter)
    late. ``stalls``: (at_s, hold_s, drain) — from ``at_s`` (true seconds
    after start) nothing is delivered for ``hold_s``, then the backlog leaves
    at ``drain`` × real time, in order. Then first in, first out (no read
    before the one before it). ``reader_ms``: a loaded host's reader, waking
    U(0, reader_ms) after its last read, takes what has arrived. ``host_step``: (at_s, step_s), the host clock
    stepped by step_s at at_s (every later t_recv is off by it).
    ``restart_at``: true seconds at which the board powers up again (t_us from 0).
    """
    rng = np.random.default_rng(seed)
    true_s = np.arange(1, int(seconds * rate_hz) + 1) / rate_hz
    board_us = np.rint(true_s * (1 + ppm * 1e-6) * 1e6).astype(np.int64)
    raw = (board_us + offset_us) % WRAP
    if restart_at is not None:
        after = true_s >= restart_at
        raw[after] = np.rint((true_s[after] - restart_at) * (1 + ppm * 1e-6) * 1e6).astype(np.int64)
    ends = np.unique(np.minimum(np.cumsum(rng.integers(1, 5, true_s.size)), true_s.size) - 1)
    release = true_s[ends] + LATENCY + rng.uniform(0, jitter_ms * 1e-3, ends.size)
    for at, hold, drain in stalls:
        held = true_s[ends] >= at
        release[held] = np.maximum(release[held], at + hold + (true_s[ends][held] - at) / drain)
    arrival = np.maximum.accumulate(release)[np.searchsorted(ends, np.arange(true_s.size))]  # per frame
    if reader_ms:
        wakes = np.cumsum(rng.uniform(0, reader_ms * 1e-3, int(4 * arrival[-1] / (reader_ms * 1e-3)) + 16))
        arrival = wakes[np.searchsorted(wakes, arrival)]
    if host_step is not None:
        arrival = arrival + np.where(arrival >= host_step[0], host_step[1], 0.0)
    bounds = np.r_[0, np.flatnonzero(np.diff(arrival)) + 1, true_s.size]
    return [(raw[a:b], start + float(arrival[a]), start + true_s[a:b]) for a, b in zip(bounds[:-1], bounds[1:])]


def run(clock, stream):
    """Feed every read: (t_recv, stamps, truth + LATENCY), (n,) each, per frame."""
    return tuple(np.concatenate(a) for a in zip(*[(np.full(true.size, t), clock.observe(t_us, t), true + LATENCY)
                                                   for t_us, t, true in stream]))


def run_flagged(clock, stream):
    """``run``, and whether each frame's read was ``suspect`` (n,)."""
    out, suspect = [], []
    for read in stream:
        out.append(run(clock, [read]))
        suspect.append(np.full(read[2].size, clock.suspect))
    return tuple(np.concatenate(a) for a in zip(*out)) + (np.concatenate(suspect),)

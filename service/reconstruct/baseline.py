"""Zero-load baseline per channel: auto-tare on start and on demand."""
from __future__ import annotations

from typing import Callable

import numpy as np

DEFAULT_TARE_FRAMES = 100
NOISE_FLOOR_PF = 2e-4  # never trust a tare's noise estimate below 0.2 fF
OUTLIER_SIGMAS = 6.0  # a tare reading this many robust σ from its channel's median is a glitch, not the zero
MAD_TO_SIGMA = 1.4826  # σ of normal noise from its median absolute deviation
STEP_SHARE = 0.1  # a channel with this share of its tare readings left out saw a step (a load), not glitches
STEP_READINGS = 3  # ... and at least this many (a short window's one glitch is a large share)
MAX_RESTARTS = 5  # tares begun again for steps before the window is taken as it is


class Baseline:
    """Mean capacitance of the first ``frames`` readings after start or tare.

    Sentinel channels (NaN) are left out of the mean. A channel that gave no
    valid reading in the window keeps a NaN baseline (no force) until it has
    given ``frames`` valid readings of its own, then gets its baseline late:
    a trace that was open at start-up and recovers is not lost for good.
    A window that gave no channel a zero (a cable plugged in after it: open
    sentinels throughout) is no tare of the sensor at all: its first valid
    reading begins the window again, so the readings that make the zero are
    a tare window's (null and flagged ``taring`` live) and the zero is made
    as any (glitches, steps, own level), not channel by channel. A sensor
    that never sends one keeps no zero, its channels named as such.
    ``whole`` (a quad: each of its forces combines every channel): a channel
    without a zero leaves the sensor without one, so instead of a late zero
    of its own (made on another window than the others') the sensor's
    tare begins again at its first reading whose channels are all
    plausible and at one level (none off the others' level, ``off_level``):
    its null frames are flagged ``taring`` then, as any tare's, and its four
    zeros come from one window. Its zeros are judged each against the
    level of the others, so two channels off (5× or 0.41× the other two)
    are found as one is; the channels found off are named unzeroed.
    The sensor must be unloaded while it tares: a load present then becomes
    the new zero (the price of auto-tare; a later tare with the sensor free
    corrects it).

    ``window`` ((channels,) low and high pF, level0.tare_window_pF): a
    reading outside it is implausible (1 aF, the converter's top count) and,
    like a sentinel, takes no part in the mean; None accepts every reading.
    ``own_level`` (level0.own_level_window): given a finished tare's zeros,
    the window around the sensor's own level; a channel whose zero lies
    outside it (a converter fault while it tared: 5× its neighbours) gets
    none, and waits for a late zero within that window.

    A glitch inside the window (one reading of a mux settling late, ESD:
    plausible as a capacitance, 50 % off the others) would shift the zero
    for as long as the tare holds, a phantom load or a hidden one. So each
    channel's readings are kept, and those more than OUTLIER_SIGMAS robust
    σ (from the median absolute deviation, at least the noise floor) from
    the channel's median leave the mean and spread (``rejected`` counts
    them). Noise never goes that far (≈ 2·10⁻⁹ of readings); a tare
    without a glitch gives the plain mean, bit for bit.

    Glitches are single readings. A channel with STEP_SHARE of its readings
    left out (and at least STEP_READINGS) saw a step — a load put down or let go while it tared — and
    the level most of its readings had may be the load's: the tare begins
    again (``restarts`` counts it), at most MAX_RESTARTS times in a row,
    after which the window is taken as it is (the majority level).
    """

    def __init__(self, channels: int, frames: int = DEFAULT_TARE_FRAMES,
                 window: tuple[np.ndarray, np.ndarray] | None = None,
                 own_level: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray] | None] | None = None,
                 whole: bool = False) -> None:
        if frames < 1:
            raise ValueError(f"tare needs at least 1 frame, got frames={frames}")
        self.frames = frames
        self.window = self._window = window
        self.own_level = own_level
        self.whole = whole
        self._sum = np.zeros(channels)
        self._sum_sq = np.zeros(channels)
        self._count = np.zeros(channels, dtype=np.int64)
        self._samples = np.full((frames, channels), np.nan)  # row k: each channel's k-th valid reading
        self.rejected = np.zeros(channels, dtype=np.int64)  # glitches left out of this tare, per channel
        self._seen = 0
        self.value = np.full(channels, np.nan)
        self.std = np.full(channels, np.nan)
        self._late = np.zeros(channels, dtype=bool)
        self._any_late = False  # checked per reading: a bool, not an array scan
        self.zeroless = False  # ready, and no channel has a zero: the next valid reading begins the window again
        self.restarts = 0  # windows begun again for a step since the last tare asked for

    @property
    def ready(self) -> bool:
        return self._seen >= self.frames

    def tare(self) -> None:
        """Start a fresh baseline over the next ``frames`` readings."""
        self._begin()
        self.restarts = 0

    def _begin(self) -> None:
        self.window = self._window
        self._sum[:] = 0.0
        self._sum_sq[:] = 0.0
        self._count[:] = 0
        self._samples.fill(np.nan)
        self.rejected = np.zeros_like(self.rejected)
        self._seen = 0
        self.value = np.full_like(self.value, np.nan)
        self.std = np.full_like(self.std, np.nan)
        self._late[:] = False
        self._any_late = False
        self.zeroless = False

    def preset(self, value_pF: np.ndarray, std_pF: np.ndarray) -> None:
        """Take a zero made elsewhere (a recording's, made live before it
        began) as complete; a channel without one (NaN) waits for its own
        late zero as here."""
        self.tare()
        self.value, self.std = value_pF.copy(), std_pF.copy()
        self._seen = self.frames
        self._late = np.isnan(self.value)
        self._narrow_late()
        self._any_late = bool(self._late.any())
        self.zeroless = self._without_zero()  # as live: it tares from its first valid reading

    def rewindow(self, window: tuple[np.ndarray, np.ndarray] | None) -> None:
        """Take ``window`` (another calibration's C0: calibration_choice.py)
        from the next reading on: the zeros made keep, a tare under way or
        a channel still without a zero takes readings within it (a late
        one within its own level's window, as before), and a sensor without
        any zero begins its tare at its first reading inside it."""
        self.window = self._window = window
        if self.ready:
            self._narrow_late()

    def window_so_far(self) -> dict | None:
        """A tare window in progress as JSON values (None once ready): readings
        ``seen``, ``restarts``, and per channel its valid readings ``count``,
        their running ``sum_pF`` and ``sum_sq_pF2`` and the readings
        themselves, ``samples_pF`` (row k: each channel's k-th, None for none):
        what a recording begun now stores so its replay goes on with it."""
        if self.ready:
            return None
        rows = int(self._count.max(initial=0))
        return {"seen": self._seen, "restarts": self.restarts, "count": self._count.tolist(),
                "sum_pF": self._sum.tolist(), "sum_sq_pF2": self._sum_sq.tolist(),
                "samples_pF": [[None if v != v else v for v in row] for row in self._samples[:rows].tolist()]}

    def resume_window(self, so_far: dict) -> None:
        """Go on with a tare window ``window_so_far`` gave (made elsewhere: a
        recording's, begun while the sensor tared); ValueError when it is not
        this baseline's size."""
        count = np.array(so_far["count"], dtype=np.int64)
        total, total_sq = np.array(so_far["sum_pF"], dtype=float), np.array(so_far["sum_sq_pF2"], dtype=float)
        samples = np.array([[np.nan if v is None else v for v in row] for row in so_far["samples_pF"]], dtype=float)
        seen = int(so_far["seen"])
        shapes = {count.shape, total.shape, total_sq.shape} | ({samples.shape[1:]} if samples.size else set())
        if shapes != {self._count.shape} or not len(samples) <= seen < self.frames:
            raise ValueError(f"tare window of {seen} readings ({len(samples)} kept) of {count.size} channels: this "
                             f"baseline has {self._count.size} channels and a window of {self.frames}")
        self.tare()
        self._count, self._sum, self._sum_sq = count, total, total_sq
        if samples.size:
            self._samples[: len(samples)] = samples
        self._seen, self.restarts = seen, int(so_far["restarts"])

    def substitute(self, channels: np.ndarray, values_pF: np.ndarray) -> None:
        """Take ``values_pF`` (channels,) as the zero of ``channels`` (bool
        mask): a loaded tare's taxels get the calibration's C0. A new array,
        so caches keyed on it see the change."""
        self.value = np.where(channels, values_pF, self.value)

    def changes_zero(self, capacitance_pF: np.ndarray) -> bool:
        """Whether this reading (n,) pF would change the zero of the readings
        after it — complete a late channel's, or begin the window again of a
        sensor that has none — changing nothing."""
        if not self._any_late or not self.ready:
            return False
        if self.zeroless:
            return self._begins_again(capacitance_pF)
        valid = self._valid(capacitance_pF, self._late)
        return bool(np.any(self._late & valid & (self._count + 1 >= self.frames)))

    def _without_zero(self) -> bool:
        """Whether the sensor has no zero to read with: none of its channels
        has one (a whole sensor: one of them lacks one)."""
        return bool(self._late.any() if self.whole else self._late.all())

    def _begins_again(self, capacitance_pF: np.ndarray) -> bool:
        """Whether this reading begins the window again of a sensor without a
        zero: a channel of it valid (a whole sensor: all, and at one level)."""
        if not self.whole:
            return bool(self._valid(capacitance_pF, self._late).any())
        every = np.ones(self._late.shape, dtype=bool)
        return bool(self._valid(capacitance_pF, every).all()) and not self.off_level(capacitance_pF).any()

    def off_level(self, values_pF: np.ndarray) -> np.ndarray:
        """(n,) bool: the channels of ``values_pF`` outside the window of the
        others' level (own_level on the rest; judged only with enough of
        them); all False without an own_level."""
        off = np.zeros(values_pF.shape, dtype=bool)
        if self.own_level is None:
            return off
        for k in range(values_pF.size):
            rest = values_pF.copy()
            rest[k] = np.nan
            window = self.own_level(rest)
            if window is not None:
                off[k] = not window[0][k] <= values_pF[k] <= window[1][k]
        return off & (values_pF == values_pF)  # a NaN has no zero anyway: not off

    def update(self, capacitance_pF: np.ndarray) -> bool:
        """Feed one reading of shape (channels,); return whether the baseline
        is ready (the reading that completes it is already tared)."""
        if self.ready:
            if self.zeroless and self._begins_again(capacitance_pF):
                self._begin()  # the sensor's first valid reading (class docstring): not a restart for a step
                return self.update(capacitance_pF)
            if self._any_late and not self.zeroless:  # a sensor without a zero takes no late one
                self._accumulate(capacitance_pF, self._late)
                done = self._late & (self._count >= self.frames)
                if done.any():
                    self._finish(done)
                    self._late &= ~done
                    self._any_late = bool(self._late.any())
            return True
        self._accumulate(capacitance_pF, np.ones(self._count.shape, dtype=bool))
        self._seen += 1
        if self.ready:
            self._finish(self._count > 0)
            if self.restarts < MAX_RESTARTS and np.any((self.rejected > STEP_SHARE * self._count) & (self.rejected >= STEP_READINGS)):
                self._begin()
                self.restarts += 1
                return False
            self._late = self._count == 0
            self._set_aside_off_level()
            self._any_late = bool(self._late.any())
            self.zeroless = self._without_zero()  # a grid's never by a set-aside: at most a quarter of the zeros go
        return self.ready

    def _set_aside_off_level(self) -> None:
        """Channels whose zero lies outside the sensor's own level's window
        lose it; they and those that had none wait for a late zero inside
        the window of the zeros kept (what a replay starting from them finds).
        A whole sensor's zeros are judged each against the others' level
        (``off_level``), every one found off set aside: it tares again anyway."""
        if self.whole:
            off = self.off_level(self.value)
        else:
            window = self.own_level(self.value) if self.own_level is not None else None
            if window is None:
                return
            off = (self.value < window[0]) | (self.value > window[1])  # NaN compares False
        if not self.whole and np.count_nonzero(off) > np.count_nonzero(self.value == self.value) // 4:
            return  # no level most channels agree on (2 of a quad's 4 off): nothing to tell the faulty by
        if off.any():
            self.value = np.where(off, np.nan, self.value)
            self.std = np.where(off, np.nan, self.std)
            self._sum[off], self._sum_sq[off], self._count[off] = 0.0, 0.0, 0
            self._samples[:, off] = np.nan
            self._late |= off
        self._narrow_late()

    def _narrow_late(self) -> None:
        """The late channels take readings only within the window around the level of the zeros there are."""
        window = self.own_level(self.value) if self.own_level is not None and self._late.any() else None
        if window is not None:
            low, high = self._window if self._window is not None else (-np.inf, np.inf)
            self.window = (np.where(self._late, window[0], low), np.where(self._late, window[1], high))

    def _valid(self, capacitance_pF: np.ndarray, channels: np.ndarray) -> np.ndarray:
        """The ``channels`` (n,) bool whose reading counts towards the zero."""
        if self.window is None:
            return channels & ~np.isnan(capacitance_pF)
        # NaN compares False: a sentinel is left out as before
        return channels & (capacitance_pF >= self.window[0]) & (capacitance_pF <= self.window[1])

    def _accumulate(self, capacitance_pF: np.ndarray, channels: np.ndarray) -> None:
        valid = self._valid(capacitance_pF, channels)
        self._sum[valid] += capacitance_pF[valid]
        self._sum_sq[valid] += capacitance_pF[valid] ** 2
        self._samples[self._count[valid], valid] = capacitance_pF[valid]
        self._count += valid

    def _finish(self, channels: np.ndarray) -> None:
        """Set the baseline of ``channels`` (new arrays, so caches keyed on
        them see the change). The spread is the channel's noise floor."""
        total, total_sq, kept = self._without_glitches(channels)
        count = np.maximum(kept, 1)
        mean = total / count
        spread = np.sqrt(np.maximum(total_sq / count - mean**2, 0.0))
        self.value = np.where(channels, mean, self.value)
        self.std = np.where(channels & (kept > 1), spread, self.std)

    def _without_glitches(self, channels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(sum, sum of squares, count) of each channel's readings with its
        glitches taken out (the running sums themselves where there are none)."""
        samples = self._samples[:, channels]
        if not samples.size or np.isnan(samples).all():
            return self._sum, self._sum_sq, self._count
        with np.errstate(invalid="ignore"):
            median = np.nanmedian(samples, axis=0)
            deviation = np.abs(samples - median)
            limit = OUTLIER_SIGMAS * np.maximum(MAD_TO_SIGMA * np.nanmedian(deviation, axis=0), NOISE_FLOOR_PF)
            glitch = deviation > limit  # NaN (no reading) compares False
        if not glitch.any():
            return self._sum, self._sum_sq, self._count
        good = np.where(glitch | np.isnan(samples), 0.0, samples)  # the channels with a glitch: summed afresh
        hit = np.flatnonzero(channels)[glitch.any(axis=0)]
        columns = glitch.any(axis=0)
        total, total_sq, kept = self._sum.copy(), self._sum_sq.copy(), self._count.copy()
        total[hit] = good[:, columns].sum(axis=0)
        total_sq[hit] = (good[:, columns] ** 2).sum(axis=0)
        kept[hit] -= glitch[:, columns].sum(axis=0)
        self.rejected = self.rejected.copy()
        self.rejected[hit] += glitch[:, columns].sum(axis=0)
        return total, total_sq, kept

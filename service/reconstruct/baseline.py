"""Zero-load baseline per channel: auto-tare on start and on demand."""
from __future__ import annotations

import numpy as np

DEFAULT_TARE_FRAMES = 100


class Baseline:
    """Mean capacitance of the first ``frames`` readings after start or tare.

    Sentinel channels (NaN) are left out of the mean; a channel that never
    gave a valid reading keeps a NaN baseline, so it can never yield a force.
    The sensor must be unloaded while it tares: a load present then becomes
    the new zero (the price of auto-tare; a later tare with the sensor free
    corrects it).
    """

    def __init__(self, channels: int, frames: int = DEFAULT_TARE_FRAMES) -> None:
        if frames < 1:
            raise ValueError(f"tare needs at least 1 frame, got frames={frames}")
        self.frames = frames
        self._sum = np.zeros(channels)
        self._sum_sq = np.zeros(channels)
        self._count = np.zeros(channels, dtype=np.int64)
        self._seen = 0
        self.value = np.full(channels, np.nan)
        self.std = np.full(channels, np.nan)

    @property
    def ready(self) -> bool:
        return self._seen >= self.frames

    def tare(self) -> None:
        """Start a fresh baseline over the next ``frames`` readings."""
        self._sum[:] = 0.0
        self._sum_sq[:] = 0.0
        self._count[:] = 0
        self._seen = 0
        self.value = np.full_like(self.value, np.nan)
        self.std = np.full_like(self.std, np.nan)

    def update(self, capacitance_pF: np.ndarray) -> bool:
        """Feed one reading of shape (channels,); return whether the baseline
        is ready (the reading that completes it is already tared)."""
        if self.ready:
            return True
        valid = ~np.isnan(capacitance_pF)
        self._sum[valid] += capacitance_pF[valid]
        self._sum_sq[valid] += capacitance_pF[valid] ** 2
        self._count += valid
        self._seen += 1
        if self.ready:
            count = np.maximum(self._count, 1)
            mean = self._sum / count
            self.value = np.where(self._count > 0, mean, np.nan)
            # The spread of the tare window is the channel's noise floor.
            self.std = np.where(self._count > 1, np.sqrt(np.maximum(self._sum_sq / count - mean**2, 0.0)), np.nan)
        return self.ready

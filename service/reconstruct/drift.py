"""Slow common-mode drift of a grid, followed on its unloaded taxels.

Temperature and the fatigue creep of paper 001 §5.2 move every taxel's
capacitance together and slowly; a press moves a few taxels and fast. So
the drift is the median relative change of the taxels that read within
``band`` noise of the current drift estimate (the unloaded ones), followed
by an exponential average with time constant ``tau_s``. The median ignores
a press on a minority of taxels however slow it is; the estimate is frozen
while fewer than half the taxels are unloaded (a plate over the whole
array), and the frame is then flagged ``drift_suspect`` once that has
lasted ``suspect_after_s`` — as it is when the drift exceeds ``max_drift``.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DriftTracker:
    tau_s: float = 5.0
    band: float = 4.0
    max_drift: float = 0.01
    suspect_after_s: float = 10.0
    drift: float = 0.0
    _last_t: float | None = None
    _frozen_since: float | None = None

    def reset(self) -> None:
        self.drift, self._last_t, self._frozen_since = 0.0, None, None

    def update(self, relative: np.ndarray, noise: np.ndarray, t_s: float) -> bool:
        """Feed one frame of ΔC/C0 (n,) at time ``t_s``; return drift_suspect."""
        dt = 0.0 if self._last_t is None else min(max(t_s - self._last_t, 0.0), self.tau_s)
        self._last_t = t_s
        valid = ~np.isnan(relative)
        quiet = valid & (np.abs(relative - self.drift) < self.band * noise)
        if quiet.sum() * 2 >= valid.sum() and quiet.any():
            self.drift += (float(np.median(relative[quiet])) - self.drift) * (dt / self.tau_s)
            self._frozen_since = None
        elif self._frozen_since is None:
            self._frozen_since = t_s
        frozen_long = self._frozen_since is not None and t_s - self._frozen_since >= self.suspect_after_s
        return frozen_long or abs(self.drift) > self.max_drift

    @staticmethod
    def correct(relative: np.ndarray, drift: float) -> np.ndarray:
        """Remove a common-mode relative change: (1 + r)/(1 + d) − 1."""
        return (1.0 + relative) / (1.0 + drift) - 1.0

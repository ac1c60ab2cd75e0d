"""ForceFrame: one reconstructed frame, the unit every listener receives."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..readings import SensorInfo
from .contact import summarise
from .taxel_flags import TAXEL_FLAG_NAMES


@dataclass(slots=True)
class ForceFrame:
    """Forces of one scan.

    ``forces_N`` has shape (rows*cols,) for a grid (row-major normal force per
    taxel) or (3,) for a quad (Fx, Fy, Fz); NaN means "no value" and is
    serialised as null.
    """

    sensor: SensorInfo
    seq: int
    t_us: int
    t_host: float
    forces_N: np.ndarray
    capacitance_pF: np.ndarray
    flags: list[str]
    level: str
    taxel_flags: np.ndarray | None = None  # grid: (rows*cols,) bit set, see taxel_flags.TAXEL_FLAG_NAMES
    calibration: str = ""  # id of the calibration the forces rest on (registry id or "builtin-…")
    sigma_N: np.ndarray | None = None  # 1-σ of each force, shape of forces_N; NaN where the force is
    t_host_scan: float = float("nan")  # the scan's time on the host clock (s since the epoch), NaN: not mapped
    instance: str = ""  # a gateway's frame: the service instance that published it (host:pid:random); "" otherwise
    _contact: dict | None = field(default=None, init=False, repr=False, compare=False)

    @property
    def contact(self) -> dict | None:
        """Grid: total_N, cop_x_mm, cop_y_mm, area_mm2, contacts; None for a quad
        or a frame without any force (taring). Computed on first use: most
        listeners of a 1 kHz stream never ask."""
        if self._contact is None and self.sensor.kind == "grid" and not np.isnan(self.forces_N).all():
            self._contact = summarise(self.forces_N, self.sensor.rows, self.sensor.cols, self.sigma_N)
        return self._contact

    def keep_contact(self, summary: dict | None) -> None:
        """The contact summary found for many frames at once
        (record/contact_batch.py), bit for bit ``contact``'s."""
        self._contact = summary

    def taxel_flag_lists(self) -> dict[str, list[int]]:
        """Per-taxel flags as {name: [row-major taxel indices]}, only flags set."""
        return taxel_flag_lists(self.taxel_flags)


def taxel_flag_lists(bits: np.ndarray | None) -> dict[str, list[int]]:
    """(n,) per-taxel flag bits (taxel_flags.TAXEL_FLAG_NAMES) as {name: [row-major
    taxel indices]}, only flags set."""
    if bits is None or not np.count_nonzero(bits):  # ndarray.any() costs 5× more at this size, on every frame
        return {}
    out = {}
    for bit, name in TAXEL_FLAG_NAMES.items():
        hits = np.flatnonzero(bits & bit)
        if hits.size:
            out[name] = hits.tolist()
    return out

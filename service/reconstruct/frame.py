"""ForceFrame: one reconstructed frame, the unit every listener receives."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..readings import SensorInfo


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

    def export_dict(self) -> dict:
        """The replay export / stream shape (one JSON object per frame)."""
        key = "taxels_N" if self.sensor.kind == "grid" else "fxyz_N"
        return {
            "sensor": self.sensor.id,
            "seq": self.seq,
            "t_us": self.t_us,
            "kind": self.sensor.kind,
            key: self.forces_N,
            "flags": self.flags,
        }

    def stream_dict(self) -> dict:
        out = self.export_dict()
        out["t_host"] = self.t_host
        if self.sensor.kind == "grid":
            out["rows"] = self.sensor.rows
            out["cols"] = self.sensor.cols
        return out


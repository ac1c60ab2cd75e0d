"""Forward physics of the simulated sensors: force → capacitance (pF).

Grid: each taxel follows the layered model's ΔC/C0(F) table scaled to its
table-1 sensitivity (service.physics.taxel_response), its neighbours feel the
mechanical crosstalk measured in paper 000, an optional common-mode drift
(temperature) scales every channel, and the multiplexer may leak a fraction
of each channel into the next one scanned. Quad: the calibrated curves of
the carbon black/PDMS paper (fits 34 and 35) through the four electrodes.
The quad's C0 is not given by the paper: ε0·εr·S/d with S = 10×10 mm²,
d = 2 mm and an assumed εr = 5 gives about 2.2 pF per electrode.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from service.physics.crosstalk_model import PAPER_MECHANICAL_COUPLING, CrosstalkModel
from service.physics.paper_data import PITCH_MM, GridCalibration, grid_calibration, taxel_centres_mm
from service.physics.quad_model import QuadModel
from service.physics.taxel_response import taxel_response

GRID_PITCH_MM = PITCH_MM
QUAD_C0_PF = (2.21, 2.18, 2.24, 2.20)


@dataclass
class Drift:
    """Common-mode relative drift: a slow sinusoid of ``amplitude`` (ΔC/C0)
    and ``period_s``, as a day's temperature swing compressed."""

    amplitude: float = 0.0
    period_s: float = 60.0

    def __call__(self, t: float) -> float:
        return self.amplitude * math.sin(2 * math.pi * t / self.period_s)


@dataclass
class SimGrid:
    id: int
    rows: int = 8
    cols: int = 8
    mounting: str = "flat"
    mechanical_coupling: float = PAPER_MECHANICAL_COUPLING
    electrical_leakage: float = 0.0
    drift: Drift = field(default_factory=Drift)
    calibration: GridCalibration | None = None  # None: table 1 (8x8) or its mean (other shapes)
    serial: str | None = None  # announced in INFO when set (protocol: the sensor's own identity)
    kind: str = field(default="grid", init=False)

    def __post_init__(self) -> None:
        calibration = self.calibration or grid_calibration(self.rows, self.cols)
        if (calibration.rows, calibration.cols) != (self.rows, self.cols):
            raise ValueError(f"calibration is {calibration.rows}x{calibration.cols}, the grid {self.rows}x{self.cols}")
        self.c0_pF = np.array(calibration.c0_pF)
        self.response = taxel_response(calibration, self.mounting)
        self.crosstalk = CrosstalkModel(self.rows, self.cols, self.mechanical_coupling, self.electrical_leakage)

    @property
    def channels(self) -> int:
        return self.rows * self.cols

    def taxel_centres_mm(self) -> tuple[np.ndarray, np.ndarray]:
        return taxel_centres_mm(self.rows, self.cols)

    def capacitance(self, forces_N: np.ndarray, t: float = 0.0) -> np.ndarray:
        """(rows*cols,) normal forces → (rows*cols,) capacitances in pF as read."""
        relative = self.crosstalk.mix_mechanical(self.response.forward(forces_N))
        return self.crosstalk.leak(self.c0_pF * (1.0 + relative) * (1.0 + self.drift(t)))

    def info(self) -> dict:
        doc = {"id": self.id, "kind": "grid", "rows": self.rows, "cols": self.cols}
        return doc if self.serial is None else {**doc, "serial": self.serial}


@dataclass
class SimQuad:
    id: int
    c0_pF: tuple[float, float, float, float] = QUAD_C0_PF
    model: QuadModel = field(default_factory=QuadModel)
    kind: str = field(default="quad", init=False)
    channels: int = field(default=4, init=False)

    def capacitance(self, fxyz_N: np.ndarray, t: float = 0.0) -> np.ndarray:
        """(Fx, Fy, Fz) → (4,) capacitances C11, C12, C21, C22 in pF."""
        return np.asarray(self.c0_pF) * (1.0 + self.model.forward(np.asarray(fxyz_N, dtype=float)))

    def info(self) -> dict:
        return {"id": self.id, "kind": "quad"}

"""What the two papers measured, as the service carries it.

Table 1 of the 8x8 array paper (Liang et al. 2015): per-taxel initial
capacitance C0 and measured sensitivity (%/N over 0–10 N), copied into
``service/data`` so the service never reads anything outside its package;
the array's 4 mm pitch and taxel centres.

Quad sensor (Carbon black/PDMS paper, 2022): the paper's least-squares
fits, eq (34) normal ΔC/C0 = −0.0009 F² + 0.0343 F + 0.0032 over 0–20 N and
eq (35) tangential ΔC/C0 = −0.0004 F² + 0.0077 F + 0.0011 over 0–10 N. The
constant terms are fit offsets (a tared sensor reads ΔC = 0 at zero force),
so the level-0 slopes are the linear coefficients, 0.0343 /N and 0.0077 /N.
"""
from __future__ import annotations

import csv
from dataclasses import dataclass
from functools import lru_cache
from importlib import resources

import numpy as np

TABLE1_ROWS = 8
TABLE1_COLS = 8
MEAN_SENSITIVITY_PER_N = 0.01247  # table 1 mean, used for grids of other shapes

FIT34 = (-0.0009, 0.0343, 0.0032)  # normal: ΔC/C0 = c2 F² + c1 F + c0, 0–20 N
FIT35 = (-0.0004, 0.0077, 0.0011)  # tangential, 0–10 N
NORMAL_RANGE_N = 20.0
SHEAR_RANGE_N = 10.0
QUAD_NORMAL_SLOPE_PER_N = FIT34[1]
QUAD_SHEAR_SLOPE_PER_N = FIT35[1]
QUAD_DIELECTRIC_MM = 2.0
QUAD_ELECTRODE_AREA_MM2 = 100.0

PITCH_MM = 4.0

# Ids of the calibrations every sensor without its own uses (the registry's built-ins).
BUILTIN_GRID_ID = "builtin-table1"
BUILTIN_QUAD_ID = "builtin-fits34-35"


@dataclass(frozen=True)
class GridCalibration:
    """Per-taxel data of one grid, arrays of shape (rows*cols,), row-major."""

    rows: int
    cols: int
    c0_pF: np.ndarray
    sensitivity_per_N: np.ndarray  # fractional ΔC/C0 per newton


@lru_cache(maxsize=1)
def table1() -> GridCalibration:
    """Table 1 of the 8x8 array paper as arrays of shape (64,), row-major."""
    text = resources.files("service").joinpath("data/array8x8_table1.csv").read_text()
    c0 = np.full(TABLE1_ROWS * TABLE1_COLS, np.nan)
    sens = np.full(TABLE1_ROWS * TABLE1_COLS, np.nan)
    for row in csv.DictReader(text.splitlines()):
        index = (int(row["row"]) - 1) * TABLE1_COLS + int(row["col"]) - 1
        c0[index] = float(row["c0_pF"])
        sens[index] = float(row["sensitivity_pct_per_N"]) / 100.0
    if np.isnan(c0).any() or np.isnan(sens).any():
        raise ValueError("table 1 data is incomplete: every one of the 64 taxels needs C0 and sensitivity")
    c0.flags.writeable = False
    sens.flags.writeable = False
    return GridCalibration(TABLE1_ROWS, TABLE1_COLS, c0, sens)


def grid_calibration(rows: int, cols: int) -> GridCalibration:
    """Calibration for a grid without its own: table 1 for an 8x8 grid, the
    table's mean sensitivity (and C0) for any other shape."""
    if (rows, cols) == (TABLE1_ROWS, TABLE1_COLS):
        return table1()
    n = rows * cols
    return GridCalibration(rows, cols, np.full(n, float(table1().c0_pF.mean())), np.full(n, MEAN_SENSITIVITY_PER_N))


@lru_cache(maxsize=16)
def taxel_centres_mm(rows: int, cols: int, pitch_mm: float = PITCH_MM) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of each taxel centre, shape (rows*cols,) each, in the array
    frame: origin at the centre, x along columns, y along rows (cached: do
    not modify)."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return (c - (cols - 1) / 2) * pitch_mm, (r - (rows - 1) / 2) * pitch_mm

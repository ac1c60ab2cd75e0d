"""Contact summary of grid frames: total force, centre of pressure, area, contacts.

Array frame: origin at the array's centre, x along columns (column 1 at
x = −(cols−1)/2 · pitch), y along rows (row 1 at y = −(rows−1)/2 · pitch),
millimetres. A taxel is in contact when its force exceeds the threshold;
contacts are 4-connected regions of such taxels.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

PITCH_MM = 4.0
DEFAULT_THRESHOLD_N = 0.05


@lru_cache(maxsize=16)
def taxel_centres_mm(rows: int, cols: int, pitch_mm: float = PITCH_MM) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of each taxel centre, shape (rows*cols,) each (cached: do not modify)."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return (c - (cols - 1) / 2) * pitch_mm, (r - (rows - 1) / 2) * pitch_mm


def _regions(cells: list[int], cols: int) -> int:
    """4-connected regions among active cell indices (row-major); a flood
    fill over the few active cells beats any array method at this size."""
    remaining = set(cells)
    regions = 0
    while remaining:
        regions += 1
        stack = [remaining.pop()]
        while stack:
            cell = stack.pop()
            row, col = divmod(cell, cols)
            for neighbour, inside in ((cell - cols, row > 0), (cell + cols, True), (cell - 1, col > 0), (cell + 1, col < cols - 1)):
                if inside and neighbour in remaining:
                    remaining.remove(neighbour)
                    stack.append(neighbour)
    return regions


def count_regions(active: np.ndarray) -> np.ndarray:
    """Number of 4-connected regions of True in (..., rows, cols) masks."""
    cols = active.shape[-1]
    flat = active.reshape(-1, active.shape[-2] * cols)
    counts = np.array([_regions(np.flatnonzero(mask).tolist(), cols) if mask.any() else 0 for mask in flat], dtype=np.int64)
    return counts.reshape(active.shape[:-2])


def summarise(forces_N: np.ndarray, rows: int, cols: int, threshold_N: float = DEFAULT_THRESHOLD_N) -> dict:
    """Contact summary of (..., rows*cols) forces (NaN = no reading).

    Returns arrays of shape (...): total_N, cop_x_mm, cop_y_mm (NaN without
    contact), area_mm2, contacts."""
    forces = np.asarray(forces_N, dtype=float)
    active = forces > threshold_N  # NaN compares False: no reading, no contact
    loaded = np.where(active, forces, 0.0)
    total = loaded.sum(axis=-1)
    if not active.any():
        zeros = np.zeros(total.shape)
        return {"total_N": zeros, "cop_x_mm": np.full(total.shape, np.nan), "cop_y_mm": np.full(total.shape, np.nan),
                "area_mm2": zeros, "contacts": np.zeros(total.shape, dtype=np.int64)}
    x, y = taxel_centres_mm(rows, cols)
    with np.errstate(invalid="ignore", divide="ignore"):
        cop_x = np.where(total > 0, (loaded * x).sum(axis=-1) / total, np.nan)
        cop_y = np.where(total > 0, (loaded * y).sum(axis=-1) / total, np.nan)
    return {
        "total_N": total,
        "cop_x_mm": cop_x,
        "cop_y_mm": cop_y,
        "area_mm2": active.sum(axis=-1) * PITCH_MM * PITCH_MM,
        "contacts": count_regions(active.reshape(active.shape[:-1] + (rows, cols))),
    }

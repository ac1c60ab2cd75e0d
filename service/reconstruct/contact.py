"""Contact summary of grid frames: total force, centre of pressure, area, contacts.

Array frame: origin at the array's centre, x along columns (column 1 at
x = −(cols−1)/2 · pitch), y along rows (row 1 at y = −(rows−1)/2 · pitch),
millimetres. A taxel is in contact when its force exceeds the threshold;
contacts are 4-connected regions of such taxels.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import PITCH_MM, taxel_centres_mm

DEFAULT_THRESHOLD_N = 0.05


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


def summarise(forces_N: np.ndarray, rows: int, cols: int, threshold_N: float = DEFAULT_THRESHOLD_N) -> dict:
    """Contact summary of one frame's (rows*cols,) forces (NaN = no reading).

    Returns plain numbers: total_N, cop_x_mm, cop_y_mm (NaN without
    contact), area_mm2, contacts."""
    active = np.flatnonzero(forces_N > threshold_N)  # NaN compares False: no reading, no contact
    if not active.size:
        return {"total_N": 0.0, "cop_x_mm": float("nan"), "cop_y_mm": float("nan"), "area_mm2": 0.0, "contacts": 0}
    loaded = forces_N[active]
    total = float(loaded.sum())
    x, y = taxel_centres_mm(rows, cols)
    return {
        "total_N": total,
        "cop_x_mm": float(x[active] @ loaded) / total,
        "cop_y_mm": float(y[active] @ loaded) / total,
        "area_mm2": active.size * PITCH_MM * PITCH_MM,
        "contacts": _regions(active.tolist(), cols),
    }

"""Contact summary of grid frames: total force, centre of pressure, area, contacts.

Array frame: origin at the array's centre, x along columns (column 1 at
x = −(cols−1)/2 · pitch), y along rows (row 1 at y = −(rows−1)/2 · pitch),
millimetres. A taxel is in contact when its force exceeds the threshold
and NOISE_SIGMAS times its σ (``contact_threshold``); contacts are
4-connected regions of such taxels.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import PITCH_MM, taxel_centres_mm

DEFAULT_THRESHOLD_N = 0.05
# A fixed 0.05 N alone put phantom contacts on untouched low-C0 or large grids (a 1x4 at 3 pF: 60 % of frames, a
# 16x16: 41 %): their noise is that size. At 4 σ an untouched 16x16 shows one in ~0.5 % of frames (tests/test_contact.py).
NOISE_SIGMAS = 4.0
NOISE_CAP_N = 0.5  # σ of a large force holds its gain and model terms: no reason to miss it


def contact_threshold(sigma_N: np.ndarray | None, threshold_N: float = DEFAULT_THRESHOLD_N) -> np.ndarray | float:
    """Per taxel (σ's shape), the force above which it is in contact:
    ``threshold_N``, or NOISE_SIGMAS σ where larger (at most NOISE_CAP_N). A
    null σ (a saturated taxel's; none kept) or none: ``threshold_N``."""
    if sigma_N is None:
        return threshold_N
    # σ as float32, as the history ring keeps it: a frame read back from history has the same contacts.
    return np.minimum(np.fmax(threshold_N, NOISE_SIGMAS * np.asarray(sigma_N, dtype=np.float32)),
                      max(threshold_N, NOISE_CAP_N))


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


def summarise(forces_N: np.ndarray, rows: int, cols: int, sigma_N: np.ndarray | None = None,
              threshold_N: float = DEFAULT_THRESHOLD_N) -> dict:
    """Contact summary of one frame's (rows*cols,) forces (NaN = no reading)
    with their σ (rows*cols,) (None: the threshold alone).

    Returns plain numbers: total_N, cop_x_mm, cop_y_mm (NaN without
    contact), area_mm2, contacts."""
    active = np.flatnonzero(forces_N > contact_threshold(sigma_N, threshold_N))  # NaN compares False: no contact
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

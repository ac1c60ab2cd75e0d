"""Contact summary of grid frames: total force, centre of pressure, area, contacts.

Array frame: origin at the array's centre, x along columns (column 1 at
x = −(cols−1)/2 · pitch), y along rows (row 1 at y = −(rows−1)/2 · pitch),
millimetres. A taxel is in contact when its force exceeds the threshold;
contacts are 4-connected regions of such taxels, counted by label
propagation vectorised over a batch of frames.
"""
from __future__ import annotations

import numpy as np

PITCH_MM = 4.0
DEFAULT_THRESHOLD_N = 0.05


def taxel_centres_mm(rows: int, cols: int, pitch_mm: float = PITCH_MM) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) of each taxel centre, shape (rows*cols,) each."""
    r, c = np.divmod(np.arange(rows * cols), cols)
    return (c - (cols - 1) / 2) * pitch_mm, (r - (rows - 1) / 2) * pitch_mm


def count_regions(active: np.ndarray) -> np.ndarray:
    """Number of 4-connected regions of True in (..., rows, cols) masks."""
    shape = active.shape
    rows, cols = shape[-2:]
    big = rows * cols
    labels = np.where(active, np.arange(big).reshape(rows, cols), big)
    while True:
        best = labels.copy()
        best[..., 1:, :] = np.minimum(best[..., 1:, :], labels[..., :-1, :])
        best[..., :-1, :] = np.minimum(best[..., :-1, :], labels[..., 1:, :])
        best[..., :, 1:] = np.minimum(best[..., :, 1:], labels[..., :, :-1])
        best[..., :, :-1] = np.minimum(best[..., :, :-1], labels[..., :, 1:])
        best = np.where(active, best, big)
        if np.array_equal(best, labels):
            break
        labels = best
    own = np.arange(big).reshape(rows, cols)
    return (active & (labels == own)).sum(axis=(-2, -1))


def summarise(forces_N: np.ndarray, rows: int, cols: int, threshold_N: float = DEFAULT_THRESHOLD_N) -> dict:
    """Contact summary of (..., rows*cols) forces (NaN = no reading).

    Returns arrays of shape (...): total_N, cop_x_mm, cop_y_mm (NaN without
    contact), area_mm2, contacts."""
    forces = np.nan_to_num(np.asarray(forces_N, dtype=float), nan=0.0)
    active = forces > threshold_N
    loaded = np.where(active, forces, 0.0)
    total = loaded.sum(axis=-1)
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

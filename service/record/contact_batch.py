"""Contact summaries of many grid frames at once, equal bit for bit to
``reconstruct.contact.summarise`` frame by frame.

Frames are grouped by their number k of loaded taxels: each group's loaded
forces form a (m, k) matrix whose row sums and row dot products run the same
numpy kernels, on the same contiguous k values, as the per-frame code (a
row sum of a C-contiguous matrix is the pairwise sum of a 1-D array; a
stacked (1, k) @ (k, 1) product is the vector dot product). Contacts (4-connected
regions) are integers, counted by label propagation on all frames together.
"""
from __future__ import annotations

import numpy as np

from ..physics.paper_data import PITCH_MM, taxel_centres_mm
from ..reconstruct.contact import DEFAULT_THRESHOLD_N, contact_threshold


def summaries(forces_N: np.ndarray, rows: int, cols: int, sigma_N: np.ndarray | None = None,
              threshold_N: float = DEFAULT_THRESHOLD_N) -> list[dict | None]:
    """Per frame of (N, rows*cols) forces and their σ (N, rows*cols) (None:
    the threshold alone): ForceFrame.contact's value (None for a frame
    without any force)."""
    found = columns(forces_N, rows, cols, sigma_N, threshold_N)
    return [None if none else {"total_N": total, "cop_x_mm": x, "cop_y_mm": y, "area_mm2": area, "contacts": contacts}
            for none, total, x, y, area, contacts in zip(*(column.tolist() for column in found))]


def sigmas(frames, shape: tuple[int, int]) -> np.ndarray:
    """(N, n) σ of N frames of one grid, 0 for a frame without (the threshold alone, as summarise without σ)."""
    if all(f.sigma_N is not None for f in frames):
        return np.concatenate([f.sigma_N for f in frames]).reshape(shape)
    return np.stack([np.zeros(shape[1]) if f.sigma_N is None else f.sigma_N for f in frames])


def columns(forces_N: np.ndarray, rows: int, cols: int, sigma_N: np.ndarray | None = None,
            threshold_N: float = DEFAULT_THRESHOLD_N) -> tuple:
    """(no force at all, total_N, cop_x_mm, cop_y_mm, area_mm2, contacts), each (N,)."""
    active = forces_N > contact_threshold(sigma_N, threshold_N)  # NaN compares False
    counts = np.count_nonzero(active, axis=1)
    total = np.zeros(len(forces_N))
    cop_x = np.full(len(forces_N), np.nan)
    cop_y = np.full(len(forces_N), np.nan)
    x, y = taxel_centres_mm(rows, cols)
    for k in np.unique(counts[counts > 0]).tolist():
        members = np.flatnonzero(counts == k)
        mask = active[members]
        loaded = forces_N[members][mask].reshape(-1, k)
        sums = loaded.sum(axis=1)
        total[members] = sums
        for centres, out in ((x, cop_x), (y, cop_y)):
            taken = np.broadcast_to(centres, mask.shape)[mask].reshape(-1, k)
            out[members] = np.matmul(taken[:, None, :], loaded[:, :, None]).ravel() / sums
    return np.isnan(forces_N).all(axis=1), total, cop_x, cop_y, counts * PITCH_MM * PITCH_MM, regions(active, rows, cols)


def regions(active: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """4-connected regions of each frame's (rows*cols,) active taxels: every
    active taxel takes the smallest index of its neighbours until nothing
    changes; a region is a taxel that kept its own index."""
    out = np.zeros(len(active), dtype=np.int64)
    busy = np.flatnonzero(active.any(axis=1))
    if not busy.size:
        return out
    on = active[busy].reshape(-1, rows, cols)
    none = rows * cols
    index = np.arange(none).reshape(rows, cols)
    labels = np.where(on, index, none)
    while True:
        spread = labels.copy()
        np.minimum(spread[:, 1:], labels[:, :-1], out=spread[:, 1:])
        np.minimum(spread[:, :-1], labels[:, 1:], out=spread[:, :-1])
        np.minimum(spread[:, :, 1:], labels[:, :, :-1], out=spread[:, :, 1:])
        np.minimum(spread[:, :, :-1], labels[:, :, 1:], out=spread[:, :, :-1])
        spread = np.where(on, spread, none)
        if np.array_equal(spread, labels):
            break
        labels = spread
    out[busy] = np.count_nonzero(on & (labels == index), axis=(1, 2))
    return out

"""One-dimensional piecewise polynomial bases for the Ritz solver.

A basis is C0-continuous on a partition ``breaks`` of an interval, of
degree ``p`` on every element. Three families span the same space and
differ only in conditioning:

``legendre``
    hierarchical integrated Legendre (Lobatto) functions: linear vertex
    functions plus bubbles (P_k − P_{k−2})/√(2(2k−1)), k = 2..p, whose
    derivatives are orthogonal — the stiffness of the bubbles is diagonal.
``lagrange``
    nodal Lagrange functions at the Gauss–Lobatto–Legendre points.
``monomial``
    vertex functions plus bubbles (1 − ξ²) ξ^(k−2): the naive choice, whose
    Gram matrices lose about a digit per degree — kept to show what the
    conditioning guard is for.

Only vertex functions are nonzero at element ends (true of all three), so a
Dirichlet condition at either end of the interval removes one function.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.polynomial import legendre as npleg

FAMILIES = ("legendre", "lagrange", "monomial")


def gauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Legendre points and weights on [−1, 1], shape (n,) each."""
    return npleg.leggauss(n)


def _gll_points(p: int) -> np.ndarray:
    """The p+1 Gauss–Lobatto–Legendre points on [−1, 1]."""
    interior = npleg.legroots(npleg.legder([0] * p + [1])) if p > 1 else np.array([])
    return np.concatenate([[-1.0], np.sort(interior), [1.0]])


def local_functions(family: str, p: int, xi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values and ξ-derivatives of the p+1 local functions at points ``xi``.

    Returns two arrays of shape (p+1, len(xi)); rows 0 and 1 are the vertex
    functions at ξ = −1 and ξ = +1, rows 2.. the element's interior functions.
    """
    if p < 1:
        raise ValueError(f"polynomial degree must be >= 1, got p={p}")
    xi = np.asarray(xi, dtype=float)
    values = np.empty((p + 1, xi.size))
    slopes = np.empty((p + 1, xi.size))
    if family == "lagrange":
        nodes = _gll_points(p)
        order = [0, p] + list(range(1, p))
        for row, i in enumerate(order):
            others = np.delete(nodes, i)
            coeffs = np.poly(others) / np.prod(nodes[i] - others)
            values[row] = np.polyval(coeffs, xi)
            slopes[row] = np.polyval(np.polyder(coeffs), xi)
        return values, slopes
    values[0], slopes[0] = (1 - xi) / 2, -0.5
    values[1], slopes[1] = (1 + xi) / 2, 0.5
    for k in range(2, p + 1):
        if family == "legendre":
            c = np.zeros(k + 1)
            c[k], c[k - 2] = 1.0, -1.0
            c /= np.sqrt(2.0 * (2 * k - 1))
            values[k] = npleg.legval(xi, c)
            slopes[k] = npleg.legval(xi, npleg.legder(c))
        elif family == "monomial":
            values[k] = (1 - xi**2) * xi ** (k - 2)
            slopes[k] = -2 * xi ** (k - 1) + (k - 2) * (1 - xi**2) * xi ** max(k - 3, 0) * (k > 2)
        else:
            raise ValueError(f"unknown basis family {family!r}; known: {', '.join(FAMILIES)}")
    return values, slopes


@dataclass(frozen=True)
class Basis1D:
    """A C0 piecewise basis of degree ``p`` on the partition ``breaks``.

    Global numbering: vertex functions 0..ne, then each element's p−1
    interior functions in element order. ``size`` = ne·p + 1.
    """

    breaks: tuple[float, ...]
    p: int
    family: str = "legendre"

    def __post_init__(self) -> None:
        if self.family not in FAMILIES:
            raise ValueError(f"unknown basis family {self.family!r}; known: {', '.join(FAMILIES)}")
        if len(self.breaks) < 2 or np.any(np.diff(self.breaks) <= 0):
            raise ValueError(f"breaks must be strictly increasing with at least 2 points, got {self.breaks}")
        if self.p < 1:
            raise ValueError(f"polynomial degree must be >= 1, got p={self.p}")

    @property
    def elements(self) -> int:
        return len(self.breaks) - 1

    @property
    def size(self) -> int:
        return self.elements * self.p + 1

    @cached_property
    def dofs(self) -> np.ndarray:
        """(elements, p+1) global index of each local function."""
        ne, p = self.elements, self.p
        out = np.empty((ne, p + 1), dtype=np.int64)
        out[:, 0] = np.arange(ne)
        out[:, 1] = np.arange(1, ne + 1)
        out[:, 2:] = ne + 1 + np.arange(ne * (p - 1)).reshape(ne, p - 1)
        return out

    def end_dof(self, end: str) -> int:
        """Global index of the vertex function at the interval's 'start' or 'end'."""
        return {"start": 0, "end": self.elements}[end]

    def quadrature(self, points_per_element: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Gauss points over the whole partition: (x, weights, element index),
        each of shape (elements·n,). Default n = p + 2 (exact for products of
        two basis functions times a linear weight)."""
        n = points_per_element or self.p + 2
        xi, w = gauss(n)
        a, b = np.asarray(self.breaks[:-1]), np.asarray(self.breaks[1:])
        half = (b - a) / 2
        x = (a[:, None] + half[:, None] * (xi[None, :] + 1)).ravel()
        weights = (half[:, None] * w[None, :]).ravel()
        element = np.repeat(np.arange(self.elements), n)
        return x, weights, element

    def evaluate(self, x: np.ndarray, derivative: int = 0) -> np.ndarray:
        """Dense (len(x), size) matrix of basis values (or first derivatives)
        at points ``x`` inside the partition."""
        x = np.asarray(x, dtype=float)
        breaks = np.asarray(self.breaks)
        if np.any(x < breaks[0] - 1e-12 * (breaks[-1] - breaks[0])) or np.any(x > breaks[-1] * (1 + 1e-12) + 1e-300):
            raise ValueError(f"points outside [{breaks[0]}, {breaks[-1]}]")
        element = np.clip(np.searchsorted(breaks, x, side="right") - 1, 0, self.elements - 1)
        a, b = breaks[element], breaks[element + 1]
        xi = 2 * (x - a) / (b - a) - 1
        out = np.zeros((x.size, self.size))
        for e in np.unique(element):
            sel = np.nonzero(element == e)[0]
            values, slopes = local_functions(self.family, self.p, xi[sel])
            local = values if derivative == 0 else slopes * (2 / (b[sel[0]] - a[sel[0]]))
            out[np.ix_(sel, self.dofs[e])] = local.T
        return out

    def gram(self, da: int, db: int, weight_per_element: np.ndarray | None = None) -> np.ndarray:
        """Dense (size, size) matrix ∫ φ_i^(da) φ_j^(db) c(x) dx with c constant
        on each element (``weight_per_element``, shape (elements,); default 1)."""
        x, w, element = self.quadrature()
        if weight_per_element is not None:
            w = w * np.asarray(weight_per_element, dtype=float)[element]
        left = self.evaluate(x, da)
        right = left if da == db else self.evaluate(x, db)
        return (left * w[:, None]).T @ right

"""Ritz energy solver for one taxel of the 8x8 PET/PDMS/PET array (paper 000).

The unit cell is a layered plate: x, y ∈ [−a, a] (a = 2 mm), z ∈ [0, H]
(bottom PET 25 µm, PDMS 20 µm, top PET 25 µm), bottom face clamped, outer
side faces clamped (as the paper's edge and corner regions), a traction on
the central 3×3 mm of the top face. By symmetry only the quarter
x, y ∈ [0, a] is solved, with the mirror condition chosen per load (a normal
load is even in x and y; a shear load along x makes w and v odd in x).

Displacements are tensor products of 1-D C0 piecewise bases
(``basis1d``): in z one element per layer, so the basis is layerwise and
continuous across the interfaces while its derivative may jump there — the
strain jump the paper's global Chebyshev × sigmoid basis cannot represent.
In x and y the partition is split at the load edge (the paper's
central/edge/corner regions in another guise) and graded towards it, where
a boundary layer about (D/k)^¼ ≈ 60 µm wide forms. Since the material
depends on z only, every stiffness block is a sum of Kronecker products
A_x ⊗ A_y ⊗ A_z[c(z)] of 1-D matrices.

Units: µm, MPa; forces in MPa·µm² = µN; displacements in µm.

Every solve is guarded: the reciprocal condition number of the
Jacobi-equilibrated stiffness is estimated (1-norm, Hager/Higham) and a
solve below ``rcond_min`` raises :class:`ConditioningError`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .basis1d import Basis1D

PET_E_MPA, PET_NU = 4000.0, 0.4
PDMS_E_MPA, PDMS_NU = 0.55, 0.49


@dataclass(frozen=True)
class Layer:
    name: str
    thickness_um: float
    E_MPa: float
    nu: float

    def __post_init__(self) -> None:
        if not (self.thickness_um > 0 and self.E_MPa > 0):
            raise ValueError(f"layer {self.name!r}: thickness and E must be positive")
        if not -1.0 < self.nu < 0.5:
            raise ValueError(f"layer {self.name!r}: Poisson ratio nu={self.nu} must lie in (-1, 0.5)")

    @property
    def lame(self) -> tuple[float, float]:
        """(λ, G) in MPa."""
        E, nu = self.E_MPa, self.nu
        return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))

    @property
    def confined_modulus(self) -> float:
        """λ + 2G: the stiffness of the layer compressed with no lateral strain."""
        lam, G = self.lame
        return lam + 2 * G


def paper_stack(pdms_nu: float = PDMS_NU, pdms_E: float = PDMS_E_MPA) -> tuple[Layer, Layer, Layer]:
    return (
        Layer("PET (lower)", 25.0, PET_E_MPA, PET_NU),
        Layer("PDMS", 20.0, pdms_E, pdms_nu),
        Layer("PET (upper)", 25.0, PET_E_MPA, PET_NU),
    )


@dataclass(frozen=True)
class Taxel:
    """Geometry of one unit (half-widths of the quarter model, µm)."""

    stack: tuple[Layer, ...] = field(default_factory=paper_stack)
    half_unit_um: float = 2000.0
    half_load_um: float = 1500.0
    half_electrode_um: float = 1500.0
    lower_electrode_interface: int = 1  # top of layer 0
    upper_electrode_interface: int = 2  # bottom of layer 2
    outer_edge: str = "clamped"  # or "roller": normal displacement zero, tangential free

    def __post_init__(self) -> None:
        if self.outer_edge not in ("clamped", "roller"):
            raise ValueError(f"outer_edge must be 'clamped' or 'roller', got {self.outer_edge!r}")

    @property
    def interfaces_um(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum([layer.thickness_um for layer in self.stack])])

    @property
    def gap_um(self) -> float:
        z = self.interfaces_um
        return z[self.upper_electrode_interface] - z[self.lower_electrode_interface]


class ConditioningError(RuntimeError):
    """The stiffness matrix is too ill-conditioned for a trustworthy solve."""


def graded_breaks(half_unit: float, edge: float, first: float = 40.0, ratio: float = 2.5) -> tuple[float, ...]:
    """In-plane partition of [0, half_unit] split at the load edge and graded
    towards it geometrically (first element ``first`` µm, growing by ``ratio``)."""
    inner, outer = [edge], [edge]
    h = first
    while inner[-1] - h > 0.35 * edge:
        inner.append(inner[-1] - h)
        h *= ratio
    h = first
    while outer[-1] + h < half_unit - 0.3 * (half_unit - edge):
        outer.append(outer[-1] + h)
        h *= ratio
    return tuple(sorted({0.0, *inner, *outer, half_unit}))


@dataclass(frozen=True)
class RitzOptions:
    p: int = 6  # in-plane degree
    pz: int = 4  # degree across each layer
    family: str = "legendre"
    breaks: tuple[float, ...] | None = None  # default: graded_breaks for the taxel
    rcond_min: float = 1e-12


@dataclass(frozen=True)
class Load:
    """A traction on the top face of the quarter model.

    ``traction(x, y)`` (MPa) is evaluated on arrays of points; ``direction``
    is "z" (normal, positive pushing down) or "x" (shear along +x).
    """

    traction: Callable[[np.ndarray, np.ndarray], np.ndarray]
    direction: str = "z"
    points_per_element: int | None = None  # quadrature for the load; default exact for patch loads


def patch_load(q_MPa: float, half_width_um: float, direction: str = "z") -> Load:
    """Uniform traction ``q_MPa`` on |x|, |y| ≤ half_width (the paper's q0)."""

    def traction(x, y):
        return q_MPa * ((np.abs(x) <= half_width_um + 1e-9) & (np.abs(y) <= half_width_um + 1e-9))

    return Load(traction, direction)


COMPONENTS = ("u", "v", "w")
# Displacement components that vanish on the mirror planes x = 0 and y = 0:
# a normal load is even in x and y; a shear load along x makes v and w odd in x.


@dataclass
class RitzSolution:
    taxel: Taxel
    options: RitzOptions
    bases: tuple[Basis1D, Basis1D, Basis1D]
    free: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]
    coefficients: dict[str, np.ndarray]  # component -> (nx, ny, nz) over its free functions
    rcond: float
    dofs: int

    def displacement(self, component: str, x: np.ndarray, y: np.ndarray, z: float) -> np.ndarray:
        """Displacement component (µm) on the tensor grid x × y at height z.

        Returns an array of shape (len(x), len(y))."""
        bx, by, bz = self.bases
        fx, fy, fz = self.free[component]
        c = self.coefficients[component]
        zrow = bz.evaluate(np.array([z]))[0, fz]
        plane = np.tensordot(c, zrow, axes=([2], [0]))
        return bx.evaluate(x)[:, fx] @ plane @ by.evaluate(y)[:, fy].T


def _free(size: int, basis: Basis1D, zero_start: bool, zero_end: bool) -> np.ndarray:
    removed = {basis.end_dof("start")} if zero_start else set()
    if zero_end:
        removed.add(basis.end_dof("end"))
    return np.array([i for i in range(size) if i not in removed], dtype=np.int64)


def _sparse(matrix: np.ndarray) -> sp.csr_matrix:
    return sp.csr_matrix(np.where(np.abs(matrix) > 0.0, matrix, 0.0))


def estimate_rcond(matrix: sp.spmatrix, lu) -> float:
    """1-norm reciprocal condition estimate from the matrix and its LU."""
    n = matrix.shape[0]
    inverse = spla.LinearOperator((n, n), matvec=lu.solve, rmatvec=lambda b: lu.solve(b, trans="T"))
    return 1.0 / (spla.norm(matrix, 1) * spla.onenormest(inverse))


MIRROR = {
    "z": {"x": {"u": True, "v": False, "w": False}, "y": {"u": False, "v": True, "w": False}},
    "x": {"x": {"u": False, "v": True, "w": True}, "y": {"u": False, "v": True, "w": False}},
}


class RitzSystem:
    """Assembled and factorised stiffness of the quarter unit for loads in
    one direction ("z" normal, "x" shear); ``solve`` reuses the factors, so a
    family of loads costs one back-substitution each.

    Raises ConditioningError when the equilibrated stiffness has rcond below
    ``options.rcond_min``."""

    def __init__(self, taxel: Taxel | None = None, options: RitzOptions | None = None, direction: str = "z") -> None:
        if direction not in MIRROR:
            raise ValueError(f"load direction must be 'z' or 'x', got {direction!r}")
        self.taxel = taxel = taxel or Taxel()
        self.options = options = options or RitzOptions()
        self.direction = direction
        breaks = options.breaks or graded_breaks(taxel.half_unit_um, taxel.half_load_um)
        for needed in (taxel.half_load_um, taxel.half_electrode_um):
            if not np.any(np.isclose(breaks, needed)):
                raise ValueError(f"in-plane breaks {breaks} must contain the load/electrode edge {needed} µm")
        bx = Basis1D(tuple(breaks), options.p, options.family)
        bz = Basis1D(tuple(taxel.interfaces_um), options.pz, options.family)
        self.bases = (bx, bx, bz)
        mirror = MIRROR[direction]
        clamped = taxel.outer_edge == "clamped"
        self.free = {
            c: (
                _free(bx.size, bx, mirror["x"][c], clamped or c == "u"),
                _free(bx.size, bx, mirror["y"][c], clamped or c == "v"),
                _free(bz.size, bz, True, False),
            )
            for c in COMPONENTS
        }
        stiffness = self._assemble()
        self.dofs = stiffness.shape[0]
        self._scale = 1.0 / np.sqrt(stiffness.diagonal())
        equilibrated = (sp.diags(self._scale) @ stiffness @ sp.diags(self._scale)).tocsc()
        self._lu = spla.splu(equilibrated, permc_spec="MMD_AT_PLUS_A")
        self.factor_bytes = (self._lu.L.nnz + self._lu.U.nnz) * 12  # float64 value + int32 index
        self.rcond = estimate_rcond(equilibrated, self._lu)
        if not self.rcond >= options.rcond_min:
            raise ConditioningError(
                f"stiffness rcond {self.rcond:.2e} is below the guard {options.rcond_min:.0e} "
                f"(basis {options.family!r}, p={options.p}, pz={options.pz}): the solve would not be trustworthy"
            )

    def _assemble(self) -> sp.csc_matrix:
        bx, _, bz = self.bases
        lam = np.array([layer.lame[0] for layer in self.taxel.stack])
        mu = np.array([layer.lame[1] for layer in self.taxel.stack])
        gx = {(a, b): bx.gram(a, b) for a in (0, 1) for b in (0, 1)}
        gz = {(a, b, name): bz.gram(a, b, weight) for a in (0, 1) for b in (0, 1) for name, weight in (("lam", lam), ("mu", mu))}
        free = self.free

        def term(i: str, j: str, test_dir: int, trial_dir: int, coef: str) -> sp.spmatrix:
            """∫ c ∂_test_dir φ^i ∂_trial_dir φ^j as a Kronecker product."""
            parts = []
            for d in range(3):
                a, b = int(test_dir == d), int(trial_dir == d)
                matrix = gz[(a, b, coef)] if d == 2 else gx[(a, b)]
                parts.append(_sparse(matrix[np.ix_(free[i][d], free[j][d])]))
            return sp.kron(parts[0], sp.kron(parts[1], parts[2], format="csr"), format="csr")

        blocks = []
        for i, ci in enumerate(COMPONENTS):
            row = []
            for j, cj in enumerate(COMPONENTS):
                # λ div u div v + G (∂_j u_i ∂_j v_i + ∂_i u_j ∂_j v_i), component by component
                block = term(ci, cj, i, j, "lam") + term(ci, cj, j, i, "mu")
                if i == j:
                    for k in range(3):
                        block = block + term(ci, cj, k, k, "mu")
                row.append(block)
            blocks.append(row)
        return sp.bmat(blocks, format="csc")

    def load_vector(self, load: Load) -> np.ndarray:
        if load.direction != self.direction:
            raise ValueError(f"a {load.direction!r} load needs a system built for direction {load.direction!r}")
        bx, _, bz = self.bases
        loaded = {"z": "w", "x": "u"}[load.direction]
        xq, wq, _ = bx.quadrature(load.points_per_element)
        surface = load.traction(xq[:, None], xq[None, :]) * np.outer(wq, wq)
        fx, fy, fz = self.free[loaded]
        in_plane = bx.evaluate(xq)[:, fx].T @ surface @ bx.evaluate(xq)[:, fy]
        sign = -1.0 if load.direction == "z" else 1.0  # a normal load pushes down (−z)
        top = bz.evaluate(np.array([self.taxel.interfaces_um[-1]]))[0, fz]
        parts = []
        for c in COMPONENTS:
            n = int(np.prod([len(f) for f in self.free[c]]))
            parts.append(sign * np.kron(in_plane.ravel(), top) if c == loaded else np.zeros(n))
        return np.concatenate(parts)

    def solve(self, load: Load) -> RitzSolution:
        solution = self._scale * self._lu.solve(self._scale * self.load_vector(load))
        coefficients, offset = {}, 0
        for c in COMPONENTS:
            shape = tuple(len(f) for f in self.free[c])
            n = int(np.prod(shape))
            coefficients[c] = solution[offset : offset + n].reshape(shape)
            offset += n
        return RitzSolution(self.taxel, self.options, self.bases, self.free, coefficients, self.rcond, self.dofs)


def solve(load: Load, taxel: Taxel | None = None, options: RitzOptions | None = None) -> RitzSolution:
    """Assemble, factorise and solve for one load (see RitzSystem)."""
    return RitzSystem(taxel, options, load.direction).solve(load)

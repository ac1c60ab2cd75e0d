"""Independent reference: the taxel as a 3-D scikit-fem model.

Quadratic 27-node hexahedra (Q2) on a tensor mesh of the same quarter unit,
with the same boundary conditions as the Ritz model but nothing else in
common: a different discretisation (h-refined local elements, not p-refined
global tensor bases), a different assembly (scikit-fem's forms), and a
different capacitance quadrature (point probes of the FE field).

Run ``python -m tests.fem_reference`` to print a refinement study; the
converged figures are stored in service/physics/data/fem_reference.json
for ``tactile model check``, and tests/test_physics_fem.py recomputes them.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.sparse.linalg import spsolve
from skfem import Basis, BilinearForm, ElementHex2, ElementVector, FacetBasis, LinearForm, MeshHex, condense, solve
from skfem.helpers import ddot, sym_grad, trace

from service.physics.capacitance import GapField
from service.physics.ritz import Taxel, graded_breaks


def _refine(breaks, level: int) -> np.ndarray:
    points = [breaks[0]]
    for a, b in zip(breaks[:-1], breaks[1:]):
        points.extend(np.linspace(a, b, level + 1)[1:])
    return np.array(points)


def fem_solution(taxel: Taxel, q_MPa: float, level: int, z_per_layer: int, full_load: bool = False):
    """Solve the quarter unit; return (basis, solution vector, mesh x-nodes)."""
    a = taxel.half_unit_um
    x = _refine(graded_breaks(a, taxel.half_load_um), level) if not full_load else np.linspace(0, a, level + 1)
    z = _refine(tuple(taxel.interfaces_um), z_per_layer)
    mesh = MeshHex.init_tensor(x, x, z)
    element = ElementVector(ElementHex2())
    basis = Basis(mesh, element, intorder=4)
    interfaces = taxel.interfaces_um
    lam = np.array([layer.lame[0] for layer in taxel.stack])
    mu = np.array([layer.lame[1] for layer in taxel.stack])

    def layer_of(zc):
        return np.clip(np.searchsorted(interfaces, zc, side="right") - 1, 0, len(taxel.stack) - 1)

    @BilinearForm
    def elasticity(u, v, w):
        layer = layer_of(w.x[2])
        eu, ev = sym_grad(u), sym_grad(v)
        return lam[layer] * trace(eu) * trace(ev) + 2.0 * mu[layer] * ddot(eu, ev)

    top = interfaces[-1]
    half_load = a if full_load else taxel.half_load_um
    loaded = mesh.facets_satisfying(lambda p: (p[2] > top - 1e-9) & (p[0] < half_load + 1e-9) & (p[1] < half_load + 1e-9))
    facet_basis = FacetBasis(mesh, element, facets=loaded, intorder=4)

    @LinearForm
    def pressure(v, w):
        return -q_MPa * v[2]

    K = elasticity.assemble(basis)
    f = pressure.assemble(facet_basis)
    fixed = [basis.get_dofs(lambda p: p[2] < 1e-9).all()]
    fixed.append(basis.get_dofs(lambda p: p[0] < 1e-9).all(["u^1"]))
    fixed.append(basis.get_dofs(lambda p: p[1] < 1e-9).all(["u^2"]))
    if full_load:  # rollers: the 1-D confined compression
        fixed.append(basis.get_dofs(lambda p: p[0] > a - 1e-9).all(["u^1"]))
        fixed.append(basis.get_dofs(lambda p: p[1] > a - 1e-9).all(["u^2"]))
    else:
        fixed.append(basis.get_dofs(lambda p: (p[0] > a - 1e-9) | (p[1] > a - 1e-9)).all())
    u = solve(*condense(K, f, D=np.unique(np.concatenate(fixed))), solver=spsolve)
    return basis, u, x


def gap_field_fem(taxel: Taxel, basis, u, x_nodes, force_N: float, points: int = 4) -> GapField:
    """Gap change per newton over the electrode quarter, by probing the FE
    field at Gauss points of each mesh cell under the electrode."""
    xi, wi = np.polynomial.legendre.leggauss(points)
    cells = [(a, b) for a, b in zip(x_nodes[:-1], x_nodes[1:]) if b <= taxel.half_electrode_um + 1e-9]
    xq = np.concatenate([(a + b) / 2 + (b - a) / 2 * xi for a, b in cells])
    wq = np.concatenate([(b - a) / 2 * wi for a, b in cells])
    X, Y = np.meshgrid(xq, xq, indexing="ij")
    z = taxel.interfaces_um

    def w_at(height):
        pts = np.vstack([X.ravel(), Y.ravel(), np.full(X.size, height)])
        return (basis.split_bases()[2].probes(pts) @ u[basis.split_indices()[2]]).reshape(X.shape)

    upper = w_at(z[taxel.upper_electrode_interface])
    lower = w_at(z[taxel.lower_electrode_interface])
    return GapField(taxel.gap_um, (upper - lower) / force_N, np.outer(wq, wq))


def confined_compression(taxel: Taxel, q_MPa: float = 0.1):
    """The 1-D case: PDMS and PET compressions (µm) from a full-face load
    with roller sides, read at the unit's centre line."""
    basis, u, _ = fem_solution(taxel, q_MPa, level=1, z_per_layer=1, full_load=True)
    z = taxel.interfaces_um
    wb = basis.split_bases()[2]
    uw = u[basis.split_indices()[2]]
    heights = [wb.probes(np.array([[500.0], [500.0], [h]])) @ uw for h in z]
    w = np.array([float(np.ravel(h)[0]) for h in heights])
    return {"pet_lower_um": -(w[1] - w[0]), "pdms_um": -(w[2] - w[1]), "pet_upper_um": -(w[3] - w[2])}


def study(levels=(1, 2, 3), z_per_layer=(1, 2, 2), nu=None):
    from service.physics.capacitance import sensitivity_per_N
    from service.physics.ritz import paper_stack

    taxel = Taxel(stack=paper_stack(nu)) if nu else Taxel()
    rows = []
    for level, nz in zip(levels, z_per_layer):
        t0 = time.time()
        basis, u, x = fem_solution(taxel, 0.1, level, nz)
        field = gap_field_fem(taxel, basis, u, x, 0.9)
        rows.append(
            {
                "level": level,
                "z_per_layer": nz,
                "dofs": int(u.size),
                "dC_C0_100kPa": float(field.relative_change(0.9)[0]),
                "sensitivity_pct_per_N": 100 * sensitivity_per_N(field),
                "max_gap_closure_um_100kPa": float(-field.dgap_per_N.min() * 0.9),
                "seconds": round(time.time() - t0, 1),
            }
        )
        print(rows[-1], flush=True)
    return rows


def richardson(values: list[float]) -> float:
    """Extrapolate the last three values of a geometric refinement sequence."""
    a, b, c = values[-3:]
    ratio = (b - a) / (c - b)
    return c + (c - b) / (ratio - 1)


def write_reference(path="service/physics/data/fem_reference.json", levels=(1, 2, 3), z_per_layer=(1, 2, 2)):
    """Run the refinement study and store the extrapolated figures that
    ``tactile model check`` compares the Ritz model with."""
    import json

    rows = study(levels, z_per_layer)
    reference = {
        "source": f"scikit-fem Q2 hexahedra, graded tensor mesh, levels {levels[0]}–{levels[-1]} "
                  f"({rows[-1]['dofs']} dofs), Richardson-extrapolated",
        "dC_C0_100kPa": richardson([r["dC_C0_100kPa"] for r in rows]),
        "sensitivity_per_N": richardson([r["sensitivity_pct_per_N"] for r in rows]) / 100,
        "max_gap_closure_um_100kPa": rows[-1]["max_gap_closure_um_100kPa"],
        "study": rows,
    }
    with open(path, "w") as out:
        json.dump(reference, out, indent=1)
    return reference


if __name__ == "__main__":
    print(write_reference())

"""Force → ΔC/C0 tables of the 8x8 taxel, built offline from the Ritz model.

Three load shapes, each a curve over a force grid:

``uniform``  the paper's q0 on the central 3×3 mm (eq 18 scaling);
``uneven``   the array mounted on a 30 mm radius (paper §4.3): the bump's top
             is a cylinder, x²/2R below flat at x, and a flat loading bar
             presses it through the bump's own compliance (Winkler,
             E = 2.03 MPa over its 1 mm height), so the pressure
             k (δ − x²/2R)⁺ is concentrated on the centre line at small
             force and spreads to the whole bump as force grows;
``shear``    a uniform tangential traction on the 3×3 mm (capacitance from
             gap tilt and electrode slide).

A table is a versioned artifact keyed by a hash of every parameter that
shaped it; the service only loads them (JSON, milliseconds). A table ends at
the force where the gap would close by MAX_GAP_CLOSURE anywhere (the model is
not trusted past it); the service saturates there with a flag.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from .capacitance import gap_field, shear_relative_change
from .ritz import Load, RitzOptions, RitzSystem, Taxel, paper_stack, patch_load
from .table_files import ForceTable, TableSpec

Q0_MPA = 0.1
SHEAR_MAX_N = 10.0


def _taxel(spec: TableSpec) -> Taxel:
    return Taxel(stack=paper_stack(spec.pdms_nu, spec.pdms_E_MPa))


def _grid(max_force_N: float, step_N: float) -> np.ndarray:
    return np.append(np.arange(0.0, max_force_N, step_N), max_force_N)


def _contact_depth(force_N: float, k_MPa_per_mm: float, radius_mm: float, half_mm: float) -> float:
    """Bar indentation δ (mm) that carries ``force_N`` on the curved bump."""
    def carried(delta):
        c = min(np.sqrt(2 * radius_mm * delta), half_mm)
        return 2 * half_mm * 2 * k_MPa_per_mm * (delta * c - c**3 / (6 * radius_mm)) - force_N

    from scipy.optimize import brentq  # building tables only: not on the service's start-up path

    return brentq(carried, 0.0, 10.0)


def uneven_load(force_N: float, spec: TableSpec, taxel: Taxel) -> Load:
    half_mm = taxel.half_load_um / 1000
    k = spec.bump_E_MPa / spec.bump_height_mm
    delta = _contact_depth(force_N, k, spec.mount_radius_mm, half_mm)

    def traction(x, y):
        xm = x / 1000
        inside = (np.abs(x) <= taxel.half_load_um + 1e-9) & (np.abs(y) <= taxel.half_load_um + 1e-9)
        return np.where(inside, k * np.maximum(delta - xm**2 / (2 * spec.mount_radius_mm), 0.0), 0.0)

    return Load(traction, "z", points_per_element=32)


def build(spec: TableSpec, progress: Callable[[float], None] = lambda fraction: None) -> ForceTable:
    """Solve the model for ``spec`` and tabulate ΔC/C0 against force."""
    taxel = _taxel(spec)
    unit_force = Q0_MPA * (2 * taxel.half_load_um / 1000) ** 2  # N carried by q0 on the load area
    if spec.shape == "shear":
        system = RitzSystem(taxel, RitzOptions(p=spec.p, pz=spec.pz), "x")
        progress(0.5)
        solution = system.solve(patch_load(Q0_MPA, taxel.half_load_um, "x"))
        forces = _grid(SHEAR_MAX_N, spec.step_N)
        table = ForceTable(spec, forces, shear_relative_change(solution, unit_force, forces), SHEAR_MAX_N, system.rcond)
        progress(1.0)
        return table
    system = RitzSystem(taxel, RitzOptions(p=spec.p, pz=spec.pz), "z")
    progress(0.3)
    uniform = gap_field(system.solve(patch_load(Q0_MPA, taxel.half_load_um)), unit_force)
    forces = _grid(uniform.max_force_N, spec.step_N)
    if spec.shape == "uniform":
        progress(1.0)
        return ForceTable(spec, forces, uniform.relative_change(forces), uniform.max_force_N, system.rcond)
    values = [0.0]
    for i, force in enumerate(forces[1:], 1):
        field_ = gap_field(system.solve(uneven_load(force, spec, taxel)), force)
        value = field_.relative_change(force)[0]
        if np.isnan(value):
            forces = forces[:i]
            break
        values.append(value)
        progress(0.3 + 0.7 * i / len(forces))
    progress(1.0)
    return ForceTable(spec, forces, np.array(values), float(forces[-1]), system.rcond)

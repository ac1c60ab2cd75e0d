"""`tactile model check`: the validation figures of the forward models.

Each check computes a figure, compares it with a reference and a tolerance,
and passes or fails; the command exits non-zero when any fails. The FEM
reference figures come from tests/fem_reference.py (scikit-fem, a test
dependency) and are stored in ``service/physics/data/fem_reference.json``
(package data of service.physics); the test suite recomputes them.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from importlib import resources
from typing import Callable

import numpy as np
import orjson

from ..physics import quad_fits
from ..physics.capacitance import c0_pF, gap_field, sensitivity_per_N
from ..physics.ritz import RitzOptions, RitzSystem, Taxel, paper_stack, patch_load
from ..physics.tables import Q0_MPA

PAPER_SENSITIVITY_PREDICTED = 0.0125
PAPER_SENSITIVITY_MEASURED = 0.01247
PAPER_MAX_DEFLECTION_UM = 0.22
CHECK_OPTIONS = RitzOptions(p=4, pz=3)


@dataclass(frozen=True)
class Check:
    """A figure against a reference: ``mode`` "rel" or "abs" error within
    ``tolerance``, or "min": the figure must be at least the reference."""

    name: str
    value: float
    reference: float
    tolerance: float = 0.0
    mode: str = "rel"
    note: str = ""

    @property
    def error(self) -> float:
        diff = abs(self.value - self.reference)
        if self.mode == "rel":
            return diff / abs(self.reference)
        return diff if self.mode == "abs" else max(self.reference - self.value, 0.0)

    @property
    def passed(self) -> bool:
        return bool(self.error <= self.tolerance)

    def as_dict(self) -> dict:
        return {**asdict(self), "error": self.error, "passed": self.passed}


def fem_reference() -> dict:
    return orjson.loads(resources.files("service").joinpath("physics/data/fem_reference.json").read_bytes())


def confined_compression(options: RitzOptions = RitzOptions(p=2, pz=2)) -> dict[str, float]:
    """Ritz compressions (µm) of the layers under q0 over the whole face with
    roller sides: the 1-D case, exact for a layerwise basis."""
    taxel = Taxel(outer_edge="roller", half_load_um=2000.0, half_electrode_um=1500.0)
    solution = RitzSystem(taxel, RitzOptions(p=options.p, pz=options.pz, breaks=(0.0, 1500.0, 2000.0))).solve(
        patch_load(Q0_MPA, 2000.0)
    )
    centre = np.array([0.0])
    w = [solution.displacement("w", centre, centre, z)[0, 0] for z in taxel.interfaces_um]
    return {"pet_lower_um": w[0] - w[1], "pdms_um": w[1] - w[2], "pet_upper_um": w[2] - w[3]}


def _taxel_figures(taxel: Taxel, options: RitzOptions) -> tuple[float, float, float, float]:
    system = RitzSystem(taxel, options, "z")
    field = gap_field(system.solve(patch_load(Q0_MPA, taxel.half_load_um)), 0.9)
    return float(field.relative_change(0.9)[0]), sensitivity_per_N(field), float(-field.dgap_per_N.min() * 0.9), system.rcond


RUN_STEPS = 5  # progress calls of run(): one per model solved or fitted


def _no_progress(done: int, total: int, what: str) -> None:
    pass


def run(progress: Callable[[int, int, str], None] = _no_progress) -> list[Check]:
    """Every check; ``progress(done, RUN_STEPS, what)`` after each model solved or fitted."""
    checks: list[Check] = []
    taxel = Taxel()
    checks.append(Check("C0 with the paper's k = 9e9 (pF)", c0_pF(taxel, paper_constant=True), 10.66, 0.01, "abs",
                        note=f"exact ε0 gives {c0_pF(taxel):.3f} pF"))
    pdms, pet = taxel.stack[1], taxel.stack[0]
    exact = confined_compression()
    progress(1, RUN_STEPS, "1-D confined compression")
    checks.append(Check("1-D confined compression, PDMS (µm)", exact["pdms_um"], Q0_MPA * pdms.thickness_um / pdms.confined_modulus, 1e-6))
    checks.append(Check("1-D confined compression, PET (µm)", exact["pet_upper_um"], Q0_MPA * pet.thickness_um / pet.confined_modulus, 1e-6))

    change, sensitivity, deflection, rcond = _taxel_figures(taxel, CHECK_OPTIONS)
    progress(2, RUN_STEPS, "taxel model")
    fem = fem_reference()
    checks.append(Check("Ritz vs FEM: ΔC/C0 at 100 kPa", change, fem["dC_C0_100kPa"], 0.01, note=f"FEM {fem['source']}"))
    checks.append(Check("Ritz vs FEM: sensitivity 0–10 N (/N)", sensitivity, fem["sensitivity_per_N"], 0.01))
    checks.append(Check("Ritz: rcond of the equilibrated stiffness, at least the guard", rcond, CHECK_OPTIONS.rcond_min, mode="min"))

    lagrange = _taxel_figures(taxel, RitzOptions(p=3, pz=3, family="lagrange"))[0]
    progress(3, RUN_STEPS, "Lagrange basis")
    legendre = _taxel_figures(taxel, RitzOptions(p=3, pz=3, family="legendre"))[0]
    progress(4, RUN_STEPS, "Legendre basis")
    checks.append(Check("Same space, other basis (GLL Lagrange vs Legendre), ΔC/C0", lagrange, legendre, 1e-8))

    checks.append(Check("Paper: sensitivity predicted 1.25 %/N", sensitivity, PAPER_SENSITIVITY_PREDICTED, 0.1,
                        note="ν of PDMS dominates; see docs/models.md"))
    checks.append(Check("Paper: sensitivity measured mean 1.247 %/N", sensitivity, PAPER_SENSITIVITY_MEASURED, 0.1))
    checks.append(Check("Paper: maximum deflection 0.22 µm at 100 kPa", deflection, PAPER_MAX_DEFLECTION_UM, 0.15))

    _, reports = quad_fits.default_quad_calibration()
    progress(5, RUN_STEPS, "quad fits")
    normal, shear = reports["normal_yeoh"], reports["shear"]
    checks.append(Check("Quad Yeoh fit to (34): residual RMS (N)", normal.residual_rms_N, 0.0, 0.5, "abs",
                        note=f"S·C10 {normal.parameters['c10_area_N']:.3f}±{normal.std_errors['c10_area_N']:.3f} N, "
                             f"S·C20 {normal.parameters['c20_area_N']:.3f}±{normal.std_errors['c20_area_N']:.3f} N, "
                             f"usable to {normal.usable_range_N:.2f} N"))
    checks.append(Check("Quad shear fit to (35): residual RMS (N)", shear.residual_rms_N, 0.0, 0.05, "abs",
                        note=f"a {shear.parameters['a_per_N']:.5f}/N, b {shear.parameters['b_per_N2']:.5f}/N², "
                             f"usable to {shear.usable_range_N:.2f} N; paper form b=a² leaves "
                             f"{reports['shear_paper_form'].residual_rms_N:.2f} N RMS"))
    return checks


def poisson_study(nus=(0.485, 0.49, 0.495), options: RitzOptions = RitzOptions(p=3, pz=3),
                  progress: Callable[[int, int, str], None] = _no_progress) -> list[dict]:
    """Sensitivity against the PDMS Poisson ratio (the dominant parameter);
    ``progress(done, len(nus), what)`` after each ratio."""
    rows = []
    for i, nu in enumerate(nus, 1):
        change, sensitivity, deflection, _ = _taxel_figures(Taxel(stack=paper_stack(nu)), options)
        progress(i, len(nus), f"ν = {nu}")
        rows.append({"nu": nu, "dC_C0_100kPa": change, "sensitivity_per_N": sensitivity, "max_deflection_um": deflection})
    return rows


def report_text(checks: list[Check]) -> str:
    lines = []
    for check in checks:
        mark = "PASS" if check.passed else "FAIL"
        bound = "≥ reference" if check.mode == "min" else f"{check.mode} error {check.error:.2e} ≤ {check.tolerance:g}"
        lines.append(f"{mark}  {check.name}: {check.value:.6g} (reference {check.reference:.6g}, {bound})"
                     + (f"  [{check.note}]" if check.note else ""))
    return "\n".join(lines)

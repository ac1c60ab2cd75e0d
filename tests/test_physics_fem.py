"""The Ritz model against the independent scikit-fem reference."""
import pytest

from service.reports.model_check import confined_compression, fem_reference
from service.physics.capacitance import gap_field, sensitivity_per_N
from service.physics.ritz import RitzOptions, RitzSystem, Taxel, patch_load
from tests import fem_reference as fem


def test_fem_confined_compression_is_exact():
    result = fem.confined_compression(Taxel(outer_edge="roller"))
    exact = confined_compression()
    for layer in ("pdms_um", "pet_upper_um", "pet_lower_um"):
        assert result[layer] == pytest.approx(exact[layer], rel=1e-6)


def test_ritz_within_one_percent_of_fem_and_stored_reference_reproduced():
    taxel = Taxel()
    basis, u, x = fem.fem_solution(taxel, 0.1, level=2, z_per_layer=2)
    fem_field = fem.gap_field_fem(taxel, basis, u, x, 0.9)
    stored = fem_reference()
    level2 = next(row for row in stored["study"] if row["level"] == 2)
    assert fem_field.relative_change(0.9)[0] == pytest.approx(level2["dC_C0_100kPa"], rel=1e-9)

    ritz = gap_field(RitzSystem(taxel, RitzOptions(p=3, pz=3)).solve(patch_load(0.1, 1500.0)), 0.9)
    assert ritz.relative_change(0.9)[0] == pytest.approx(fem_field.relative_change(0.9)[0], rel=0.01)
    assert sensitivity_per_N(ritz) == pytest.approx(sensitivity_per_N(fem_field), rel=0.01)
    assert ritz.relative_change(0.9)[0] == pytest.approx(stored["dC_C0_100kPa"], rel=0.01)

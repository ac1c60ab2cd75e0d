"""Ritz taxel model: exact 1-D case, basis independence, conditioning guard,
convergence, Poisson ratio sweep, gap closure."""
import numpy as np
import pytest

from service.physics.capacitance import MAX_GAP_CLOSURE, GapField, c0_pF, gap_field, sensitivity_per_N
from service.reports.model_check import confined_compression
from service.physics.ritz import (
    ConditioningError,
    Layer,
    RitzOptions,
    RitzSystem,
    Taxel,
    paper_stack,
    patch_load,
)

Q0 = 0.1  # MPa
SPLIT = (0.0, 1500.0, 2000.0)


def uniform_field(options, taxel=None):
    taxel = taxel or Taxel()
    system = RitzSystem(taxel, options)
    return gap_field(system.solve(patch_load(Q0, 1500.0)), 0.9), system


def test_c0_of_the_paper():
    assert c0_pF(Taxel(), paper_constant=True) == pytest.approx(10.66, abs=0.005)


def test_confined_compression_is_exact():
    # Closed form: a layer under q with no lateral strain shortens by q t / (λ + 2G).
    result = confined_compression()
    assert result["pdms_um"] == pytest.approx(0.1 * 20 * (1.49 * 0.02) / (0.55 * 0.51), rel=1e-6)
    assert result["pdms_um"] == pytest.approx(0.2125, abs=5e-5)
    assert result["pet_upper_um"] == pytest.approx(0.1 * 25 * (1.4 * 0.2) / (4000 * 0.6), rel=1e-6)
    assert result["pet_lower_um"] == pytest.approx(result["pet_upper_um"], rel=1e-6)


def test_other_bases_spanning_the_same_space_give_the_same_answer():
    values = [uniform_field(RitzOptions(p=2, pz=2, family=f, breaks=SPLIT))[0].relative_change(0.9)[0]
              for f in ("legendre", "lagrange", "monomial")]
    assert values[1] == pytest.approx(values[0], rel=1e-9)
    assert values[2] == pytest.approx(values[0], rel=1e-9)


def test_order_sweep_of_the_naive_basis_hits_the_rcond_guard():
    options = dict(pz=1, breaks=SPLIT)
    with pytest.raises(ConditioningError, match="rcond .* below the guard"):
        for p in (4, 8, 12, 14):
            RitzSystem(Taxel(), RitzOptions(p=p, family="monomial", **options))
    assert RitzSystem(Taxel(), RitzOptions(p=12, family="legendre", **options)).rcond > 1e-9


def test_error_falls_monotonically_with_order_on_the_split_domain():
    values = [uniform_field(RitzOptions(p=p, pz=2))[0].relative_change(0.9)[0] for p in (1, 2, 3, 4)]
    errors = [abs(v - values[-1]) for v in values[:-1]]
    assert errors[0] > errors[1] > errors[2]
    assert errors[2] < 1e-3 * values[-1]


@pytest.mark.parametrize("nu", [0.48, 0.499])
def test_nearly_incompressible_pdms_solves(nu):
    field, system = uniform_field(RitzOptions(p=2, pz=2), Taxel(stack=paper_stack(nu)))
    assert system.rcond >= 1e-12
    assert 0 < field.relative_change(0.9)[0] < 0.05


def test_order_convergence_holds_at_nu_0_4999():
    # Near incompressibility low orders lock (too stiff); raising p must
    # still converge monotonically, from below.
    taxel = Taxel(stack=paper_stack(0.4999))
    values = [uniform_field(RitzOptions(p=p, pz=2), taxel)[0].relative_change(0.9)[0] for p in (1, 2, 3, 4)]
    assert values[0] < values[1] < values[2] < values[3]
    steps = np.diff(values)
    assert steps[2] < 0.2 * steps[1]
    # Squeeze-out lets the layer yield more than confined compression allows.
    layer = taxel.stack[1]
    assert values[3] > 0.1 / layer.confined_modulus


def test_sensitivity_falls_with_poisson_ratio():
    sens = [sensitivity_per_N(uniform_field(RitzOptions(p=2, pz=2), Taxel(stack=paper_stack(nu)))[0])
            for nu in (0.48, 0.485, 0.49, 0.495)]
    assert all(a > b for a, b in zip(sens, sens[1:]))


def test_poisson_ratio_of_one_half_is_refused():
    with pytest.raises(ValueError, match="nu=0.5"):
        Layer("PDMS", 20.0, 0.55, 0.5)


def test_gap_closure_saturates_never_negative():
    field = GapField(20.0, np.full((2, 2), -0.5), np.full((2, 2), 1.0))
    assert field.max_force_N == pytest.approx(MAX_GAP_CLOSURE * 20 / 0.5)
    values = field.relative_change(np.array([0.0, 10.0, 20.0, 30.0]))
    assert values[0] == 0 and values[1] == pytest.approx(1 / (1 - 0.25) - 1)
    assert np.isnan(values[3]) and not np.any(values[:3] < 0)


def test_load_edge_must_be_a_break():
    with pytest.raises(ValueError, match="must contain the load/electrode edge 1500"):
        RitzSystem(Taxel(), RitzOptions(p=2, breaks=(0.0, 1000.0, 2000.0)))

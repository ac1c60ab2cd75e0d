"""1-D bases: derivatives, exact integrals, conditioning."""
import numpy as np
import pytest

from service.physics.basis1d import FAMILIES, Basis1D

BREAKS = (0.0, 0.7, 1.0, 2.5)


@pytest.mark.parametrize("family", FAMILIES)
def test_derivatives_match_finite_differences(family):
    basis = Basis1D(BREAKS, 5, family)
    x = np.array([0.1, 0.5, 0.85, 1.7, 2.4])
    h = 1e-6
    numeric = (basis.evaluate(x + h) - basis.evaluate(x - h)) / (2 * h)
    np.testing.assert_allclose(basis.evaluate(x, 1), numeric, atol=1e-7 * np.abs(numeric).max())


@pytest.mark.parametrize("family", FAMILIES)
def test_reproduces_polynomials_of_its_degree(family):
    basis = Basis1D(BREAKS, 4, family)
    x = np.linspace(0, 2.5, 60)
    values = basis.evaluate(x)
    target = 3 * x**4 - x**3 + 0.5
    coefficients = np.linalg.lstsq(values, target, rcond=None)[0]
    np.testing.assert_allclose(values @ coefficients, target, atol=1e-10)


def test_gram_integrates_exactly():
    basis = Basis1D(BREAKS, 3, "legendre")
    x = np.linspace(0, 2.5, 40)
    # Coefficients of f(x) = x² and g(x) = 1 in the basis.
    E = basis.evaluate(x)
    f = np.linalg.lstsq(E, x**2, rcond=None)[0]
    g = np.linalg.lstsq(E, np.ones_like(x), rcond=None)[0]
    assert f @ basis.gram(0, 0) @ g == pytest.approx(2.5**3 / 3, rel=1e-12)
    assert f @ basis.gram(1, 1) @ f == pytest.approx(4 * 2.5**3 / 3, rel=1e-12)  # ∫ (2x)² dx
    weights = np.array([1.0, 2.0, 10.0])  # per element
    expected = 0.7**3 / 3 + 2 * (1.0 - 0.7**3) / 3 + 10 * (2.5**3 - 1.0) / 3
    assert f @ basis.gram(0, 0, weights) @ g == pytest.approx(expected, rel=1e-12)


def test_integrated_legendre_bubbles_have_diagonal_stiffness():
    basis = Basis1D((0.0, 2.0), 8, "legendre")
    bubbles = basis.gram(1, 1)[2:, 2:]
    np.testing.assert_allclose(bubbles, np.diag(np.diag(bubbles)), atol=1e-13)


def test_monomial_bubbles_lose_conditioning_with_degree():
    conds = [np.linalg.cond(Basis1D((0.0, 1.0), p, "monomial").gram(1, 1)[2:, 2:]) for p in (4, 8, 12)]
    legendre = np.linalg.cond(Basis1D((0.0, 1.0), 12, "legendre").gram(1, 1)[2:, 2:])
    assert conds[0] < conds[1] < conds[2] and conds[2] > 1e5 * legendre


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="strictly increasing"):
        Basis1D((0.0, 0.0, 1.0), 2)
    with pytest.raises(ValueError, match="unknown basis family 'cheb'"):
        Basis1D((0.0, 1.0), 2, "cheb")

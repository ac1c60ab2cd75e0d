"""Quad sensor models: Yeoh normal law, shear law, fits and calibration."""
import numpy as np
import pytest

from service.physics import paper_data, quad_fits, shear, yeoh


def yeoh_energy(lam, c10, c20):
    i1 = lam**2 + 2 / lam
    return c10 * (i1 - 3) + c20 * (i1 - 3) ** 2


def test_yeoh_force_is_minus_the_energy_derivative_times_area():
    # Independent reference: nominal stress P = dW/dλ (incompressible uniaxial),
    # by central differences on the strain energy itself.
    area_mm2, c10, c20 = 100.0, 0.03, 0.3
    relative = np.array([0.01, 0.1, 0.3])
    lam = 1 / (1 + relative)
    h = 1e-7
    nominal = (yeoh_energy(lam + h, c10, c20) - yeoh_energy(lam - h, c10, c20)) / (2 * h)
    np.testing.assert_allclose(yeoh.normal_force(relative, area_mm2 * c10, area_mm2 * c20), -area_mm2 * nominal, rtol=1e-6)


def test_yeoh_units_sign_and_small_strain_limit():
    # MPa · mm² = N; compression (ΔC > 0) gives a positive force, 6 S C10 per unit strain.
    area_N = 100.0 * 0.03
    assert yeoh.normal_force(1e-6, area_N, 0.0) == pytest.approx(6 * area_N * 1e-6, rel=1e-5)
    assert yeoh.normal_force(0.2, area_N, 0.3) > 0
    assert yeoh.normal_force(-0.05, area_N, 0.3) < 0


def test_shear_inverse_round_trip_and_paper_form():
    a, b = shear.paper_coefficients(d0_mm=2.0, shear_modulus_MPa=0.3, area_mm2=100.0)
    assert b == pytest.approx(a * a)
    forces = np.array([-3.0, -0.1, 0.0, 0.2, 5.0])
    recovered, out = shear.shear_force(shear.shear_response(forces, 0.0077, 0.0004), 0.0077, 0.0004)
    np.testing.assert_allclose(recovered, forces, atol=1e-12)
    assert not out.any()


def test_shear_outside_its_domain_is_flagged_never_nan():
    a, b = 0.5, 0.25  # paper form b = a²: the root needs r ≤ a²/(4b) = 0.25 (eq 29's x ≤ 0.25)
    force, out = shear.shear_force(np.array([0.24, 0.26, 0.3, -0.4]), a, b)
    assert not np.isnan(force).any()
    assert out.tolist() == [False, True, True, True]
    assert force[2] == pytest.approx(shear.turning_force(a, b)) and force[3] == pytest.approx(-shear.turning_force(a, b))


@pytest.mark.parametrize(
    "coefficients, top, inside, beyond",
    [(paper_data.FIT34, 0.330, 0.2, 0.331), (paper_data.FIT35, 0.0382, 0.03, 0.0383)],
)
def test_fit_inverses_hold_at_the_turn_and_flag(coefficients, top, inside, beyond):
    c2, c1, c0 = coefficients
    assert c0 - c1 * c1 / (4 * c2) == pytest.approx(top, abs=1e-3)
    force, out = quad_fits.invert_fit(coefficients, np.array([inside, beyond, c0, c0 - 0.001, 0.0]))
    assert np.polyval(coefficients, force[0]) == pytest.approx(inside)
    assert force[1] == pytest.approx(quad_fits.fit_turning_force(coefficients))
    assert force[2] == 0 and force[3] == 0 and force[4] == 0
    assert out.tolist() == [False, True, False, True, True]


def test_yeoh_fit_recovers_known_parameters():
    forces = np.linspace(0.5, 15, 30)
    relative = np.array([quad_fits.QuadCalibration(3.0, 5.0, 0.01, 0.0, 20, 8).normal_relative(f) for f in forces])
    report = quad_fits.fit_yeoh(forces, relative, 15.0)
    assert report.parameters["c10_area_N"] == pytest.approx(3.0, rel=1e-6)
    assert report.parameters["c20_area_N"] == pytest.approx(5.0, rel=1e-6)
    assert report.residual_rms_N < 1e-6


def test_default_calibration_figures():
    calibration, reports = quad_fits.default_quad_calibration()
    assert calibration.normal_usable_N == pytest.approx(0.9 * 0.0343 / 0.0018)  # 17.15 N, before the 19.06 N turn
    assert calibration.shear_usable_N == pytest.approx(0.9 * 0.0077 / 0.0008)  # 8.66 N, before 9.625 N
    assert reports["normal_yeoh"].residual_rms_N < 0.5
    assert reports["shear"].parameters["a_per_N"] == pytest.approx(0.0077, rel=1e-6)
    # The paper's own shear form (b = a²) cannot follow its measured curvature.
    assert reports["shear_paper_form"].residual_rms_N > 10 * reports["shear"].residual_rms_N + 0.1
    force, out = calibration.invert_normal(np.array([-0.01, 0.1, 0.5]))
    assert out.tolist() == [True, False, True] and force[2] == pytest.approx(calibration.normal_usable_N)


def test_paper_yeoh_parameters_do_not_reproduce_fit_34():
    mismatch = quad_fits.paper_parameters_mismatch()
    assert mismatch["area_matching_slope_mm2"] == pytest.approx(162.0, abs=0.5)
    assert mismatch["paper_model_force_N"] > 2 * mismatch["force_at_fit_end_N"]

"""What a quad session can tell of the normal–shear coupling c (paper 001 §5.3).

Under one preload Fz the shear response is t(F)·(1 − c·n(Fz)) with n(Fz) a
constant: c and the shear slope a change it alike and cannot be told apart.
A tester's session with shear at 2 N only was fitted to c = 1.921 ± 0.208
(truth 1.0; a second schedule 1.708 ± 0.221) and read combined loads at
other preloads with Fx, Fy 0.18–0.30 N RMS, 14–18 % of loaded frames beyond
3σ, unflagged.

The sessions (tests/quad_ft_session.py) come from the model written out
there, not the simulator's."""
import numpy as np
import pytest

from service.calibration.calibrate_quad import coupling_said, fit_document
from service.reconstruct.sensor_calibration import from_document
from tests.quad_ft_session import QUAD, SHEAR, normal_response, odd, read_back, session


def fitted(preloads, coupling, seed=0):
    return session(preloads, coupling, seed).fit()


def test_shear_under_one_preload_leaves_the_coupling_undetermined():
    """c = 0 here: c is not fitted, the slope a is the sensor's (was fitted
    with a c of its own, the pair anywhere along the line the data allows)."""
    fit = fitted((2.0,), 0.0)
    assert not fit.coupling_kept and fit.coupling == 0.0 and fit.coupling_se is None
    assert fit.shear[0] == pytest.approx(SHEAR[0], rel=0.02)
    assert fit.shear_preload_N[0] == pytest.approx(2.0 * 0.975, rel=0.03)  # the schedule's 0.9–1.05 of it
    assert fit.shear_preload_N[1] < 0.1
    said = coupling_said(fit)
    assert "not determined" in said and "one normal load" in said and "two preloads" in said
    assert fit_document(fit)["coupling_se"] is None


def test_an_undetermined_couplings_sigma_covers_shear_read_under_other_preloads():
    """c = 1 and shear pressed under 2 N only: read under 2–10 N the shear
    is off by up to c·(n(10 N) − n(2 N))/(1 − c·n(2 N)) = 24 % of itself;
    within 3σ throughout (was 14–18 % of frames beyond it on the tester's quad)."""
    truth, forces, sigma = read_back(fitted((2.0,), 1.0), 1.0)
    error = np.abs(forces - truth)
    n = normal_response(truth[:, 2])
    n2 = normal_response(2.0)
    relative = 1.0 - (1.0 - n) / (1.0 - n2)  # what the coupling takes off a shear read with the 2 N slope
    assert relative.max() > 0.2 and error[:, :2].max() > 0.5  # the test's loads show the coupling
    beyond = (error > 3 * sigma).mean(axis=0)
    print(f"undetermined coupling: shear RMS {np.sqrt((error[:, :2] ** 2).mean(axis=0)).round(3)} N, "
          f"beyond 3σ {beyond.round(4)}, within 1σ {(error <= sigma).mean(axis=0).round(3)}")
    assert beyond.max() < 0.003


def test_two_preloads_determine_the_coupling():
    fit = fitted((3.0, 9.0), 1.0)
    assert fit.coupling_kept and fit.coupling == pytest.approx(1.0, abs=0.05) and fit.coupling_se < 0.05
    assert fit.shear[0] == pytest.approx(SHEAR[0], rel=0.02)
    assert fit.shear_preload_N[1] > 2.0
    assert coupling_said(fit).startswith("coupling: c = ")
    truth, forces, sigma = read_back(fit, 1.0)
    assert np.sqrt(((forces - truth)[:, :2] ** 2).mean()) < 0.05


def test_a_negative_coupling_is_left_out_with_the_slope_fitted_without_it():
    """The model holds c ≥ 0 only (normal load reduces the shear response).
    A fit of c < 0 standing 3σ clear of 0 was kept and stored as 0 with the
    slope fitted along with it (tester: raw c = −3.75, a = 0.00447 for
    0.00889, 0.44 N residual); now the slope is refitted without c, so the
    stored a is the c = 0 least-squares slope of the session (here, on the
    noiseless shear, its closed form: linear in a and b)."""
    coupling = -0.3
    data = session((3.0, 9.0), coupling)
    fit = data.fit()
    assert not fit.coupling_kept and fit.coupling == 0.0
    assert fit.coupling_fitted[0] == pytest.approx(coupling, abs=0.02)
    f = data.truth_N
    n = normal_response(f[:, 2])
    shear = np.abs(f[:, :2]).max(axis=1) > 0.1
    force = f[shear][:, :2].ravel()
    response = (odd(f[shear][:, :2], *SHEAR) * (1.0 - coupling * n[shear])[:, None]).ravel()
    (a, minus_b), *_ = np.linalg.lstsq(np.stack([force, -np.sign(force) * force * force], axis=1), response, rcond=None)
    assert a > 1.04 * SHEAR[0]  # the loads show the (negative) coupling
    assert fit.shear[0] == pytest.approx(a, rel=0.01)
    assert fit.shear[1] == pytest.approx(minus_b, rel=0.05)
    assert "c = -0.30" in coupling_said(fit) and "fitted without it" in coupling_said(fit)


def test_a_coupling_left_out_keeps_what_the_data_said_of_it():
    """c left out was stored with ``coupling_se`` 0 and said "c within 0.000
    of 0". Now its σ is what the fit said of it, √(c² + se²) about the 0
    stored, and shear read away from the session's mean preload carries it:
    with c = −0.3 left out, read under 2–10 N within 2σ (its error up to
    0.3·(n(10 N) − n(6 N)) = 3.7 % of the shear; with σ_c 0, 3.3 % of Fy
    beyond 2σ, the worst 3.4σ)."""
    fit = fitted((3.0, 9.0), 0.0)
    c, se = fit.coupling_fitted
    assert not fit.coupling_kept and abs(c) < 3 * se
    assert fit.coupling_se == pytest.approx(np.hypot(c, se)) and fit.coupling_se > 0
    said = coupling_said(fit)
    assert f"c = {c:.3f} ± {se:.3f}" in said and "within 0.000" not in said and "not shown by the data" in said

    negative = fitted((3.0, 9.0), -0.3)
    assert negative.coupling_se == pytest.approx(0.3, abs=0.01)
    truth, forces, sigma = read_back(negative, -0.3)
    error = np.abs(forces - truth)
    assert error[:, :2].max() > 0.1  # the coupling shows
    assert (error > 2 * sigma).mean(axis=0).max() < 0.003 and not (error > 3 * sigma).any()


def test_older_documents_load_with_their_coupling_se():
    """Documents stored before (``coupling_se`` 0, no ``shear_preload_N``)
    load as they did: no coupling term in σ."""
    fit = fitted((3.0, 9.0), 0.0)
    document = {**fit_document(fit), "id": "old-quad", "kind": "quad", "coupling_se": 0.0}
    del document["shear_preload_N"]
    calibration = from_document(document, QUAD)
    assert calibration.quad.coupling == 0.0 and calibration.quad_coupling_sigma is None
    with pytest.raises(ValueError, match="coupling_se: -1"):
        from_document({**fit_document(fit), "id": "bad", "kind": "quad", "coupling_se": -1}, QUAD)

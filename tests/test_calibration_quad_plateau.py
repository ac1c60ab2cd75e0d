"""A quad whose response stops rising inside the calibration session's range.

A tester's quad, flat in Fz above 14.6 N and pressed to 18 N, was stored with
a quadratic pulled off its rising part by the flat frames (Fz residual
0.66 N, in-range bias −0.18 N) and a usable top the flat level never
reached: 22 and 30 N read 13.1 N unflagged. Another, turning at 16.2 N,
was flagged right, but the flat frames' 0.39 N residual went into every
Fz σ (30× its error). The simulated sensor here is held flat past its
model's usable force (QuadModel.forward), the same physics."""
import io
from dataclasses import replace

import numpy as np
import orjson
import pytest

from firmware_sim.quad_session import Load, quad_schedule, quad_session, user_quad_model, validation_loads
from firmware_sim.calibration_session import QUIET_S
from service.calibration.book import CalibrationBook
from service.calibration.calibrate_quad import calibrate_quad, quad_document, quad_summary
from service.calibration.registry import Registry
from service.physics.quad_model import QuadModel
from service.replay import replay

RATE_HZ = 200.0
FLAT_N = 11.0


def calibrated(tmp_path, model, **schedule):
    sim = quad_session(model=model, loads=quad_schedule(0, **schedule), rate_hz=RATE_HZ)
    (tmp_path / "s.bin").write_bytes(sim.raw)
    (tmp_path / "r.csv").write_text(sim.reference_csv)
    return sim, calibrate_quad(tmp_path / "s.bin", tmp_path / "r.csv")


def replayed(tmp_path, sim, result, loads):
    """(truth (k, 3), forces (k, 3), σ (k, 3) NaN for null, flags) of a separate sequence."""
    registry = tmp_path / "registry.sqlite3"
    with Registry(registry) as r:
        r.add(quad_document(result), activate=True)
    check = quad_session(model=sim.model, loads=loads, rate_hz=RATE_HZ, seed=3, c0_pF=sim.c0_pF)
    (tmp_path / "v.bin").write_bytes(check.raw)
    out = io.BytesIO()
    replay(tmp_path / "v.bin", out, calibrations=CalibrationBook(registry))
    lines = [orjson.loads(line) for line in out.getvalue().splitlines()]
    truth = dict(zip(check.truth_t_us.tolist(), check.truth_N))
    return (np.stack([truth[line["t_us"]] for line in lines]), np.array([line["fxyz_N"] for line in lines], float),
            np.array([[np.nan if s is None else s for s in line["sigma_N"]] for line in lines], float),
            [line["flags"] for line in lines])


@pytest.fixture(scope="module")
def flat(tmp_path_factory):
    """The same sensor and schedule, once flat in Fz above FLAT_N (pressed to 13.5–15.8 N), once not."""
    model = user_quad_model(1)
    plain = calibrated(tmp_path_factory.mktemp("plain"), model)
    return plain, calibrated(tmp_path_factory.mktemp("flat"), replace(model, normal_usable_N=FLAT_N))


def test_a_flat_normal_response_sets_the_usable_top_where_it_stops_rising(flat):
    (_, plain), (sim, result) = flat
    fit = result.fit
    assert plain.fit.flat_N == (None, None)
    assert fit.flat_N[0] == pytest.approx(FLAT_N, rel=0.01) and fit.flat_N[1] is None
    # a little under it: a reading on the flat part, noise and all, is past the top (held and flagged)
    assert 0.97 * FLAT_N < fit.usable_N[0] < FLAT_N
    assert fit.usable_N[1] == pytest.approx(plain.fit.usable_N[1], rel=0.01)
    assert any(f"Fz response flat above {FLAT_N:.1f} N" in line and f"usable to {fit.usable_N[0]:.1f} N" in line
               for line in quad_summary(result))
    document = quad_document(result)
    assert document["normal_usable_N"] == fit.usable_N[0]
    assert document["statistics"]["flat_above_N"] == {"normal": fit.flat_N[0], "shear": None}


def test_the_rising_part_is_fitted_as_well_as_without_the_flat_part(flat):
    (_, plain), (sim, result) = flat
    truth = sim.model
    assert result.fit.normal[1] == pytest.approx(truth.normal_fit[1], rel=0.01)
    assert result.fit.normal[0] == pytest.approx(truth.normal_fit[0], rel=0.05)
    assert result.fit.rms_N[2] < 1.5 * plain.fit.rms_N[2] + 0.005


def test_a_later_reading_past_the_flat_top_is_held_and_flagged(flat, tmp_path):
    _, (sim, result) = flat
    loads = [Load(QUIET_S, (0.0, 0.0, 8.0)), Load(QUIET_S + 4.0, (0.0, 0.0, 20.0))]
    truth, forces, sigma, flags = replayed(tmp_path, sim, result, loads)
    past = truth[:, 2] > FLAT_N + 0.05
    assert past.sum() > 50
    held = forces[past, 2]
    assert np.allclose(held, held[0]) and 0.97 * FLAT_N < held[0] < FLAT_N
    assert all("normal_out_of_range" in flags[i] for i in np.flatnonzero(past)) and np.isnan(sigma[past, 2]).all()
    within = (truth[:, 2] > 0.5) & (truth[:, 2] < 0.95 * FLAT_N)
    assert np.sqrt(np.mean((forces[within, 2] - truth[within, 2]) ** 2)) < 0.03
    assert not any("normal_out_of_range" in flags[i] for i in np.flatnonzero(within))


def test_the_sigma_of_a_quad_turning_inside_the_session_comes_from_its_usable_range(tmp_path):
    """The tester's q20c: flat past a smooth turn (16.2 N there, 15 N here), pressed to 18 N."""
    c1 = user_quad_model(1).normal_fit[1]
    model = replace(user_quad_model(1), normal_fit=(-c1 / 30.0, c1, 0.0), normal_usable_N=15.0)
    sim, result = calibrated(tmp_path, model, normal_peak_N=18.0)
    assert result.fit.rms_N[2] < 0.05
    truth, forces, sigma, _ = replayed(tmp_path, sim, result, validation_loads())
    loaded = (np.linalg.norm(truth, axis=1) > 0.1) & np.isfinite(sigma[:, 2])
    error = np.sqrt(np.mean((forces[loaded, 2] - truth[loaded, 2]) ** 2))
    assert np.median(sigma[loaded, 2]) < 3.0 * error
    assert result.fit.flat_N[0] == pytest.approx(15.0, rel=0.02)


def test_a_flat_shear_response_sets_the_shear_usable_top(tmp_path):
    sim, result = calibrated(tmp_path, replace(user_quad_model(1), shear_usable_N=3.0), shear_peak_N=4.8)
    fit = result.fit
    assert fit.shear[0] == pytest.approx(sim.model.shear_a, rel=0.02)
    assert max(fit.rms_N) < 0.1
    assert fit.flat_N[0] is None and fit.flat_N[1] == pytest.approx(3.0, rel=0.02)
    assert 0.92 * 3.0 < fit.usable_N[1] < 3.0  # the noise margin is wider in N: the shear slope is a fifth of Fz's


def test_an_uploaded_usable_top_only_narrows_the_curves_own():
    normal, shear = (-0.0009, 0.0343), (0.0077, 0.0004)
    own = QuadModel.from_fits(normal, shear)
    narrowed = QuadModel.from_fits(normal, shear, 0.0, 12.0, 100.0)
    assert narrowed.normal_usable_N == 12.0 and narrowed.shear_usable_N == own.shear_usable_N
    for bad in (0.5, float("nan"), "12", True):
        with pytest.raises(ValueError, match="normal_usable_N"):
            QuadModel.from_fits(normal, shear, 0.0, bad)


def turning_loads(peaks: list[float]) -> list[Load]:
    """Shear along +X to each peak under a 5 N preload (grip), one after another."""
    loads, t = [], QUIET_S
    for peak in peaks:
        loads.append(Load(t, (peak, 0.0, 0.0), 1.2, 5.0))
        t = loads[-1].end_s + 0.6
    return loads


@pytest.mark.parametrize("session_peak_N", [4.0, 12.0])
def test_shear_past_the_calibrated_range_or_its_turn_is_held_and_flagged_not_folded_back(tmp_path, session_peak_N):
    """A sensor whose shear response is eq (28)'s quadratic to the end, turning at a/2b = 9.6 N: past it a
    larger shear gives a smaller ΔC/C0. Calibrated to 4.2 N, the stored usable end (8.8 N) was the curve's
    extrapolation and a true 12 N read 7.2 N, 14 N 5.3 N, unflagged; calibrated to 12.6 N (past the turn,
    found as flat at 9.3 N, usable to 8.0 N) 12 N read 7.3 N unflagged. Now the axis is usable to the
    session's reach at most, and to under the level the response fell back to: every force from there to
    the mirror of that end about the turn (the forces the curve maps onto the same readings) is held at the
    end, flagged, σ null."""
    model = replace(user_quad_model(1), shear_usable_N=50.0)  # the simulator's quad without its flat top
    a, b = model.shear_a, model.shear_b
    turn = a / (2 * b)
    assert 9.0 < turn < 10.0 and a * 12.0 - b * 144.0 < a * 8.0 - b * 64.0  # the generator's response turns
    sim, result = calibrated(tmp_path, model, shear_peak_N=session_peak_N)
    fit = result.fit
    reach = np.abs(sim.truth_N[:, :2]).max()
    assert fit.shear_reach_N == pytest.approx(reach, abs=0.05)
    end = fit.usable_N[1]
    assert end <= fit.shear_reach_N
    if reach > turn:  # held under where the response fell back to: the true curve's level at the reach
        response = a * reach - b * reach * reach
        assert end < (a - np.sqrt(a * a - 4 * b * response)) / (2 * b)
    truth, forces, sigma, flags = replayed(tmp_path, sim, result, turning_loads([3.0, 6.0, 9.0, 12.0, 14.0]))
    folded = (truth[:, 0] > end + 0.1) & (truth[:, 0] < 2 * turn - end - 0.3)
    assert folded.sum() > 50
    assert all("shear_out_of_range" in flags[i] for i in np.flatnonzero(folded))
    assert np.allclose(forces[folded, 0], end) and np.isnan(sigma[folded, 0]).all()
    within = (truth[:, 0] > 0.5) & (truth[:, 0] < 0.95 * end)
    assert np.sqrt(np.mean((forces[within, 0] - truth[within, 0]) ** 2)) < 0.1
    assert not any("shear_out_of_range" in flags[i] for i in np.flatnonzero(within))
    if reach < turn:
        assert any(f"shear usable to {end:.1f} N, the largest shear the session pressed" in line
                   for line in quad_summary(result))

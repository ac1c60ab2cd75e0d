"""A reference instrument not zeroed before the session: its rest level is
found in its log and subtracted, for a grid's load cell and a quad's F/T
sensor, and the calibration equals the zeroed one's (simulator's truth)."""
import re

import numpy as np
import pytest

from firmware_sim.calibration_session import probe_schedule, session
from firmware_sim.quad_session import quad_session
from service.calibration.calibrate import calibrate, document, summary_lines
from service.calibration.calibrate_quad import calibrate_quad, quad_document
from service.calibration.reference_zero import rest_level


def _shifted(csv: str, offsets) -> str:
    """The reference CSV with ``offsets`` (one per force column) added to every numeric line."""
    lines = csv.splitlines()
    out = [lines[0]]
    for line in lines[1:]:
        parts = line.split(",")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            out.append(line)  # the instrument's junk lines stay junk
            continue
        out.append(",".join([parts[0]] + [f"{v + o:.5f}" for v, o in zip(values[1:], offsets)]))
    return "\n".join(out) + "\n"


def _presses(t: np.ndarray) -> np.ndarray:
    """Presses of 12 N every 6 s (half the time loaded), never pulled."""
    return 12.0 * np.clip(np.sin(2 * np.pi * t / 6.0), 0.0, None) ** 2


@pytest.mark.parametrize("offset", [0.0, -0.3, 0.4, 2.0])
def test_the_rest_level_of_presses_and_pauses_is_the_offset(offset):
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 60.0, 0.01)
    sigma = 0.01
    level = rest_level(_presses(t) + offset + rng.normal(0.0, sigma, t.size), sigma, 30)
    assert level == pytest.approx(offset, abs=4 * sigma / np.sqrt(0.3 * t.size))
    assert rest_level(_presses(t) + offset, 0.0, 30) == pytest.approx(offset, abs=1e-12)  # noiseless


def test_an_undershoot_after_each_release_is_not_the_rest_level():
    """A load cell that reads −0.25 N after each release, creeping back to 0
    over 0.3 s: its pauses' low values are not where it rests."""
    rng = np.random.default_rng(6)
    t = np.arange(0.0, 60.0, 0.01)
    since = (t % 6.0) - 3.0  # each press ends at a multiple of 6 s + 3 s
    undershoot = np.where(since > 0, -0.25 * np.exp(-since / 0.3), 0.0)
    level = rest_level(_presses(t) + undershoot + rng.normal(0.0, 0.01, t.size), 0.01, 30)
    assert abs(level) < 0.01


def test_a_load_held_long_is_not_the_rest_level_but_a_preload_throughout_is():
    rng = np.random.default_rng(7)
    t = np.arange(0.0, 60.0, 0.01)
    held = np.where((t % 10.0) < 7.0, 3.0, 0.0)  # a quad's preload held 70 % of the time, released between
    assert abs(rest_level(held + rng.normal(0.0, 0.01, t.size), 0.01, 30)) < 0.01
    assert rest_level(held + 1.0 + rng.normal(0.0, 0.01, t.size), 0.01, 30) == pytest.approx(1.0, abs=0.01)


@pytest.fixture(scope="module")
def grid_session(tmp_path_factory):
    sim = session(presses=probe_schedule(taxels=[9, 27, 45], repeats=2), rate_hz=200.0, seed=4)
    out = tmp_path_factory.mktemp("zero")
    (out / "session.bin").write_bytes(sim.raw)
    (out / "zeroed.csv").write_text(sim.reference_csv)
    return sim, out, calibrate(out / "session.bin", out / "zeroed.csv", allow_partial=True)


@pytest.mark.parametrize("offset", [0.2, -0.2])
def test_a_load_cell_off_zero_is_said_and_subtracted_when_asked(grid_session, offset):
    """+0.2 N joins the pauses to the presses: the refusal says the rest
    level may be why; −0.2 N calibrates biased, and the summary warns. With
    --zero-reference both calibrate as the zeroed log does."""
    sim, out, reference = grid_session
    (out / "off.csv").write_text(_shifted(sim.reference_csv, [offset]))
    hint = rf"rests at force {re.escape(f'{offset:+.3f}')} N between loads, not 0 .*--zero-reference"
    if offset > 0:
        with pytest.raises(ValueError, match=r"no taxel could be calibrated .*; note: the reference " + hint):
            calibrate(out / "session.bin", out / "off.csv", allow_partial=True)
    else:
        biased = calibrate(out / "session.bin", out / "off.csv", allow_partial=True)
        assert re.search(hint, biased.reference.zero_warning)
        assert document(biased)["statistics"]["reference_rest_warning"] == biased.reference.zero_warning
        assert any("(used as logged) — WARNING: the reference rests at" in line for line in summary_lines(biased))
    off = calibrate(out / "session.bin", out / "off.csv", allow_partial=True, zero_reference=True)
    assert sorted(off.fits) == sorted(reference.fits) == [9, 27, 45]
    assert len(off.presses) == len(reference.presses) == 6
    for t in (9, 27, 45):
        assert off.fits[t].gain == pytest.approx(reference.fits[t].gain, rel=2e-3)
        assert off.fits[t].gain == pytest.approx(sim.gain[t], rel=5e-3)
        assert off.fits[t].residual_rms_N < 0.03
    assert off.reference.zero_N[-1] == pytest.approx(offset, abs=3e-3) and off.reference.zero_subtracted
    assert abs(reference.reference.zero_N[-1]) < 3e-3 and not reference.reference.zero_subtracted
    assert reference.reference.zero_warning is None
    statistics = document(off)["statistics"]
    assert statistics["reference_rest_N"] == off.reference.zero_N[-1] and statistics["reference_rest_subtracted"]
    said = [re.search(r"at rest force ([-+][0-9.]+) N \(subtracted\)", line) for line in summary_lines(off)]
    assert [float(m.group(1)) for m in said if m] == [pytest.approx(offset, abs=3e-3)]
    assert any("(within tolerance of 0: used as logged)" in line for line in summary_lines(reference))


@pytest.mark.parametrize("preloads", [(3.0, 9.0), (1.0, 3.0)])
def test_a_quad_ft_sensor_off_zero_or_preloaded(tmp_path, preloads):
    """Off zero on every axis: refused for want of an unloaded stretch, the
    rest levels named; with --zero-reference calibrated as the zeroed log.
    Zeroed, with a light preload held longer than the pauses: calibrated as
    logged (whatever the rest-level estimate says of it)."""
    from firmware_sim.quad_session import quad_schedule

    sim = quad_session(loads=quad_schedule(0, preloads=preloads), rate_hz=250.0, seed=0)
    (tmp_path / "session.bin").write_bytes(sim.raw)
    (tmp_path / "zeroed.csv").write_text(sim.reference_csv)
    (tmp_path / "off.csv").write_text(_shifted(sim.reference_csv, [-0.15, 0.1, 0.3]))
    reference = calibrate_quad(tmp_path / "session.bin", tmp_path / "zeroed.csv")
    assert reference.fit.normal[1] == pytest.approx(sim.model.normal_fit[1], rel=0.01)
    if preloads[0] < 2.0:  # the light preload can pass for the rest: a warning, as logged (not subtracted)
        assert not reference.reference.zero_subtracted
        return
    with pytest.raises(ValueError, match=r"unloaded frames.*; note: the reference rests at Fx -0\.150 N, Fy \+0\.100 N, "
                                         r"Fz \+0\.300 N between loads"):
        calibrate_quad(tmp_path / "session.bin", tmp_path / "off.csv")
    off = calibrate_quad(tmp_path / "session.bin", tmp_path / "off.csv", zero_reference=True)
    np.testing.assert_allclose(off.reference.zero_N, [-0.15, 0.1, 0.3], atol=3e-3)
    assert off.fit.normal[1] == pytest.approx(reference.fit.normal[1], rel=3e-3)
    assert off.fit.shear[0] == pytest.approx(reference.fit.shear[0], rel=3e-3)
    np.testing.assert_allclose(off.fit.c0_pF, reference.fit.c0_pF, rtol=1e-5)
    assert quad_document(off)["statistics"]["reference_rest_N"]["z"] == off.reference.zero_N[2]

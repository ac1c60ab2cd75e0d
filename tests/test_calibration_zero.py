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


@pytest.mark.parametrize("offset", [0.0, -0.3, 0.4, 2.0])
def test_the_rest_level_of_presses_and_pauses_is_the_offset(offset):
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 60.0, 0.01)
    loads = 12.0 * np.clip(np.sin(2 * np.pi * t / 6.0), 0.0, None) ** 2  # pressed half the time, never pulled
    sigma = 0.01
    level = rest_level(loads + offset + rng.normal(0.0, sigma, t.size), sigma)
    assert level == pytest.approx(offset, abs=4 * sigma / np.sqrt(0.3 * t.size))
    assert rest_level(loads + offset, 0.0) == offset  # noiseless: the resting samples' own value


@pytest.fixture(scope="module")
def grid_session(tmp_path_factory):
    sim = session(presses=probe_schedule(taxels=[9, 27, 45], repeats=2), rate_hz=200.0, seed=4)
    out = tmp_path_factory.mktemp("zero")
    (out / "session.bin").write_bytes(sim.raw)
    return sim, out


@pytest.mark.parametrize("offset", [0.2, -0.2])
def test_a_grid_calibrates_the_same_from_a_load_cell_off_zero(grid_session, offset):
    sim, out = grid_session
    (out / "zeroed.csv").write_text(sim.reference_csv)
    (out / "off.csv").write_text(_shifted(sim.reference_csv, [offset]))
    reference = calibrate(out / "session.bin", out / "zeroed.csv", allow_partial=True)
    off = calibrate(out / "session.bin", out / "off.csv", allow_partial=True)
    assert sorted(off.fits) == sorted(reference.fits) == [9, 27, 45]
    assert len(off.presses) == len(reference.presses) == 6
    for t in (9, 27, 45):
        assert off.fits[t].gain == pytest.approx(reference.fits[t].gain, rel=2e-3)
        assert off.fits[t].gain == pytest.approx(sim.gain[t], rel=5e-3)
        assert off.fits[t].residual_rms_N < 0.03
    assert off.reference.zero_N[-1] == pytest.approx(offset, abs=3e-3)
    assert abs(reference.reference.zero_N[-1]) < 3e-3
    assert document(off)["statistics"]["reference_zero_N"] == off.reference.zero_N[-1]
    said = [re.search(r"its zero at rest ([-+][0-9.]+) N \(subtracted\)", line) for line in summary_lines(off)]
    assert [float(m.group(1)) for m in said if m] == [pytest.approx(offset, abs=3e-3)]


def test_a_quad_calibrates_the_same_from_an_ft_sensor_off_zero(tmp_path):
    sim = quad_session(rate_hz=250.0, seed=0)
    (tmp_path / "session.bin").write_bytes(sim.raw)
    (tmp_path / "zeroed.csv").write_text(sim.reference_csv)
    (tmp_path / "off.csv").write_text(_shifted(sim.reference_csv, [-0.15, 0.1, 0.3]))
    reference = calibrate_quad(tmp_path / "session.bin", tmp_path / "zeroed.csv")
    off = calibrate_quad(tmp_path / "session.bin", tmp_path / "off.csv")
    np.testing.assert_allclose(off.reference.zero_N, [-0.15, 0.1, 0.3], atol=3e-3)
    assert off.fit.normal[1] == pytest.approx(reference.fit.normal[1], rel=3e-3)
    assert off.fit.normal[1] == pytest.approx(sim.model.normal_fit[1], rel=0.01)
    assert off.fit.shear[0] == pytest.approx(reference.fit.shear[0], rel=3e-3)
    np.testing.assert_allclose(off.fit.c0_pF, reference.fit.c0_pF, rtol=1e-5)
    assert quad_document(off)["statistics"]["reference_zero_N"]["z"] == off.reference.zero_N[2]

"""The tare window is set by the C0 of the calibration in use: a sensor far
from the papers' C0 (0.3–0.5 pF taxels, 17 pF quad electrodes) tares once
its own calibration, with its measured C0, is uploaded; on the built-in one
/health says its capacitances lie outside what that calibration expects."""
import time

import numpy as np
import orjson
import pytest

from service.health import health_report
from service.live_service import TactileService
from service.protocol import FrameType, encode_frame
from service.readings import Reading, SensorInfo
from service.reconstruct import Reconstructor
from service.reconstruct.calibration_upload import tare_window
from service.reconstruct.sensor_calibration import builtin, from_document
from service.physics.paper_data import table1

GRID = SensorInfo(0, "grid", 8, 8)
QUAD = SensorInfo(1, "quad", 2, 2)
TINY_C0 = np.random.default_rng(5).uniform(0.3, 0.5, 64)  # small taxels, pF
BIG_QUAD_C0 = np.array([17.0, 17.4, 16.8, 17.2])  # large electrodes, pF
SENSITIVITY = 0.0125  # /N, the upload's 1.25 %/N
LINEAR_NORMAL, LINEAR_SHEAR = [0.0, 0.0343], [0.0077, 0.0]  # ΔC/C0 = 0.0343 F (normal), 0.0077 F (shear)
TABLE_TOP_FLAT = 0.784622  # the flat model table's top ΔC/C0 (level0.py: 0.785)


def reading(info, capacitance, seq):
    capacitance = np.asarray(capacitance, dtype=float)
    return Reading(info, seq, seq * 1000, 0.0, 0, 0, capacitance, bool(np.isnan(capacitance).any()), False)


def feed(rec, info, c0, first, count, rng, relative=0.0):
    """``count`` readings of C0 (n,) pF times (1 + relative) with 0.01 % noise; the last frame."""
    frame = None
    for seq in range(first, first + count):
        (frame,) = rec.process(reading(info, c0 * (1 + relative) * (1 + rng.normal(0, 1e-4, c0.size)), seq))
    return frame


def test_a_measured_c0_sets_the_tare_window_and_table_1_the_built_ins():
    """(low, high) = C0 · 0.5 / 3 … C0 · (1 + 0.7846) · 1.5 · 3 (level0.py), C0 the calibration's measured
    one: 0.4 pF gives 0.0667–3.212 pF, where table 1's 10.66 pF taxel gave 1.777–85.6 pF."""
    low, high = tare_window(GRID, "flat", builtin(GRID))
    c0 = table1().c0_pF
    np.testing.assert_allclose(low, c0 / 6, rtol=1e-12)
    np.testing.assert_allclose(high, c0 * (1 + TABLE_TOP_FLAT) * 4.5, rtol=1e-6)
    rec = Reconstructor(tare_frames=5, level="level0")
    document = rec.prepare_calibration(GRID, {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": TINY_C0.tolist()})[2]
    low, high = tare_window(GRID, "flat", from_document(document, GRID))
    np.testing.assert_allclose(low, TINY_C0 / 6, rtol=1e-12)
    np.testing.assert_allclose(high, TINY_C0 * (1 + TABLE_TOP_FLAT) * 4.5, rtol=1e-6)


def test_taxels_without_a_measured_c0_are_expected_at_the_measured_ones_level():
    """A session that measured half the taxels (the rest carry table 1's C0): the others are expected at
    table 1's C0 times the measured ones' median C0 / table 1 (0.4 / 10.66 here), not at table 1's."""
    c0 = table1().c0_pF
    document = Reconstructor(level="level0").prepare_calibration(
        GRID, {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": (c0 * 0.0375).tolist()})[2]
    document["taxels"]["source"] = ["upload"] * 32 + ["builtin-table1"] * 32
    document["taxels"]["c0_pF"][32:] = c0[32:].tolist()  # as a session leaves the taxels it did not fit
    low, _ = tare_window(GRID, "flat", from_document(document, GRID))
    np.testing.assert_allclose(low, c0 * 0.0375 / 6, rtol=1e-9)


def test_a_tiny_c0_grid_stays_null_on_the_built_in_and_reads_its_press_after_its_c0_is_uploaded():
    rng = np.random.default_rng(1)
    rec = Reconstructor(tare_frames=10, level="level0")
    frame = feed(rec, GRID, TINY_C0, 0, 20, rng)
    assert np.isnan(frame.forces_N).all() and rec.unzeroed(0) == list(range(64))  # 0.3–0.5 pF < 1.3 pF: no zero
    rec.set_calibration(GRID, {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": TINY_C0.tolist()})
    rec.tare(0, judge=False)
    feed(rec, GRID, TINY_C0, 20, 10, rng)
    assert rec.unzeroed(0) == []
    np.testing.assert_allclose(rec.baseline(0), TINY_C0, rtol=1e-4)
    relative = np.zeros(64)
    relative[10] = SENSITIVITY * 2.0  # 2 N on taxel 10: F = (ΔC/C0) / s
    frame = feed(rec, GRID, TINY_C0, 30, 1, rng, relative)
    assert frame.forces_N[10] == pytest.approx(2.0, abs=0.05)
    assert np.abs(np.delete(frame.forces_N, 10)).max() < 0.05 and "out_of_range" not in frame.flags


def test_a_sensor_without_a_zero_tares_on_its_own_once_its_c0_is_uploaded():
    """No tare asked: its first reading inside the new window begins the tare (baseline.py)."""
    rng = np.random.default_rng(2)
    rec = Reconstructor(tare_frames=10, level="level0")
    feed(rec, GRID, TINY_C0, 0, 20, rng)
    rec.set_calibration(GRID, {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": TINY_C0.tolist()})
    frame = feed(rec, GRID, TINY_C0, 20, 11, rng)
    assert rec.unzeroed(0) == [] and np.abs(frame.forces_N).max() < 0.05


def test_a_zero_made_before_the_upload_is_kept_bit_for_bit():
    """Swapping the calibration keeps the zero (calibration_choice.py); only a later tare takes the new window."""
    rng = np.random.default_rng(3)
    c0 = table1().c0_pF
    rec = Reconstructor(tare_frames=10, level="level0")
    feed(rec, GRID, c0, 0, 10, rng)
    zero = rec.baseline(0).copy()
    rec.set_calibration(GRID, {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": (c0 * 1.0001).tolist()})
    relative = np.zeros(64)
    relative[3] = SENSITIVITY * 1.0
    frame = feed(rec, GRID, c0, 10, 1, rng, relative)
    np.testing.assert_array_equal(rec.baseline(0), zero)
    assert frame.forces_N[3] == pytest.approx(1.0, abs=0.05) and rec.loaded_at_tare(0) == []


def test_a_17_pF_quad_reads_its_press_after_its_measured_c0_is_uploaded():
    rng = np.random.default_rng(4)
    rec = Reconstructor(tare_frames=10)
    frame = feed(rec, QUAD, BIG_QUAD_C0, 0, 20, rng)
    assert np.isnan(frame.forces_N).all() and rec.unzeroed(1) == [0, 1, 2, 3]  # 17 pF > 13.5 pF: no zero
    rec.set_calibration(QUAD, {"normal_fit": LINEAR_NORMAL, "shear_fit": LINEAR_SHEAR,
                               "c0_pF": BIG_QUAD_C0.tolist()})
    rec.tare(1, judge=False)
    feed(rec, QUAD, BIG_QUAD_C0, 20, 10, rng)
    np.testing.assert_allclose(rec.baseline(1), BIG_QUAD_C0, rtol=1e-4)
    frame = feed(rec, QUAD, BIG_QUAD_C0, 30, 1, rng, 0.0343 * 5.0)  # 5 N normal: every electrode + 17.15 %
    np.testing.assert_allclose(frame.forces_N, [0.0, 0.0, 5.0], atol=0.05)


def test_a_quad_document_carries_its_sessions_c0_into_the_tare_window():
    """``tactile calibrate`` writes a quad's C0 (calibrate_quad.py): the window is 17 pF's, 2.83–69.9 pF."""
    document = {"schema": 1, "kind": "quad", "id": "q", "normal_fit": LINEAR_NORMAL, "shear_fit": LINEAR_SHEAR,
                "c0_pF": BIG_QUAD_C0.tolist()}
    low, high = tare_window(QUAD, "flat", from_document(document, QUAD))
    np.testing.assert_allclose(low, BIG_QUAD_C0 / 6, rtol=1e-12)
    np.testing.assert_allclose(high, BIG_QUAD_C0 * 3.1 * 4.5, rtol=1e-9)  # top ΔC/C0 2.1 of the linear fits


@pytest.mark.parametrize("c0, said", [([17.0, 17.4, 16.8], "c0_pF: expected 4 values"),
                                      ([17.0, 17.4, 16.8, 1e-9], "c0_pF[3] = 1e-09 pF is outside"),
                                      ([17.0, True, 16.8, 17.2], "c0_pF: expected a list of numbers")])
def test_a_bad_quad_c0_is_refused_naming_it(c0, said):
    with pytest.raises(ValueError, match=said.replace("[", r"\[").replace("]", r"\]")):
        Reconstructor().prepare_calibration(QUAD, {"normal_fit": LINEAR_NORMAL, "shear_fit": LINEAR_SHEAR,
                                                   "c0_pF": c0})


def _tiny_grid_service():
    service = TactileService("sim://")
    info = orjson.dumps({"board": "b", "serial": "B-7", "sensors": [{"id": 0, "kind": "grid", "rows": 8, "cols": 8}]})
    counts = np.round(TINY_C0 * 1e6).astype("<u4")  # aF
    scans = b"".join(encode_frame(FrameType.GRID, 0, s, 1000 * (s + 1), counts.tobytes()) for s in range(150))
    service.pipeline.feed(encode_frame(FrameType.INFO, 255, 0, 0, info) + scans, time.time())
    return service, counts


def test_health_says_the_capacitances_lie_outside_what_the_built_in_calibration_expects():
    service, _ = _tiny_grid_service()
    report = health_report(service)
    lines = [p for p in report["problems"] if p.startswith("sensor 0")]
    assert len(lines) == 1, lines
    low, high = TINY_C0.min(), TINY_C0.max()
    assert f"all 64 taxels read {low:.3g}–{high:.3g} pF" in lines[0]
    c0 = table1().c0_pF
    assert f"outside the {c0.min() / 6:.3g}–{c0.max() * (1 + TABLE_TOP_FLAT) * 4.5:.3g} pF" in lines[0]
    assert "builtin-table1" in lines[0] and "c0_pF" in lines[0] and "until they read plausibly" not in lines[0]


def test_health_is_ok_once_the_sensors_own_c0_is_uploaded():
    service, counts = _tiny_grid_service()
    service.pipeline.set_calibration(service.pipeline.interpreter.sensors[0],
                                     {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": TINY_C0.tolist()})
    scans = b"".join(encode_frame(FrameType.GRID, 0, s, 1000 * (s + 1), counts.tobytes()) for s in range(150, 300))
    service.pipeline.feed(scans, time.time())
    report = health_report(service)
    assert report["sensors"]["0"]["unzeroed_channels"] == []
    assert not [p for p in report["problems"] if p.startswith("sensor 0")], report["problems"]
    assert np.abs(service.pipeline.latest[0].forces_N).max() < 0.05


def test_health_says_a_measured_c0_the_sensor_does_not_read_is_not_this_sensors():
    """Another sensor's calibration (table 1's C0 as measured) on the 0.3–0.5 pF grid: no zero, said so."""
    service, counts = _tiny_grid_service()
    service.pipeline.set_calibration(service.pipeline.interpreter.sensors[0],
                                     {"sensitivity_pct_per_N": [1.25] * 64, "c0_pF": table1().c0_pF.tolist()})
    scans = b"".join(encode_frame(FrameType.GRID, 0, s, 1000 * (s + 1), counts.tobytes()) for s in range(150, 160))
    service.pipeline.feed(scans, time.time())
    outside = health_report(service)["sensors"]["0"]["outside_calibration"]
    assert outside["measured"] is True and outside["channels"] == list(range(64))
    assert outside["read_pF"] == pytest.approx([TINY_C0.min(), TINY_C0.max()], abs=1e-6)
    (line,) = [p for p in health_report(service)["problems"] if p.startswith("sensor 0")]
    assert "its C0 measured" in line and "the calibration is not this sensor's" in line

"""A quad whose electrodes misread while it tared (baseline.py, ``whole``).

Every force of a quad combines all four electrodes. One electrode open or
implausible through the tare window got a late zero of its own 99 frames
after it first read, those frames null and flagged ``out_of_range`` on
plausible readings; two electrodes off their quad's level (5× or 0.41× the
other two) were kept as zeros: numbers from the faulty readings while the
fault lasted, and null, ``out_of_range``, on every frame once they
recovered, until someone tared by hand. Now the quad tares again from its
first reading with all four electrodes plausible and at one level."""
import numpy as np
import pytest

from service.physics.paper_data import FIT34
from service.physics.quad_model import NOMINAL_C0_PF
from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.reconstruct import Reconstructor

QUADS = 3  # quad 0 misreads; 1 and 2 are its working twins
PRESS = 0.015  # ΔC/C0 on all four electrodes: pure normal force
PRESS_FROM = 500
SCANS = 600


def paper_fz(relative: float) -> float:
    """Fz (N) of fit (34) without its offset (ΔC/C0 = c2 F² + c1 F), on its rising branch."""
    c2, c1, _ = FIT34
    return (c1 - np.sqrt(c1 * c1 + 4.0 * c2 * relative)) / (-2.0 * c2)


def run(misread, level="full"):
    """{(sensor, seq): frame} of SCANS scans at 1 kHz; ``misread(k, raw)`` edits quad 0's counts at scan k;
    every quad pressed by PRESS from PRESS_FROM on. Also {scan: unzeroed electrodes of quad 0}."""
    rng = np.random.default_rng(7)
    pipeline = Pipeline(Reconstructor(level=level), map_clock=False)
    frames, unzeroed = {}, {}
    for k in range(SCANS):
        scan = []
        for sid in range(QUADS):
            pf = NOMINAL_C0_PF * (1 + rng.normal(0, 2e-4, 4)) * (1 + (PRESS if k >= PRESS_FROM else 0.0))
            raw = np.round(pf * 1e6).astype("<u4")
            if sid == 0:
                misread(k, raw)
            scan.append(encode_frame(FrameType.QUAD, sid, k, 1000 * (k + 1), raw.tobytes()))
        for frame in pipeline.feed(b"".join(scan), 1 + k * 1e-3):
            frames[frame.sensor.id, frame.seq] = frame
        unzeroed[k] = pipeline.reconstructor.unzeroed(0)
    return frames, unzeroed


def assert_twins_unaffected(frames):
    for sid in range(1, QUADS):
        assert all(frames[sid, k].flags == [] and np.isfinite(frames[sid, k].forces_N).all() for k in range(100, SCANS))


def assert_reads_the_press(frames, first_read: int):
    """Null and ``taring`` from the first good reading for a tare window, then as its twins: 0 and the press."""
    assert [frames[0, k].flags for k in range(first_read, first_read + 99)] == [["taring"]] * 99
    assert all(np.isnan(frames[0, k].forces_N).all() for k in range(first_read, first_read + 99))
    assert [frames[0, k].flags for k in range(first_read + 99, SCANS)] == [[]] * (SCANS - first_read - 99)
    before = np.array([frames[0, k].forces_N for k in range(first_read + 99, PRESS_FROM)])
    assert np.abs(before).max() < 0.05
    pressed = np.array([frames[0, k].forces_N for k in range(PRESS_FROM + 5, SCANS)])
    assert np.median(pressed[:, 2]) == pytest.approx(paper_fz(PRESS), rel=0.02)
    assert np.abs(pressed[:, :2]).max() < 0.05


@pytest.mark.parametrize("bad", [0xFFFFFFFF, 1, 0xFFFFFFFE])  # open sentinel, 1 aF, the converter's top count
@pytest.mark.parametrize("level", ["level0", "full"])
def test_an_electrode_without_a_zero_tares_its_quad_again_from_its_first_plausible_reading(bad, level):
    """Electrode 2 misreads through the tare window and 50 scans more."""
    def misread(k, raw):
        if k < 150:
            raw[2] = bad

    frames, unzeroed = run(misread, level)
    waiting = [frames[0, k] for k in range(100, 150)]
    said = "open_channel" if bad == 0xFFFFFFFF else "out_of_range"  # and stale once the count repeated 50 frames
    assert all(np.isnan(f.forces_N).all() and said in f.flags and set(f.flags) <= {said, "stale"} for f in waiting)
    assert unzeroed[149] == [2]
    assert_reads_the_press(frames, 150)
    assert unzeroed[SCANS - 1] == []
    assert_twins_unaffected(frames)


@pytest.mark.parametrize("factor", [5.0, 0.41])
def test_two_electrodes_off_their_quads_level_while_it_tared_give_no_numbers_and_tare_again(factor):
    """Electrodes 0 and 1 read ``factor``× their level (a converter fault at power-up, plausible against the
    nominal C0) until scan 300. No level tells the faulty pair from the good one: the quad has no zero,
    each electrode named unzeroed, its frames null and flagged until all four read at one level."""
    def misread(k, raw):
        if k < 300:
            raw[:2] = np.round(raw[:2] * factor).astype(raw.dtype)

    frames, unzeroed = run(misread)
    faulty = [frames[0, k] for k in range(100, 300)]
    assert all(np.isnan(f.forces_N).all() and "out_of_range" in f.flags for f in faulty)
    assert unzeroed[299] == [0, 1, 2, 3]
    assert_reads_the_press(frames, 300)
    assert unzeroed[SCANS - 1] == []
    assert_twins_unaffected(frames)

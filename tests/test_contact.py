"""Contacts are taxels above 0.05 N and above 4 σ of their own: a fixed
0.05 N alone reported contacts on untouched grids whose noise is that size
(a tester's 1x4 at 3 pF: 60 % of frames; a 16x16: 41 %). Grids fed as a
board sends them, their noise 2 fF; presses by paper 000's gap law."""
import numpy as np
import orjson
import pytest

from service.pipeline import Pipeline
from service.protocol import FrameType, encode_frame
from service.reconstruct import Reconstructor
from service.reconstruct.contact import summarise
from service.record.contact_batch import summaries

K_PER_N = 0.0112  # gap law ΔC/C0 = kF/(1 − kF): 6.1 % at 5.2 N, as table 1's taxels


def frames(rows: int, cols: int, c0_pF: float, pressed: dict[int, float], n: int, seed: int) -> list:
    """The full level's frames after a 300-frame tare, then ``n`` with ``pressed`` {taxel: N}."""
    rng = np.random.default_rng(seed)
    info = {"board": "b", "sensors": [{"id": 0, "kind": "grid", "rows": rows, "cols": cols}]}
    force = np.zeros(rows * cols)
    force[list(pressed)] = list(pressed.values())
    loaded = c0_pF * (1 + K_PER_N * force / (1 - K_PER_N * force))
    data = encode_frame(FrameType.INFO, 255, 0, 0, orjson.dumps(info))
    for seq in range(300 + n):
        pf = (c0_pF if seq < 300 else loaded) + rng.normal(0, 0.002, rows * cols)
        data += encode_frame(FrameType.GRID, 0, seq, 1000 * (seq + 1), np.round(pf * 1e6).astype("<u4").tobytes())
    out = Pipeline(Reconstructor(level="full"), map_clock=False).feed(data, 1.0)
    return [f for f in out if not np.isnan(f.forces_N).all()][-n:]


@pytest.mark.parametrize("rows, cols, c0_pF", [(1, 4, 3.0), (4, 4, 6.0), (16, 16, 10.5), (8, 8, 10.66)])
def test_an_untouched_grid_has_no_contact(rows, cols, c0_pF):
    untouched = frames(rows, cols, c0_pF, {}, 2000, seed=rows * cols)
    phantom = sum(f.contact["contacts"] > 0 for f in untouched) / len(untouched)
    by_threshold_alone = sum(summarise(f.forces_N, rows, cols)["contacts"] > 0 for f in untouched) / len(untouched)
    assert phantom < 0.005 and (by_threshold_alone > 0.05 or c0_pF > 10)


def test_a_press_above_the_noise_is_one_contact_where_it_is():
    """0.6 N on one taxel of a 1x4 at 3 pF (noise ~0.06 N): one contact of
    16 mm² at that taxel, in every frame; with the threshold alone a second,
    phantom one came and went, moving the centre of pressure."""
    pressed = frames(1, 4, 3.0, {1: 0.6}, 1000, seed=5)
    assert all(f.contact["contacts"] == 1 and f.contact["area_mm2"] == 16.0 for f in pressed)
    assert {round(f.contact["cop_x_mm"], 6) for f in pressed} == {-2.0}
    alone = [summarise(f.forces_N, 1, 4) for f in pressed]
    assert sum(s["area_mm2"] > 16.0 for s in alone) > 50


def test_the_batch_summary_with_sigma_is_the_per_frame_one_bit_for_bit():
    rng = np.random.default_rng(2)
    forces = rng.random((3000, 16)) * rng.random((3000, 1)) * 0.4 - 0.05
    sigma = rng.random((3000, 16)) * 0.1
    sigma[rng.random(sigma.shape) < 0.05] = np.nan  # saturated: σ null, the threshold alone
    forces[rng.random(forces.shape) < 0.02] = np.nan
    expected = [None if np.isnan(f).all() else summarise(f, 4, 4, s) for f, s in zip(forces, sigma)]
    assert [orjson.dumps(s) for s in summaries(forces, 4, 4, sigma)] == [orjson.dumps(s) for s in expected]
    assert sum(s["contacts"] for s in expected if s) != sum(summarise(f, 4, 4)["contacts"] for f in forces
                                                           if not np.isnan(f).all())

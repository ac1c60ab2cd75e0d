"""The bench's whole-process figures and its naive reference decoder."""
import io
import sys

import numpy as np
import orjson
import pytest

from service.physics.paper_data import table1
from service.protocol import FrameType, encode_frame
from service.reports import bench_process, naive_decoder


def test_the_naive_decoder_gives_first_order_forces_and_skips_a_corrupt_frame():
    cal = table1()
    load = np.linspace(0.0, 2.0, 64)
    capacitance_pF = cal.c0_pF * (1 + cal.sensitivity_per_N * load)
    counts = np.round(capacitance_pF * 1e6).astype("<u4")
    counts[9] = 0xFFFFFFFF
    grid = encode_frame(FrameType.GRID, 0, 7, 7000, counts.tobytes(), flags=1)
    c0 = naive_decoder.QUAD_C0_PF
    quad = encode_frame(FrameType.QUAD, 1, 3, 7000, np.round(np.array([1.0, 1.02, 1.0, 1.02]) * c0 * 1e6).astype("<u4").tobytes())
    bad = bytearray(grid)
    bad[40] ^= 0xFF
    out = io.BytesIO()
    assert naive_decoder.export(b"\x00junk" + bytes(bad) + grid + quad, out) == 2
    g, q = (orjson.loads(line) for line in out.getvalue().splitlines())
    assert (g["sensor"], g["seq"], g["t_us"], g["kind"], g["flags"]) == (0, 7, 7000, "grid", ["saturated"])
    forces = np.array([np.nan if v is None else v for v in g["taxels_N"]])
    assert np.isnan(forces[9])
    np.testing.assert_allclose(np.delete(forces, 9), np.delete(load, 9), atol=2e-4)  # 1 aF rounding
    # r12 = r22 = 0.02, r11 = r21 = 0: Fx = 0.04/4/0.0077, Fy = 0, Fz = 0.04/4/0.0343 (level0.py's slopes)
    np.testing.assert_allclose(q["fxyz_N"], [0.01 / 0.0077, 0.0, 0.01 / 0.0343], rtol=1e-4, atol=1e-6)
    assert g["contact"]["area_mm2"] == 16.0 * np.count_nonzero(np.delete(load, 9) > 0.05)


def test_cpu_seconds_counts_the_child_and_says_when_it_fails():
    idle = bench_process.cpu_seconds([sys.executable, "-c", "pass"])
    busy = bench_process.cpu_seconds([sys.executable, "-c", "sum(range(30_000_000))"])
    assert busy > idle + 0.2
    with pytest.raises(RuntimeError, match="exit 3"):
        bench_process.cpu_seconds([sys.executable, "-c", "raise SystemExit(3)"])


def test_figures_are_medians_and_ratios_to_the_naive_decoder(monkeypatch):
    monkeypatch.setattr(bench_process, "_captures", lambda directory, seconds: (directory / "a", directory / "b", directory / "c"))
    (times := iter([2.0, 1.0, 0.5, 0.8, 0.3] + [3.0, 0.4, 0.7, 0.9, 0.3] + [2.5, 0.6, 0.6, 1.0, 0.2]))
    monkeypatch.setattr(bench_process, "cpu_seconds", lambda command: next(times))
    monkeypatch.setattr(bench_process.Path, "stat", lambda self: type("S", (), {"st_size": 123})())
    figures = bench_process.whole_process(seconds=2.0, repeats=3)
    rows = {row["command"]: row for row in figures["rows"]}
    assert rows["naive decoder → jsonl"]["cpu_s"] == 2.5
    assert rows["replay --raw → jsonl"]["ratio_to_naive"] == pytest.approx(2.5 / 0.6)
    assert rows["replay --raw → parquet"]["grid_frames_per_s"] == pytest.approx(2000 / 0.6)
    assert rows["start-up (0.1 s capture)"]["ratio_to_naive"] is None
    assert "| replay --raw → jsonl | 0.60 | 3,333 | 4.17 |" in bench_process.render(figures)

"""The report generators (service/reports): the noise floor they state errors
against, their figures, what happens without matplotlib, and their place above
the runtime."""
import csv
import math
import sys
from pathlib import Path

import pytest

from service.cli import main
from service.reports import bench, convergence, plotting

ROOT = Path(__file__).parents[1]
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_noise_floor_is_the_rms_over_the_table1_taxels_of_noise_over_c0_times_sensitivity():
    # Independently of service.calibration: read the paper's table 1 as shipped and apply
    # ΔC/C0 = s·F, so σ_F = σ_C / (C0 · s) per taxel (σ_C = 1 fF = 1e-3 pF, s in %/N).
    with open(ROOT / "service" / "data" / "array8x8_table1.csv", newline="") as f:
        taxels = list(csv.DictReader(f))
    assert len(taxels) == 64
    sigma_N = [1e-3 / (float(t["c0_pF"]) * float(t["sensitivity_pct_per_N"]) / 100) for t in taxels]
    expected = math.sqrt(sum(s * s for s in sigma_N) / len(sigma_N))

    assert bench.noise_floor_N() == pytest.approx(expected, rel=1e-12)
    assert bench.noise_floor_N(2.5) == pytest.approx(2.5 * expected, rel=1e-12)  # linear in the noise
    # The figure the docs quote (σ ≈ 0.0076 N; 2× = 0.0153 N): C0 ≈ 10.4 pF, s ≈ 1.25 %/N.
    assert expected == pytest.approx(0.00765, abs=5e-5)


def _bench_report():
    rows = [
        {"scenario": scenario, "level": level, "batch_us_per_grid_frame": cost, "rms_loaded_N": err}
        for scenario in ("press", "slide")
        for level, cost, err in (("level0", 0.5, 0.2), ("table", 2.0, 0.01), ("full", 4.0, 0.009))
    ]
    return {"rows": rows, "noise_floor_N": 0.0076, "text": "| a | table |"}


def _convergence_result():
    row = {"p": 2, "pz": 2, "dofs": 100, "rcond": 1e-6, "seconds": 0.1, "factor_MB": 1.0,
           "dC_C0": 0.01, "sensitivity": 0.0125, "error_dC_C0": 1e-3, "error_sensitivity": 2e-3}
    finer = {**row, "p": 3, "dofs": 400, "seconds": 0.5, "error_dC_C0": 1e-5}
    return {"reference": {**row, "p": 6, "pz": 4}, "series": {"graded p": [row, finer], "pz": [row],
                                                               "monomial p": [{"p": 4, "pz": 2, "refused": "rcond"}]}}


def test_the_plotting_helper_sets_up_every_panel_and_saves_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    fig, axes = plotting.figure(plotting.Panel("x", "y", yscale="log"), plotting.Panel("dofs", "s", "log", "log"))
    assert [(ax.get_xlabel(), ax.get_xscale(), ax.get_yscale()) for ax in axes] == [("x", "linear", "log"), ("dofs", "log", "log")]
    assert tuple(fig.get_size_inches()) == (2 * plotting.PANEL_SIZE_IN[0], plotting.PANEL_SIZE_IN[1])
    axes[0].plot([1, 2], [1e-3, 1e-5])
    path = plotting.save_png(fig, tmp_path / "f.png")
    assert path == tmp_path / "f.png" and path.read_bytes().startswith(PNG_MAGIC)


def test_a_figure_needs_a_panel():
    with pytest.raises(ValueError, match="panel"):
        plotting.figure()


@pytest.mark.parametrize("module, result, names", [
    (bench, _bench_report(), ["bench.md", "bench.png"]),
    (convergence, _convergence_result(), ["convergence.md", "convergence.png"]),
])
def test_write_docs_writes_the_table_and_the_figure(tmp_path, module, result, names):
    pytest.importorskip("matplotlib")
    written = module.write_docs(result, tmp_path / "out")
    assert [p.name for p in written] == names
    assert written[1].read_bytes().startswith(PNG_MAGIC)


@pytest.mark.parametrize("module, result, png", [
    (bench, _bench_report(), "bench.png"),
    (convergence, _convergence_result(), "convergence.png"),
])
def test_without_matplotlib_write_docs_fails_clearly_and_writes_nothing(tmp_path, monkeypatch, module, result, png):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib -> ImportError
    with pytest.raises(plotting.PlottingUnavailable, match=rf"{png}.*matplotlib.*pip install -e \"\.\[docs\]\" in the source tree"):
        module.write_docs(result, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_bench_out_without_matplotlib_is_a_cli_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(bench, "run", lambda seconds: _bench_report())
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    assert main(["bench", "--seconds", "2", "--out", str(tmp_path / "docs")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("tactile bench: error: writing bench.png needs matplotlib")
    assert 'pip install -e ".[docs]" in the source tree' in err
    assert not (tmp_path / "docs").exists()

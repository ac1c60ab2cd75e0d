"""`tactile model convergence`: error against order of the Ritz taxel model.

Series (uniform q0 on the taxel; figures ΔC/C0 at 100 kPa and the 0–10 N
sensitivity, errors relative to a high-order reference):

* in-plane degree p on the graded partition split at the load edge (pz fixed);
* the same with the partition split at the load edge only (no grading);
* degree pz across each layer (p fixed);
* the naive monomial basis on the split partition until the rcond guard
  refuses it.

Each row records dofs, assembly+factorisation+solve time and the memory of
the sparse LU factors. Writes docs/convergence.md and docs/convergence.png.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Callable

from ..physics.capacitance import gap_field, sensitivity_per_N
from ..physics.ritz import ConditioningError, RitzOptions, RitzSystem, Taxel, patch_load
from ..physics.tables import Q0_MPA
from . import plotting

REFERENCE = RitzOptions(p=6, pz=4)
SPLIT_ONLY = (0.0, 1500.0, 2000.0)


def _run(options: RitzOptions) -> dict:
    taxel = Taxel()
    t0 = time.perf_counter()
    system = RitzSystem(taxel, options, "z")
    field = gap_field(system.solve(patch_load(Q0_MPA, taxel.half_load_um)), 0.9)
    return {
        "p": options.p,
        "pz": options.pz,
        "family": options.family,
        "partition": "split" if options.breaks == SPLIT_ONLY else "graded",
        "dofs": system.dofs,
        "rcond": system.rcond,
        "seconds": time.perf_counter() - t0,
        "factor_MB": system.factor_bytes / 1e6,
        "dC_C0": float(field.relative_change(0.9)[0]),
        "sensitivity": sensitivity_per_N(field),
    }


P_SERIES = range(1, 6)
PZ_SERIES = range(1, 5)
MONOMIAL_SERIES = range(2, 16, 2)


def _no_progress(done: int, total: int, what: str) -> None:
    pass


def run(progress: Callable[[int, int, str], None] = _no_progress) -> dict:
    """Every series; ``progress(done, total, what)`` after each model solved
    (the monomial series may end early, refused by the conditioning guard)."""
    total = 1 + 2 * len(P_SERIES) + len(PZ_SERIES) + len(MONOMIAL_SERIES)
    done = 0

    def step(what: str) -> None:
        nonlocal done
        done += 1
        progress(done, total, what)

    reference = _run(REFERENCE)
    step(f"reference p={REFERENCE.p} pz={REFERENCE.pz}")
    series: dict[str, list[dict]] = {"graded p": [], "split-only p": [], "pz": [], "monomial p": []}
    for p in P_SERIES:
        series["graded p"].append(_run(RitzOptions(p=p, pz=4)))
        step(f"graded p={p}")
        series["split-only p"].append(_run(RitzOptions(p=p, pz=4, breaks=SPLIT_ONLY)))
        step(f"split-only p={p}")
    for pz in PZ_SERIES:
        series["pz"].append(_run(RitzOptions(p=5, pz=pz)))
        step(f"pz={pz}")
    for p in MONOMIAL_SERIES:
        try:
            series["monomial p"].append(_run(RitzOptions(p=p, pz=2, family="monomial", breaks=SPLIT_ONLY)))
            step(f"monomial p={p}")
        except ConditioningError as exc:
            series["monomial p"].append({"p": p, "pz": 2, "refused": str(exc)})
            progress(total, total, f"monomial p={p} refused")
            break
    for rows in series.values():
        for row in rows:
            if "dC_C0" in row:
                row["error_dC_C0"] = abs(row["dC_C0"] / reference["dC_C0"] - 1)
                row["error_sensitivity"] = abs(row["sensitivity"] / reference["sensitivity"] - 1)
    return {"reference": reference, "series": series}


def write_docs(result: dict, out_dir: Path) -> list[Path]:
    """Write convergence.md and convergence.png to ``out_dir`` (matplotlib
    required: plotting.PlottingUnavailable, nothing written, without it)."""
    plotting.require("convergence.png")
    out_dir.mkdir(parents=True, exist_ok=True)
    ref = result["reference"]
    lines = [
        "# Ritz taxel model: convergence against order",
        "",
        "Produced by `tactile model convergence --out docs` (uniform q0 = 100 kPa on the 3×3 mm load,",
        f"reference p = {ref['p']}, pz = {ref['pz']}: ΔC/C0 = {ref['dC_C0']:.7f}, sensitivity",
        f"{100 * ref['sensitivity']:.5f} %/N, {ref['dofs']} dofs, {ref['seconds']:.0f} s, LU {ref['factor_MB']:.0f} MB).",
        "Errors are relative to the reference; times are assembly + factorisation + rcond estimate + solve on one core.",
        "",
    ]
    for name, rows in result["series"].items():
        lines += [f"## {name}", "", "| p | pz | dofs | error ΔC/C0 | error sensitivity | rcond | time s | LU MB |", "|---|---|---|---|---|---|---|---|"]
        for row in rows:
            if "refused" in row:
                lines.append(f"| {row['p']} | {row['pz']} | — | refused by the rcond guard | | | | |")
            else:
                lines.append(
                    f"| {row['p']} | {row['pz']} | {row['dofs']} | {row['error_dC_C0']:.2e} | {row['error_sensitivity']:.2e} | "
                    f"{row['rcond']:.1e} | {row['seconds']:.1f} | {row['factor_MB']:.1f} |"
                )
        lines.append("")
    md = out_dir / "convergence.md"
    md.write_text("\n".join(lines))
    return [md, plot(result, out_dir / "convergence.png")]


def plot(result: dict, path: Path) -> Path:
    """Left: relative error of ΔC/C0 against degree; right: time against dofs."""
    fig, (ax1, ax2) = plotting.figure(
        plotting.Panel("polynomial degree (p, or pz for the pz series)", "relative error of ΔC/C0 at 100 kPa", yscale="log"),
        plotting.Panel("dofs", "time (s)", xscale="log", yscale="log"),
        size_in=(10, 4),
    )
    for name, rows in result["series"].items():
        ok = [r for r in rows if "dC_C0" in r and r["error_dC_C0"] > 0]
        key = "pz" if name == "pz" else "p"
        ax1.plot([r[key] for r in ok], [r["error_dC_C0"] for r in ok], "o-", label=name)
        ax2.plot([r["dofs"] for r in ok], [r["seconds"] for r in ok], "o-", label=name)
    ax1.legend()
    return plotting.save_png(fig, path)

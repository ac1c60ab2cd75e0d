"""The calibration report: Markdown and two PNGs.

``calibration.md`` holds the alignment, a table like paper 000's table 1
(C0, sensitivity in both readings, gain ± error, residual RMS in N, presses,
largest force) and the taxels not pressed (which keep their previous
calibration); ``response.png`` one small panel per taxel (the samples and the
fitted curve, ΔC/C0 against force); ``residuals.png`` the 8×8 map of residual
RMS and of the gain.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..reports import plotting
from .calibrate import Calibration
from .fit import table_cells, unit_response


def _curve(result: Calibration, taxel: int, forces: np.ndarray) -> np.ndarray:
    """The fitted ΔC/C0 at ``forces`` (m,) for one taxel."""
    fit = result.fits[taxel]
    if fit.model == "empirical":
        return np.interp(forces, fit.curve_force_N, fit.curve_relative)
    return unit_response(result.mounting).forward(forces[:, None] * fit.gain)[:, 0]


def response_png(result: Calibration, path: Path) -> Path:
    """A rows×cols grid of panels: samples (every 4th) and the fitted curve."""
    plt = plotting.pyplot(str(path))
    info = result.session.info
    fig, axes = plt.subplots(info.rows, info.cols, figsize=(1.6 * info.cols, 1.4 * info.rows), sharex=True, sharey=True,
                             squeeze=False)
    forces = np.linspace(0.0, result.full_scale_N, 50)
    for taxel in range(info.channels):
        ax = axes[taxel // info.cols][taxel % info.cols]
        ax.tick_params(labelsize=5)
        ax.set_title(f"r{taxel // info.cols + 1}c{taxel % info.cols + 1}", fontsize=6, pad=2)
        if taxel in result.samples:
            data = result.samples[taxel]
            ax.plot(data.force_N[::4], 100 * data.relative[::4], ".", ms=1, color="0.6")
        if taxel in result.fits:
            ax.plot(forces, 100 * _curve(result, taxel, forces), "-", lw=0.8,
                    color="C3" if result.fits[taxel].model == "empirical" else "C0")
        else:
            ax.text(0.5, 0.5, "not pressed", ha="center", va="center", fontsize=6, transform=ax.transAxes)
    fig.supxlabel("force (N)", fontsize=8)
    fig.supylabel("ΔC/C0 (%)", fontsize=8)
    return plotting.save_png(fig, path)


def residual_png(result: Calibration, path: Path) -> Path:
    """Two maps: residual RMS (N) and gain, NaN (blank) where not fitted."""
    info = result.session.info
    rms = np.full(info.channels, np.nan)
    gain = np.full(info.channels, np.nan)
    for t, fit in result.fits.items():
        rms[t], gain[t] = fit.residual_rms_N, fit.gain
    fig, axes = plotting.figure(plotting.Panel("column", "row"), plotting.Panel("column", "row"))
    for ax, values, title in ((axes[0], rms, "residual RMS (N)"), (axes[1], gain, "gain κ")):
        image = ax.imshow(values.reshape(info.rows, info.cols), origin="upper", cmap="viridis",
                          extent=(0.5, info.cols + 0.5, info.rows + 0.5, 0.5))
        ax.set_title(title)
        fig.colorbar(image, ax=ax)
    return plotting.save_png(fig, path)


def markdown(result: Calibration, document: dict, calibration_id: str) -> str:
    """The report's text (links the two PNGs)."""
    info, a = result.session.info, result.alignment
    lines = [f"# Calibration {calibration_id}", "",
             f"Sensor `{document['sensor']['key']}` ({info.rows}×{info.cols}), session `{result.session.path}` "
             f"({len(result.session.t_s)} frames, {result.session.rate_hz:.1f} Hz), reference `{result.reference.path}` "
             f"({len(result.reference.t_s)} samples, {result.reference.rate_hz:.1f} Hz, "
             f"{result.reference.skipped} lines skipped). Model table: {result.mounting} mounting.", "",
             "## Clock alignment", "",
             f"t_ref = offset + t_board·(1 + rate): offset {a.offset_s:+.5f} s, rate {a.rate_ppm:+.2f} ppm, match "
             f"(normalised correlation) {a.quality:.4f}; runner-up lag {a.runner_up_lag_s:+.2f} s at {a.runner_up:.3f} "
             f"against {a.coarse_best:.3f}. Presses: {len(result.presses)}, set aside: {len(result.flagged_presses)}. "
             f"Reference noise {result.reference_noise_N:.4f} N.", "",
             "## Per taxel", "",
             "Sensitivity of the fitted curve over 0–10 N: least-squares slope with intercept (paper 000's reading, "
             "what the service's per-taxel gain is solved from) and through the origin; for an `empirical` curve "
             "(the model could not follow the data: reduced χ² > 4) over 0 N to the largest force pressed.", "",
             "| taxel | C0 pF | sens. %/N (LS) | sens. %/N (origin) | gain κ ± 1σ | residual RMS N | presses | max N | curve |",
             "|---|---|---|---|---|---|---|---|---|"]
    lines += ["| " + " | ".join(table_cells(t, info.cols, result.fits[t])) + " |" for t in sorted(result.fits)]
    carried = [t for t in range(info.channels) if t not in result.fits]
    lines += ["", "## Not calibrated in this session", ""]
    if not carried:
        lines.append("None: every taxel was pressed and fitted.")
    else:
        lines.append(f"These keep their previous calibration ({document.get('previous') or 'table 1'}): "
                     + ", ".join(f"r{t // info.cols + 1}c{t % info.cols + 1}" for t in carried) + ".")
        lines += [f"* {why}" for _, why in sorted(result.problems.items())]
    lines += [f"* press at {p.start_s:.2f} s set aside: {p.problem}" for p in result.flagged_presses]
    lines += ["", "![response per taxel](response.png)", "", "![residual map](residuals.png)", ""]
    return "\n".join(lines)


def write_report(result: Calibration, document: dict, calibration_id: str, out_dir: str | Path) -> Path:
    """Write calibration.md, response.png and residuals.png into ``out_dir``; returns the Markdown's path."""
    plotting.require("the calibration report's PNGs")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    response_png(result, out / "response.png")
    residual_png(result, out / "residuals.png")
    path = out / "calibration.md"
    path.write_text(markdown(result, document, calibration_id))
    return path

"""The one matplotlib set-up of the report figures (bench.png, convergence.png).

matplotlib is an optional dependency (the ``docs`` extra): it is imported
here only, and only when a figure is drawn, with the non-interactive Agg
backend so reports render on a headless machine. A report whose command
promises a PNG calls :func:`require` before it writes anything: without
matplotlib that raises :class:`PlottingUnavailable`, a ValueError the CLI
prints as ``tactile <command>: error: ...``, rather than skipping the PNG.

Usage::

    fig, (ax,) = figure(Panel("cost (µs)", "error (N)", xscale="log", yscale="log"))
    ax.plot(...)
    path = save_png(fig, out_dir / "bench.png")
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

INSTALL_HINT = 'pip install -e ".[docs]" in the source tree'  # "tactile" on PyPI is another package
DPI = 110
PANEL_SIZE_IN = (5.0, 4.0)


class PlottingUnavailable(ValueError):
    """matplotlib, which a report needs for its PNG, is not installed."""

    def __init__(self, what: str = "the report's figure"):
        super().__init__(f"writing {what} needs matplotlib, which is not installed; "
                         f"install it with: {INSTALL_HINT} (or pip install matplotlib)")


def pyplot(what: str = "the report's figure") -> Any:
    """matplotlib.pyplot on the Agg backend; PlottingUnavailable naming
    ``what`` when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        raise PlottingUnavailable(what) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def require(what: str) -> None:
    """Fail now, before any output is written, if ``what`` (e.g. "bench.png")
    could not be drawn."""
    pyplot(what)


@dataclass(frozen=True)
class Panel:
    """How one set of axes is labelled and scaled ("linear" or "log")."""

    xlabel: str
    ylabel: str
    xscale: str = "linear"
    yscale: str = "linear"


def figure(*panels: Panel, size_in: tuple[float, float] | None = None) -> tuple[Any, list[Any]]:
    """A figure with one set of axes per panel, side by side, each labelled,
    scaled and gridded (major and minor lines, faint) the common way.
    ``size_in`` defaults to PANEL_SIZE_IN per panel."""
    if not panels:
        raise ValueError("a figure needs at least one panel")
    plt = pyplot()
    if size_in is None:
        size_in = (PANEL_SIZE_IN[0] * len(panels), PANEL_SIZE_IN[1])
    fig, axes = plt.subplots(1, len(panels), figsize=size_in, squeeze=False)
    axes = list(axes[0])
    for ax, panel in zip(axes, panels):
        ax.set_xscale(panel.xscale)
        ax.set_yscale(panel.yscale)
        ax.set_xlabel(panel.xlabel)
        ax.set_ylabel(panel.ylabel)
        ax.grid(True, which="both", alpha=0.3)
    return fig, axes


def save_png(fig: Any, path: Path, dpi: int = DPI) -> Path:
    """Lay the figure out tightly, write it as a PNG at ``path`` (its
    directory must exist), release it, and return ``path``."""
    plt = pyplot(str(path))
    try:
        fig.tight_layout()
        fig.savefig(path, dpi=dpi, format="png")
    finally:
        plt.close(fig)
    return Path(path)

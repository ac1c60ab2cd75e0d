"""Fidelity levels, and the cheapest one that meets a scene's error budget.

A configuration names its scene; the choice follows the measured figures of
``tactile bench`` (docs/bench.md, 1 fF noise, noise floor σ ≈ 0.0076 N per
taxel, budget 2σ on loaded taxels):

* level0 never meets it on a loaded taxel: it ignores the gap nonlinearity
  (0.1–0.2 N RMS on the press and slide scenes);
* table meets it for single and multi contacts on a clean board
  (0.009 N press, 0.012 N slide);
* full is needed as soon as the multiplexer leaks (0.031 N with table at
  1 % leakage) or the baseline drifts (0.20 N with table), and is what an
  unknown board gets.

Mounting picks the load-shape table (flat: uniform load; curved: the
uneven load of a bump bent on a 30 mm radius). Shear on the 8x8 array only
slides and tilts the electrodes (−0.016 %/N, below its noise): it needs no
level of its own, and the quad sensor measures it.
"""
from __future__ import annotations

from dataclasses import dataclass

from ..physics.mountings import MOUNTINGS

GRID_LEVELS = ("level0", "table", "full")
LEVELS = GRID_LEVELS + ("auto",)
DEFAULT_LEVEL = "full"


@dataclass(frozen=True)
class SceneConfig:
    mounting: str = "flat"  # flat | curved
    contacts: str = "multi"  # single | multi
    shear: bool = False
    clean_board: bool = False  # known free of multiplexer leakage and drift

    def __post_init__(self) -> None:
        if self.mounting not in MOUNTINGS:
            raise ValueError(f"mounting must be one of {', '.join(MOUNTINGS)}, got {self.mounting!r}")
        if self.contacts not in ("single", "multi"):
            raise ValueError(f"contacts must be 'single' or 'multi', got {self.contacts!r}")


def choose_level(scene: SceneConfig) -> tuple[str, str]:
    """(level, reason) for a scene."""
    if not scene.clean_board:
        return "full", "a board not known to be clean may leak between channels or drift: full compensates both"
    return "table", f"{scene.contacts} contact on a clean board: table inversion meets 2σ; crosstalk and drift need no model"

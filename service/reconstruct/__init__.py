"""Reconstruction: readings (capacitance) → ForceFrames (forces + flags).

``Reconstructor`` (reconstructor.py) keeps each sensor's baseline and
processor; grids go through grid.py (level0.py, crosstalk.py, drift.py),
quads through quad.py; levels.py names the fidelity levels. The names below
are imported on first use, so that reading the level names (the CLI's
choices) does not load the numerical code.
"""
from importlib import import_module

_EXPORTS = {"ForceFrame": ".force_frame", "Reconstructor": ".reconstructor", "DEFAULT_LEVEL": ".levels",
            "LEVELS": ".levels"}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(module, __name__), name)

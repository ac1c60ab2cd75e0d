"""Reconstruction: readings (capacitance) → ForceFrames (forces + flags).

``Reconstructor`` (reconstructor.py) keeps each sensor's baseline and
processor; grids go through grid.py (level0.py, crosstalk.py, drift.py),
quads through quad.py; levels.py names the fidelity levels.
"""
from .force_frame import ForceFrame
from .levels import DEFAULT_LEVEL, LEVELS
from .reconstructor import Reconstructor

__all__ = ["DEFAULT_LEVEL", "ForceFrame", "LEVELS", "Reconstructor"]

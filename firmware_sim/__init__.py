"""Board simulator: speaks protocol v1 byte for byte, with ground truth."""
from .board import Board, BoardConfig, capture

__all__ = ["Board", "BoardConfig", "capture"]

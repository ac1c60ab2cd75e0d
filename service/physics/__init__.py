"""Offline physics: forward models, calibration and the tables built from them."""

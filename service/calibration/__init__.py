"""Calibrating a user's own grid sensor from a reference-load session.

reference.py (the instrument's CSV) · session.py (the board's bytes → capacitance
on the board clock) · dead_taxels.py (channels without a usable reading all session) · alignment.py (reference clock → board clock) ·
segmentation.py (presses, attributed to taxels) · fit.py (per-taxel gain of the
model curve, or an empirical curve) · calibrate.py (the whole run) ·
registry.py (SQLite store of immutable calibrations; imports only physics and
readings, for the live service) · report.py (Markdown + PNG) · cli.py
(``tactile calibrate``, ``tactile calibrations ...``).
"""

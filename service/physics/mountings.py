"""How a grid is mounted, and the load-shape table of the taxel model each mounting needs.

Flat: a uniform load on each taxel. Curved: the uneven load of a bump bent
on a 30 mm radius (physics/tables.py builds both).
"""
MOUNTINGS = {"flat": "uniform", "curved": "uneven"}

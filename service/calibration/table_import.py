"""A table-1-style CSV (row, col, c0_pF, sensitivity_pct_per_N) as a calibration document.

"Sensitivity" is ambiguous: the least-squares slope of ΔC/C0 over 0–10 N
with an intercept (table 1's reading) and the one through the origin differ
by ~2.5 % on this convex response, so the CSV imports only with its reading
named. Each taxel's gain is the one whose model curve has that slope in
that reading (TaxelResponse.from_table); C0 is the table's, measured on
the sensor the table is for.
"""
from __future__ import annotations

import csv
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from ..physics.taxel_response import SENSITIVITY_RANGE_PCT_PER_N, TaxelResponse, model_table
from .registry import SCHEMA

REQUIRED = ("row", "col", "c0_pF", "sensitivity_pct_per_N")


def _cells(path: Path) -> dict[tuple[int, int], tuple[float, float]]:
    with open(path, newline="") as stream:
        reader = csv.DictReader(stream)
        missing = [name for name in REQUIRED if name not in (reader.fieldnames or [])]
        if missing:
            raise ValueError(f"{path}: no column {', '.join(missing)} (needs {', '.join(REQUIRED)})")
        cells = {}
        for line, row in enumerate(reader, start=2):
            try:
                key = (int(row["row"]), int(row["col"]))
                c0, sensitivity = float(row["c0_pF"]), float(row["sensitivity_pct_per_N"])
            except (TypeError, ValueError):
                raise ValueError(f"{path}, line {line}: row and col must be integers, c0_pF and "
                                 "sensitivity_pct_per_N numbers") from None
            low, high = SENSITIVITY_RANGE_PCT_PER_N
            if not (c0 > 0 and low < sensitivity < high):
                raise ValueError(f"{path}, line {line}: C0 {c0} pF must be positive and the sensitivity "
                                 f"{sensitivity} %/N within ({low:g}, {high:g})")
            if key in cells:
                raise ValueError(f"{path}, line {line}: taxel row {key[0]}, col {key[1]} given twice")
            cells[key] = (c0, sensitivity)
    return cells


def table_document(path: str | Path, reading: str, sensor_key: str, mounting: str = "flat") -> dict:
    """The registry document of the CSV at ``path``; ValueError naming the file and line."""
    path = Path(path)
    cells = _cells(path)
    rows, cols = max((r for r, _ in cells), default=0), max((c for _, c in cells), default=0)
    absent = [(r, c) for r in range(1, rows + 1) for c in range(1, cols + 1) if (r, c) not in cells]
    if not cells or absent:
        raise ValueError(f"{path}: taxels missing from the table: {absent[:5] or 'all'}")
    c0 = np.array([cells[(r, c)][0] for r in range(1, rows + 1) for c in range(1, cols + 1)])
    sensitivity = np.array([cells[(r, c)][1] for r in range(1, rows + 1) for c in range(1, cols + 1)])
    table = model_table(mounting)
    response = TaxelResponse.from_table(table.force_N, table.relative_change, sensitivity / 100.0, table.dense, reading)
    response.check()
    n = rows * cols
    ls = sensitivity if reading == "intercept" else [None] * n
    origin = sensitivity if reading == "origin" else [None] * n
    return {"schema": SCHEMA, "kind": "grid", "rows": rows, "cols": cols, "mounting": mounting,
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            "note": f"imported from {path.name}: sensitivity read as the least-squares slope "
                    f"{'with an intercept' if reading == 'intercept' else 'through the origin'} over 0–10 N",
            "sensor": {"key": sensor_key}, "sources": [{"role": "table", "name": str(path)}],
            "taxels": {"gain": response.gain.tolist(), "gain_se": [None] * n, "c0_pF": c0.tolist(),
                       "sensitivity_pct_per_N": list(map(_number, ls)),
                       "sensitivity_origin_pct_per_N": list(map(_number, origin)),
                       "model": ["table"] * n, "source": ["table import"] * n, "curves": {}}}


def _number(value):
    return None if value is None else float(value)

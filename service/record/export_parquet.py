"""The replay export as a Parquet table (``tactile replay … --export OUT.parquet``).

One row per data frame, the JSON lines' keys as columns (grids and quads in
one table: a column a frame's kind does not have is null), plus the
calibration id and the 1-σ of each force:

    sensor u8 · seq u16 · t_us u32 · kind string
    taxels_N list<f64>    (grids; NaN = no reading, JSON's null)
    fxyz_N   list<f64>[3] (quads)
    flags list<string> · taxel_flags map<string, list<i32>> (grids)
    contact struct<total_N f64, cop_x_mm f64, cop_y_mm f64, area_mm2 f64, contacts i32> (grids;
            null for a frame without any force; the centre of pressure NaN without contact)
    calibration string · sigma_N list<f32> (null where the frame has none)

Forces are the reconstruction's float64, bit for bit. Columns are built per
batch with numpy and written in row groups of ROW_GROUP rows; pandas
(``read_parquet``) and polars (``read_parquet``) open the file as it is.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..reconstruct import ForceFrame
from .contact_batch import columns

ROW_GROUP = 65_536
CONTACT = pa.struct([("total_N", pa.float64()), ("cop_x_mm", pa.float64()), ("cop_y_mm", pa.float64()),
                     ("area_mm2", pa.float64()), ("contacts", pa.int32())])
SCHEMA = pa.schema([
    ("board", pa.string()), ("sensor", pa.uint8()), ("seq", pa.uint16()), ("t_us", pa.uint32()), ("kind", pa.string()),
    ("taxels_N", pa.list_(pa.float64())), ("fxyz_N", pa.list_(pa.float64(), 3)),
    ("flags", pa.list_(pa.string())), ("taxel_flags", pa.map_(pa.string(), pa.list_(pa.int32()))),
    ("contact", CONTACT), ("calibration", pa.string()), ("sigma_N", pa.list_(pa.float32())),
])


def _lists(arrays: list[np.ndarray | None], dtype, fixed: int | None = None) -> pa.Array:
    """A list column from per-row arrays (None: a null row)."""
    missing = np.array([a is None for a in arrays])
    mask = pa.array(missing) if missing.any() else None
    if fixed is not None:
        filler = np.full(fixed, np.nan, dtype)
        values = np.concatenate([filler if a is None else a for a in arrays]).astype(dtype, copy=False)
        return pa.FixedSizeListArray.from_arrays(pa.array(values), fixed, mask=mask)
    present = [a for a in arrays if a is not None]
    values = np.concatenate(present).astype(dtype, copy=False) if present else np.empty(0, dtype)
    offsets = np.concatenate([[0], np.cumsum([0 if a is None else a.size for a in arrays])]).astype(np.int32)
    return pa.ListArray.from_arrays(pa.array(offsets), pa.array(values), mask=mask)


def _contacts(frames: list[ForceFrame]) -> pa.Array:
    """The grids' contact summaries (contact_batch, per sensor), null for
    quads and for frames without any force."""
    n = len(frames)
    found = [np.ones(n, bool)] + [np.full(n, np.nan) for _ in range(4)] + [np.zeros(n, np.int32)]
    by_sensor: dict[object, list[int]] = {}
    for i, f in enumerate(frames):
        if f.sensor.kind == "grid":
            by_sensor.setdefault(f.sensor, []).append(i)
    for info, indices in by_sensor.items():
        for out, column in zip(found, columns(np.stack([frames[i].forces_N for i in indices]), info.rows, info.cols)):
            out[indices] = column
    fields = [pa.array(column, type=field.type) for column, field in zip(found[1:], CONTACT)]
    return pa.StructArray.from_arrays(fields, fields=list(CONTACT), mask=pa.array(found[0]))


def _taxel_flags(frames: list[ForceFrame]) -> pa.Array:
    def entries(f: ForceFrame):
        if f.sensor.kind != "grid":
            return None
        if f.taxel_flags is None or not np.count_nonzero(f.taxel_flags):
            return []
        return list(f.taxel_flag_lists().items())

    return pa.array([entries(f) for f in frames], SCHEMA.field("taxel_flags").type)


def table(frames: list[ForceFrame]) -> pa.Table:
    """The rows of a batch of frames."""
    grid = [f.sensor.kind == "grid" for f in frames]
    columns = [
        pa.array([f.sensor.board for f in frames], pa.string()),
        pa.array(np.array([f.sensor.id for f in frames], np.uint8)),
        pa.array(np.array([f.seq for f in frames], np.uint16)),
        pa.array(np.array([f.t_us for f in frames], np.uint32)),
        pa.array([f.sensor.kind for f in frames], pa.string()),
        _lists([f.forces_N if g else None for f, g in zip(frames, grid)], np.float64),
        _lists([None if g else f.forces_N for f, g in zip(frames, grid)], np.float64, fixed=3),
        pa.array([f.flags for f in frames], pa.list_(pa.string())),
        _taxel_flags(frames),
        _contacts(frames),
        pa.array([f.calibration for f in frames], pa.string()),
        _lists([f.sigma_N for f in frames], np.float32),
    ]
    return pa.Table.from_arrays(columns, schema=SCHEMA)


class Parquet:
    """``write(frames)`` per batch, ``close()`` at the end (which writes the
    file's footer: without it the file does not open)."""

    def __init__(self, path: str | Path) -> None:
        self._writer = pq.ParquetWriter(str(path), SCHEMA)
        self._pending: list[pa.Table] = []
        self._rows = 0

    def write(self, frames: list[ForceFrame]) -> None:
        if not frames:
            return
        self._pending.append(table(frames))
        self._rows += len(frames)
        if self._rows >= ROW_GROUP:
            self._flush()

    def _flush(self) -> None:
        if self._pending:
            self._writer.write_table(pa.concat_tables(self._pending), row_group_size=ROW_GROUP)
        self._pending, self._rows = [], 0

    def close(self) -> None:
        self._flush()
        self._writer.close()

"""The replay export as a Parquet table (``tactile replay … --export OUT.parquet``).

One row per data frame, the JSON lines' keys as columns (grids and quads in
one table: a column a frame's kind does not have is null), plus the
calibration id and the 1-σ of each force:

    sensor u8 · seq u16 · t_us u32 · kind string
    rows u16 · cols u16   (grids: the taxels' shape)
    taxels_N list<f64>    (grids, row-major; null = no reading, as in JSON)
    fxyz_N   list<f64>[3] (quads)
    flags list<string> · taxel_flags map<string, list<i32>> (grids)
    contact struct<total_N f64, cop_x_mm f64, cop_y_mm f64, area_mm2 f64, contacts i32> (grids;
            null for a frame without any force; the centre of pressure null without contact)
    calibration string · sigma_N list<f32> (one per force; an element null where its
            force has no σ: all of them in the tare window)

Forces are the reconstruction's float64, bit for bit; a value the JSON
line gives as null is a Parquet null, never NaN (a number to pandas'
sums, pyarrow's, polars' and DuckDB's null counts). Columns are built per
batch from numpy buffers (arrow_columns.py: no pandas import, no Python
object per value) and written in row groups of ROW_GROUP rows, text columns
dictionary-encoded (the floats' dictionaries cost half the write and saved
nothing); pandas (``read_parquet``) and polars (``read_parquet``) open the
file as it is.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from ..fanout.encoding import sigma_of
from ..reconstruct import ForceFrame
from .arrow_columns import fixed_lists, floats, lists, numbers, strings, structs
from .contact_batch import columns, sigmas

ROW_GROUP = 65_536
GATHER = 1024  # frames made into columns together; 4 096 a table faulted its temporaries in again (export.py)
CONTACT = pa.struct([("total_N", pa.float64()), ("cop_x_mm", pa.float64()), ("cop_y_mm", pa.float64()),
                     ("area_mm2", pa.float64()), ("contacts", pa.int32())])
TAXEL_FLAGS = pa.map_(pa.string(), pa.list_(pa.int32()))
SCHEMA = pa.schema([
    ("board", pa.string()), ("sensor", pa.uint8()), ("seq", pa.uint16()), ("t_us", pa.uint32()), ("kind", pa.string()),
    ("rows", pa.uint16()), ("cols", pa.uint16()), ("taxels_N", pa.list_(pa.float64())), ("fxyz_N", pa.list_(pa.float64(), 3)),
    ("flags", pa.list_(pa.string())), ("taxel_flags", TAXEL_FLAGS),
    ("contact", CONTACT), ("calibration", pa.string()), ("sigma_N", pa.list_(pa.float32())),
])
TEXT_COLUMNS = ["board", "kind", "flags", "taxel_flags", "calibration"]  # dictionary-encoded; floats are not worth it


def _grid_forces(frames: list[ForceFrame], grid: np.ndarray) -> tuple[pa.Array, pa.Array]:
    """(taxels_N, contact) columns: the grids' forces stacked once, their
    contact summaries per sensor (contact_batch)."""
    n = len(frames)
    rows = np.flatnonzero(grid).tolist()
    forces = [frames[i].forces_N for i in rows]
    sizes = np.zeros(n, np.int64)
    sizes[rows] = [a.size for a in forces]
    flat = np.concatenate(forces) if forces else np.empty(0)
    found = [np.ones(n, bool)] + [np.full(n, np.nan) for _ in range(4)] + [np.zeros(n, np.int32)]
    by_sensor: dict[object, list[int]] = {}
    for k, i in enumerate(rows):
        by_sensor.setdefault(frames[i].sensor, []).append(k)
    starts = np.concatenate([[0], np.cumsum(sizes[rows])])
    for info, ks in by_sensor.items():
        size = info.rows * info.cols
        if len(by_sensor) == 1 and len(flat) == len(rows) * size:
            block = flat.reshape(-1, size)
        else:
            block = np.stack([flat[starts[k] : starts[k] + size] for k in ks])
        targets = [rows[k] for k in ks]
        sigma = sigmas([frames[i] for i in targets], block.shape)
        for out, column in zip(found, columns(block, info.rows, info.cols, sigma)):
            out[targets] = column
    contact = structs([floats(column) if field.type == pa.float64() else numbers(column, field.type)
                       for column, field in zip(found[1:], CONTACT)], CONTACT, ~found[0])
    return lists(floats(flat), sizes, grid), contact


def _quad_forces(frames: list[ForceFrame], grid: np.ndarray) -> pa.Array:
    values = np.full((len(frames), 3), np.nan)
    rows = np.flatnonzero(~grid).tolist()
    if rows:
        values[rows] = np.stack([frames[i].forces_N for i in rows])
    return fixed_lists(values, pa.list_(pa.float64(), 3), ~grid)


def _flags(frames: list[ForceFrame]) -> pa.Array:
    sizes = np.fromiter((len(f.flags) for f in frames), np.int64, len(frames))
    return lists(strings([name for f in frames for name in f.flags]), sizes)


def _taxel_flags(frames: list[ForceFrame], grid: np.ndarray) -> pa.Array:
    """{flag: [taxels]} of each grid frame (empty when none is set), null for quads."""
    entries = [f.taxel_flag_lists() if g else {} for f, g in zip(frames, grid.tolist())]
    hits = [taxels for entry in entries for taxels in entry.values()]
    flat = np.fromiter((t for taxels in hits for t in taxels), np.int32)
    pairs = structs([strings([name for entry in entries for name in entry]),
                     lists(numbers(flat, pa.int32()), np.fromiter(map(len, hits), np.int64, len(hits)))],
                    pa.struct([TAXEL_FLAGS.key_field, TAXEL_FLAGS.item_field]))
    return lists(pairs, np.fromiter(map(len, entries), np.int64, len(entries)), grid, TAXEL_FLAGS)


def _sigma(frames: list[ForceFrame]) -> pa.Array:
    """One σ per force, null where there is none (the tare window: all null), as the JSON line."""
    sigma = [sigma_of(f) for f in frames]
    sizes = np.fromiter((s.size for s in sigma), np.int64, len(sigma))
    values = np.concatenate(sigma).astype(np.float32, copy=False) if sigma else np.empty(0, np.float32)
    return lists(floats(values, pa.float32()), sizes)


def table(frames: list[ForceFrame]) -> pa.Table:
    """The rows of a batch of frames."""
    grid = np.fromiter((f.sensor.kind == "grid" for f in frames), bool, len(frames))
    taxels, contact = _grid_forces(frames, grid)
    columns_ = [
        strings([f.sensor.board for f in frames]),
        numbers(np.fromiter((f.sensor.id for f in frames), np.uint8, len(frames)), pa.uint8()),
        numbers(np.fromiter((f.seq for f in frames), np.uint16, len(frames)), pa.uint16()),
        numbers(np.fromiter((f.t_us for f in frames), np.uint32, len(frames)), pa.uint32()),
        strings([f.sensor.kind for f in frames]),
        numbers(np.fromiter((f.sensor.rows for f in frames), np.uint16, len(frames)), pa.uint16(), grid),
        numbers(np.fromiter((f.sensor.cols for f in frames), np.uint16, len(frames)), pa.uint16(), grid),
        taxels,
        _quad_forces(frames, grid),
        _flags(frames),
        _taxel_flags(frames, grid),
        contact,
        strings([f.calibration for f in frames]),
        _sigma(frames),
    ]
    return pa.Table.from_arrays(columns_, schema=SCHEMA)


class Parquet:
    """``write(frames)`` per batch, ``close()`` at the end (which writes the
    file's footer: without it the file does not open)."""

    def __init__(self, path: str | Path) -> None:
        self._writer = pq.ParquetWriter(str(path), SCHEMA, use_dictionary=TEXT_COLUMNS)
        self._pending: list[pa.Table] = []
        self._rows = 0
        self._waiting: list[ForceFrame] = []  # frames not made into columns yet: a recorded read holds a few

    def write(self, frames: list[ForceFrame]) -> None:
        self._waiting += frames
        if len(self._waiting) >= GATHER:
            self._tabled()
        if self._rows >= ROW_GROUP:
            self._flush()

    def _tabled(self) -> None:
        """The waiting frames as batches of columns of GATHER frames or fewer
        (an MCAP replay writes each recorded read: per read, the columns cost 0.4 ms)."""
        waiting, self._waiting = self._waiting, []
        for start in range(0, len(waiting), GATHER):
            self._pending.append(table(waiting[start:start + GATHER]))
        self._rows += len(waiting)

    def _flush(self) -> None:
        self._tabled()
        if self._pending:
            self._writer.write_table(pa.concat_tables(self._pending), row_group_size=ROW_GROUP)
        self._pending, self._rows = [], 0

    def close(self) -> None:
        self._flush()
        self._writer.close()

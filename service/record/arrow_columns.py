"""Arrow columns straight from numpy buffers, for the Parquet export.

``pa.array`` on anything — a Python list or a numpy array — first asks
whether pandas is installed and imports it (0.26 s of a replay's CPU, more
than writing the file); building each column from its buffers
(``Array.from_buffers``) needs neither pandas nor a Python object per value.
Every function takes ``present`` (N,) bool, None for all present; a null
row's values are whatever filler the caller put there.
"""
from __future__ import annotations

import numpy as np
import pyarrow as pa


def _validity(present: np.ndarray | None) -> pa.Buffer | None:
    return None if present is None or present.all() else pa.py_buffer(np.packbits(present, bitorder="little"))


def numbers(values: np.ndarray, type_: pa.DataType, present: np.ndarray | None = None) -> pa.Array:
    """A primitive column: ``values`` (N,) already of ``type_``'s numpy dtype."""
    values = np.ascontiguousarray(values, dtype=type_.to_pandas_dtype())
    return pa.Array.from_buffers(type_, len(values), [_validity(present), pa.py_buffer(values)])


def offsets_of(sizes: np.ndarray) -> np.ndarray:
    """(N + 1,) int32 offsets of rows of ``sizes`` values."""
    out = np.zeros(len(sizes) + 1, np.int32)
    np.cumsum(sizes, out=out[1:])
    return out


def strings(texts: list[str], present: np.ndarray | None = None) -> pa.Array:
    """A utf-8 string column."""
    encoded = [text.encode() for text in texts]
    offsets = offsets_of(np.fromiter(map(len, encoded), np.int64, len(encoded)))
    return pa.Array.from_buffers(pa.string(), len(texts), [_validity(present), pa.py_buffer(offsets),
                                                            pa.py_buffer(b"".join(encoded))])


def lists(values: pa.Array, sizes: np.ndarray, present: np.ndarray | None = None,
          type_: pa.DataType | None = None) -> pa.Array:
    """A list column: row i holds the next ``sizes[i]`` of ``values`` (0 for a null row)."""
    type_ = type_ or pa.list_(values.type)
    return pa.Array.from_buffers(type_, len(sizes), [_validity(present), pa.py_buffer(offsets_of(sizes))],
                                 children=[values])


def floats(values: np.ndarray, type_: pa.DataType = pa.float64()) -> pa.Array:
    """A float column whose NaNs are nulls (what JSON's null is: no value, not a number)."""
    values = np.ascontiguousarray(values, dtype=type_.to_pandas_dtype())
    return numbers(values, type_, ~np.isnan(values))


def fixed_lists(values: np.ndarray, type_: pa.DataType, present: np.ndarray | None = None) -> pa.Array:
    """A fixed-size list column from (N, size) float ``values``, NaN a null."""
    flat = floats(values.ravel(), type_.value_type)
    return pa.Array.from_buffers(type_, len(values), [_validity(present)], children=[flat])


def structs(children: list[pa.Array], type_: pa.StructType, present: np.ndarray | None = None) -> pa.Array:
    """A struct column of ``children``, one per field of ``type_``."""
    return pa.Array.from_buffers(type_, len(children[0]), [_validity(present)], children=children)

"""A history answer's JSON, column by column from the ring's arrays.

Equal byte for byte to ``orjson.dumps([to_json_dict(frame, fields) …])``
without its brackets, but each number column (stamps, forces, σ, raw,
contact summaries) is formatted for all the frames in one orjson call on
an array and the objects are assembled from a template, so the Python work
per frame is a few list items instead of a ForceFrame, its dicts and a
contact summary: a 5 s window of an 8×8 grid costs the event loop ~10× less.

The template's keys and their order are those ``to_json_dict`` gives the
first frame; a key this module does not know, or a column whose first value
differs from ``to_json_dict``'s, sends the frames through ``to_json_dict``
one by one: a new key is answered as that function defines it, only slower.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import orjson

from ..history import Columns, History
from ..record.contact_batch import columns as contact_columns
from .encoding import to_json_dict

OPTIONS = orjson.OPT_SERIALIZE_NUMPY
Column = Callable[[Columns], list[bytes]]


def _dumps(value) -> bytes:
    return orjson.dumps(value, option=OPTIONS)


def _numbers(values: np.ndarray) -> list[bytes]:
    """Each number's JSON (NaN is null, as orjson writes a float's NaN)."""
    return _dumps(values)[1:-1].split(b",")


def _rows(values: np.ndarray) -> list[bytes]:
    """Each row's JSON list, from one orjson call on the (k, n) array."""
    return [b"[" + row + b"]" for row in _dumps(values)[2:-2].split(b"],[")]


def _shared(values: list) -> list[bytes]:
    """JSON of values that repeat (flag sets, calibration ids): once per distinct value."""
    known: dict = {}
    return [known.get(v) or known.setdefault(v, _dumps(list(v) if isinstance(v, tuple) else v)) for v in values]


def _objects(keys: tuple[str, ...], columns: list[list[bytes]]) -> list[bytes]:
    template = b"{" + b",".join(_dumps(key).replace(b"%", b"%%") + b":%b" for key in keys) + b"}"
    return [template % values for values in zip(*columns)]


def _contact(c: Columns) -> list[bytes]:
    none, *numbers = contact_columns(c.forces, c.info.rows, c.info.cols)
    names = ("total_N", "cop_x_mm", "cop_y_mm", "area_mm2", "contacts")
    summaries = _objects(names, [_numbers(column) for column in numbers])
    return [b"null" if empty else text for empty, text in zip(none.tolist(), summaries)]


def _taxel_flags(c: Columns) -> list[bytes]:
    """``{}`` for a frame without taxel flags (most), the frame's own lists
    (once per distinct pattern) otherwise."""
    known: dict[bytes, bytes] = {}
    out = []
    for j, hit in enumerate(c.taxel_flags.any(axis=1).tolist()):
        if not hit:
            out.append(b"{}")
            continue
        key = c.taxel_flags[j].tobytes()
        if key not in known:
            known[key] = _dumps(c.frame(j).taxel_flag_lists())
        out.append(known[key])
    return out


def _wrench(values: np.ndarray) -> list[bytes]:
    xyz = iter(_numbers(values.ravel()))
    return [b'{"force":{"x":%b,"y":%b,"z":%b}}' % axes for axes in zip(xyz, xyz, xyz)]


HEADER: dict[str, Column | None] = {  # None: the sensor's own, the same in every frame
    "sensor_id": None,
    "sensor_name": None,
    "kind": None,
    "seq": lambda c: _numbers(c.seq),
    "board_time_us": lambda c: _numbers(c.t_us),
    "stamp": lambda c: _numbers(c.t_host),
    "scan_stamp": lambda c: _numbers(c.t_scan),
    "calibration": lambda c: _shared(c.calibrations),
}
KEYS: dict[str, Column | dict | None] = {  # a dict: a nested object's keys
    "header": HEADER,
    "rows": None,
    "cols": None,
    "force_N": lambda c: _rows(c.forces),
    "sigma_N": lambda c: _rows(c.sigma),
    "contact": _contact,
    "wrench": lambda c: _wrench(c.forces),
    "wrench_sigma": lambda c: _wrench(c.sigma),
    "raw": lambda c: [b'{"capacitance_pF":%b}' % row for row in _rows(c.raw)],
    "flags": lambda c: _shared(c.flags),
    "taxel_flags": _taxel_flags,
}


def _fill(known: dict, sample: dict, c: Columns) -> list[bytes] | None:
    """Each frame's object with the sample's keys, or None when a key is
    unknown or its first value differs from the sample's."""
    columns = []
    for key, value in sample.items():
        if key not in known:
            return None
        encode = known[key]
        if isinstance(encode, dict):
            column = _fill(encode, value, c)
        else:
            column = [_dumps(value)] * len(c) if encode is None else encode(c)
        if column is None or column[0] != _dumps(value):
            return None
        columns.append(column)
    return _objects(tuple(sample), columns)


def frame_texts(c: Columns, fields: frozenset[str]) -> list[bytes]:
    """Each frame's JSON object."""
    if not len(c):
        return []
    objects = _fill(KEYS, to_json_dict(c.frame(0), fields), c)
    return objects if objects is not None else [_dumps(to_json_dict(c.frame(j), fields)) for j in range(len(c))]


class RingTexts:
    """The JSON of one ring's frames for one set of fields, kept by slot
    across reads: clients polling the last seconds ask, read after read,
    for nearly the same frames, so only those appended since the last read
    need encoding. At most as large as the ring's frames in JSON (5000 frames
    of an 8×8 grid: ~6 MB; with raw and σ ~16 MB)."""

    def __init__(self, history: History, fields: frozenset[str]) -> None:
        self.history, self.fields = history, fields
        self._forget()

    def _forget(self) -> None:
        self._capacity = self.history.capacity
        self._numbers = np.full(self._capacity, -1, dtype=np.int64)
        self._texts = np.full(self._capacity, b"", dtype=object)  # an array: a window's texts in one indexing
        self.bytes = 0

    def kept(self, slots: np.ndarray) -> tuple[list[bytes | None], np.ndarray]:
        """The text of each slot's frame (None where it was not encoded yet),
        and the positions in ``slots`` of those not encoded."""
        if self.history.capacity != self._capacity:  # shrunk: slots and numbers mean other frames
            self._forget()
        hits = self._numbers[slots] == self.history.numbers(slots)
        texts = self._texts[slots]
        texts[~hits] = None
        return texts.tolist(), np.flatnonzero(~hits)

    def encode(self, slots: np.ndarray) -> list[bytes]:
        """Encode the frames now at ``slots``, and keep them."""
        if self.history.capacity != self._capacity:
            self._forget()
        numbers = self.history.numbers(slots)
        texts = frame_texts(self.history.columns(slots), self.fields)
        self._numbers[slots] = numbers
        for slot, text in zip(slots.tolist(), texts):
            self.bytes += len(text) - len(self._texts[slot])
            self._texts[slot] = text
        return texts


class RecentRings:
    """``RingTexts`` of the rings (and fields) read last, the oldest
    forgotten while all of them hold more than ``max_bytes`` of text (the
    one asked for is always kept)."""

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._rings: dict[tuple[History, frozenset[str]], RingTexts] = {}  # oldest first

    def get(self, history: History, fields: frozenset[str]) -> RingTexts:
        key = (history, fields)
        texts = self._rings.pop(key, None) or RingTexts(history, fields)
        while self._rings and sum(kept.bytes for kept in self._rings.values()) + texts.bytes > self.max_bytes:
            del self._rings[next(iter(self._rings))]
        self._rings[key] = texts
        return texts

"""A history answer's JSON, frame by frame, built column by column from the ring's arrays.

Each frame's text is byte for byte ``orjson.dumps(to_json_dict(frame, fields))``,
but each number column (stamps, forces, σ, raw) is formatted for all the
frames of a step in one orjson call on an array, and the objects are filled
into a template with the sensor's constants written in, so the Python work
per frame is a few list items and its contact summary instead of a
ForceFrame's dicts.

The template's keys and their order are those ``to_json_dict`` gives the
first frame; a key this module does not know, or a column whose first value
differs from ``to_json_dict``'s, sends the frames through ``to_json_dict``
one by one: a new key is answered as that function defines it, only slower.
Encoded frames are kept per ring slot (``RingTexts``), so that the next read
of an overlapping window encodes only the frames that arrived since.
"""
from __future__ import annotations

from typing import Callable

import numpy as np
import orjson

from ..history import Columns, History
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


def _contact(c: Columns) -> list[bytes]:
    """Frame by frame: in the few frames of a step, cheaper than contact_batch's grouping."""
    return [_dumps(c.frame(j).contact) for j in range(len(c))]


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


Layout = tuple[bytes, list[Column]]  # a frame's template (one %b per column) and its columns


def layout(c: Columns, fields: frozenset[str]) -> Layout | None:
    """How ``to_json_dict`` lays out these frames (those of one sensor, for
    ``fields``), checked on the first frame; None when it cannot be built
    from columns."""
    columns: list[Column] = []
    template = _template(KEYS, to_json_dict(c.frame(0), fields), c, columns)
    return None if template is None else (template, columns)


def _template(known: dict, sample: dict, c: Columns, columns: list[Column]) -> bytes | None:
    """An object with the sample's keys: the sensor's constants written in,
    a %b for each column (appended to ``columns``); None when a key is
    unknown or a column's first value differs from the sample's."""
    parts = []
    for key, value in sample.items():
        if key not in known:
            return None
        encode = known[key]
        if isinstance(encode, dict):
            text = _template(encode, value, c, columns)
            if text is None:
                return None
        elif encode is None:
            text = _dumps(value).replace(b"%", b"%%")
        elif encode(c)[0] == _dumps(value):
            columns.append(encode)
            text = b"%b"
        else:
            return None
        parts.append(_dumps(key).replace(b"%", b"%%") + b":" + text)
    return b"{" + b",".join(parts) + b"}"


def frame_texts(c: Columns, fields: frozenset[str], plan: Layout | None = None) -> list[bytes]:
    """Each frame's JSON object, by ``plan`` (checked on these frames if not given)."""
    if not len(c):
        return []
    plan = plan or layout(c, fields)
    if plan is None:
        return [_dumps(to_json_dict(c.frame(j), fields)) for j in range(len(c))]
    template, columns = plan
    return [template % values for values in zip(*(encode(c) for encode in columns))]


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
        self._plan: Layout | None = None  # checked once, on the first frames encoded
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
        c = self.history.columns(slots)
        if self._plan is None:
            self._plan = layout(c, self.fields)
        texts = frame_texts(c, self.fields, self._plan)
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

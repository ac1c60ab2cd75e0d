"""History answers' frames in JSON, kept across reads.

Clients polling the last seconds ask, read after read, for nearly the same
frames (two polls of a 5 s window 0.25 s apart share 95 % of them), so each
frame's JSON is kept by ring slot and only the frames that arrived since
the last read are encoded.

Each frame is encoded as every JSON frame is, ``to_json_dict`` and orjson:
building a whole window's JSON column by column from the ring's arrays was
tried and is ~2× cheaper in 5000-frame calls, but no cheaper in the few
frames a turn of the event loop may take (~0.2 ms), which is what a read
encodes now.
"""
from __future__ import annotations

import numpy as np
import orjson

from ..history import History
from .encoding import to_json_dict


class RingTexts:
    """The JSON of one ring's frames for one set of fields, by slot. At most
    as large as the ring's frames in JSON (5000 frames of an 8×8 grid: ~6 MB;
    with raw and σ ~16 MB)."""

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
        texts = [orjson.dumps(to_json_dict(frame, self.fields), option=orjson.OPT_SERIALIZE_NUMPY)
                 for frame in self.history.frames_at(slots)]
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

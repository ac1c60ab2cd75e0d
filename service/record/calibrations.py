"""The calibrations a recording was made with, read back for its replay."""
from __future__ import annotations

from pathlib import Path

import orjson

from .mcap_reader import iter_messages


def recorded_calibrations(path: str | Path) -> dict[int, dict]:
    """{sensor id: document} of the first calibration each sensor used in
    the recording (the recorder writes one before the first frame that uses
    it); built-in ones (no document) are left out, as a replay without a
    document uses the built-in calibration anyway."""
    found: dict[int, dict] = {}
    for _, message in iter_messages(path, {"/calibrations"}):
        doc = orjson.loads(message.data)
        if doc.get("document") is not None:
            found.setdefault(int(doc["sensor"]), doc["document"])
    return found

"""The calibrations a recording was made with, read back for its replay."""
from __future__ import annotations

import logging
from pathlib import Path

import orjson

from .mcap_reader import iter_messages

log = logging.getLogger(__name__)


def recorded_calibrations(path: str | Path) -> tuple[dict, dict]:
    """({sensor: document}, {sensor: (calibration id, load cycles)}) of
    the first calibration each sensor used in the recording (the recorder
    writes one before the first frame that uses it) and the load-cycle
    counts the sensor started with, each sensor by its address (board/id),
    or by its id in a recording made before boards were named; built-in calibrations (no document) are
    left out of the first, as a replay without a document uses the built-in
    one anyway."""
    found: dict[int, dict] = {}
    cycles: dict[int, tuple[str, list[int]]] = {}
    used: dict[int | str, list[str]] = {}
    for _, message in iter_messages(path, {"/calibrations"}):
        doc = orjson.loads(message.data)
        sensor = f"{doc['board']}/{int(doc['sensor'])}" if doc.get("board") else int(doc["sensor"])
        if doc["id"]:  # frames made while the sensor had no state name none
            used.setdefault(sensor, []).append(doc["id"])
        # The first calibration's document only: a sensor that began on a built-in one (no document) and
        # had one uploaded later replays on the built-in throughout, as the warning below says.
        if doc.get("document") is not None and used.get(sensor, [None])[0] == doc["id"]:
            found.setdefault(sensor, doc["document"])
        if doc.get("cycles_at_start") is not None:
            cycles.setdefault(sensor, (doc["id"], doc["cycles_at_start"]))
    for sensor, ids in used.items():
        if len(set(ids)) > 1:  # a replay would give the first one's forces throughout: say so
            log.warning("%s: sensor %s changed calibration while recording (%s); the replay reconstructs with the "
                        "first throughout, so its forces after the change differ from the recorded ones",
                        path, sensor, " → ".join(ids))
    return found, cycles

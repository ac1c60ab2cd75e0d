"""The calibrations a recording was made with, read back for its replay."""
from __future__ import annotations

import logging
import re
from pathlib import Path

import orjson

from ..physics.paper_data import BUILTIN_GRID_ID, BUILTIN_QUAD_ID, TABLE1_COLS, TABLE1_ROWS
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
        differ = [cid for cid in ids[1:] if cid != ids[0] and not _builtin_in_replay(cid, found.get(sensor))]
        if differ:  # the replay does not make these changes: say so
            log.warning("%s: sensor %s changed calibration while recording (%s); the replay reconstructs with the "
                        "first throughout (a built-in one where the first does not fit the sensor's shape), so its "
                        "forces with %s differ from the recorded ones", path, sensor, " → ".join(ids), ", ".join(differ))
    return found, cycles


def _builtin_in_replay(calibration_id: str, first: dict | None) -> bool:
    """Whether the replay reconstructs with the built-in ``calibration_id``
    too: where the sensor's first calibration has no document (``first``)
    or one that does not fit the shape this built-in is for (a board
    restarted with another, a 4×4 grid now 16×16), the replay's sensor
    takes the built-in calibration of its shape, as live did."""
    if calibration_id == BUILTIN_QUAD_ID:
        shape = ("quad",)
    elif calibration_id == BUILTIN_GRID_ID:
        shape = ("grid", TABLE1_ROWS, TABLE1_COLS)
    else:
        named = re.fullmatch(r"builtin-mean-(\d+)x(\d+)", calibration_id)  # sensor_calibration.builtin's ids
        if named is None:
            return False  # not a built-in: the replay never has it
        shape = ("grid", int(named[1]), int(named[2]))
    if first is None:
        return True
    return (first.get("kind"), first.get("rows"), first.get("cols"))[: len(shape)] != shape

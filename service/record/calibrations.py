"""The calibrations a recording was made with, read back for its replay."""
from __future__ import annotations

import logging
import re
from pathlib import Path

import orjson

from ..physics.paper_data import BUILTIN_GRID_ID, BUILTIN_QUAD_ID, TABLE1_COLS, TABLE1_ROWS
from .mcap_reader import iter_messages, read_calibrations_set, read_changes
from .resume import resumed_calibrations

log = logging.getLogger(__name__)


def recorded_calibrations(path: str | Path) -> tuple[dict, dict]:
    """({sensor: [entry, …]}, {sensor: {(key, calibration id): load cycles}}):
    each calibration a sensor used in the recording, in the order it first
    did (the recorder writes one before the first frame that uses it), as
    {"id", "key": the sensor identity it was chosen under (None in a
    recording made before it was recorded), "document": None for a built-in
    one}, and the load-cycle counts the sensor of that identity had under
    each when it began using it (another sensor plugged in at the address
    has its own, reconstruct/identity.py); each sensor by its address (board/id), or by its id in a
    recording made before boards were named. The replay reconstructs with
    the first entry of the sensor's identity at the time (calibration/book.py):
    a board whose INFO came after its first frames names its sensors' own
    calibration then, as live; a calibration set for the same identity
    while recording (an upload) is set again where it was (replay.py), in a
    recording made before those were recorded it is not, and a warning says so.
    A recording whose first reads were lost (a damaged chunk, with them the
    first entries) begins each sensor on the calibration it ran on where its
    replay begins (record/resume.py; a later upload is not that)."""
    found: dict[int | str, list[dict]] = {}
    cycles: dict[int | str, dict[tuple, list[int]]] = {}
    for _, message in iter_messages(path, {"/calibrations"}):
        doc = orjson.loads(message.data)
        sensor = _address(doc)
        if not doc["id"]:  # frames made while the sensor had no state name none
            continue
        entries = found.setdefault(sensor, [])
        if not any((e["id"], e["key"]) == (doc["id"], doc.get("key")) for e in entries):
            entries.append({"id": doc["id"], "key": doc.get("key"), "document": doc.get("document")})
        if doc.get("cycles_at_start") is not None:
            cycles.setdefault(sensor, {}).setdefault((doc.get("key"), doc["id"]), doc["cycles_at_start"])
    _begin_where_resumed(path, found)
    replayed = read_calibrations_set(path)  # set again by the replay where they were set (replay.py)
    for sensor, entries in found.items():
        differ = [e["id"] for e in _not_replayed(entries) if (sensor, e["id"]) not in replayed]
        if differ:  # the replay does not make these changes: say so
            log.warning("%s: sensor %s changed calibration while recording (%s); the replay reconstructs with the "
                        "first throughout (a built-in one where the first does not fit the sensor's shape), so its "
                        "forces with %s differ from the recorded ones", path, sensor,
                        " → ".join(e["id"] for e in entries), ", ".join(differ))
    return found, cycles


def _address(doc: dict) -> int | str:
    """A recorded sensor's address: board/id, or its id in a recording made before boards were named."""
    return f"{doc['board']}/{int(doc['sensor'])}" if doc.get("board") else int(doc["sensor"])


def _begin_where_resumed(path: str | Path, found: dict[int | str, list[dict]]) -> None:
    """Put first, in ``found``, each sensor's calibration in force where the
    replay of a board whose first reads were lost begins: the entry that
    named it may be lost with them, and the first left can be one set only
    later. A document found nowhere else in the file (not a built-in one)
    cannot be reconstructed on: the entry has none, so the sensor takes the
    built-in calibration and its frames name that, and a warning says so."""
    documents = {e["id"]: e["document"] for entries in found.values() for e in entries if e["document"]}
    documents |= {change["id"]: change for made in read_changes(path).values() for _, _, change in made
                  if isinstance(change, dict)}
    for after_reads, in_force in resumed_calibrations(path):
        for ran in in_force:
            sensor, calibration_id = _address(ran), ran["id"]
            document = documents.get(calibration_id)
            if document is None and not calibration_id.startswith("builtin"):
                log.warning("%s: sensor %s ran on calibration %s at read %d, where its replay begins after the lost "
                            "start, and that calibration's document was lost with it: replayed on the built-in "
                            "calibration, which its frames name", path, sensor, calibration_id, after_reads)
            begins = {"id": calibration_id, "key": ran["key"], "document": document}
            found[sensor] = [begins] + [e for e in found.get(sensor, []) if (e["id"], e["key"]) != (calibration_id,
                                                                                                   ran["key"])]


def first_for_identity(entries: list[dict], key: str) -> dict:
    """The entry a replay reconstructs a sensor of identity ``key`` with:
    the first chosen under that identity, else (a recording made before
    identities were recorded, or a sensor now known otherwise) the first."""
    return next((e for e in entries if e["key"] == key), entries[0])


def _not_replayed(entries: list[dict]) -> list[dict]:
    """Later entries the replay does not take: chosen under an identity an
    earlier entry has (a calibration uploaded while recording), unless a
    built-in one the replay's sensor takes anyway."""
    missed = []
    for k, entry in enumerate(entries[1:], 1):
        first = next(e for e in entries[:k + 1] if e["key"] == entry["key"])
        if first is not entry and not _builtin_in_replay(entry["id"], first["document"]):
            missed.append(entry)
    return missed


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

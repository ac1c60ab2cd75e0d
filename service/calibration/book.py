"""Which calibration each sensor is reconstructed with, for serve, record and replay.

In this order, the first that has one for the sensor:

1. ``recorded``: the calibrations a recording was made with, a built-in one
   included (a replay of an .mcap gives its recorded forces bit for bit,
   whatever the registry holds now), by sensor address: the first chosen
   under the sensor's identity at the time (a board whose INFO came after its
   first frames is named then, and its sensors' own calibrations with it);
2. ``pinned``: ``--calibration ID|FILE`` documents, matched to the sensor
   whose identity (registry.sensor_identity) they were made for, else to the
   sensor of the same id and shape (a calibration made through one board,
   used through another); a built-in id (``builtin-table1``,
   ``builtin-mean-RxC`` for grids, ``builtin-fits34-35`` for quads) pins the
   built-in calibration for every sensor of its kind not pinned otherwise
   (to compare against it);
3. the registry's active calibration of the sensor's identity — followed
   while a live service runs: ``registry_active`` tells which is active now,
   board.py swaps it in;
4. none: the reconstruction's built-in one (table 1, fits 34/35), which
   every frame then names.

Load-cycle counts (reconstruct/fatigue.py) come the same way: a
recording's counts at its start for the sensor's identity (never the
registry's, in a replay), else the
registry's for the sensor and the calibration in use; a live service saves
them back (``save_cycles``). Each sensor's last zero likewise
(``load_zero``, ``save_zeros``: reconstruct/stored_zero.py), the registry's
alone: never in a replay.

A registry that cannot be read is reported (``problems``) and skipped: a
sensor's data never stops for its calibration. Lookups open the registry
for the moment of the lookup (sensors are resolved when first seen, and
again when another takes an address's place: reconstruct/identity.py, on
whatever thread reconstructs them).
"""
from __future__ import annotations

import json
import logging
import re
from pathlib import Path

from ..physics.paper_data import BUILTIN_GRID_ID, BUILTIN_QUAD_ID
from ..readings import SensorInfo
from ..reconstruct.sensor_calibration import SensorCalibration, from_document
from ..record.calibrations import first_for_identity, recorded_calibrations
from .registry import Registry, UnknownCalibration, sensor_identity

log = logging.getLogger(__name__)


def load_pinned(values: list[str], registry_path: str | Path | None) -> list[dict]:
    """``--calibration`` values: a JSON file (``tactile calibrations export``)
    when one exists at that path, else a registry id (a unique prefix will
    do); ValueError naming the value."""
    documents = []
    for value in values:
        path = Path(value)
        if value.startswith("builtin-") and not path.is_file():
            if value not in (BUILTIN_GRID_ID, BUILTIN_QUAD_ID) and not re.fullmatch(r"builtin-mean-\d+x\d+", value):
                raise ValueError(f"--calibration {value}: no such built-in calibration (known: {BUILTIN_GRID_ID}, "
                                 f"builtin-mean-RxC for other grids, {BUILTIN_QUAD_ID})")
            documents.append({"id": value, "kind": "quad" if value == BUILTIN_QUAD_ID else "grid"})
            continue
        if path.is_file():
            try:
                document = json.loads(path.read_text())
            except (OSError, json.JSONDecodeError) as exc:
                raise ValueError(f"--calibration {value}: not a calibration JSON file ({exc})") from None
            if not isinstance(document, dict) or "id" not in document:
                raise ValueError(f"--calibration {value}: not a calibration document (no id)")
        else:
            try:
                with Registry(registry_path) as registry:
                    document = registry.get(value)
            except UnknownCalibration as exc:
                raise ValueError(f"--calibration {value}: neither a file nor a stored calibration ({exc})") from None
        documents.append(document)
    return documents


def book_from_options(registry: str | None, calibration: list[str] | None, mounting: str = "flat",
                      recording: str | Path | None = None) -> CalibrationBook:
    """The book of ``--registry``, ``--calibration`` (repeatable) and, for a
    replay of an .mcap ``recording``, the calibrations it was made with."""
    recorded, cycles = {}, {}
    replaying = recording is not None and Path(recording).suffix == ".mcap"
    if replaying:
        recorded, cycles = recorded_calibrations(recording)
    return CalibrationBook(registry, load_pinned(calibration or [], registry), recorded, mounting=mounting,
                           recorded_cycles=cycles, replaying=replaying)


class CalibrationBook:
    """``for_sensor(board, info)``: the sensor's SensorCalibration, or None
    for the built-in one (module docstring for the order)."""

    def __init__(self, registry_path: str | Path | None = None, pinned: list[dict] | None = None,
                 recorded: dict[int | str, list[dict]] | None = None, use_registry: bool = True,
                 mounting: str = "flat", recorded_cycles: dict[int | str, dict[tuple, list[int]]] | None = None,
                 replaying: bool = False) -> None:
        """``recorded``, ``recorded_cycles``: a recording's (record/calibrations.py),
        ``replaying`` one: its sensors' load cycles are its own, never the registry's."""
        self.registry_path = registry_path
        self.pinned = list(pinned or [])
        self.recorded = dict(recorded or {})
        self.recorded_cycles = dict(recorded_cycles or {})
        self.replaying = replaying or bool(self.recorded)
        self.use_registry = use_registry
        self.mounting = mounting
        self.problems: list[str] = []
        self._activated: dict[tuple[str, str], str | None] = {}  # (sensor key, calibration id) → activation time

    def with_pinned(self, values: list[str]) -> CalibrationBook:
        """This book with ``values`` (ids or files, as ``--calibration``)
        pinned first: one board's own choice (robot.toml); ValueError naming
        a value that is neither."""
        book = CalibrationBook(self.registry_path, load_pinned(values, self.registry_path) + self.pinned,
                               self.recorded, self.use_registry, self.mounting, self.recorded_cycles, self.replaying)
        book.problems = self.problems  # one list of problems for /health
        return book

    def for_sensor(self, board: dict, info: SensorInfo, mounting: str | None = None) -> SensorCalibration | None:
        """ValueError (the reconstruction keeps the built-in one and says why)
        when the calibration found does not fit the sensor. ``mounting``: the
        board's (default: the book's)."""
        key = sensor_identity(board, info)["key"]
        entries = self._recorded(self.recorded, info)
        if entries:  # as recorded, a built-in one included: not what the registry holds since
            document = first_for_identity(entries, key)["document"]
        else:
            document = self._pinned_for(key, info)
            if document is None and self.use_registry:
                document = self._active(key)
        if document is None or str(document.get("id", "")).startswith("builtin"):
            return None
        return from_document(document, info, mounting or self.mounting)

    @staticmethod
    def _recorded(found: dict, info: SensorInfo):
        """A recording's entry for the sensor: by its address (board/id), or
        by its id in a recording made before boards were named."""
        return found.get(info.address) or found.get(info.id)

    def _pinned_for(self, key: str, info: SensorInfo) -> dict | None:
        for document in self.pinned:
            if (document.get("sensor") or {}).get("key") == key:
                return document
        misfits = []
        for document in self.pinned:
            sensor = document.get("sensor") or {}
            if sensor.get("sensor_id") != info.id:
                continue
            shape = (document.get("kind"), document.get("rows"), document.get("cols"))
            if document.get("kind") == info.kind and (info.kind == "quad" or shape[1:] == (info.rows, info.cols)):
                return document
            misfits.append(f"pinned calibration {document.get('id')} is for a {_shape(*shape)}; sensor "
                           f"{info.address} is a {_shape(info.kind, info.rows, info.cols)}: not used")
        for missed in misfits:  # asked for by name and none fits: never set aside silently
            if missed not in self.problems:
                self.problems.append(missed)
                log.warning(missed)
        for document in self.pinned:
            if str(document.get("id", "")).startswith("builtin-") and document.get("kind") == info.kind:
                return document
        return None

    def _active(self, key: str) -> dict | None:
        try:
            with Registry(self.registry_path) as registry:
                return registry.active_or_none(key)
        except Exception as exc:  # noqa: BLE001 — an unreadable registry: built-in calibrations, reported
            problem = f"calibration registry {self.registry_path or 'default'}: {type(exc).__name__}: {exc}"
            if problem not in self.problems:
                self.problems.append(problem)
                log.warning("%s; sensors use the built-in calibrations", problem)
            return None

    @property
    def follows_registry(self) -> bool:
        """Whether sensors follow the registry's activations while the service
        runs: a book with a registry, not a replay's (its calibrations are its recording's)."""
        return self.use_registry and not self.replaying

    def registry_active(self, board: dict, sensors: list[SensorInfo]) -> dict[int, tuple[dict, str]]:
        """{sensor id: (its identity (registry.sensor_identity), the id of the
        calibration active for it in the registry)} of those of ``sensors``
        that have one and whose calibration is the registry's (none pinned for
        them), in one query; {} when the book does not follow the registry.
        The registry's errors are raised."""
        if not self.follows_registry:
            return {}
        identities = {}
        for info in sensors:
            sensor = sensor_identity(info.board_info or board, info)  # as for_sensor looked it up
            if self._pinned_for(sensor["key"], info) is None:
                identities[info.id] = sensor
        if not identities:
            return {}
        with Registry(self.registry_path) as registry:
            active = registry.active_ids([sensor["key"] for sensor in identities.values()])
        return {sid: (sensor, active[sensor["key"]]) for sid, sensor in identities.items() if sensor["key"] in active}

    def document(self, calibration_id: str) -> dict:
        """The registry's document of ``calibration_id``, with its id (UnknownCalibration naming it)."""
        with Registry(self.registry_path) as registry:
            return registry.get(calibration_id)

    def forget_activation_times(self) -> None:
        """A sensor's active calibration changed: ``activated_at`` reads the registry again."""
        self._activated.clear()

    def load_cycles(self, board: dict, info: SensorInfo, calibration_id: str) -> list[int] | None:
        """Load cycles kept for the sensor under this calibration: a
        recording's own at its start, else the registry's (None: none)."""
        key = sensor_identity(board, info)["key"]
        recorded = self._recorded(self.recorded_cycles, info) or {}
        for identity in (key, None):  # None: a recording made before identities were recorded
            if (identity, calibration_id) in recorded:
                return recorded[(identity, calibration_id)]
        if not self.use_registry or self.replaying:
            return None  # a replay of a recording counts from what it recorded, never from today's registry
        with Registry(self.registry_path) as registry:
            return registry.cycles(key, calibration_id)

    def save_cycles(self, board: dict, counts: list) -> None:
        """``counts``: [(info, calibration id, counts)] (Reconstructor.cycle_counts()'s values), kept (``_keep``)."""
        self._keep(board, counts, Registry.save_cycles)

    def load_zero(self, board: dict, info: SensorInfo, calibration_id: str) -> dict | None:
        """The zero the registry keeps for the sensor under this calibration
        (registry.zero); None without one, and always in a replay (its zeros are its recording's)."""
        if not self.use_registry or self.replaying:
            return None
        with Registry(self.registry_path) as registry:
            return registry.zero(sensor_identity(board, info)["key"], calibration_id)

    def save_zeros(self, board: dict, zeros: list) -> None:
        """``zeros``: [(info, calibration id, zero)] (Reconstructor.zeros_to_keep()'s values), kept (``_keep``)."""
        self._keep(board, zeros, Registry.save_zeros)

    def _keep(self, board: dict, items: list, write) -> None:
        """[(info, calibration id, value)] written to the registry by ``write`` (a live service's, not a
        replay's), each sensor under the identity its INFO gave it."""
        if not self.use_registry or self.replaying or not items:
            return
        entries = [(sensor_identity(info.board_info or board, info)["key"], cid, value) for info, cid, value in items]
        with Registry(self.registry_path) as registry:
            write(registry, entries)

    def store(self, document: dict) -> str:
        """Store and activate ``document`` (an upload through the API); its id."""
        with Registry(self.registry_path) as registry:
            cid = registry.add(document, activate=True)
        self._activated.clear()
        return cid

    def activated_at(self, board: dict, info: SensorInfo, calibration_id: str) -> str | None:
        """When the sensor's calibration ``calibration_id`` was activated in the
        registry; read once per calibration in use (/health asks every second)."""
        if not self.use_registry:
            return None
        key = (sensor_identity(board, info)["key"], calibration_id)
        if key not in self._activated:
            try:
                with Registry(self.registry_path) as registry:
                    self._activated[key] = registry.activated_at(key[0])
            except Exception:  # noqa: BLE001 — only for /health; the problem is reported by lookups
                return None
        return self._activated[key]


def _shape(kind, rows, cols) -> str:
    return f"{rows}x{cols} grid" if kind == "grid" else str(kind)

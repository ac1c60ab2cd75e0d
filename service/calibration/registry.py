"""The calibration registry: immutable calibrations in SQLite, one active per sensor.

A calibration is a JSON document (calibrate.py builds it); its id is the
first 16 hex digits of the sha256 of its canonical JSON (sorted keys, no
spaces, the ``id`` field left out; reconstruct/sensor_calibration.py), so the same content always has the same
id: export → import gives it back, and a document whose id does not match
its content is refused. Rows are never updated nor deleted (triggers refuse
it); ``activate`` only moves the sensor's pointer. Each write is one
transaction (SQLite, WAL journal): a crash leaves the previous state, never
half a calibration. Load-cycle counts (reconstruct/fatigue.py) and each
sensor's last zero (reconstruct/stored_zero.py) are the mutable tables: per
sensor and calibration, so a recalibration starts anew.

A sensor is identified as protocol.md says: its own ``serial`` when INFO
carries one, else the board's serial (or name) and the sensor's id. An 8x8
array without a calibration of its own uses table 1 of paper 000, the
built-in calibration BUILTIN_ID.

Location: the ``path`` argument, else $TACTILE_REGISTRY, else
$XDG_DATA_HOME/tactile/registry.sqlite3 (~/.local/share when unset).

This module imports nothing above service.physics, service.readings, service.board_info and the
calibration's reconstruction side (reconstruct/sensor_calibration.py): the
live service loads calibrations through it.
"""
from __future__ import annotations

import json
import os
import sqlite3
from pathlib import Path

from ..physics.paper_data import BUILTIN_GRID_ID, grid_calibration
from ..board_info import name_from_info
from ..readings import SensorInfo
from ..reconstruct.sensor_calibration import SCHEMA, calibration_id, canonical, check_for_its_sensor

BUILTIN_ID = BUILTIN_GRID_ID
BUILTIN_NOTE = ("built-in: table 1 of Liang et al. 2015 (paper 000), the calibration every 8x8 array without "
                "its own uses; not measured on this sensor")

_DDL = """
CREATE TABLE IF NOT EXISTS calibrations (
    id TEXT PRIMARY KEY, sensor_key TEXT NOT NULL, created TEXT NOT NULL, document TEXT NOT NULL);
CREATE INDEX IF NOT EXISTS calibrations_sensor ON calibrations (sensor_key, created);
CREATE TABLE IF NOT EXISTS active (
    sensor_key TEXT PRIMARY KEY, calibration_id TEXT NOT NULL REFERENCES calibrations (id), activated TEXT NOT NULL);
CREATE TABLE IF NOT EXISTS cycles (
    sensor_key TEXT NOT NULL, calibration_id TEXT NOT NULL, counts TEXT NOT NULL, updated TEXT NOT NULL,
    PRIMARY KEY (sensor_key, calibration_id));
CREATE TABLE IF NOT EXISTS zeros (
    sensor_key TEXT NOT NULL, calibration_id TEXT NOT NULL, zero_pF TEXT NOT NULL, std_pF TEXT NOT NULL,
    frames INTEGER NOT NULL, saved REAL NOT NULL, PRIMARY KEY (sensor_key, calibration_id));
CREATE TRIGGER IF NOT EXISTS calibrations_immutable BEFORE UPDATE ON calibrations
    BEGIN SELECT RAISE(ABORT, 'calibrations are immutable'); END;
CREATE TRIGGER IF NOT EXISTS calibrations_kept BEFORE DELETE ON calibrations
    BEGIN SELECT RAISE(ABORT, 'calibrations are never deleted'); END;
"""


def default_path() -> Path:
    """$TACTILE_REGISTRY, else $XDG_DATA_HOME (or ~/.local/share)/tactile/registry.sqlite3."""
    if os.environ.get("TACTILE_REGISTRY"):
        return Path(os.environ["TACTILE_REGISTRY"])
    base = os.environ.get("XDG_DATA_HOME") or str(Path.home() / ".local" / "share")
    return Path(base) / "tactile" / "registry.sqlite3"


def sensor_identity(board: dict, info: SensorInfo) -> dict:
    """``key`` (what the registry indexes) and what it was made of: the
    sensor's serial, else its board's serial and its id, else the board's
    model and its id — with the name the user gave the board
    (``--source NAME=URL``) when that is not the one its INFO gives, since
    two boards of one model without serials are told apart only by it."""
    board_name = board.get("serial") or board.get("board") or "unknown-board"
    if not board.get("serial") and info.board and info.board != name_from_info(board):
        board_name = f"{board_name}@{info.board}"
    key = f"sensor:{info.serial}" if info.serial else f"board:{board_name}/sensor:{info.id}"
    return {"key": key, "sensor_serial": info.serial, "board_serial": board.get("serial"),
            "board": board.get("board"), "sensor_id": info.id}


def builtin_document(rows: int = 8, cols: int = 8) -> dict:
    """Table 1 (8x8; the table's mean for other shapes) as a registry document, id BUILTIN_ID."""
    from ..physics.taxel_response import taxel_response  # the model tables: only when table 1 is asked for

    base = grid_calibration(rows, cols)
    n = rows * cols
    gains = taxel_response(base).gain
    taxels = {"c0_pF": [float(c) for c in base.c0_pF], "gain": [float(g) for g in gains], "gain_se": [None] * n,
              "sensitivity_pct_per_N": [100 * float(s) for s in base.sensitivity_per_N],
              "sensitivity_origin_pct_per_N": [None] * n, "residual_rms_N": [None] * n, "presses": [None] * n,
              "max_force_N": [None] * n, "model": ["table"] * n, "source": [BUILTIN_ID] * n, "curves": {}}
    return {"id": BUILTIN_ID if (rows, cols) == (8, 8) else f"builtin-mean-{rows}x{cols}", "schema": SCHEMA,
            "kind": "grid", "rows": rows, "cols": cols, "note": BUILTIN_NOTE, "sensor": None, "taxels": taxels}


class UnknownCalibration(ValueError):
    """No calibration (or more than one) answers to an id."""


class RegistryUnusable(OSError):
    """The registry's file cannot be opened as one (not SQLite, a directory, no permission)."""


class Registry:
    """The store at ``path`` (default: default_path()); created on first use;
    RegistryUnusable naming it when its file cannot be."""

    def __init__(self, path: str | Path | None = None) -> None:
        self.path = Path(path) if path is not None else default_path()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        try:
            self._db = sqlite3.connect(self.path, isolation_level=None)
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA foreign_keys=ON")
            self._db.executescript(_DDL)
        except sqlite3.Error as exc:
            raise RegistryUnusable(f"calibration registry {self.path} cannot be used ({exc}): give another with "
                                   "--registry, or move this file away to start an empty one") from None

    def close(self) -> None:
        self._db.close()

    def __enter__(self) -> Registry:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def add(self, document: dict, activate: bool = False) -> str:
        """Store ``document`` (idempotent); ValueError if it carries an id its content does not give."""
        cid = calibration_id(document)
        if document.get("id") not in (None, cid):
            raise ValueError(f"calibration id {document['id']} does not match its content (which gives {cid}): "
                             "edited or corrupt")
        if document.get("schema") != SCHEMA or not (document.get("sensor") or {}).get("key"):
            raise ValueError(f"not a calibration document of schema {SCHEMA} with a sensor key")
        text = canonical(document).decode()
        with self._transaction():
            self._db.execute("INSERT OR IGNORE INTO calibrations VALUES (?, ?, ?, ?)",
                             (cid, document["sensor"]["key"], document.get("created", ""), text))
            if activate:
                self._activate(cid, document["sensor"]["key"])
        return cid

    def get(self, cid: str) -> dict:
        """The document of ``cid`` (a unique prefix will do), with its id; UnknownCalibration naming it."""
        if cid == BUILTIN_ID:
            return builtin_document()
        rows = self._db.execute("SELECT id, document FROM calibrations WHERE id LIKE ? || '%'", (cid,)).fetchall()
        if len(rows) != 1:
            raise UnknownCalibration(f"{'no' if not rows else 'more than one'} calibration {cid!r} in {self.path}")
        return {"id": rows[0][0], **json.loads(rows[0][1])}

    def list(self, sensor_key: str | None = None) -> list[dict]:
        """(id, sensor key, created, active) of every stored calibration, oldest first, then the built-in."""
        rows = self._db.execute(
            "SELECT c.id, c.sensor_key, c.created, a.calibration_id IS NOT NULL FROM calibrations c "
            "LEFT JOIN active a ON a.calibration_id = c.id AND a.sensor_key = c.sensor_key "
            "WHERE ? IS NULL OR c.sensor_key = ? ORDER BY c.created, c.id", (sensor_key, sensor_key)).fetchall()
        out = [{"id": r[0], "sensor_key": r[1], "created": r[2], "active": bool(r[3])} for r in rows]
        return out + [{"id": BUILTIN_ID, "sensor_key": "(any 8x8 array without its own)", "created": "",
                       "active": False, "note": BUILTIN_NOTE}]

    def activate(self, cid: str) -> dict:
        """Make ``cid`` the active calibration of its sensor; returns the document."""
        document = self.get(cid)
        if document["id"].startswith("builtin"):
            raise ValueError("the built-in calibration is what a sensor without an active one uses; it is not activated")
        with self._transaction():
            self._activate(document["id"], document["sensor"]["key"])
        return document

    def active(self, sensor_key: str, rows: int = 8, cols: int = 8) -> dict:
        """The sensor's active calibration, or the built-in one (table 1 for 8x8)."""
        return self.active_or_none(sensor_key) or builtin_document(rows, cols)

    def active_or_none(self, sensor_key: str) -> dict | None:
        """The sensor's active calibration, None when it has none."""
        row = self._db.execute("SELECT calibration_id FROM active WHERE sensor_key = ?", (sensor_key,)).fetchone()
        return self.get(row[0]) if row else None

    def active_ids(self, sensor_keys: list[str]) -> dict[str, str]:
        """{sensor key: its active calibration's id} of those of ``sensor_keys`` that have one, in one query
        (a running service asks every few seconds whether another process activated another)."""
        if not sensor_keys:
            return {}
        rows = self._db.execute(f"SELECT sensor_key, calibration_id FROM active WHERE sensor_key IN "
                                f"({', '.join('?' * len(sensor_keys))})", list(sensor_keys)).fetchall()
        return dict(rows)

    def activated_at(self, sensor_key: str) -> str | None:
        row = self._db.execute("SELECT activated FROM active WHERE sensor_key = ?", (sensor_key,)).fetchone()
        return row[0] if row else None

    def cycles(self, sensor_key: str, cid: str) -> list[int] | None:
        """Load cycles counted on the sensor since calibration ``cid`` became
        its own (per taxel; a quad: one), None when none were kept."""
        row = self._db.execute("SELECT counts FROM cycles WHERE sensor_key = ? AND calibration_id = ?",
                               (sensor_key, cid)).fetchone()
        return None if row is None else json.loads(row[0])

    def save_cycles(self, entries: list[tuple[str, str, list[int]]]) -> None:
        """(sensor key, calibration id, counts) of several sensors, in one transaction."""
        with self._transaction():
            self._db.executemany(
                "INSERT INTO cycles VALUES (?, ?, ?, strftime('%Y-%m-%dT%H:%M:%SZ', 'now')) "
                "ON CONFLICT (sensor_key, calibration_id) DO UPDATE SET counts = excluded.counts, "
                "updated = excluded.updated", [(key, cid, json.dumps(counts)) for key, cid, counts in entries])

    def zero(self, sensor_key: str, cid: str) -> dict | None:
        """The sensor's last zero under calibration ``cid``: {zero_pF, std_pF
        (per channel, None where it had none), frames (its tare window),
        saved (Unix time)}; None when none was kept."""
        row = self._db.execute("SELECT zero_pF, std_pF, frames, saved FROM zeros WHERE sensor_key = ? AND "
                               "calibration_id = ?", (sensor_key, cid)).fetchone()
        return None if row is None else {"zero_pF": json.loads(row[0]), "std_pF": json.loads(row[1]),
                                         "frames": row[2], "saved": row[3]}

    def save_zeros(self, entries: list[tuple[str, str, dict]]) -> None:
        """(sensor key, calibration id, zero as ``zero`` gives it) of several sensors, in one transaction."""
        with self._transaction():
            self._db.executemany(
                "INSERT INTO zeros VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (sensor_key, calibration_id) DO UPDATE SET "
                "zero_pF = excluded.zero_pF, std_pF = excluded.std_pF, frames = excluded.frames, saved = excluded.saved",
                [(key, cid, json.dumps(z["zero_pF"]), json.dumps(z["std_pF"]), int(z["frames"]), float(z["saved"]))
                 for key, cid, z in entries])

    def export(self, cid: str, path: str | Path) -> str:
        document = self.get(cid)
        Path(path).write_text(json.dumps(document, indent=1, sort_keys=True, allow_nan=False) + "\n")
        return document["id"]

    def import_(self, path: str | Path) -> str:
        try:
            document = json.loads(Path(path).read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not JSON: {exc}") from None
        if not isinstance(document, dict):
            raise ValueError(f"{path}: not a calibration document")
        try:  # calibrate refuses what the service cannot use; an import as well
            check_for_its_sensor(document)
        except ValueError as exc:
            raise ValueError(f"{path}: not imported, the service could not use it: {exc}") from None
        return self.add(document)

    def _activate(self, cid: str, key: str) -> None:
        self._db.execute("INSERT INTO active VALUES (?, ?, strftime('%Y-%m-%dT%H:%M:%SZ', 'now')) "
                         "ON CONFLICT (sensor_key) DO UPDATE SET calibration_id = excluded.calibration_id, "
                         "activated = excluded.activated", (key, cid))

    def _transaction(self):
        return _Transaction(self._db)


class _Transaction:
    """BEGIN IMMEDIATE … COMMIT, ROLLBACK on any exception."""

    def __init__(self, db: sqlite3.Connection) -> None:
        self._db = db

    def __enter__(self) -> None:
        self._db.execute("BEGIN IMMEDIATE")

    def __exit__(self, kind, *exc) -> None:
        self._db.execute("ROLLBACK" if kind else "COMMIT")

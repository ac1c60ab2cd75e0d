"""The boards a service reads: ``--source [NAME=]URL`` (repeatable) or a robot
description file (``--config robot.toml``).

    # robot.toml
    [[board]]
    name = "left_hand"            # letters, digits, '_', '-'; starts with a letter
    source = "/dev/ttyACM0"       # any source URL (sim://, socket://, replay://, a device)
    level = "full"                # optional: the fidelity level (default: --level)
    mounting = "flat"             # optional: the grid mounting (default: --mounting)
    calibration = ["3f2a", "left-palm.json"]   # optional: calibrations pinned for this board's sensors

    [[board]]
    name = "right_hand"
    source = "socket://10.0.0.7:5000"

Every error names the file, the board and the key.
"""
from __future__ import annotations

import re
import tomllib
from pathlib import Path

from .board import BoardSpec, check_board_name
from .physics.mountings import MOUNTINGS
from .reconstruct.levels import LEVELS

NAMED_SOURCE = re.compile(r"([A-Za-z][A-Za-z0-9_-]{0,31})=(.+)")
LOOKS_NAMED = re.compile(r"([^=:/]*)=(.+)")  # a name before '=' that is not in a URL's path or query
BOARD_KEYS = {"name", "source", "level", "mounting", "calibration"}


def parse_source(text: str, level: str, mounting: str) -> BoardSpec:
    """``NAME=URL`` or a bare URL (the board is then named from its INFO)."""
    named = NAMED_SOURCE.fullmatch(text)
    if named:
        return BoardSpec(named.group(2), named.group(1), level, mounting)
    meant = LOOKS_NAMED.fullmatch(text)
    if meant:  # NAME=URL with a name no board can have: say so, not that '1bad=sim' is no URL scheme
        try:
            check_board_name(meant.group(1))
        except ValueError as exc:
            raise ValueError(f"--source {text}: {exc}") from None
    return BoardSpec(text, None, level, mounting)


def specs_from_sources(sources: list[str], level: str, mounting: str) -> list[BoardSpec]:
    specs = [parse_source(text, level, mounting) for text in sources]
    _check_unique(specs, "--source")
    return specs


def load_robot(path: str | Path, level: str, mounting: str) -> list[BoardSpec]:
    """The boards of a robot description file; ValueError naming the file,
    the board and what is wrong."""
    path = Path(path)
    try:
        document = tomllib.loads(path.read_text())
    except OSError as exc:
        raise ValueError(f"--config {path}: cannot read it ({exc.strerror})") from None
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"--config {path}: not TOML ({exc})") from None
    unknown = set(document) - {"board"}
    if unknown:
        raise ValueError(f"{path}: unknown table(s) {sorted(unknown)}; a robot file holds [[board]] entries")
    boards = document.get("board")
    if not isinstance(boards, list) or not boards:
        raise ValueError(f"{path}: no [[board]] entries")
    specs = [_board(path, i, entry, level, mounting) for i, entry in enumerate(boards)]
    _check_unique(specs, str(path))
    return specs


def _board(path: Path, index: int, entry: dict, level: str, mounting: str) -> BoardSpec:
    where = f"{path}: board {index + 1}" + (f" ({entry['name']!r})" if isinstance(entry.get("name"), str) else "")
    unknown = set(entry) - BOARD_KEYS
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {sorted(unknown)}; known: {', '.join(sorted(BOARD_KEYS))}")
    for key in ("name", "source"):
        if not isinstance(entry.get(key), str):
            raise ValueError(f"{where}: {key!r} must be a string, got {entry.get(key)!r}")
    try:
        check_board_name(entry["name"])
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    level = entry.get("level", level)
    if level not in LEVELS:
        raise ValueError(f"{where}: level {level!r} is not one of {', '.join(LEVELS)}")
    mounting = entry.get("mounting", mounting)
    if not isinstance(mounting, str) or mounting not in MOUNTINGS:  # a list or table is no key of MOUNTINGS
        raise ValueError(f"{where}: mounting {mounting!r} is not one of {', '.join(MOUNTINGS)}")
    calibration = entry.get("calibration", [])
    if isinstance(calibration, str):
        calibration = [calibration]
    if not isinstance(calibration, list) or not all(isinstance(c, str) for c in calibration):
        raise ValueError(f"{where}: calibration must be an id, a file or a list of them, got {calibration!r}")
    relative = [str(path.parent / c) if (path.parent / c).is_file() else c for c in calibration]
    return BoardSpec(entry["source"], entry["name"], level, mounting, tuple(relative))


def _check_unique(specs: list[BoardSpec], where: str) -> None:
    names = [s.name for s in specs if s.name is not None]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        raise ValueError(f"{where}: board name(s) {', '.join(twice)} given twice")
    sources = [s.source for s in specs]
    again = sorted({s for s in sources if sources.count(s) > 1 and not s.startswith("sim://")})
    if again:
        raise ValueError(f"{where}: source(s) {', '.join(again)} given twice (one reader per device)")

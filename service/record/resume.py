"""Where a replay begins when a recording lost its first reads (a damaged
chunk: with them the board's INFO and the tare on its first frames).

The recorder writes, once a second of reads, the zeros and INFO in force
before a read (``/resume``); a replay of a board whose first reads are gone
begins at the first such point after them, as the recording ran from
there, rather than describing its sensors by their frames alone (under the
name "board") and taring them again on whatever load came next, each sensor
on the calibration it then ran on (record/calibrations.py). The reads
between the damage and that point (a second at most) are skipped: the
zeros they were reconstructed with are unknown.
"""
from __future__ import annotations

from pathlib import Path

from .mcap_reader import read_numbered, read_resumes


def resume_point(resumes: list[dict], first: int) -> dict | None:
    """Where a board whose reads before ``first`` were lost begins again: the
    first recorded point from there on whose zeros cover every sensor it then
    described (else the first from there on; None without one)."""
    later = [point for point in resumes if point["after_reads"] >= first]
    covered = [point for point in later if set(point["described"]) <= {int(z["sensor"]) for z in point["sensors"]}]
    return (covered or later or [None])[0]


def lost_start(path: str | Path, board: str | None) -> tuple[int, dict | None]:
    """(the number of ``board``'s first read the recording holds, the point
    its replay begins at, when that is not 0 and one was recorded)."""
    first = next((number for name, number, _, _ in read_numbered(path) if name == board), 0)
    return first, resume_point(read_resumes(path).get(board, []), first) if first else None


def resumed_calibrations(path: str | Path) -> list[tuple[int, list[dict]]]:
    """(the read a board whose first reads were lost begins at, the calibration
    each of its sensors then ran on: [{"board", "sensor", "id", "key"}], none
    in a recording made before /resume held them) of each such board."""
    points = (lost_start(path, board)[1] for board in read_resumes(path))
    return [(point["after_reads"], point.get("calibrations", [])) for point in points if point is not None]

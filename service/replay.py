"""Offline replay of recordings and raw captures through the live pipeline.

A recording is a sequence of timed byte chunks (record/readers.py); they go
through the same pipeline as live data, paced by a ``Pacer`` (injectable
clock, any speed, or as fast as possible). As fast as possible, the bytes
go in large chunks (a raw capture is not decoded just to time them; a
recording's reads are joined, JOIN_READS a call, split at its tares, calibrations set and link events) and
the pipeline keeps no history: an export needs neither, and the forces do
not depend on how the stream is cut.
A raw capture's readings are held until each sensor's auto-tare is
complete, so every exported frame has forces. A recording is replayed as it
ran live (the tare window null and flagged), with the tares made while it
was recorded made again before the same read, and so the calibrations set then (uploads), and at the level and mounting
it was recorded with (unless told otherwise), so its forces come out bit for
bit as recorded; frames a live link held for the board's INFO (after a
reopen, a restart whose INFO was lost) are held likewise, from the state the
recording began with to where its INFO came or the recording's ``/link``
says the wait passed or the link dropped, so they are read under the same
description, on the same side of a tare (one made before 2026-11-25 has no
``/link``: its frames are read as they came). One begun on a running service starts from the zeros then
in force (recorded as ``/baselines``), not from a tare on whatever load it
begins with; the full level's tracked state (drift, crosstalk estimates)
starts afresh, so its forces are close to the recorded ones, not equal.
One whose first reads were lost (a damaged chunk: with them its INFO, its
zeros) begins at the first point after them where it recorded the zeros
and INFO then in force (``/resume``, once a second of reads), as it ran
from there; the reads in between are skipped.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import BinaryIO, Protocol

from .pipeline import Pipeline
from .reconstruct import DEFAULT_LEVEL, ForceFrame, Reconstructor
from .record.export import JsonLines, export_line
from .record.pacing import Pacer
from .record.mcap_reader import read_baselines, read_numbered, read_changes, read_resumes, read_settings
from .record.resume import resume_point
from .record.readers import HostTime, is_timed_by_host, timed_chunks

JOIN_READS = 256  # recorded reads of a board joined into one call at full speed

__all__ = ["Pacer", "Writer", "export_line", "replay", "replay_boards"]

log = logging.getLogger(__name__)


class Writer(Protocol):
    def write(self, frames: list[ForceFrame]) -> None: ...


def replay(path: str | Path, export: BinaryIO | None = None, level: str | None = None, mounting: str | None = None,
           pacer: Pacer | None = None, writer: Writer | None = None, calibrations=None) -> Pipeline:
    """Replay a one-board recording (.mcap) or raw capture (any other suffix)
    (``replay_boards`` for any number of boards); returns its pipeline,
    whose counters tell what was dropped."""
    pipelines = replay_boards(path, export, level, mounting, pacer, writer, calibrations)
    if len(pipelines) > 1:
        raise ValueError(f"{path} holds boards {', '.join(pipelines)}: replay_boards replays them all")
    return next(iter(pipelines.values()))


def replay_boards(path: str | Path, export: BinaryIO | None = None, level: str | None = None,
                  mounting: str | None = None, pacer: Pacer | None = None, writer: Writer | None = None,
                  calibrations=None) -> dict[str, Pipeline]:
    """Replay a recording (.mcap, of one board or several) or raw capture
    (any other suffix); write one JSON line per data frame to ``export``,
    or each batch of frames to ``writer`` (record.export_parquet.Parquet,
    say), every board's in the order its reads were received.
    ``calibrations``: a calibration/book.py CalibrationBook (None: built-in
    calibrations). ``level``, ``mounting``: None reconstructs each board
    as it was recorded (``/settings``), else at DEFAULT_LEVEL, flat.
    Returns each board's pipeline by its name."""
    pacer = pacer or Pacer(math.inf)
    hold = not is_timed_by_host(path)
    own = writer is None and export is not None  # a paced replay's lines go out as they come (a pipe may read them)
    writer = writer or (JsonLines(export, gather=math.isinf(pacer.speed)) if export is not None else None)
    pipelines: dict[str | None, Pipeline] = {}
    # A one-board recording's topics do not name its board; its calibrations do.
    named = {key.split("/")[0] for key in getattr(calibrations, "recorded_cycles", {}) if isinstance(key, str)}
    only = next(iter(named)) if len(named) == 1 else None

    def pipeline_of(board: str | None) -> Pipeline:
        pipeline = pipelines.get(board)
        if pipeline is None:
            # A recording begun mid-stream (or resumed after its lost start) has no INFO: its name then, its zeros.
            began = resumed.get(board) or zeros.get(board, {})
            recorded = settings.get(board, {})
            reconstructor = Reconstructor(hold_until_tared=hold, level=level or recorded.get("level", DEFAULT_LEVEL),
                                          mounting=mounting or recorded.get("mounting", "flat"))
            pipeline = pipelines[board] = Pipeline(
                reconstructor, clock=lambda: 0.0,
                keep_history=False, calibrations=calibrations, map_clock=not hold,
                board_name=board or only or began.get("board"))
            # Frames held for the board's INFO as live held them (its link's events are among the changes).
            identify = (resumed[board] if board in resumed else recorded).get("identify")
            if identify is not None:
                _hold_as_recorded(pipeline, identify, path)
            if writer is not None:
                pipeline.listeners.append(writer.write)
            pipeline.preset_began(began)
        return pipeline

    paced = not math.isinf(pacer.speed)
    # A raw capture's reads are not numbered (no tares to place among them).
    chunks = read_numbered(path) if not hold else ((None, 0, t, chunk) for t, chunk in timed_chunks(path, paced=paced))
    changes = {} if hold else read_changes(path)  # tares, calibrations set and the link's events, where they were
    zeros = {} if hold else read_baselines(path)  # a recording begun on a running service: the zeros it began with
    settings = {} if hold else read_settings(path)
    resumes = {} if hold else read_resumes(path)
    resumed: dict[str | None, dict] = {}
    starts: dict[str | None, int] = {}  # each board's first read replayed

    def start_of(board: str | None, first: int) -> int:
        """The read a board's replay begins at, its reads before ``first`` lost."""
        if first == 0:
            return 0
        point = resume_point(resumes.get(board, []), first)
        if point is None:
            log.warning("%s: board %s's reads before read %d are lost (a damaged chunk), and with them its INFO and "
                        "zeros: replayed from there, its sensors described by their frames and tared afresh",
                        path, board or "(the only one)", first)
            return first
        resumed[board] = point
        # An earlier tare is in its zeros; an earlier calibration set is set again where it begins.
        begin = point["after_reads"]
        changes[board] = [(max(n, begin), sensor, change) for n, sensor, change in changes.get(board, [])
                          if n >= begin or isinstance(change, dict)]
        log.warning("%s: board %s's reads before read %d are lost (a damaged chunk), and with them its INFO and zeros: "
                    "replayed from read %d, where the recording holds those then in force (%d reads skipped)",
                    path, point["board"], first, point["after_reads"], point["after_reads"] - first)
        return point["after_reads"]

    if hold:
        pipeline_of(None)  # a capture without a frame still has its (empty) pipeline
    # Paced, a recording waits by its receive times with the host clock's steps taken out (not what the
    # pipeline gets: its stamps stay as recorded).
    pacing_time = HostTime() if paced and not hold else lambda board, t, chunk: t
    t_last = 0.0
    # At full speed a recording's reads (a frame or two per sensor each, as the live port gave them) are joined,
    # a board's consecutive reads up to JOIN_READS, never across a change made while recording (a raw capture's
    # chunks are a megabyte already).
    joined: list[tuple[bytes, float]] = []
    joined_board: str | None = None

    def feed_joined() -> None:
        if joined:
            pipeline_of(joined_board).feed_many(joined)
            joined.clear()

    try:
        for board, number, t_recorded, chunk in chunks:
            start = starts.get(board)
            if start is None:
                start = starts[board] = start_of(board, number)
            if number < start:
                continue
            pacer.wait(pacing_time(board, t_recorded, chunk), len(chunk))
            pending = changes.get(board)
            redo = bool(pending) and pending[0][0] <= number  # made live before this read was decoded
            if hold or board != joined_board or redo or len(joined) >= JOIN_READS:
                feed_joined()
            pipeline = pipeline_of(board)
            while pending and pending[0][0] <= number:
                _, sensor_id, change = pending.pop(0)
                pipeline.redo(sensor_id, change)
            joined.append((chunk, t_recorded))
            joined_board = board
            t_last = t_recorded
            if paced:  # out at its own time: held for the next read's wait, it came out a whole pause late
                feed_joined()
        feed_joined()
        for pipeline in pipelines.values():
            counters = pipeline.decoder.counters
            truncated, discarded = counters.truncated, counters.bytes_discarded
            pipeline.finish(t_last)
            if hold and counters.truncated > truncated:  # a recording's cut is its reader's to say
                log.warning("%s ends inside a frame: its last %d bytes are no whole frame (dropped, counted as "
                            "truncated): the capture was cut short", path, counters.bytes_discarded - discarded)
    finally:  # an interrupted replay's export keeps every frame made so far (the writer gathers them)
        if own:
            writer.close()
    return {pipeline.interpreter.name: pipeline for pipeline in pipelines.values()}


def _hold_as_recorded(pipeline: Pipeline, state: dict, path: str | Path) -> None:
    """``pipeline``'s frames held for the board's INFO as live held them,
    from the recorded ``state``; one no recording writes is said, and the
    replay holds nothing (its frames read as they came)."""
    try:
        pipeline.identify_as_recorded(state)
    except ValueError as exc:
        log.warning("%s: board %s's frames are replayed as they came, none held for its INFO: %s", path,
                    pipeline.interpreter.name, exc)


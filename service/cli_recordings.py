"""``tactile record`` and ``tactile replay``: a source into a recording, and a
recording back through the pipeline (exported, or served with ``--serve``).

Both exit 1 when nothing came (no byte, no valid frame) and leave no empty
file behind that they created; ``record`` says on stderr what the link does
(a LinkWatcher), ``replay`` shows its progress through the file.
"""
from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

from .cli_commands import progress_bar
from .cli_link import LinkWatcher, quiet_readout_transitions
from .cli_serve import cmd_serve
from .reconstruct.levels import DEFAULT_LEVEL
from .sources import check_source

DEFAULTS = {"level": DEFAULT_LEVEL, "mounting": "flat"}  # a replay's, where its recording does not say


def cmd_record(args) -> int:
    from .handover import ThreadSink
    from .pipeline import Pipeline
    from .readout import Readout
    from .reconstruct import Reconstructor
    from .record.recorder import Recorder

    from .calibration.book import book_from_options

    check_source(args.source)
    book = book_from_options(args.registry, args.calibration, args.mounting)
    pipeline = Pipeline(Reconstructor(level=args.level, mounting=args.mounting), calibrations=book)
    outputs = [Path(p) for p in (args.out, args.raw) if p]
    if len(outputs) == 2 and outputs[0].resolve() == outputs[1].resolve():
        raise ValueError(f"--out and --raw name the same file ({args.out}): the raw bytes would overwrite the recording")
    new = [p for p in outputs if not p.exists()]
    existing = [p for p in outputs if p not in new]
    if existing and not args.overwrite:  # as POST /record/start: a recording is not lost to a repeated command
        raise ValueError(f"{' and '.join(f'{p} ({p.stat().st_size} bytes)' for p in existing)} exist"
                         f"{'s' if len(existing) == 1 else ''}: name another file, or give --overwrite")
    recorder = Recorder(args.out, args.raw)
    recorder.attach(pipeline)
    readout = Readout(args.source, ThreadSink(pipeline.feed, pipeline.link_lost))
    quiet_readout_transitions()
    watcher = LinkWatcher(lambda: readout.link)
    readout.start()
    watcher.start()
    until = f"for {args.seconds:g} s" if args.seconds else "Ctrl-C to stop"
    print(f"recording {args.source} to {args.out}" + (f" and {args.raw}" if args.raw else "") + f"; {until}",
          flush=True)
    started = time.monotonic()
    try:
        deadline = started + args.seconds if args.seconds else None
        while recorder.active and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        readout.stop()
        watcher.stop(final_look=False)
        status = recorder.stop()
    if status["error"]:
        print(json.dumps(status, indent=1))
        return 1
    if readout.link.last_data_time is None:  # not one byte came
        removed = [p for p in new if p.exists() and _unlink(p)]  # only files this command created
        kept = existing
        why = f" ({readout.link.last_error})" if readout.link.last_error else ""
        note = f"; removed the empty {' and '.join(map(str, removed))}" if removed else ""
        note += f"; {' and '.join(map(str, kept))} existed before and now hold an empty recording" if kept else ""
        print(f"tactile record: nothing recorded: no byte from {args.source} in {time.monotonic() - started:.1f} s"
              f"{why}{note}", file=sys.stderr)
        return 1
    print(json.dumps(status, indent=1))
    return 0


EXPORT_SUFFIXES = {".jsonl": "jsonl", ".ndjson": "jsonl", ".parquet": "parquet"}


def export_format(export: str) -> str:
    """``--export``'s format by its suffix, in any case ('-': JSON lines to stdout); ValueError for any other."""
    if export == "-":
        return "jsonl"
    found = EXPORT_SUFFIXES.get(Path(export).suffix.lower())
    if found is None:  # .csv, .gz … got plain JSON lines without a word
        raise ValueError(f"--export {export}: no format for {Path(export).suffix or 'a name without a suffix'}; "
                         f"name it {' or '.join(EXPORT_SUFFIXES)} (or - for JSON lines on stdout)")
    return found


def replay_settings(args, path: str) -> dict:
    """{board: {"level", "mounting"}} ``path`` was recorded with (record's
    /settings; {} for a raw capture or an older recording), saying where
    ``args.level`` or ``args.mounting`` differ from them: the forces will
    differ from the recorded ones. None (not given) leaves each board its own."""
    from .record.mcap_reader import read_settings

    recorded = read_settings(path) if Path(path).suffix == ".mcap" and Path(path).is_file() else {}
    for name in ("level", "mounting"):
        given = getattr(args, name)
        made = sorted({board[name] for board in recorded.values() if name in board})  # one unknown is left out
        if given not in (None, "auto") and made and made != [given]:  # auto says what it chose, after
            print(f"tactile replay: {path} was recorded at {name} {' and '.join(made)}; replaying at {given}, so its "
                  "forces differ from the recorded ones", file=sys.stderr)
    return recorded


def _unlink(path: Path) -> bool:
    try:
        path.unlink()
        return True
    except OSError:
        return False


class _ProgressPacer:
    """A Pacer that also moves a bar by bytes of the file: a raw capture's
    by the bytes each wait releases (its chunks are cut by board time, of
    any size); an MCAP recording's progress is its recorded time against
    the span its summary gives, scaled to the file's size."""

    def __init__(self, pacer, bar, path: Path) -> None:
        from .record.readers import is_timed_by_host

        self._pacer, self._bar = pacer, bar
        self.speed = pacer.speed
        self._size = path.stat().st_size
        self._span = _mcap_span(path) if is_timed_by_host(path) else None
        self._timed = is_timed_by_host(path)

    def wait(self, t_recorded: float, size: int = 0) -> None:
        self._pacer.wait(t_recorded, size)
        if not self._timed:
            done = self._bar.n + size
        elif self._span is not None:
            t0, t1 = self._span
            done = self._size * min(max((t_recorded - t0) / (t1 - t0), 0.0), 1.0) if t1 > t0 else self._bar.n
        else:
            return
        self._bar.update(min(done, self._size) - self._bar.n)


def _close(out, writer) -> None:
    """The export's file, and the Parquet writer's footer."""
    if writer is not None:
        writer.close()
    if out is not None:
        out.close()


def _mcap_span(path: Path) -> tuple[float, float] | None:
    """(first, last) message time in s from an MCAP's summary; None without one (a file cut short)."""
    try:
        from mcap.reader import make_reader

        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            return None
        return summary.statistics.message_start_time * 1e-9, summary.statistics.message_end_time * 1e-9
    except Exception:  # no summary is no reason to refuse the replay
        return None


def _summary(pipeline) -> dict:
    """What a replay of one board dropped and how it reconstructed (printed on stderr)."""
    counters = pipeline.decoder.counters.as_dict()
    reconstructor = pipeline.reconstructor
    return {"stream": {k: v for k, v in counters.items() if k != "sensors"}, "sensors": counters["sensors"],
            "rejected": pipeline.interpreter.rejected, "level": reconstructor.level,
            "level_reason": reconstructor.level_reason}


def cmd_replay(args) -> int:
    from .calibration.book import book_from_options
    from .record.pacing import Pacer
    from .record.mcap_reader import boards_in
    from .replay import replay_boards

    if args.file and args.raw:
        raise ValueError(f"name one recording: {args.file} or --raw {args.raw}")
    path = args.file or args.raw
    if path is None:
        raise ValueError("name a recording: tactile replay FILE (or --raw FILE)")
    recorded = replay_settings(args, path)
    if args.serve:
        import math
        import urllib.parse

        from .board import BoardSpec

        speed = 1.0 if args.speed is None else args.speed
        url = f"replay://{urllib.parse.quote(str(path))}?speed={'max' if math.isinf(speed) else speed}"
        boards = boards_in(path) if Path(path).suffix == ".mcap" and Path(path).is_file() else [None]
        # A recording of several boards: a replay:// source per board, named as they were, each at its own
        # level and mounting unless told.
        args.board_specs = [
            BoardSpec(url if b is None else f"{url}&board={urllib.parse.quote(b)}", b,
                      *(getattr(args, name) or recorded.get(b, {}).get(name, DEFAULTS[name])
                        for name in ("level", "mounting")))
            for b in boards]
        args.level, args.mounting = args.level or DEFAULTS["level"], args.mounting or DEFAULTS["mounting"]
        args.recording = path
        return cmd_serve(args)
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    speed = args.speed if args.speed is not None else float("inf")
    to_stdout = args.export == "-"
    export_is_new = bool(args.export) and not to_stdout and not Path(args.export).exists()
    columnar = bool(args.export) and export_format(args.export) == "parquet"
    out = sys.stdout.buffer if to_stdout else open(args.export, "wb") if args.export and not columnar else None
    bar = progress_bar(total=Path(path).stat().st_size, unit="B", unit_scale=True, desc=Path(path).name)
    writer = None
    try:
        book = book_from_options(args.registry, args.calibration, args.mounting or "flat", path)
        if columnar:
            from .record.export_parquet import Parquet

            writer = Parquet(args.export)
        pipelines = replay_boards(path, out, level=args.level, mounting=args.mounting,
                                  pacer=_ProgressPacer(Pacer(speed), bar, Path(path)), writer=writer, calibrations=book)
    except BrokenPipeError:
        if not to_stdout:
            raise
        # The reader stopped (`| head`): end quietly, as a pipeline's tools do.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, OSError):  # not a recording after all: leave no empty export behind
        if export_is_new:
            _close(out, writer)
            out = writer = None
            _unlink(Path(args.export))
        raise
    finally:
        bar.close()
        _close(None if to_stdout else out, writer)
    summaries = {name: _summary(pipeline) for name, pipeline in pipelines.items()}
    print(json.dumps(next(iter(summaries.values())) if len(summaries) == 1 else {"boards": summaries}, indent=1),
          file=sys.stderr)
    for name, pipeline in pipelines.items():
        if args.level == "auto":
            which = f" for board {name}" if len(pipelines) > 1 else ""
            print(f"tactile replay: level auto chose {pipeline.reconstructor.level}{which}: "
                  f"{pipeline.reconstructor.level_reason}", file=sys.stderr)
    counted = [p.decoder.counters.as_dict() for p in pipelines.values()]
    frames, bytes_in = sum(c["frames"] for c in counted), sum(c["bytes_in"] for c in counted)
    # An INFO alone is a valid frame: a capture whose every data frame is corrupt must not pass as exported.
    data = sum(s["frames"] for c in counted for s in c["sensors"].values())
    if data == 0:
        removed = export_is_new and _unlink(Path(args.export))
        crc = sum(c["crc_errors"] for c in counted)
        what = "no valid frame" if frames == 0 else f"no valid data frame ({frames} INFO/ERROR, {crc} CRC errors)"
        print(f"tactile replay: {path}: {what} in {bytes_in} bytes (is it a capture of the board?)"
              + (f"; removed the empty {args.export}" if removed else ""), file=sys.stderr)
        return 1
    return 0

"""``GET /health``: the live service's state in one document."""
from __future__ import annotations

import time

from .board import Board, calibration_state
from .board_info import UNKNOWN_KIND
from .history import BELOW_ZERO_S
from .interpreter import shown_text
from .protocol import MAX_PAYLOAD
from .readout import MIN_STALE_S, LinkState

STALE_SCAN_PERIODS = 20


def stale_after_s(board: dict) -> float:
    """Silence that makes the link or a sensor stale: max(0.5 s, 20 scan
    periods at the rate the board announced in INFO)."""
    rate = board.get("rate_hz")
    if isinstance(rate, (int, float)) and not isinstance(rate, bool) and rate > 0:
        return max(MIN_STALE_S, STALE_SCAN_PERIODS / rate)
    return MIN_STALE_S


def frame_stale(board, frame, now: float) -> bool:
    """Whether /health calls ``frame``'s sensor stale when ``frame`` is its
    last (``now``: s since the epoch): a board.Board's sensor after
    stale_after_s without a frame, a gateway's remote board by its own rule
    (RemoteBoard.sensor_stale)."""
    age = now - frame.t_host
    if isinstance(board, Board):
        return age > stale_after_s(board.info)
    return board.sensor_stale(frame.sensor.id, age, now)


def _sensors(pipeline, now: float, counters: dict, stale_after: float, book=None) -> dict:
    sensors = {}
    name = pipeline.interpreter.name
    unlisted = pipeline.interpreter.unlisted
    dropped = pipeline.interpreter.dropped
    sent = pipeline.interpreter.sent_since_restart
    for sid, info in sorted(pipeline.interpreter.sensors.items()):
        meter = pipeline.rates.get(sid)
        latest = pipeline.latest.get(sid)
        history = pipeline.history.get(sid)
        # A read stamped while this snapshot began reads as a few µs old, not in the future.
        age = None if latest is None else max(0.0, now - latest.t_host)
        stale = age is None or age > stale_after
        sensors[str(sid)] = {
            "board": name,
            "id": sid,
            "kind": info.kind,
            "rows": info.rows,
            "cols": info.cols,
            "serial": info.serial,
            # Another sensor took this address's place ({count, from, to}): re-tared, its own calibration and counts.
            "replaced": pipeline.reconstructor.replaced(sid),
            "rate_hz": 0.0 if stale or meter is None else round(meter.rate_hz, 1),
            "stale": stale,
            "last_frame_age_s": None if age is None else round(age, 3),
            "calibration": calibration_state(pipeline, sid, now, book),
            "fatigue": pipeline.reconstructor.fatigue(sid),
            "not_in_info": sid in unlisted,
            # Sends nothing, and the INFO in force does not list it: an INFO once did, or the board restarted
            # (its INFO, then frames from 0) and it sent nothing since. One that stops while the board runs on
            # (a board whose INFO cannot list every sensor; an INFO? reply is no restart) is stale: a failure.
            "retired": stale and (sid in dropped or (sid in unlisted and sid not in sent)),
            "unzeroed_channels": pipeline.reconstructor.unzeroed(sid),
            # Most channels read outside what the calibration's C0 lets a tare take: no zero until calibrated.
            "outside_calibration": None if latest is None else
            pipeline.reconstructor.outside_expected(sid, latest.capacitance_pF),
            "tare_glitches": {str(k): n for k, n in pipeline.reconstructor.tare_glitches(sid).items()},
            "tare_restarts": pipeline.reconstructor.tare_restarts(sid),
            "below_zero": [] if history is None or stale else history.below_zero(),
            "faulty_channels": {} if history is None or stale else _faulty(pipeline.reconstructor, sid, history),
            "info_problem": pipeline.interpreter.undescribed.get(sid),
            **counters["sensors"].get(str(sid), {}),
        }
    return sensors


def _faulty(reconstructor, sid: int, history) -> dict[str, list[int]]:
    """History.faulty, without the channels the tare gave no zero (their own problem line says so)."""
    unzeroed = set(reconstructor.unzeroed(sid))
    found = history.faulty(outside=lambda pF: reconstructor.implausible(sid, pF),
                           kept=lambda: reconstructor.loaded_at_tare(sid))
    found = {flag: [c for c in channels if c not in unzeroed] for flag, channels in found.items()}
    return {flag: channels for flag, channels in found.items() if channels}


DEAD_CHANNEL = "a dead channel? Check the sensor's cable and connector"
# What each persistent flag says of a channel, and what to do about it.
FAULTS = {
    "no_reading": ("no reading (an open or shorted channel: null)", DEAD_CHANNEL),
    "out_of_range": ("an implausible reading (null)", DEAD_CHANNEL),
    "stale": ("a stale reading (its converter repeats one count: null)", DEAD_CHANNEL),
    "loaded_at_tare": ("been loaded when tared (its zero is the calibration's C0, or the one it had before the "
                       "service restarted or it left its address)",
                       "lift the load and tare it again (POST /sensors/{board}/{sid}/tare)"),
}


def _fault_lines(sid: str, sensor: dict) -> list[str]:
    """One problem line per flag of ``faulty_channels``."""
    noun = "electrodes" if sensor["kind"] == "quad" else "taxels"
    lines = []
    for flag, channels in sensor["faulty_channels"].items():
        if len(channels) == sensor["rows"] * sensor["cols"]:  # one line a dashboard can show, not 64 positions
            named = f"all {len(channels)} {noun}"
        else:
            named = noun + " " + ", ".join(f"{c} (row {c // sensor['cols']}, col {c % sensor['cols']})" for c in channels)
        what, advice = FAULTS[flag]
        lines.append(f"sensor {sid}: {named} had {what} in most of the last {BELOW_ZERO_S:g} s's frames: "
                     + advice.format(board=sensor["board"], sid=sid))
    return lines


def _reconstruction(pipeline) -> dict:
    reconstructor = pipeline.reconstructor
    return {
        "level": reconstructor.level,
        "level_reason": reconstructor.level_reason,
        "mounting": reconstructor.mounting,
        "crosstalk": {str(sid): reconstructor.crosstalk_report(sid)
                      for sid, info in pipeline.interpreter.sensors.items() if info.kind == "grid"},
        "errors": {str(sid): error for sid, error in reconstructor.errors().items()},
    }


def _problems(link: dict, sensors: dict, errors: dict, dropping: dict[str, str] | None = None) -> list[str]:
    """Why the status is degraded, one line each (empty when ok). ``dropping``:
    the line of each sensor whose frames are being dropped (_dropping), in
    place of its "stale": its frames come, and are not read."""
    dropping = dropping or {}
    problems = []
    if link["state"] == "stale":  # connected, silent: an error from before it connected is not why
        problems.append(f"link stale: connected, no bytes for {link['silent_s']:g} s")
    elif link["state"] != "up":
        problems.append(f"link {link['state']}" + (f": {link['last_error']}" if link["last_error"] else ""))
    problems += [f"sensor {sid} stale" for sid, sensor in sensors.items()
                 if sensor["stale"] and not sensor.get("retired") and sid not in dropping]
    problems += dropping.values()
    problems += [f"sensor {sid} reconstruction fails: {error['error']} ({error['count']} times)"
                 for sid, error in errors.items() if error["active"]]
    problems += [f"sensor {sid} uses the built-in calibration: its own could not be used ({s['calibration']['problem']})"
                 for sid, s in sensors.items() if (s.get("calibration") or {}).get("problem")]
    problems += [f"sensor {sid}: calibration {refused['id']}, activated in the registry, cannot be used for it "
                 f"({refused['reason']}): not applied, it keeps calibration {refused['kept']}"
                 for sid, s in sensors.items() if (refused := (s.get("calibration") or {}).get("not_applied"))]
    problems += [f"sensor {sid}: taxels {s['calibration']['below_c0']} read below the C0 of calibration "
                 f"{s['calibration']['id']} at the tare: it is not this sensor's as it is now (made on another "
                 "sensor, or C0 drifted), so loaded taxels cannot be told" for sid, s in sensors.items()
                 if (s.get("calibration") or {}).get("below_c0")]
    problems += [f"sensor {sid} is another sensor: {s['replaced']['to']} where {s['replaced']['from']} was; re-tared, "
                 f"it reads with the built-in calibration {s['calibration']['id']}, none being stored for it (calibrate "
                 f"it, or upload its own: PUT /sensors/{s['board']}/{sid}/calibration)" for sid, s in sensors.items()
                 if s.get("replaced") and (s.get("calibration") or {}).get("builtin")]
    problems += [_outside_line(sid, s) for sid, s in sensors.items() if s.get("outside_calibration")]
    problems += [f"sensor {sid}: channels {channels} have no zero (no plausible reading while it "
                 "tared, or one far off the sensor's own level: a fault then): their forces are null until they read "
                 "plausibly" for sid, s in sensors.items() if (channels := _unzeroed_otherwise(s))]
    problems += [f"sensor {sid}: {_outputs(s)} below {'its' if s['kind'] == 'quad' else 'their'} tared zero for "
                 f"{BELOW_ZERO_S:g} s: tared under a load since removed? Tare it again unloaded "
                 f"(POST /sensors/{s['board']}/{sid}/tare)" for sid, s in sensors.items() if s.get("below_zero")]
    problems += [line for sid, s in sensors.items() if s.get("faulty_channels") for line in _fault_lines(sid, s)]
    return problems


# Corrupt frames above this share of the window's are a fault, not the rare error of a long run: a sound link
# corrupts next to nothing (USB bulk transfers are CRC-checked and resent; a 2 Mbaud UART at a bit error rate of
# 1e-9 spoils one 272-byte GRID frame in ~370 000), and 1 % costs a 1 kHz sensor 10 frames a second.
CORRUPT_SHARE = 0.01
CORRUPT_MIN_FRAMES = 5  # and at least this many: one bad frame among a slow board's few (10 at 1 Hz) is no pattern
CORRUPT_SENSORS_NAMED = 3
# Bytes skipped (no part of a good frame) above this share of the window's bytes are a fault: a sound link skips
# only the frame a (re)open cuts and the bytes of corrupt frames (the CRC line's, which this one may repeat); a
# tenth is a link carrying something besides the protocol (a wrong baud rate reads as nearly all garbage, another
# device's output, noise), and every such byte costs the decoder a search.
DISCARDED_SHARE = 0.1
DISCARDED_MIN_BYTES = 4096  # and at least this many: ~4 of the largest frames (1 040 bytes), cut at reopens


def _dropping(interpreter, now: float) -> dict[str, str]:
    """The problem line of each sensor whose data frames were rejected in the last PROBLEM_WINDOW_S, by id."""
    lines = {}
    for sid, drops in sorted(interpreter.drops.items()):
        if count := drops.recent(now):
            lines[str(sid)] = (f"sensor {sid}: {count} frames dropped in the last {drops.window_s:g} s: "
                               f"{drops.latest}")
    return lines


def _board_lines(pipeline, now: float) -> list[str]:
    """The board's ERROR frames, the link's corrupt data frames and its skipped bytes over the last
    PROBLEM_WINDOW_S, a line each."""
    lines = []
    errors = pipeline.interpreter.recent_errors
    if count := errors.recent(now):
        latest = shown_text(pipeline.interpreter.board_errors[-1][1])
        lines.append(f"the board sent {count} ERROR frames in the last {errors.window_s:g} s, the latest: \"{latest}\"")
    corruption = pipeline.corruption
    corrupt = corruption.corrupt.recent(now)
    total = corrupt + corruption.frames.recent(now)
    if corrupt >= CORRUPT_MIN_FRAMES and corrupt > CORRUPT_SHARE * total:
        claimed = sorted(((n, sid) for sid, c in corruption.by_sensor.items() if (n := c.recent(now))), reverse=True)
        named = ", ".join(f"sensor {sid} ({n})" for n, sid in claimed[:CORRUPT_SENSORS_NAMED])
        lines.append(f"{corrupt} of {total} data frames ({_percent(corrupt / total)} %) in the last "
                     f"{corruption.window_s:g} s failed their CRC check and were dropped"
                     f"{f', by their headers from {named}' if named else ''}: a loose cable or connector, electrical "
                     "noise, or a wrong baud rate?")
    return lines + _skipped_line(corruption, now)


def _skipped_line(corruption, now: float) -> list[str]:
    """The link's bytes that were no part of a good frame, a line when they are a large share of the window's."""
    skipped, received = corruption.discarded.recent(now), corruption.bytes_in.recent(now)
    if skipped < DISCARDED_MIN_BYTES or skipped <= DISCARDED_SHARE * received:
        return []
    return [f"{skipped} of {received} bytes ({_percent(skipped / received)} %) received in the last "
            f"{corruption.window_s:g} s were no part of a good frame and were skipped: a wrong baud rate, another "
            "device's output on this port, or electrical noise?"]


def _identify_lines(pipeline, now: float) -> list[str]:
    """What the waits for the board's INFO found (identify.py; a replay's, as its live link's did), a line each."""
    if pipeline.identification is None:
        return []
    return _unidentified_line(pipeline) + _info_wait_line(pipeline, now)


def _unidentified_line(pipeline) -> list[str]:
    """A board read without having said what it is (Interpreter.unidentified), a line while it lasts."""
    why = pipeline.interpreter.unidentified
    if why is None:
        return []
    after = "its link opened" if why == "opened" else "it restarted"
    board = pipeline.interpreter.board
    serial = f" (serial {shown_text(str(board['serial']))})" if board.get("serial") else ""
    read = (f"as the board that was there before{serial}, on its sensors' zeros" if board
            else "from their sizes alone (no INFO came), on the zeros its sensors took")
    return [f"the board did not answer INFO? within {pipeline.identification.wait_s:.2f} s after {after}: its frames "
            f"are read {read}, flagged unidentified, until its INFO comes"]


def _info_wait_line(pipeline, now: float) -> list[str]:
    """The board's restarts with their power-up INFO lost and its waits for INFO that ended without it, one
    line while any was in the last PROBLEM_WINDOW_S: each is a fault (a board sends INFO at power-up and
    answers INFO?), and each cost its frames a wait."""
    waits, wait_s = pipeline.info_waits, pipeline.identification.wait_s
    restarts, unanswered = waits.restarts.recent(now), waits.unanswered.recent(now)
    did = ([f"restarted {_times(restarts)} with its power-up INFO lost"] if restarts else []) + (
        [f"left {unanswered} INFO? unanswered within {wait_s:.2f} s"] if unanswered else [])
    if not did:
        return []
    went = ("its frames went on without it, flagged unidentified" if unanswered
            else f"its frames waited up to {wait_s:.2f} s for its INFO each time")
    cause = "; a board that restarts by itself: its power supply, a watchdog, its firmware?" if restarts else ""
    return [f"the board {' and '.join(did)} in the last {waits.window_s:g} s: {went}{cause}"]


def _times(count: int) -> str:
    return "once" if count == 1 else f"{count} times"


def _percent(share: float) -> str:
    """``share`` (0..1) in per cent to 2 digits: 1.5, 19, 100."""
    return f"{100 * share:.0f}" if share >= 0.1 else f"{100 * share:.2g}"


def _unzeroed_otherwise(sensor: dict) -> list[int]:
    """The channels without a zero that ``outside_calibration`` does not name (its own line says why)."""
    named = set((sensor.get("outside_calibration") or {}).get("channels", ()))
    return [c for c in sensor.get("unzeroed_channels") or () if c not in named]


def _outside_line(sid: str, sensor: dict) -> str:
    """The problem line of a sensor whose readings lie outside what its calibration's C0 lets a tare take."""
    out = sensor["outside_calibration"]
    noun = "electrodes" if sensor["kind"] == "quad" else "taxels"
    named = (f"all {len(out['channels'])} {noun}" if len(out["channels"]) == sensor["rows"] * sensor["cols"]
             else f"{noun} {out['channels']}")
    (low, high), (w_low, w_high), (c_low, c_high) = out["read_pF"], out["window_pF"], out["c0_pF"]
    upload = f"PUT /sensors/{sensor['board']}/{sid}/calibration"
    if out["measured"]:
        whose = "its C0 measured"
        advice = f"a fault, or the calibration is not this sensor's: calibrate it again, or upload its own ({upload})"
    else:
        whose = "the papers' C0, not measured on this sensor"
        advice = f"calibrate the sensor, or upload its calibration with its measured C0 (c0_pF: {upload})"
    return (f"sensor {sid}: {named} read {_span(low, high)} pF, outside the {_span(w_low, w_high)} pF a tare takes "
            f"with calibration {out['calibration']} ({whose}: {_span(c_low, c_high)} pF): no zero, their forces "
            f"stay null; {advice}, and it tares at its first reading inside")


def _span(low: float, high: float) -> str:
    """``low–high`` to 3 digits, one number when they read alike."""
    low_text, high_text = f"{low:.3g}", f"{high:.3g}"
    return low_text if low_text == high_text else f"{low_text}–{high_text}"


def _info_problems(interpreter, sensors: dict, dropping: dict[str, str]) -> list[str]:
    """What the board's INFO got wrong: an INFO refused as a whole, sensors
    that send data although it does not list them while it had room to (a
    full one: _notes), and sensors it leaves undescribed, whether they send
    data or nothing readable (those whose frames come and are dropped:
    ``dropping``'s lines)."""
    problems = [f"sensor {sid} sends data but the board's INFO {s.get('info_problem') or 'does not list it'} "
                "(its shape is taken from its frames)" for sid, s in sensors.items()
                if s.get("not_in_info") and not s["stale"] and (s.get("info_problem") or not interpreter.info_full)]
    problems += [f"the board's last INFO was refused ({interpreter.info_refused}); the description before it "
                 "stays in force"] if interpreter.info_refused else []
    return problems + [f"sensor {sid}: the board's INFO {why}; its frames are read only where their size tells "
                       "an 8x8 grid or a quad" for sid, why in sorted(interpreter.undescribed.items())
                       if str(sid) not in sensors and str(sid) not in dropping and not why.startswith(UNKNOWN_KIND)]


def _notes(interpreter, sensors: dict) -> list[str]:
    """What /health tells that is no fault: the sensors a full INFO could not list, read from their frames."""
    if not interpreter.info_full:
        return []
    taken = [sid for sid, s in sensors.items() if s["not_in_info"] and not s["retired"] and not s["info_problem"]]
    size, entries = interpreter.info_size
    return [f"the board's INFO is full ({size} of {MAX_PAYLOAD} bytes, listing {entries} sensors): {len(taken)} more "
            "sensors were taken from their data frames (a QUAD frame is a quad, a 256-byte GRID frame an 8x8 grid)"
            ] if taken else []


def _shared_serials(boards) -> list[str]:
    """A problem per serial that several boards' INFO report: a serial names one board, and its sensors'
    calibrations and load-cycle counts are stored under it (a firmware's default serial, a cloned board)."""
    by_serial: dict[str, list[str]] = {}
    for board in boards:
        interpreter = board.pipeline.interpreter if isinstance(board, Board) else None
        serial = interpreter.board.get("serial") if interpreter is not None else None
        # Sensors with serials of their own are keyed by them: only those without share the board's.
        if serial and any(not info.serial for info in interpreter.sensors.values()):
            by_serial.setdefault(str(serial), []).append(board.name)
    return [f"boards {', '.join(names)} report one serial {serial!r}: their sensors' calibrations and load-cycle "
            "counts are kept under it, shared (a firmware's default serial? give each board its own)"
            for serial, names in by_serial.items() if len(names) > 1]


def _outputs(sensor: dict) -> str:
    """What reads below zero, for a problem line."""
    if sensor["kind"] == "quad":
        return "its normal force reads"
    return f"taxels {sensor['below_zero']} read"


BOARD_FIELDS = ("link", "level", "stream", "rejected", "board_errors", "sensors", "reconstruction", "clock")


def board_health(board, now: float, book=None) -> dict:
    """One board's part of /health (``board``: a board.Board)."""
    pipeline = board.pipeline
    counters = pipeline.decoder.counters.as_dict()
    link = board.readout.link if board.readout is not None else LinkState(board.source)
    stale_after = stale_after_s(pipeline.interpreter.board)
    link_state = link.as_dict(now, stale_after)
    sensors = _sensors(pipeline, now, counters, stale_after, book)
    reconstruction = _reconstruction(pipeline)
    dropping = _dropping(pipeline.interpreter, now)
    problems = (_problems(link_state, sensors, reconstruction["errors"], dropping) + _board_lines(pipeline, now)
                + _identify_lines(pipeline, now) + _info_problems(pipeline.interpreter, sensors, dropping))
    return {
        "source": board.source,
        "info": pipeline.interpreter.board,
        "status": "ok" if not problems else "degraded",
        "problems": problems,
        "notes": _notes(pipeline.interpreter, sensors),
        "link": link_state,
        "level": pipeline.reconstructor.level,
        "stream": {k: v for k, v in counters.items() if k != "sensors"},
        "rejected": dict(pipeline.interpreter.rejected),
        "board_errors": [{"t_host": t, "text": text} for t, text in pipeline.interpreter.board_errors],
        "board_error_count": pipeline.interpreter.board_error_count,
        "sensors": sensors,
        "reconstruction": reconstruction,
        "clock": None if pipeline.clock is None else pipeline.clock.status(),
        "replay": board.source.startswith("replay://"),
    }


def health_report(service) -> dict:
    """``service``: a live_service.TactileService (or a gateway's, whose
    remote boards say their own part). Each board's part is under
    ``boards``; a one-board service also has it at the top level, as before
    boards were named; with several, the top level's ``sensors`` are keyed
    by address (board/id) and each problem names its board."""
    now = time.time()
    book = getattr(service, "calibrations", None)
    boards = {board.name: board_health(board, now, book) if isinstance(board, Board) else board.health_part(now)
              for board in service.all_boards}
    several = len(boards) > 1
    problems = [(f"board {name}: " if several else "") + problem
                for name, part in boards.items() for problem in part["problems"]]
    problems += book.problems if book is not None else []
    problems += _shared_serials(service.all_boards)
    report = {
        "status": "ok" if not problems else "degraded",
        "problems": problems,
        "notes": [(f"board {name}: " if several else "") + note for name, part in boards.items()
                  for note in part.get("notes", ())],
        "uptime_s": round(now - service.started_at, 1),
        "boards": boards,
        "websocket_clients": len(service.hub.subscribers),
        "latency": {
            "published": service.published_latency.summary(),
            **{f"sent_{kind}": meter.summary() for kind, meter in service.hub.sent_latency.items()},
        },
        "scheduling": service.scheduling.as_dict(),
        "frames_published": service.hub.frames_published,
        "replay": bool(boards) and all(part["replay"] for part in boards.values()),
        "recording": None if service.recorder is None else service.recorder.status(),
        "zenoh": None if getattr(service, "zenoh", None) is None else service.zenoh.status(),
    }
    if several:
        report["sensors"] = {f"{name}/{sid}": sensor for name, part in boards.items()
                             for sid, sensor in part["sensors"].items()}
    elif boards:
        report.update({key: next(iter(boards.values()))[key] for key in BOARD_FIELDS})
    else:
        report["sensors"] = {}  # a gateway that has heard of no board yet
    return report

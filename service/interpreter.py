"""Frames → readings: the board description INFO keeps, and data frames
in picofarads.

The decoder only checks the protocol envelope. The interpreter knows what
the payloads mean: INFO describes the board's sensors (grid shape, kind),
ERROR carries board text, and GRID/QUAD payloads become readings
(readings.py), a read's frames of one size in one numpy call.
"""
from __future__ import annotations

import logging
import math
import time
from collections import deque
from dataclasses import replace

import numpy as np
import orjson

from .board_info import UNKNOWN_KIND, UNNAMED_BOARD, default_sensor, info_is_full, name_from_info, parse_info
from .protocol import Frame, FrameType
from .readings import AF_PER_PF, OPEN_SENTINEL, SHORT_SENTINEL, Reading, SensorInfo
from .recent import RecentCount

log = logging.getLogger(__name__)
ERROR_LOG_PERIOD_S = 60.0  # a board's ERROR texts reach the log at most this often (all are in /health)
ERROR_LOG_CHARS = 200


def shown_text(text: str) -> str:
    """A board's text for a log or a problem line: escaped (a board must not write control sequences to a
    terminal or fake log lines), its first ERROR_LOG_CHARS characters."""
    shown = "".join(c if c.isprintable() else f"\\x{ord(c):02x}" for c in text[:ERROR_LOG_CHARS])
    return shown + ("…" if len(text) > ERROR_LOG_CHARS else "")


class Interpreter:
    """Keeps the board description and turns data frames into readings.

    Every SensorInfo it makes carries the board's name: ``board_name`` when
    given (``--source NAME=URL``), else settled once, at the first valid
    INFO, by ``name_board`` (default: name_from_info) and kept thereafter,
    so that a sensor's address does not change under its clients; until
    then ``board``."""

    def __init__(self, clock=time.time, board_name: str | None = None, name_board=name_from_info) -> None:
        self.board_name = board_name
        self.unnamed = UNNAMED_BOARD  # the name until one is settled (a service of several boards makes it unique)
        self.name_board = name_board
        self.board: dict = {}  # INFO's top-level fields (board, fw, serial, rate_hz, ...)
        # Sensors with a data frame since the board last restarted (all that sent, before any restart): one
        # not among them after a restart whose INFO does not list it is gone; an INFO alone (a reply to INFO?)
        # is no restart.
        self.sent_since_restart: set[int] = set()
        self._restart_clears = False  # an INFO came: the next frame flagged board_restart begins a new set
        self.sensors: dict[int, SensorInfo] = {}
        self.board_errors: deque[tuple[float, str]] = deque(maxlen=50)
        self._error_logged_at: float | None = None  # monotonic time of the last board error logged
        self.board_error_count = 0  # ERROR frames ever (board_errors keeps the last 50)
        self._errors_unlogged = 0
        self.recent_errors = RecentCount()  # ERROR frames over the last PROBLEM_WINDOW_S (/health)
        self.drops: dict[int, RecentCount] = {}  # data frames rejected by sensor, over the last seconds; latest: why
        self.rejected = {"info_invalid": 0, "shape_mismatch": 0, "unknown_shape": 0}
        self._listed: set[int] = set()  # the sensors the INFO in force describes
        self._ever_listed: set[int] = set()  # the sensors any INFO described
        self.undescribed: dict[int, str] = {}  # sensors the INFO in force names but leaves undescribed: why
        # Sensors whose data frames the INFO in force (its document) could not read, and those of them not yet
        # taken by ``newly_unreadable``: asking INFO? again brings the same answer, so each is asked for once.
        self._unreadable: set[int] = set()
        self._unreadable_new: list[int] = []
        self._info_doc: dict | None = None
        self.info_refused: str | None = None  # why the last INFO was invalid as a whole (None: it was taken)
        self.info_size = (0, 0)  # the INFO in force: (payload bytes, sensor entries)
        self._swapped_to: str | None = None  # the board that replaced the first on this link (its serial or model)
        self._fits: dict[int, tuple] = {}  # sensor → (its info, the frame type and size that fitted it): interpret_many
        self._clock = clock
        # Why the board's frames are read without its INFO, set by the pipeline when frames held for it went on
        # without one: "opened" (its link opened) or "restarted" (its power-up INFO lost); None from its next
        # valid INFO. Every reading made meanwhile is flagged ``unidentified``.
        self.unidentified: str | None = None

    @property
    def name(self) -> str:
        """The board's name (``unnamed`` until one is settled)."""
        return self.board_name or self.unnamed

    @property
    def unlisted(self) -> list[int]:
        """Sensors that send data although the board's INFO in force does not
        list them (their shape taken from their frames, or from an older
        INFO); none before any INFO."""
        return sorted(set(self.sensors) - self._listed) if self.board else []

    @property
    def info_full(self) -> bool:
        """Whether the INFO in force had no room to list another sensor (board_info.info_is_full)."""
        return bool(self.board) and info_is_full(*self.info_size)

    @property
    def dropped(self) -> list[int]:
        """Sensors an earlier INFO listed and the one in force does not (the board removed them)."""
        return sorted(self._ever_listed - self._listed)

    def interpret(self, frame: Frame, t_host: float | None = None) -> Reading | None:
        """Return a reading for a data frame, or None for INFO/ERROR frames and
        for data frames whose payload does not fit the announced sensor."""
        t_host = self._clock() if t_host is None else t_host
        info = self._sensor_for(frame, t_host)
        if info is None:
            return None
        if frame.board_restart and self._restart_clears:
            self.sent_since_restart.clear()
            self._restart_clears = False
        self.sent_since_restart.add(info.id)
        raw = np.frombuffer(frame.payload, dtype="<u4")
        capacitance = raw / AF_PER_PF
        # The two sentinels are the ends of the u32 range: one wrapped compare finds both.
        sentinel = (raw - np.uint32(SHORT_SENTINEL + 1)) >= np.uint32(OPEN_SENTINEL - 1)
        opened = shorted = False
        if np.count_nonzero(sentinel):  # ndarray.any() costs 5x more at this size
            capacitance[sentinel] = np.nan
            opened = bool((raw == OPEN_SENTINEL).any())
            shorted = bool((raw == SHORT_SENTINEL).any())
        return Reading(info, frame.seq, frame.t_us, t_host, frame.flags, frame.gap, capacitance, opened, shorted,
                       frame.board_restart, unidentified=self.unidentified is not None)

    def interpret_many(self, frames: list[Frame], t_host: float, clock=None) -> list[Reading]:
        """``interpret`` of each frame, in order, None left out: the same
        decisions and values, but the channels of all data frames of one
        size (a read's grids, its quads) converted by one numpy call each,
        not one per frame — at 1 kHz the per-call cost is what a frame
        costs. Each reading's ``capacitance_pF`` is a row of its group's array.
        ``clock`` (clock_map.ClockMap): the frames are one read received at
        ``t_host``, and each reading gets its scan's host time from it, flagged
        ``clock_suspect`` when the map cannot tell a stall from a clock step."""
        accepted: list[tuple[SensorInfo, Frame]] = []
        groups: dict[int, list[int]] = {}  # payload bytes → indices into accepted
        sensors, fits, since = self.sensors, self._fits, self.sent_since_restart
        restart = False
        unidentified = math.inf if self.unidentified else 0  # accepted frames read before the board's INFO came
        for frame in frames:
            ftype, sensor, _, _, _, payload, _, board_restart = frame
            size = len(payload)
            # The usual frame: of the same type and size as its sensor's last, which is still announced as it was.
            fit = fits.get(sensor)
            if fit is not None and fit[1] == ftype and fit[2] == size and sensors.get(sensor) is fit[0]:
                info = fit[0]
            else:
                info = self._sensor_for(frame, t_host)
                if info is None:
                    if self.unidentified is None:  # none came, or the board's INFO: the frames after it are its
                        unidentified = min(unidentified, len(accepted))
                    continue
                fits[sensor] = (info, ftype, size)
            group = groups.get(size)
            if group is None:
                group = groups[size] = []
            group.append(len(accepted))
            accepted.append((info, frame))
            if board_restart and self._restart_clears:
                since.clear()  # in place: health reads the same set
                self._restart_clears = False
            if sensor not in since:
                since.add(sensor)
            restart = restart or board_restart
        if not accepted:
            return []
        suspect = False
        if clock is None:
            scans = [math.nan] * len(accepted)
        else:
            if restart:
                clock.restart()
            scans = clock.scan_times([frame[4] for _, frame in accepted], t_host)
            suspect = clock.suspect
        out: list[Reading | None] = [None] * len(accepted)
        for size, indices in groups.items():
            raw = np.frombuffer(b"".join([accepted[i][1][5] for i in indices]), dtype="<u4")
            raw = raw.reshape(len(indices), size // 4)
            capacitance = raw / AF_PER_PF
            sentinel = (raw - np.uint32(SHORT_SENTINEL + 1)) >= np.uint32(OPEN_SENTINEL - 1)
            opened = shorted = [False] * len(indices)
            if np.count_nonzero(sentinel):
                capacitance[sentinel] = np.nan
                opened = (raw == OPEN_SENTINEL).any(axis=1).tolist()
                shorted = (raw == SHORT_SENTINEL).any(axis=1).tolist()
            for i, row, o, s in zip(indices, capacitance, opened, shorted):
                info, (_, _, flags, seq, t_us, _, gap, board_restart) = accepted[i]
                out[i] = Reading(info, seq, t_us, t_host, flags, gap, row, o, s, board_restart, scans[i], suspect,
                                 i < unidentified)
        return out

    def _log_board_error(self, text: str) -> None:
        """Log a board's ERROR text, escaped (a board must not write control
        sequences to a terminal or fake log lines) and at most once per
        ERROR_LOG_PERIOD_S of this process's time (a board sending one every
        5 ms wrote 370 KB/s of log; a replay's reads may all have one
        stamp), saying how many were not logged since; /health counts them all."""
        now = time.monotonic()
        if self._error_logged_at is not None and now - self._error_logged_at < ERROR_LOG_PERIOD_S:
            self._errors_unlogged += 1
            return
        more = f" ({self._errors_unlogged} more since the last logged, in /health)" if self._errors_unlogged else ""
        log.warning("board error: %s%s", shown_text(text), more)
        self._error_logged_at, self._errors_unlogged = now, 0

    def _sensor_for(self, frame: Frame, t_host: float) -> SensorInfo | None:
        """The sensor a data frame fits; None, having taken in an INFO or
        ERROR frame or counted a rejected data frame, otherwise."""
        if frame.type == FrameType.INFO:
            self._on_info(frame.payload)
            self._restart_clears = True
            return None
        if frame.type == FrameType.ERROR:
            text = frame.payload.decode("utf-8", errors="replace")
            self.board_errors.append((t_host, text))
            self.board_error_count += 1
            self.recent_errors.add(t_host)
            self._log_board_error(text)
            return None
        info = self.sensors.get(frame.sensor)
        if info is None:
            # Every id the protocol allows (a board of more sensors than its INFO can list): what bounds their
            # memory is the history budget they share, not a count of sensors (docs/scale.md).
            info = default_sensor(frame.sensor, frame)
            if info is None:
                self.rejected["unknown_shape"] += 1
                why = self.undescribed.get(frame.sensor, "does not describe it")
                if not why.startswith(UNKNOWN_KIND):  # a board's other sensor (a thermistor): its frames are not ours
                    self._unreadable_by(frame.sensor)
                    told = f"the board's INFO {why}" if self.board else "no INFO came"
                    self._drop(frame, t_host, f"{len(frame.payload)}-byte GRID frames, and {told} (without a "
                               "description only a 256-byte GRID frame is read, as an 8x8 grid)")
                return None
            info = replace(info, board=self.name, board_identity=self._swapped_to, board_info=self.board)
            self.sensors[frame.sensor] = info
        expected_kind = "grid" if frame.type == FrameType.GRID else "quad"
        if info.kind != expected_kind or len(frame.payload) != 4 * info.channels:
            self.rejected["shape_mismatch"] += 1
            self._unreadable_by(frame.sensor)
            told = "the board's INFO describes" if frame.sensor in self._listed else "it was taken as"
            shape = "a quad" if info.kind == "quad" else f"a {info.rows}x{info.cols} grid"
            self._drop(frame, t_host, f"{len(frame.payload)}-byte {FrameType(frame.type).name} frames where {told} "
                       f"{shape} ({4 * info.channels} bytes)")
            return None
        return info

    def _unreadable_by(self, sensor: int) -> None:
        """A data frame of ``sensor`` the INFO in force could not read (another shape, or none known)."""
        if sensor not in self._unreadable:
            self._unreadable.add(sensor)
            self._unreadable_new.append(sensor)

    def newly_unreadable(self) -> list[int]:
        """Sensors whose data frames the INFO in force first could not read since the last call (its INFO may
        have been lost: worth an INFO?), each once per INFO in force; not a sensor the INFO leaves undescribed
        for a kind this service does not read (a thermistor: UNKNOWN_KIND)."""
        new, self._unreadable_new = self._unreadable_new, []
        return new

    def _drop(self, frame: Frame, t_host: float, why: str) -> None:
        """Count a data frame rejected, under its sensor, with why (/health names the sensor while it lasts)."""
        drops = self.drops.get(frame.sensor)
        if drops is None:
            drops = self.drops[frame.sensor] = RecentCount()
        drops.add(t_host, latest=why)

    def info_document(self) -> dict | None:
        """The INFO in force as a document (its fields and the sensors it
        lists), None before any: what a recording begun now stores, since its
        bytes will not hold it (a 4x4 grid is not told from its frames)."""
        if not self.board:
            return None
        described = [{"id": sid, "kind": info.kind, "rows": info.rows, "cols": info.cols,
                      **({"serial": info.serial} if info.serial else {})} for sid, info in sorted(self.sensors.items())]
        return {**self.board, "sensors": [d for d in described if d["id"] in self._listed],
                "unlisted": [d for d in described if d["id"] not in self._listed],  # shapes from an older INFO or frames
                "info_size": list(self.info_size)}  # its bytes, which this document's do not tell: info_full

    def preset_info(self, document: dict) -> None:
        """Take ``info_document``'s document as the INFO in force (a replay
        of a recording begun mid-stream, before its first frame), with the
        shapes of the sensors it did not list."""
        self._on_info(orjson.dumps({k: v for k, v in document.items() if k not in ("unlisted", "info_size")}))
        size = document.get("info_size")  # not in older recordings
        if isinstance(size, list) and len(size) == 2 and all(type(n) is int for n in size):
            self.info_size = (size[0], size[1])
        _, unlisted, _ = parse_info(orjson.dumps({"sensors": document.get("unlisted", [])}))
        for sid, info in unlisted.items():
            self.sensors.setdefault(sid, replace(info, board=self.board_name, board_identity=self._swapped_to,
                                                 board_info=self.board))

    def _on_info(self, payload: bytes) -> None:
        try:
            doc, sensors, undescribed = parse_info(payload)
        except ValueError as exc:
            self.rejected["info_invalid"] += 1
            self.info_refused = str(exc)
            log.warning("ignoring INFO frame: %s", exc)
            return
        self.info_refused = None
        self.unidentified = None
        if doc != self._info_doc:  # another INFO in force (not the same again, as a reply to INFO? may be)
            self._info_doc, self._unreadable, self._unreadable_new = doc, set(), []
        self.info_size = (len(payload), len(doc.get("sensors", [])))
        board = {k: v for k, v in doc.items() if k != "sensors"}
        identity, before = board.get("serial") or board.get("board"), self.board.get("serial") or self.board.get("board")
        if self.board and identity != before:
            log.warning("board %s: INFO now describes board %r (was %r): its sensors without a serial of their own "
                        "are new sensors, tared afresh; those it does not list are gone", self.name, identity, before)
            self._swapped_to = identity
            for sid in [sid for sid in self.sensors if sid not in sensors]:  # in place: interpret_many holds the dict
                del self.sensors[sid]
                self._fits.pop(sid, None)
        self.board = board
        if self.board_name is None:
            self.board_name = self.name_board(self.board)
        self.sensors.update({sid: replace(info, board=self.board_name,
                                          board_identity=None if info.serial else self._swapped_to, board_info=board)
                             for sid, info in sensors.items()})
        self._listed = set(sensors)
        self._ever_listed |= self._listed
        self.undescribed = undescribed

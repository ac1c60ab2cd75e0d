"""pyserial handler for ``replay://PATH[?speed=1|2|max][&board=NAME]``: a recording as a port
(``board``: one board of a recording of several).

``tactile replay FILE --serve`` serves the API and dashboard from a
recording through exactly the live code path: the readout thread opens
this URL like a device. Reads release the recording's bytes paced by their
recorded times, stamped with them on the replay's timeline (``read_time``); at the end the port stays open and silent (like a board
that stopped), and ``/health`` shows the replay:// source.
"""
from __future__ import annotations

import threading
import time
import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from ..record.mcap_reader import boards_in, read_baselines, read_changes, read_numbered, read_settings
from ..record.pacing import Pacer, Timeline, parse_speed
from ..record.readers import is_timed_by_host, timed_chunks
from ..record.resume import lost_start


def parse_replay_url(url: str) -> tuple[str, float, str | None]:
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "replay":
        raise ValueError(f"expected a replay:// URL, got {url!r}")
    path = urllib.parse.unquote(parts.netloc + parts.path)
    options = urllib.parse.parse_qs(parts.query)
    unknown = set(options) - {"speed", "board"}
    if unknown:
        raise ValueError(f"replay:// takes only 'speed' and 'board', not {sorted(unknown)}")
    try:
        speed = parse_speed(options.get("speed", ["1"])[-1])
    except ValueError as exc:
        raise ValueError(f"replay:// {exc}") from None
    return path, speed, options.get("board", [None])[-1]


def check_url(url: str) -> None:
    """ValueError for a bad option, a missing recording or one that is not
    what its suffix says."""
    path, _, board = parse_replay_url(url)
    try:
        timed_chunks(path, board=board)
    except FileNotFoundError:
        raise ValueError(f"{url!r}: no such recording: {path}") from None


def _recording(url: str) -> tuple[str, str | None] | None:
    """(MCAP path, the board this port streams: the recording's only one when
    the URL names none, named or not); None for a raw capture."""
    path, _, board = parse_replay_url(url)
    if not is_timed_by_host(path):
        return None
    return path, board if board is not None else next(iter(boards_in(path)), None)


def recorded_start(url: str) -> tuple[int, dict | None]:
    """(the URL's recording's first read of its board, the point its replay
    begins at when the reads before that were lost: record/resume.py)."""
    recording = _recording(url)
    return (0, None) if recording is None else lost_start(*recording)


def recorded_baselines(url: str) -> dict:
    """How the URL's recording began on a running service: {"board": the
    board's name then, "sensors": the zeros in force (reconstructor.
    preset_baselines)}, or where its replay begins after its first reads
    were lost, with "after_reads"; empty for one that began with its
    stream, or a raw capture."""
    recording = _recording(url)
    if recording is None:
        return {}
    _, resumed = lost_start(*recording)
    return resumed or read_baselines(recording[0]).get(recording[1], {})


def recorded_identification(url: str) -> dict | None:
    """The URL's recording's frames' wait for the board's INFO where its
    replay begins (Identification.state: pipeline.identify_as_recorded);
    None for a recording made without one (or before 2026-11-25), a raw capture."""
    recording = _recording(url)
    if recording is None:
        return None
    _, resumed = lost_start(*recording)
    return (resumed if resumed else read_settings(recording[0]).get(recording[1], {})).get("identify")


def recorded_changes(url: str) -> list[tuple[int, int | None, bool | dict | str]]:
    """The tares made, calibrations set and the link's events while the
    URL's recording was made, as (offset in the bytes this port streams,
    sensor id, change: Pipeline.redo): the read each took effect before,
    placed by the raw channel's read numbers (pipeline.schedule_recorded).
    A raw capture has none."""
    recording = _recording(url)
    if recording is None:
        return []
    path, board = recording
    _, resumed = lost_start(path, board)
    begin = resumed["after_reads"] if resumed else 0  # an earlier tare is in the zeros it begins with
    changes = [(max(n, begin), sensor, change) for n, sensor, change in read_changes(path).get(board, [])
               if n >= begin or isinstance(change, dict)]
    if not changes:
        return []
    out, position = [], 0
    for name, number, _, data in read_numbered(path):
        if name != board or number < begin:
            continue
        while changes and changes[0][0] <= number:
            _, sensor, change = changes.pop(0)
            out.append((position, sensor, change))
        position += len(data)
    return out + [(position, sensor, change) for _, sensor, change in changes]


class Serial(SerialBase):
    """A recording behind a pyserial port; commands written to it are ignored."""

    def __init__(self, *args, **kwargs) -> None:
        self._chunks = None
        self._pending = bytearray()
        self._lock = threading.Lock()
        self.finished = False
        self.read_time: float | None = None  # the last chunk's recorded time on the replay's timeline (Source.read_time)
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        try:
            path, speed, board = parse_replay_url(self.portstr)
            resumed = recorded_start(self.portstr)[1]
            self._chunks = iter(timed_chunks(path, board=board, from_read=resumed["after_reads"] if resumed else 0))
        except (ValueError, OSError) as exc:
            raise SerialException(str(exc)) from None
        self._pacer, self._timeline = Pacer(speed), Timeline(speed)
        self.is_open = True

    def close(self) -> None:
        self.is_open = False
        super().close()

    def _reconfigure_port(self) -> None:
        """Nothing to configure on a recording."""

    @property
    def in_waiting(self) -> int:
        return len(self._pending)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            if not self._pending and not self.finished:
                try:
                    t_recorded, chunk = next(self._chunks)
                except StopIteration:
                    self.finished = True
                except (ValueError, OSError) as exc:  # a port reports a failed read as a SerialException
                    raise SerialException(str(exc)) from None
                else:
                    self._pacer.wait(t_recorded)
                    self.read_time = self._timeline.at(t_recorded)
                    self._pending += chunk
            if not self._pending and self.finished and self._timeout:
                time.sleep(self._timeout)
            data = bytes(self._pending[:size])
            del self._pending[:size]
        return data

    def write(self, data: bytes) -> int:
        return len(data)

    def reset_input_buffer(self) -> None:
        self._pending.clear()

    def reset_output_buffer(self) -> None:
        """Nothing is ever sent to a recording."""

    def _update_break_state(self) -> None:
        """No lines on a recording."""

    def _update_rts_state(self) -> None:
        """No lines on a recording."""

    def _update_dtr_state(self) -> None:
        """No lines on a recording."""

"""The board's side of a session: one grid's capacitance on the board clock.

Reads a raw capture (.bin, any suffix) or an MCAP recording (.mcap) through
the same decoder and interpreter as live data (not the reconstruction: the
calibration works on capacitance). Board times are the frames' ``t_us``,
unwrapped (it wraps every 2³² µs); a board restart inside the session
(its clock steps back) is an error, since the session's clock would no
longer be one line.
"""
from __future__ import annotations

import hashlib
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..protocol import FLAG_SATURATED, T_US_MODULUS, FrameType
from ..protocol_decoder import Decoder
from ..interpreter import Interpreter
from ..readings import AF_PER_PF, OPEN_SENTINEL, SHORT_SENTINEL, SensorInfo
from ..record.readers import is_timed_by_host, timed_chunks
from .dead_taxels import dead_taxels

READ_BYTES = 1 << 20


@dataclass
class BoardSession:
    """One grid over a session. ``t_s`` (n,) board seconds, unwrapped and
    increasing; ``capacitance_pF`` (n, rows*cols), NaN for sentinels;
    ``saturated`` (n,) the board's saturation flag per frame; ``dead`` why
    each channel with no usable reading all session is dead (dead_taxels.py;
    its column is all NaN)."""

    path: str
    sha256: str
    info: SensorInfo
    board: dict
    t_s: np.ndarray
    capacitance_pF: np.ndarray
    saturated: np.ndarray
    dead: dict[int, str]

    @property
    def rate_hz(self) -> float:
        return (len(self.t_s) - 1) / (self.t_s[-1] - self.t_s[0])


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as source:
        while block := source.read(1 << 20):
            digest.update(block)
    return digest.hexdigest()


def _pick(sensors: dict[int, SensorInfo], sensor_id: int | None, path: str, kind: str) -> SensorInfo:
    mine = {sid: info for sid, info in sensors.items() if info.kind == kind}
    if sensor_id is not None:
        if sensor_id not in mine:
            raise ValueError(f"{path}: no {kind} sensor {sensor_id} in the session ({kind}s: {sorted(mine) or 'none'})")
        return mine[sensor_id]
    if len(mine) != 1:
        raise ValueError(f"{path}: {len(mine)} {kind} sensors in the session; name one with --sensor "
                         f"({kind}s: {sorted(mine)})" if mine else f"{path}: no {kind} sensor in the session")
    return next(iter(mine.values()))


def _chunks(path: str, board: str | None = None):
    """The file's bytes in order: a recording's reads (``board``'s, in a
    recording of several), or a raw capture read straight (its reader would
    decode every chunk once more to time it, and the calibration needs no
    receive times)."""
    if is_timed_by_host(path):
        yield from (chunk for _, chunk in timed_chunks(path, paced=False, board=board))  # no time wanted
        return
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    with open(path, "rb") as source:
        while block := source.read(READ_BYTES):
            yield block


DATA = (FrameType.GRID, FrameType.QUAD)


def _frames(path: str, board: str | None = None) -> tuple[Interpreter, list]:
    """Every data frame as (sensor, t_us, flags, payload, board_restart, type);
    INFO and ERROR frames go to the interpreter (the board's description).
    Data frames skip the interpreter (one array per frame would cost as much
    as decoding); their payloads become one array at the end."""
    decoder, interpreter = Decoder(), Interpreter(clock=lambda: 0.0, board_name=board)
    frames = []
    for chunk in _chunks(path, board):
        for frame in decoder.feed(chunk):
            if frame.type in DATA:
                frames.append((frame.sensor, frame.t_us, frame.flags, frame.payload, frame.board_restart, frame.type))
            elif frame.type in (FrameType.INFO, FrameType.ERROR):
                interpreter.interpret(frame, 0.0)
    for frame in decoder.finish():
        if frame.type in DATA:
            frames.append((frame.sensor, frame.t_us, frame.flags, frame.payload, frame.board_restart, frame.type))
    return interpreter, frames


def _too_few(path: str, info: SensorInfo, kind: str, used: int, sizes: list[int], announced: bool) -> str:
    """Why a session has too few frames of its sensor: most often its frames
    are of another shape than INFO (or, without INFO, the protocol's 8x8)
    says, and that, not their number, is what to name."""
    other = Counter(size for size in sizes if size != 4 * info.channels)
    if not other:
        return f"{path}: only {used} frames of {kind} sensor {info.id}; a session needs far more"
    size, count = other.most_common(1)[0]
    said = (f"its INFO announces {info.rows}x{info.cols} ({4 * info.channels} bytes): the INFO and the frames "
            "are not of the same sensor" if announced else
            "no INFO announces it, and a grid without one is read as the protocol's 8x8 (256 bytes): capture the "
            "board's INFO with the session (it answers INFO?)")
    return (f"{path}: {count} frames of {kind} sensor {info.id} carry {size}-byte payloads ({size // 4} channels), "
            f"but {said}; {used} frames fit")


def load_session(path: str | Path, sensor_id: int | None = None, kind: str = "grid",
                 board: str | None = None) -> BoardSession:
    """The frames of one ``kind`` sensor (``sensor_id``, or the only one of
    that kind); a sensor announced by no INFO is taken from its frames (a
    grid as 8x8 when its payload is 256 bytes). ``board``: the board's name
    in the service (its sensors' registry keys carry it: docs/scale.md), and
    which board's bytes to take from a recording of several."""
    path = str(path)
    interpreter, frames = _frames(path, board)
    sensors = dict(interpreter.sensors)
    seen = {f[0]: f[5] for f in frames}  # each sensor's frame type
    for sid in set(seen) - set(sensors):
        shape = ("quad", 2, 2) if seen[sid] == FrameType.QUAD else ("grid", 8, 8)
        sensors[sid] = SensorInfo(sid, *shape, board=interpreter.name)
    info = _pick(sensors, sensor_id, path, kind)
    mine = [f for f in frames if f[0] == info.id and len(f[3]) == 4 * info.channels]
    if len(mine) < 100:
        raise ValueError(_too_few(path, info, kind, len(mine), [len(f[3]) for f in frames if f[0] == info.id],
                                  info.id in interpreter.sensors))
    restart = next((i for i, f in enumerate(mine) if f[4]), None)
    if restart is not None:
        raise ValueError(f"{path}: the board restarted during the session (sensor {info.id}, frame {restart}); "
                         "calibrate each part separately")
    t = np.array([f[1] for f in mine], dtype=np.int64)
    wraps = np.concatenate([[0], np.cumsum(np.diff(t) < -T_US_MODULUS // 2)])
    t_s = (t + wraps * T_US_MODULUS) * 1e-6
    if np.any(np.diff(t_s) <= 0):
        raise ValueError(f"{path}: board times of sensor {info.id} do not increase")
    raw = np.frombuffer(b"".join(f[3] for f in mine), dtype="<u4").reshape(len(mine), info.channels)
    capacitance = raw / AF_PER_PF
    capacitance[(raw == OPEN_SENTINEL) | (raw == SHORT_SENTINEL)] = np.nan
    dead = dead_taxels(raw)
    capacitance[:, list(dead)] = np.nan  # a stuck value is no capacitance either
    saturated = (np.array([f[2] for f in mine]) & FLAG_SATURATED) != 0
    return BoardSession(path, file_sha256(path), info, dict(interpreter.board), t_s, capacitance, saturated, dead)

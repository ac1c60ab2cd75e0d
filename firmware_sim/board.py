"""The simulated readout board: scans sensors, frames bytes, obeys commands.

The board is driven by time, not by a thread: ``advance(now)`` returns the
bytes of every scan due up to ``now`` (board seconds), so a front end can pace
it by the wall clock and a capture can run it on a virtual clock as fast as
the CPU allows. Front ends that cannot take all bytes pass ``room``: scans
that do not fit are dropped as a real board drops them, the sequence counter
still advances, and the next frame carries the OVERRUN flag.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import orjson

from service.protocol import BOARD_SENSOR_ID, FLAG_OVERRUN, FLAG_SATURATED, FrameType, encode_frame

from .scenes import get_scene
from .sensors import SimGrid, SimQuad

FULL_SCALE_AF = 0xFFFFFFFE  # largest value that is not a sentinel
MIN_RATE_HZ, MAX_RATE_HZ = 1, 5000


@dataclass
class BoardConfig:
    sensors: list = field(default_factory=lambda: [SimGrid(0), SimQuad(1)])
    rate_hz: float = 1000.0
    scene: str = "demo"
    noise_fF: float = 1.0
    seed: int = 0
    name: str = "tactile-sim-8x8-quad"
    fw: str = "sim-1.0.0"
    full_scale_pF: float = 100.0
    serial: str | None = None  # the board's serial, announced in INFO when set
    # The board's crystal: t_us = true time × (1 + clock_ppm·1e-6) + clock_offset_us (wrapping at 2**32);
    # scans keep the rate on the board's own clock, as a real board's timer does.
    clock_ppm: float = 0.0
    clock_offset_us: int = 0
    jitter_ms: float = 0.0  # one-sided delivery delay per chunk, up to this (front ends and delivery.deliveries)

    def __post_init__(self) -> None:
        get_scene(self.scene)
        if not MIN_RATE_HZ <= self.rate_hz <= MAX_RATE_HZ:
            raise ValueError(f"rate_hz={self.rate_hz} is outside {MIN_RATE_HZ}..{MAX_RATE_HZ}")
        if self.noise_fF < 0:
            raise ValueError(f"noise_fF={self.noise_fF} must be >= 0")
        if not -1e5 < self.clock_ppm < 1e5 or self.jitter_ms < 0:
            raise ValueError(f"clock_ppm={self.clock_ppm} must be within ±1e5 and jitter_ms={self.jitter_ms} >= 0")
        ids = [s.id for s in self.sensors]
        if len(set(ids)) != len(ids) or not all(0 <= i <= 254 for i in ids):
            raise ValueError(f"sensor ids must be distinct and within 0..254, got {ids}")


@dataclass(frozen=True, slots=True)
class Truth:
    sensor: int
    seq: int
    t_us: int
    values: np.ndarray  # grid: (rows*cols,) N; quad: (Fx, Fy, Fz) N


class Board:
    def __init__(self, config: BoardConfig | None = None, keep_truth: bool = False) -> None:
        self.config = config or BoardConfig()
        self.streaming = True
        self.rate_hz = float(self.config.rate_hz)
        self._scene = get_scene(self.config.scene)
        self._rng = np.random.default_rng(self.config.seed)
        self._period_anchor = 0.0  # board time of scan index 0 at the current rate
        self._scan_index = 0
        self._seq = {s.id: 0 for s in self.config.sensors}
        self._board_seq = 0
        self._overrun = False
        self._command_buffer = bytearray()
        self.truth: list[Truth] | None = [] if keep_truth else None
        self._now = 0.0
        self._clock_scale = 1.0 + self.config.clock_ppm * 1e-6  # board seconds per true second

    @property
    def next_scan_time(self) -> float:
        """True seconds of the next scan."""
        return self._next_board_scan() / self._clock_scale

    def _next_board_scan(self) -> float:
        return self._period_anchor + (self._scan_index + 1) / self.rate_hz

    def power_up(self) -> bytes:
        """What the board sends when it powers up: one INFO frame."""
        return self._info_frame()

    def info(self) -> dict:
        doc = {"board": self.config.name, "fw": self.config.fw}
        if self.config.serial is not None:
            doc["serial"] = self.config.serial
        return {**doc, "rate_hz": self.rate_hz, "sensors": [s.info() for s in self.config.sensors]}

    def advance(self, now: float, room: int | None = None) -> bytes:
        """Run every scan due by true time ``now`` (seconds since power-up); return their frames.

        ``room`` caps the bytes returned: scans beyond it are dropped.
        """
        self._now = max(self._now, now)
        out = bytearray()
        board_now = now * self._clock_scale
        while self._next_board_scan() <= board_now:
            self._scan_index += 1
            t_scan = self._period_anchor + self._scan_index / self.rate_hz
            if not self.streaming:
                continue
            scan = self._scan(t_scan, drop=room is not None and len(out) >= room)
            out += scan
        return bytes(out)

    def _scan(self, t_board: float, drop: bool) -> bytes:
        t_us = int(round(t_board * 1e6)) + self.config.clock_offset_us
        t = t_board / self._clock_scale  # the scene and the sensors live in true time
        if drop:
            self._overrun = True
            for sensor in self.config.sensors:
                self._seq[sensor.id] += 1
            return b""
        sensors = self.config.sensors
        truths = [self._scene(sensor, t) for sensor in sensors]
        capacitance_aF = np.concatenate([sensor.capacitance(truth, t) for sensor, truth in zip(sensors, truths)]) * 1e6
        # One draw and one conversion for the whole scan: at 8 sensors × 1 kHz
        # the per-call cost, not the arithmetic, is what the simulator spends.
        noisy_aF = capacitance_aF + self._rng.normal(0.0, self.config.noise_fF * 1e3, capacitance_aF.size)
        full_scale_aF = min(self.config.full_scale_pF * 1e6, FULL_SCALE_AF)
        out_of_scale = (noisy_aF >= full_scale_aF) | (noisy_aF < 1)
        payload = np.minimum(np.maximum(np.rint(noisy_aF), 1), full_scale_aF).astype("<u4").tobytes()
        out = bytearray()
        start = 0
        for sensor, truth in zip(sensors, truths):
            end = start + sensor.channels
            saturated = bool(out_of_scale[start:end].any())
            flags = (FLAG_SATURATED if saturated else 0) | (FLAG_OVERRUN if self._overrun else 0)
            seq = self._seq[sensor.id]
            frame_type = FrameType.GRID if sensor.kind == "grid" else FrameType.QUAD
            out += encode_frame(frame_type, sensor.id, seq, t_us, payload[4 * start : 4 * end], flags)
            if self.truth is not None:
                self.truth.append(Truth(sensor.id, seq % 65536, t_us % (1 << 32), truth))
            self._seq[sensor.id] = seq + 1
            start = end
        self._overrun = False
        return bytes(out)

    def receive(self, data: bytes) -> bytes:
        """Take command bytes from the host; return the board's replies."""
        self._command_buffer += data
        replies = bytearray()
        while (end := self._command_buffer.find(b"\n")) >= 0:
            line = bytes(self._command_buffer[:end]).rstrip(b"\r")
            del self._command_buffer[: end + 1]
            replies += self._command(line)
        if len(self._command_buffer) > 256:
            self._command_buffer.clear()
            replies += self._error_frame("malformed command: line too long")
        return bytes(replies)

    def _command(self, line: bytes) -> bytes:
        try:
            text = line.decode("ascii")
        except UnicodeDecodeError:
            return self._error_frame("malformed command: not ASCII")
        if text == "START":
            self.streaming = True
        elif text == "STOP":
            self.streaming = False
        elif text == "INFO?":
            return self._info_frame()
        elif text == "PING":
            return self._info_frame(pong=True)
        elif text.startswith("RATE"):
            parts = text.split(" ")
            if len(parts) != 2 or not parts[1].isdigit() or not MIN_RATE_HZ <= int(parts[1]) <= MAX_RATE_HZ:
                return self._error_frame(f"malformed command: {text!r} (RATE takes an integer 1..5000)")
            self._set_rate(int(parts[1]))
        else:
            return self._error_frame("unknown command")
        return b""

    def _set_rate(self, rate_hz: float) -> None:
        last_scan = self._period_anchor + self._scan_index / self.rate_hz
        self.rate_hz = float(rate_hz)
        self._period_anchor = last_scan
        self._scan_index = 0

    def _board_frame(self, frame_type: FrameType, payload: bytes) -> bytes:
        t_us = int(round(self._now * self._clock_scale * 1e6)) + self.config.clock_offset_us
        frame = encode_frame(frame_type, BOARD_SENSOR_ID, self._board_seq, t_us, payload)
        self._board_seq += 1
        return frame

    def _info_frame(self, pong: bool = False) -> bytes:
        doc = self.info()
        if pong:
            doc["pong"] = True
        return self._board_frame(FrameType.INFO, orjson.dumps(doc))

    def _error_frame(self, text: str) -> bytes:
        return self._board_frame(FrameType.ERROR, text.encode("utf-8"))


def capture(config: BoardConfig, seconds: float, keep_truth: bool = False) -> tuple[bytes, Board]:
    """Run a board on a virtual clock for ``seconds``: power-up INFO, then
    every scan. Returns the exact bytes and the board (with its truth)."""
    board = Board(config, keep_truth=keep_truth)
    return board.power_up() + board.advance(seconds), board

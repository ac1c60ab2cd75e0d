"""The data path in one line: bytes → frames → readings → forces → listeners.

Byte listeners (the recorder's raw channel) see every chunk as received,
before decoding; frame listeners (API hub, recorder) see each batch of
ForceFrames."""
from __future__ import annotations

import threading
import time
from typing import Callable

from .history import History
from .protocol import Decoder
from .readings import Interpreter, Reading
from .reconstruct import ForceFrame, Reconstructor

Listener = Callable[[list[ForceFrame]], None]
ByteListener = Callable[[bytes, float], None]

RATE_WINDOW_S = 1.0
HISTORY_FRAMES = 5_000  # per sensor: 5 s at 1 kHz (~5 MB for an 8x8 grid)


class RateMeter:
    """Frames per second over the last completed window of ~1 s."""

    def __init__(self) -> None:
        self.count = 0
        self._window_start: float | None = None
        self._window_count = 0
        self.rate_hz = 0.0

    def tick(self, now: float, n: int = 1) -> None:
        self.count += n
        if self._window_start is None:
            self._window_start, self._window_count = now, self.count
        elif now - self._window_start >= RATE_WINDOW_S:
            self.rate_hz = (self.count - self._window_count) / (now - self._window_start)
            self._window_start, self._window_count = now, self.count


class Pipeline:
    """Decodes and reconstructs everything fed to it and hands each batch of
    ForceFrames to the listeners. ``feed`` is called from one thread (the
    readout or a replay); ``tare`` may come from any other."""

    def __init__(self, reconstructor: Reconstructor | None = None, clock: Callable[[], float] = time.time) -> None:
        self.decoder = Decoder()
        self.interpreter = Interpreter(clock)
        self.reconstructor = reconstructor or Reconstructor()
        self.latest: dict[int, ForceFrame] = {}
        self.history: dict[int, History] = {}
        self.rates: dict[int, RateMeter] = {}
        self.listeners: list[Listener] = []
        self.byte_listeners: list[ByteListener] = []
        self._lock = threading.Lock()

    def feed(self, data: bytes, t_host: float) -> list[ForceFrame]:
        """One read: decoded, reconstructed and published as one batch."""
        return self.reconstruct(self.decode_chunks([(data, t_host)]), t_host)

    def decode_chunks(self, chunks: list[tuple[bytes, float]]) -> list[Reading]:
        """Bytes → readings, each chunk with its own receive time (byte listeners see every chunk)."""
        readings = []
        for data, t_host in chunks:
            for listener in self.byte_listeners:
                listener(data, t_host)
            with self._lock:
                readings += self._interpret(self.decoder.feed(data), t_host)
        return readings

    def reconstruct(self, readings: list[Reading], t_host: float) -> list[ForceFrame]:
        """Readings → forces, published as one batch to the listeners."""
        with self._lock:
            frames = self.reconstructor.process_many(readings) if readings else []
        self._publish(frames, t_host)
        return frames

    def finish(self, t_host: float) -> list[ForceFrame]:
        """End of a finite stream: decode what is left, release held frames."""
        with self._lock:
            readings = self._interpret(self.decoder.finish(), t_host)
            frames = (self.reconstructor.process_many(readings) if readings else []) + self.reconstructor.flush()
        self._publish(frames, t_host)
        return frames

    def link_lost(self) -> None:
        with self._lock:
            self.decoder.reset()

    def tare(self, sensor_id: int | None = None) -> list[int]:
        with self._lock:
            return self.reconstructor.tare(sensor_id)

    def set_calibration(self, info, upload: dict) -> dict:
        with self._lock:
            return self.reconstructor.set_calibration(info, upload)

    def _interpret(self, frames, t_host: float) -> list[Reading]:
        return [r for r in (self.interpreter.interpret(frame, t_host) for frame in frames) if r is not None]

    def _publish(self, frames: list[ForceFrame], t_host: float) -> None:
        if not frames:
            return
        for frame in frames:
            self.latest[frame.sensor.id] = frame
            history = self.history.get(frame.sensor.id)
            if history is None or (history.info is not frame.sensor and history.info != frame.sensor):
                history = self.history[frame.sensor.id] = History(frame.sensor, HISTORY_FRAMES, frame.forces_N.size)
            history.append(frame)
            meter = self.rates.get(frame.sensor.id)
            if meter is None:
                meter = self.rates[frame.sensor.id] = RateMeter()
            meter.tick(t_host)
        for listener in self.listeners:
            listener(frames)

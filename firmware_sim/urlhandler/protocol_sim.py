"""pyserial handler for ``sim://``: a simulated board behind a serial port.

URL: ``sim://[?scene=NAME][&rate=HZ][&noise=fF][&seed=N][&sensors=grid,quad]``
(defaults: demo, 1000, 1.0, 0, one 8x8 grid and one quad). Sensors get ids in
the order listed; a grid may give its shape as ``grid8x8``. Grid effects:
``mounting=flat|curved``, ``xtalk=`` mechanical coupling (default the
paper's −0.0028), ``leak=`` multiplexer leakage fraction (default 0),
``drift=`` common-mode drift amplitude in ΔC/C0 (default 0, period 60 s).
Timing: ``clock_ppm=`` the board clock's rate error and ``clock_offset_us=``
its value at power-up (t_us = true time × (1 + ppm·1e-6) + offset, wrapping;
default 0, 0), ``jitter_ms=`` a one-sided delivery delay per chunk of up to
this many ms (default 0; firmware_sim.delivery).

The board runs on the wall clock: a read generates the scans due since the
last one. Bytes the reader leaves unread pile up to ``BUFFER_BYTES`` (a USB
device's buffer); beyond that the board drops scans and flags OVERRUN.
"""
from __future__ import annotations

import math
import threading
import time
import urllib.parse

from serial.serialutil import PortNotOpenError, SerialBase, SerialException

from ..board import Board, BoardConfig
from ..delivery import DelayedLink
from ..sensors import Drift, SimGrid, SimQuad

BUFFER_BYTES = 1 << 16


GRID_OPTIONS = {"mounting": ("mounting", str), "xtalk": ("mechanical_coupling", float),
                "leak": ("electrical_leakage", float), "drift": ("drift", lambda v: Drift(float(v)))}
BOARD_OPTIONS = {"scene": ("scene", str), "rate": ("rate_hz", float), "noise": ("noise_fF", float), "seed": ("seed", int),
                 "clock_ppm": ("clock_ppm", float), "clock_offset_us": ("clock_offset_us", int),
                 "jitter_ms": ("jitter_ms", float)}


def parse_sensors(spec: str, **grid_options) -> list:
    """Sensors from e.g. "grid,quad" or "grid8x8,grid4x4,quad"; ``grid_options``
    (SimGrid fields) apply to every grid."""
    sensors = []
    for sensor_id, item in enumerate(s.strip() for s in spec.split(",") if s.strip()):
        if item == "quad":
            sensors.append(SimQuad(sensor_id))
        elif item.startswith("grid"):
            shape = item[4:] or "8x8"
            try:
                rows, cols = (int(v) for v in shape.split("x"))
            except ValueError:
                raise ValueError(f"bad grid shape {shape!r} in sensors={spec!r} (expected e.g. grid8x8)") from None
            sensors.append(SimGrid(sensor_id, rows, cols, **grid_options))
        else:
            raise ValueError(f"unknown sensor kind {item!r} in sensors={spec!r} (expected grid or quad)")
    if not sensors:
        raise ValueError(f"sensors={spec!r} names no sensor")
    return sensors


def check_url(url: str) -> None:
    """ValueError naming a bad option (service.sources.check_source asks every handler)."""
    config_from_url(url)


def config_from_url(url: str) -> BoardConfig:
    """BoardConfig from a ``sim://`` URL; ValueError names a bad option."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme != "sim":
        raise ValueError(f"expected a sim:// URL, got {url!r}")
    kwargs: dict = {}
    grid_options: dict = {}
    sensors_spec = "grid,quad"
    for key, values in urllib.parse.parse_qs(parts.query, keep_blank_values=True).items():
        value = values[-1]
        try:
            if key in GRID_OPTIONS:
                field_name, convert = GRID_OPTIONS[key]
                grid_options[field_name] = convert(value)
            elif key in BOARD_OPTIONS:
                field_name, convert = BOARD_OPTIONS[key]
                kwargs[field_name] = convert(value)
            elif key == "sensors":
                sensors_spec = value
            else:
                known = ", ".join([*BOARD_OPTIONS, "sensors", *GRID_OPTIONS])
                raise ValueError(f"unknown option {key!r} (known: {known})")
        except ValueError as exc:
            raise ValueError(f"sim:// option {key}={value!r}: {exc}") from None
    try:
        kwargs["sensors"] = parse_sensors(sensors_spec, **grid_options)
    except ValueError as exc:
        given = [f"sensors={sensors_spec!r}"] if "sensors" in urllib.parse.parse_qs(parts.query) else []
        raise ValueError(f"sim:// {' with '.join(given + [', '.join(sorted(grid_options))] if grid_options else given)}"
                         f": {exc}") from None
    return BoardConfig(**kwargs)


class Serial(SerialBase):
    """A simulated board as a pyserial port."""

    def __init__(self, *args, **kwargs) -> None:
        self.board: Board | None = None
        self._link: DelayedLink | None = None  # delivery jitter, when jitter_ms > 0
        self.clock = time.monotonic
        self._rx = bytearray()
        self._lock = threading.Lock()
        self._t_open = 0.0
        super().__init__(*args, **kwargs)

    def open(self) -> None:
        if self.is_open:
            raise SerialException("Port is already open.")
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        try:
            self.board = Board(config_from_url(self.portstr))
        except ValueError as exc:
            raise SerialException(str(exc)) from None
        self._t_open = self.clock()
        config = self.board.config
        self._link = DelayedLink(config.jitter_ms, config.seed) if config.jitter_ms > 0 else None
        self._rx = bytearray(self.board.power_up())
        self.is_open = True

    def close(self) -> None:
        self.is_open = False
        super().close()

    def _reconfigure_port(self) -> None:
        """Nothing to configure: baud rate and framing mean nothing here."""

    def _board_time(self) -> float:
        return self.clock() - self._t_open

    def _pump(self) -> None:
        now = self._board_time()
        held = self._link.pending if self._link else 0
        data = self.board.advance(now, room=max(BUFFER_BYTES - len(self._rx) - held, 0))
        if self._link:
            self._link.put(data, now)
            data = self._link.take(now)
        self._rx += data

    def _next_event(self) -> float:
        """Board time of the next scan or held chunk coming out."""
        return min(self.board.next_scan_time, self._link.next_release if self._link else math.inf)

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            self._pump()
            return len(self._rx)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        deadline = None if self._timeout is None else self.clock() + self._timeout
        while True:
            with self._lock:
                self._pump()
                if len(self._rx) >= size or self._timeout == 0:
                    break
                wait = self._next_event() - self._board_time()
            if deadline is not None:
                remaining = deadline - self.clock()
                if remaining <= 0:
                    break
                wait = min(wait, remaining)
            if not self.is_open:
                break
            time.sleep(max(wait, 0.0))
        with self._lock:
            data = bytes(self._rx[:size])
            del self._rx[:size]
        return data

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        with self._lock:
            self._pump()
            self._rx += self.board.receive(bytes(data))
        return len(data)

    def reset_input_buffer(self) -> None:
        with self._lock:
            self._rx.clear()

    def reset_output_buffer(self) -> None:
        """Commands are taken at once; there is no output buffer to clear."""

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        """No break line on a simulated port."""

    def _update_rts_state(self) -> None:
        """No modem lines on a simulated port."""

    def _update_dtr_state(self) -> None:
        """No modem lines on a simulated port."""

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True

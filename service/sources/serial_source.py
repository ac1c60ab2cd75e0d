"""Source over pyserial: devices, ``socket://``, pty paths and ``sim://``."""
from __future__ import annotations

import serial

from . import Source

for _handlers in ("firmware_sim.urlhandler", "service.sources"):  # sim://, replay://
    if _handlers not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(_handlers)


class SerialSource(Source):
    def __init__(self, url: str, baudrate: int = 2_000_000) -> None:
        self.url = url
        try:
            self._port = serial.serial_for_url(url, baudrate=baudrate, timeout=0)
        except ValueError as exc:  # pyserial's word for an unknown URL scheme
            raise OSError(f"cannot open {url!r}: {exc}") from None
        except serial.SerialException as exc:
            raise OSError(f"cannot open {url!r}: {exc}") from None

    def _read_internal(self, timeout: float) -> bytes:
        try:
            if self._port.timeout != timeout:  # on hardware, setting it reconfigures the port
                self._port.timeout = timeout
            data = self._port.read(max(self._port.in_waiting, 1))
            waiting = self._port.in_waiting
            if waiting:
                data += self._port.read(waiting)
            return data
        except serial.SerialException as exc:
            raise OSError(f"{self.url}: {exc}") from None

    def write(self, data: bytes) -> None:
        try:
            self._port.write(data)
        except serial.SerialException as exc:
            raise OSError(f"{self.url}: {exc}") from None

    def close(self) -> None:
        self._port.close()

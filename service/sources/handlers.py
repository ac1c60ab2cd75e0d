"""The URL schemes this service adds to pyserial's, registered in one place.

pyserial looks a ``scheme://`` URL up as module ``protocol_<scheme>`` in
each package of ``serial.protocol_handler_packages``. The service adds
``replay://`` (its own, service.sources) and the simulator's ``sim://``
(firmware_sim.urlhandler: the built-in default source needs it; the only
import of the simulator by the service). A handler module may offer
``check_url(url)``, which raises ValueError for a URL that can never open.
"""
from __future__ import annotations

import importlib
import importlib.util

import serial

HANDLER_PACKAGES = ("service.sources", "firmware_sim.urlhandler")


def register() -> None:
    """Make pyserial find ``replay://`` and ``sim://`` (idempotent)."""
    for package in HANDLER_PACKAGES:
        if package not in serial.protocol_handler_packages:
            serial.protocol_handler_packages.append(package)


def handler_module(scheme: str):
    """The module that handles ``scheme://``, or None."""
    register()
    for package in serial.protocol_handler_packages:
        name = f"{package}.protocol_{scheme}"
        if importlib.util.find_spec(name) is not None:
            return importlib.import_module(name)
    return None

"""Shared fixtures: a real server on loopback, reading the simulator; a headless browser."""
import contextlib
import socket
import threading
import time

import pytest
import uvicorn

from service.api.app import create_app
from service.api.server_options import SERVER_OPTIONS
from service.live_service import TactileService


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def live_server(service: TactileService, sensors: int, **options):
    """A uvicorn.Server serving ``service`` in a thread, as tactile serve
    serves (SERVER_OPTIONS, ``options`` overriding), started and with a
    frame of each of its ``sensors``."""
    server = uvicorn.Server(uvicorn.Config(create_app(service), host="127.0.0.1", port=free_port(), log_level="warning",
                                           **{**SERVER_OPTIONS, **options}))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not (server.started and len(service.pipeline.latest) == sensors) and time.monotonic() < deadline:
        time.sleep(0.05)
    try:
        yield server
    finally:
        server.should_exit = True
        thread.join(10)


@pytest.fixture(scope="module")
def served():
    """(base URL, list of tare calls) of a live uvicorn server in a thread."""
    service = TactileService("sim://?scene=press&sensors=grid,quad,grid4x4")
    tares = []
    original = service.pipeline.tare
    service.pipeline.tare = lambda sensor_id=None, force=False: tares.append(sensor_id) or original(sensor_id, force)
    with live_server(service, 3) as server:
        yield f"http://127.0.0.1:{server.config.port}/", tares


@pytest.fixture(scope="module")
def browser():
    """Headless Debian Chromium (tests/chromium.py; skips where it is not installed)."""
    from tests.chromium import launch, sync_api

    with sync_api.sync_playwright() as p:
        browser = launch(p)
        yield browser
        browser.close()


def pytest_configure(config):
    """Every service a test starts keeps its calibrations in a registry of
    the test run's own, never in the user's (``TACTILE_REGISTRY``)."""
    import os
    import tempfile

    from service.calibration.registry import Registry

    path = os.path.join(tempfile.mkdtemp(prefix="tactile-registry-"), "registry.sqlite3")
    Registry(path).close()  # made, as a user's is by their first calibration: commands that read it need it
    os.environ["TACTILE_REGISTRY"] = path

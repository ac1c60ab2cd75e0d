"""The FastAPI app: REST endpoints, the WebSocket stream and the dashboard.

Mutating endpoints (tare, calibration, recording) require
``Authorization: Bearer <token>`` whenever the app is given a token, which
``tactile serve`` does as soon as it binds beyond localhost. The routes are
module-level (``routes_*``, ``dashboard``) and find the service and the token
in the app's state.
"""
from __future__ import annotations

import threading
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from fastapi import Depends, FastAPI
from fastapi.exceptions import RequestValidationError
from fastapi_offline import FastAPIOffline

from . import (
    dashboard,
    routes_calibration,
    routes_health,
    routes_recording,
    routes_sensors,
    routes_stream,
)
from ..fanout.history_json import RecentRings
from .admission import Admission
from .deps import JSONResponse, known_query
from .guard import DEFAULT_MAX_BODY_BYTES, RequestGuard
from .validation_errors import validation_error

if TYPE_CHECKING:
    from ..live_service import TactileService


@asynccontextmanager
async def lifespan(app: FastAPI):
    service = app.state.service
    service.start()
    try:
        yield
    finally:
        service.stop()


def create_app(service: TactileService, token: str | None = None, bind_host: str = "127.0.0.1",
               allow_hosts: tuple[str, ...] = (), allow_origins: tuple[str, ...] = (),
               max_body_bytes: int = DEFAULT_MAX_BODY_BYTES) -> FastAPI:
    """An app serving ``service`` behind the request guard (guard.py);
    RuntimeError when the dashboard's files are missing."""
    # /docs and /redoc load their scripts from the package, not a CDN a lab without internet cannot reach.
    app = FastAPIOffline(title="tactile", version="0.1.0", lifespan=lifespan, default_response_class=JSONResponse,
                  description="Calibrated forces from capacitive tactile sensors. See docs/api.md.")
    app.state.service = service
    app.state.token = token
    app.state.heavy_reads = threading.BoundedSemaphore(routes_sensors.MAX_HEAVY_READS)
    app.state.history_sending = 0  # bytes of history answers not sent yet (routes_sensors.MAX_SENDING_BYTES)
    app.state.recent_reads = routes_sensors.RecentReads()
    app.state.recent_rings = RecentRings(routes_sensors.RECENT_RING_BYTES)
    app.state.stream_sessions = []  # routes_stream.StreamSession, oldest first
    for routes in (routes_health, routes_sensors, routes_calibration, routes_recording):
        app.include_router(routes.router, dependencies=[Depends(known_query)])
    app.include_router(routes_stream.router)  # a WebSocket's query is checked by its subscription
    dashboard.add_dashboard(app)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_middleware(Admission)
    app.add_middleware(RequestGuard, bind_host=bind_host, token=token, allow_hosts=allow_hosts,
                       allow_origins=allow_origins, max_body_bytes=max_body_bytes)
    return app

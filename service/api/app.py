"""REST endpoints, the WebSocket stream and the dashboard's static files."""
from __future__ import annotations

from contextlib import asynccontextmanager
from pathlib import Path

import orjson
from fastapi import FastAPI, HTTPException, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from ..runtime import TactileService
from .stream import Subscriber

WEB_DIR = Path(__file__).resolve().parents[2] / "web"
MAX_WS_RATE_HZ = 5000.0


class RecordRequest(BaseModel):
    path: str = Field(description="the MCAP file to write (must end in .mcap)")
    raw_path: str | None = Field(default=None, description="also write the raw bytes here")


class JSONResponse(Response):
    """orjson with numpy support: NaN (no value) becomes null."""

    media_type = "application/json"

    def render(self, content) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)


def _parse_sensors(text: str | None) -> frozenset[int] | None:
    if text is None or text == "":
        return None
    try:
        return frozenset(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"sensors={text!r} must be a comma-separated list of integer ids") from None


def _parse_rate(text: str | None) -> float | None:
    if text is None or text == "":
        return None
    try:
        rate = float(text)
    except ValueError:
        raise ValueError(f"max_rate={text!r} is not a number") from None
    if not 0 < rate <= MAX_WS_RATE_HZ:
        raise ValueError(f"max_rate={text!r} must be in (0, {MAX_WS_RATE_HZ:g}] Hz")
    return rate


def create_app(service: TactileService) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        service.start()
        try:
            yield
        finally:
            service.stop()

    app = FastAPI(title="tactile", version="0.1.0", lifespan=lifespan, default_response_class=JSONResponse)
    app.state.service = service

    def known_sensor(sensor_id: int):
        sensors = service.pipeline.interpreter.sensors
        if sensor_id not in sensors:
            known = ", ".join(str(s) for s in sorted(sensors)) or "none yet"
            raise HTTPException(404, f"unknown sensor id {sensor_id}; known: {known}")
        return sensors[sensor_id]

    @app.get("/health")
    def health() -> JSONResponse:
        return JSONResponse(service.health())

    @app.get("/sensors")
    def sensors() -> JSONResponse:
        interpreter = service.pipeline.interpreter
        return JSONResponse(
            {
                "board": interpreter.board,
                "sensors": [
                    {**info.as_dict(), "tared": service.pipeline.reconstructor.baseline(sid) is not None}
                    for sid, info in sorted(interpreter.sensors.items())
                ],
            }
        )

    @app.get("/sensors/{sensor_id}/latest")
    def latest(sensor_id: int) -> JSONResponse:
        known_sensor(sensor_id)
        frame = service.pipeline.latest.get(sensor_id)
        if frame is None:
            raise HTTPException(404, f"sensor {sensor_id} has not delivered a frame yet")
        body = frame.stream_dict()
        body["capacitance_pF"] = frame.capacitance_pF
        body["level"] = frame.level
        return JSONResponse(body)

    @app.post("/sensors/{sensor_id}/tare")
    def tare_sensor(sensor_id: int) -> JSONResponse:
        known_sensor(sensor_id)
        try:
            tared = service.pipeline.tare(sensor_id)
        except KeyError:
            raise HTTPException(409, f"sensor {sensor_id} has no frames yet to tare") from None
        return JSONResponse({"tared": tared, "frames": service.pipeline.reconstructor.tare_frames})

    @app.post("/tare")
    def tare_all() -> JSONResponse:
        return JSONResponse({"tared": service.pipeline.tare(), "frames": service.pipeline.reconstructor.tare_frames})

    @app.post("/record/start")
    def record_start(request: RecordRequest) -> JSONResponse:
        try:
            return JSONResponse(service.start_recording(request.path, request.raw_path))
        except RuntimeError as exc:
            raise HTTPException(409, str(exc)) from None
        except (OSError, ValueError) as exc:
            raise HTTPException(400, f"path: {exc}") from None

    @app.post("/record/stop")
    def record_stop() -> JSONResponse:
        status = service.stop_recording()
        if status is None:
            raise HTTPException(409, "not recording")
        return JSONResponse(status)

    @app.get("/record")
    def record_status() -> JSONResponse:
        return JSONResponse(None if service.recorder is None else service.recorder.status())

    @app.websocket("/ws")
    async def stream(websocket: WebSocket) -> None:
        await websocket.accept()
        try:
            subscriber = Subscriber(
                sensors=_parse_sensors(websocket.query_params.get("sensors")),
                max_rate_hz=_parse_rate(websocket.query_params.get("max_rate")),
            )
        except ValueError as exc:
            await websocket.send_text(orjson.dumps({"type": "error", "detail": str(exc)}).decode())
            await websocket.close(code=1008, reason=str(exc)[:120])
            return
        service.hub.subscribers.add(subscriber)
        try:
            while True:
                await websocket.send_text((await subscriber.next_message()).decode())
        except (WebSocketDisconnect, RuntimeError):
            pass
        finally:
            service.hub.subscribers.discard(subscriber)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html")

    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")
    return app

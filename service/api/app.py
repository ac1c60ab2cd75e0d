"""REST endpoints, the WebSocket stream and the dashboard's static files.

Mutating endpoints (tare, calibration, recording) require
``Authorization: Bearer <token>`` whenever the app is given a token, which
``tactile serve`` does as soon as it binds beyond localhost.
"""
from __future__ import annotations

import hmac
import site
import sys
import time
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
import orjson
from fastapi import Depends, FastAPI, Header, HTTPException, Query, WebSocket, WebSocketDisconnect
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field

from ..runtime import TactileService
from ..fanout.encoding import DEFAULT_FIELDS, FIELDS, to_json_dict
from ..fanout.hub import Subscriber
from .schemas import Contact, FrameMessage


def web_dir_candidates() -> list[Path]:
    """Where the dashboard's files may be: web/ beside the package in a
    checkout (and an editable install); share/tactile/web under the
    environment's prefix, or the user's base after ``pip install --user``,
    when installed from a wheel (pyproject's data-files)."""
    return [Path(__file__).resolve().parents[2] / "web",
            Path(sys.prefix) / "share" / "tactile" / "web",
            Path(site.getuserbase()) / "share" / "tactile" / "web"]


def find_web_dir(candidates: list[Path]) -> Path:
    for candidate in candidates:
        if (candidate / "index.html").is_file():
            return candidate
    raise RuntimeError(f"the dashboard's files are in none of {', '.join(map(str, candidates))}: reinstall tactile")


WEB_DIR = find_web_dir(web_dir_candidates())
MAX_WS_RATE_HZ = 5000.0
ALL_FIELDS = frozenset(FIELDS)


class JSONResponse(Response):
    """orjson with numpy support: NaN (no value) becomes null."""

    media_type = "application/json"

    def render(self, content) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)


class RecordRequest(BaseModel):
    path: str = Field(description="the MCAP file to write (must end in .mcap)")
    raw_path: str | None = Field(default=None, description="also write the raw bytes here")


class GridCalibrationUpload(BaseModel):
    sensitivity_pct_per_N: list[float] = Field(description="per taxel, row-major, measured 0–10 N slope in %/N")


class QuadCalibrationUpload(BaseModel):
    normal_fit: tuple[float, float] = Field(description="ΔC/C0 = c2 F² + c1 F: [c2, c1], c2 < 0 < c1")
    shear_fit: tuple[float, float] = Field(description="ΔC/C0 = a F − b F²: [a, b], a > 0, b ≥ 0")


def _parse_sensors(text: str | None) -> frozenset[int] | None:
    if text is None or text == "":
        return None
    try:
        return frozenset(int(part) for part in text.split(","))
    except ValueError:
        raise ValueError(f"sensors={text!r} must be a comma-separated list of integer ids") from None


def _parse_fields(text: str | None) -> frozenset[str]:
    if text is None or text == "":
        return DEFAULT_FIELDS
    fields = frozenset(part.strip() for part in text.split(","))
    unknown = fields - ALL_FIELDS
    if unknown:
        raise ValueError(f"fields={text!r}: unknown {sorted(unknown)}; known: {', '.join(FIELDS)}")
    return fields


def _parse_positive(name: str, text: str | None, upper: float) -> float | None:
    if text is None or text == "":
        return None
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"{name}={text!r} is not a number") from None
    if not 0 < value <= upper:
        raise ValueError(f"{name}={text!r} must be in (0, {upper:g}]")
    return value


def create_app(service: TactileService, token: str | None = None) -> FastAPI:
    @asynccontextmanager
    async def lifespan(app: FastAPI):
        service.start()
        try:
            yield
        finally:
            service.stop()

    app = FastAPI(title="tactile", version="0.1.0", lifespan=lifespan, default_response_class=JSONResponse,
                  description="Calibrated forces from capacitive tactile sensors. See docs/api.md.")
    app.state.service = service

    def authorised(authorization: str | None = Header(default=None, description="Bearer token, when the service requires one")):
        if token is None:
            return
        expected = f"Bearer {token}"
        if authorization is None or not hmac.compare_digest(authorization, expected):
            raise HTTPException(401, "this endpoint needs 'Authorization: Bearer <token>' (printed by tactile serve)")

    def known_sensor(sensor_id: int):
        sensors = service.pipeline.interpreter.sensors
        if sensor_id not in sensors:
            known = ", ".join(str(s) for s in sorted(sensors)) or "none yet"
            raise HTTPException(404, f"unknown sensor id {sensor_id}; known: {known}")
        return sensors[sensor_id]

    def latest_frame(sensor_id: int):
        known_sensor(sensor_id)
        frame = service.pipeline.latest.get(sensor_id)
        if frame is None:
            raise HTTPException(404, f"sensor {sensor_id} has not delivered a frame yet")
        return frame

    @app.get("/health")
    def health() -> JSONResponse:
        return JSONResponse(service.health())

    @app.get("/clients")
    def clients() -> JSONResponse:
        """Each WebSocket client's subscription, queue, losses and latency
        (receive stamp → handed to its socket): a controller finds its own
        stream here. Apart from /health, which is polled often, since it
        costs a percentile per client."""
        return JSONResponse({"clients": [subscriber.describe() for subscriber in list(service.hub.subscribers)]})

    @app.get("/sensors")
    def sensors() -> JSONResponse:
        interpreter = service.pipeline.interpreter
        return JSONResponse(
            {
                "board": interpreter.board,
                "sensors": [
                    {**info.as_dict(), "name": f"{info.kind}{sid}", "tared": service.pipeline.reconstructor.baseline(sid) is not None}
                    for sid, info in sorted(interpreter.sensors.items())
                ],
            }
        )

    @app.get("/sensors/{sensor_id}/latest", responses={200: {"model": FrameMessage}})
    def latest(sensor_id: int) -> JSONResponse:
        return JSONResponse(to_json_dict(latest_frame(sensor_id), ALL_FIELDS))

    @app.get("/sensors/{sensor_id}/contact", responses={200: {"model": Contact}})
    def contact(sensor_id: int) -> JSONResponse:
        frame = latest_frame(sensor_id)
        if frame.sensor.kind != "grid":
            raise HTTPException(400, f"sensor {sensor_id} is a {frame.sensor.kind}; contact summaries are for grids")
        if frame.contact is None:
            raise HTTPException(404, f"sensor {sensor_id} is still taring")
        return JSONResponse(frame.contact)

    @app.get("/sensors/{sensor_id}/history", responses={200: {"model": list[FrameMessage]}})
    def history(
        sensor_id: int,
        seconds: float = Query(2.0, gt=0, le=5, description="window length back from the latest frame (5 s kept at 1 kHz)"),
        max_points: int = Query(200, ge=1, le=5000, description="decimate to at most this many frames"),
        fields: str = Query("force,contact,flags", description=f"comma-separated: {', '.join(FIELDS)}"),
    ) -> JSONResponse:
        known_sensor(sensor_id)
        try:
            wanted = _parse_fields(fields)
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        history = service.pipeline.history.get(sensor_id)
        frames = [] if history is None else history.window(seconds, max_points)
        return JSONResponse([to_json_dict(frame, wanted) for frame in frames])

    @app.post("/sensors/{sensor_id}/tare", dependencies=[Depends(authorised)])
    def tare_sensor(sensor_id: int) -> JSONResponse:
        known_sensor(sensor_id)
        try:
            tared = service.pipeline.tare(sensor_id)
        except KeyError:
            raise HTTPException(409, f"sensor {sensor_id} has no frames yet to tare") from None
        return JSONResponse({"tared": tared, "frames": service.pipeline.reconstructor.tare_frames})

    @app.post("/tare", dependencies=[Depends(authorised)])
    def tare_all() -> JSONResponse:
        return JSONResponse({"tared": service.pipeline.tare(), "frames": service.pipeline.reconstructor.tare_frames})

    @app.put("/sensors/{sensor_id}/calibration", dependencies=[Depends(authorised)])
    def upload_calibration(sensor_id: int, body: GridCalibrationUpload | QuadCalibrationUpload) -> JSONResponse:
        info = known_sensor(sensor_id)
        try:
            applied = service.pipeline.set_calibration(info, body.model_dump())
        except ValueError as exc:
            raise HTTPException(422, str(exc)) from None
        return JSONResponse(applied)

    @app.post("/record/start", dependencies=[Depends(authorised)])
    def record_start(request: RecordRequest) -> JSONResponse:
        try:
            return JSONResponse(service.start_recording(request.path, request.raw_path))
        except RuntimeError as exc:
            raise HTTPException(409, str(exc)) from None
        except (OSError, ValueError) as exc:
            raise HTTPException(400, f"path: {exc}") from None

    @app.post("/record/stop", dependencies=[Depends(authorised)])
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
        """Query: sensors=0,1 · fields=force,raw,contact,flags · max_rate=Hz ·
        batch_ms=ms · encoding=json|binary."""
        await websocket.accept()
        params = websocket.query_params
        try:
            encoding = params.get("encoding", "json")
            if encoding not in ("json", "binary"):
                raise ValueError(f"encoding={encoding!r} must be 'json' or 'binary'")
            subscriber = Subscriber(
                sensors=_parse_sensors(params.get("sensors")),
                fields=_parse_fields(params.get("fields")),
                binary=encoding == "binary",
                max_rate_hz=_parse_positive("max_rate", params.get("max_rate"), MAX_WS_RATE_HZ),
                batch_ms=_parse_positive("batch_ms", params.get("batch_ms"), 1000.0),
            )
        except ValueError as exc:
            await websocket.send_text(orjson.dumps({"type": "error", "detail": str(exc)}).decode())
            await websocket.close(code=1008, reason=str(exc)[:120])
            return
        async def send_forever() -> None:
            while True:
                message, notice, oldest_stamp = await subscriber.next_message()
                if subscriber.batch_ms is not None:
                    await service.let_urgent_go_first()
                if notice is not None:
                    await websocket.send_text(notice.decode())
                if subscriber.binary:
                    await websocket.send_bytes(message)
                else:
                    await websocket.send_text(message.decode())
                service.hub.sent(subscriber, time.time(), oldest_stamp)

        async def until_disconnected() -> None:
            # A client that leaves is noticed here even when nothing is being
            # sent to it (a subscription that matches no frame).
            while (await websocket.receive())["type"] != "websocket.disconnect":
                pass

        service.hub.add(subscriber)
        try:
            async with anyio.create_task_group() as group:
                async def until_either_ends(run) -> None:
                    try:
                        await run()
                    except (WebSocketDisconnect, RuntimeError):  # the client went away mid-send
                        pass
                    group.cancel_scope.cancel()

                group.start_soon(until_either_ends, send_forever)
                group.start_soon(until_either_ends, until_disconnected)
        finally:
            service.hub.remove(subscriber)

    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        return FileResponse(WEB_DIR / "index.html")

    app.mount("/static", StaticFiles(directory=WEB_DIR), name="static")
    return app

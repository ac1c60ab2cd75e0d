"""Taring and calibration: tare (409 when a taxel reads loaded against its
calibration's C0, unless ``force=true``), upload (stored in the registry and
active at once), and which calibration a sensor uses. Mutations need the
token when one is set."""
from __future__ import annotations

from typing import TYPE_CHECKING

import time

from fastapi import APIRouter, Depends, HTTPException, Query

from ..health import calibration_state
from ..pipeline import LoadedAtTare
from .deps import JSONResponse, authorised, get_service, known_sensor
from .schemas import GridCalibrationUpload, QuadCalibrationUpload

if TYPE_CHECKING:
    from ..live_service import TactileService
    from ..readings import SensorInfo

router = APIRouter()
MUTATION = [Depends(authorised)]


FORCE = Query(False, description="tare even where taxels read loaded against their calibration's C0 "
                                 "(the load present becomes their zero)")


def _loaded(exc: LoadedAtTare) -> HTTPException:
    return HTTPException(409, {"error": str(exc), "loaded_taxels": {str(k): v for k, v in exc.taxels.items()}})


@router.post("/sensors/{sensor_id}/tare", dependencies=MUTATION, responses={409: {"description": "no frames yet, or taxels read loaded"}})
def tare_sensor(info: SensorInfo = Depends(known_sensor), force: bool = FORCE,
                service: TactileService = Depends(get_service)) -> JSONResponse:
    try:
        tared = service.pipeline.tare(info.id, force=force)
    except KeyError:
        raise HTTPException(409, f"sensor {info.id} has no frames yet to tare") from None
    except LoadedAtTare as exc:
        raise _loaded(exc) from None
    return JSONResponse({"tared": tared, "frames": service.pipeline.reconstructor.tare_frames})


@router.post("/tare", dependencies=MUTATION, responses={409: {"description": "taxels read loaded against their calibration's C0"}})
def tare_all(force: bool = FORCE, service: TactileService = Depends(get_service)) -> JSONResponse:
    try:
        tared = service.pipeline.tare(force=force)
    except LoadedAtTare as exc:
        raise _loaded(exc) from None
    return JSONResponse({"tared": tared, "frames": service.pipeline.reconstructor.tare_frames})


@router.put("/sensors/{sensor_id}/calibration", dependencies=MUTATION)
def upload_calibration(sensor_id: int, body: GridCalibrationUpload | QuadCalibrationUpload,
                       service: TactileService = Depends(get_service)) -> JSONResponse:
    info = known_sensor(sensor_id, service)  # after the body is validated: a bad body is 422 for any sensor
    try:
        document = service.set_calibration(info, body.model_dump(exclude_none=True))
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return JSONResponse({**document, "active": True, "stored": service.calibrations.use_registry})


@router.get("/sensors/{sensor_id}/calibration")
def sensor_calibration(info: SensorInfo = Depends(known_sensor),
                       service: TactileService = Depends(get_service)) -> JSONResponse:
    """The calibration the sensor's forces rest on (as /health shows it) and its document."""
    state = calibration_state(service.pipeline, info.id, time.time(), service.calibrations)
    if state is None:
        raise HTTPException(409, f"sensor {info.id} has no frames yet")
    calibration = service.pipeline.reconstructor.calibration(info.id)
    return JSONResponse({**state, "document": calibration.document})

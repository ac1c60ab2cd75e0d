"""Taring and calibration upload (both need the token when one is set)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends, HTTPException

from .deps import JSONResponse, authorised, get_service, known_sensor
from .schemas import GridCalibrationUpload, QuadCalibrationUpload

if TYPE_CHECKING:
    from ..live_service import TactileService
    from ..readings import SensorInfo

router = APIRouter(dependencies=[Depends(authorised)])


@router.post("/sensors/{sensor_id}/tare")
def tare_sensor(info: SensorInfo = Depends(known_sensor),
                service: TactileService = Depends(get_service)) -> JSONResponse:
    try:
        tared = service.pipeline.tare(info.id)
    except KeyError:
        raise HTTPException(409, f"sensor {info.id} has no frames yet to tare") from None
    return JSONResponse({"tared": tared, "frames": service.pipeline.reconstructor.tare_frames})


@router.post("/tare")
def tare_all(service: TactileService = Depends(get_service)) -> JSONResponse:
    return JSONResponse({"tared": service.pipeline.tare(), "frames": service.pipeline.reconstructor.tare_frames})


@router.put("/sensors/{sensor_id}/calibration")
def upload_calibration(sensor_id: int, body: GridCalibrationUpload | QuadCalibrationUpload,
                       service: TactileService = Depends(get_service)) -> JSONResponse:
    info = known_sensor(sensor_id, service)  # after the body is validated: a bad body is 422 for any sensor
    try:
        applied = service.pipeline.set_calibration(info, body.model_dump())
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    return JSONResponse(applied)

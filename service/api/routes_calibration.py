"""Taring and calibration: tare (409 when a taxel reads loaded against its
calibration's C0, unless ``force=true``), upload (stored in the registry and
active at once), and which calibration a sensor uses. Mutations need the
token when one is set."""
from __future__ import annotations

from typing import TYPE_CHECKING, Annotated

from fastapi import APIRouter, Depends, HTTPException, Query
from pydantic import Field

from ..board import RemoteBoardError
from ..calibration.registry import RegistryUnusable
from ..pipeline_changes import LoadedAtTare
from .deps import Addressed, JSONResponse, authorised, find_sensor, get_service, known_sensor
from .schemas import CalibrationDocumentUpload, GridCalibrationUpload, QuadCalibrationUpload

if TYPE_CHECKING:
    from ..live_service import TactileService

router = APIRouter()
MUTATION = [Depends(authorised)]


FORCE = Query(False, description="tare even where taxels read loaded against their calibration's C0 "
                                 "(the load present becomes their zero)")


def _loaded(exc: LoadedAtTare, board: str | None = None) -> HTTPException:
    """``board``: named in the keys of a service with several boards."""
    return HTTPException(409, {"error": (f"board {board}: " if board else "") + str(exc),
                               "loaded_taxels": {(f"{board}/{k}" if board else str(k)): v
                                                 for k, v in exc.taxels.items()}})


def _tared(service: TactileService, boards, force: bool, sensor_id: int | None = None) -> JSONResponse:
    """Tare on each of ``boards``; a LoadedAtTare on any is a 409 and tares none
    (the boards are judged first, then tared)."""
    several = len(service.all_boards) > 1
    try:
        for board in boards if not force else ():
            loaded = board.loaded(sensor_id)
            if loaded:
                raise _loaded(LoadedAtTare(loaded), board.name if several else None)
        tared, frames, waiting = [], 0, []
        for board in boards:
            try:
                done, frames = board.tare(sensor_id, force=force)
            except LoadedAtTare as exc:  # loaded between the look and the tare
                raise _loaded(exc, board.name if several else None) from None
            tared += [f"{board.name}/{sid}" for sid in done] if several else done
            readout = getattr(board, "readout", None)
            if done and readout is not None and not readout.link.up:
                waiting.append(board.name)
    except RemoteBoardError as exc:
        raise HTTPException(409, str(exc)) from None
    answer = {"tared": tared, "frames": frames}
    if waiting:  # said, since the answer alone reads as done
        answer["note"] = (f"board{'s' if len(waiting) > 1 else ''} {', '.join(waiting)} not connected: "
                          "the tare takes its next frames once it is back")
    return JSONResponse(answer)


@router.post("/sensors/{sensor_id}/tare", dependencies=MUTATION, responses={409: {"description": "no frames yet, or taxels read loaded"}})
@router.post("/sensors/{board}/{sensor_id}/tare", dependencies=MUTATION, responses={409: {"description": "no frames yet, or taxels read loaded"}})
def tare_sensor(found: Addressed = Depends(known_sensor), force: bool = FORCE,
                service: TactileService = Depends(get_service)) -> JSONResponse:
    try:
        return _tared(service, [found.board], force, found.info.id)
    except KeyError:
        raise HTTPException(409, f"sensor {found.info.address} has no frames yet to tare") from None


@router.post("/tare", dependencies=MUTATION, responses={409: {"description": "taxels read loaded against their calibration's C0"}})
def tare_all(force: bool = FORCE, board: str | None = Query(None, description="only this board's sensors"),
             service: TactileService = Depends(get_service)) -> JSONResponse:
    boards = service.all_boards
    if board is not None:
        boards = [b for b in boards if b.name == board]
        if not boards:
            raise HTTPException(404, f"unknown board {board!r}; boards: {', '.join(b.name for b in service.all_boards)}")
    return _tared(service, boards, force)


# A document first: it also holds a quad's normal_fit and shear_fit, and a short form would take it, anew.
CalibrationUpload = Annotated[CalibrationDocumentUpload | GridCalibrationUpload | QuadCalibrationUpload,
                              Field(union_mode="left_to_right")]


@router.put("/sensors/{sensor_id}/calibration", dependencies=MUTATION)
@router.put("/sensors/{board}/{sensor_id}/calibration", dependencies=MUTATION)
def upload_calibration(sensor_id: int, body: CalibrationUpload, board: str | None = None,
                       service: TactileService = Depends(get_service)) -> JSONResponse:
    found = find_sensor(service, sensor_id, board)  # after the body is validated: a bad body is 422 for any sensor
    try:
        # A document is taken as it is (its id covers every key, null ones too); a short form without its nulls.
        upload = body.model_dump(by_alias=True) if isinstance(body, CalibrationDocumentUpload) else \
            body.model_dump(exclude_none=True)
        document = found.board.set_calibration(found.info, upload)
    except ValueError as exc:
        raise HTTPException(422, str(exc)) from None
    except RemoteBoardError as exc:
        raise HTTPException(409, str(exc)) from None
    except RegistryUnusable as exc:  # the service's store, not the upload: nothing was set
        raise HTTPException(503, str(exc)) from None
    return JSONResponse({**document, "active": True, "stored": found.board.calibrations.use_registry})


@router.get("/sensors/{sensor_id}/calibration")
@router.get("/sensors/{board}/{sensor_id}/calibration")
def sensor_calibration(found: Addressed = Depends(known_sensor)) -> JSONResponse:
    """The calibration the sensor's forces rest on (as /health shows it) and its document."""
    state = found.board.calibration(found.info.id)
    if state is None:
        raise HTTPException(409, f"sensor {found.info.address} has no frames yet")
    return JSONResponse(state)

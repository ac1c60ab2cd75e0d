"""Recording to MCAP: status, start and stop (start and stop need the token
when one is set)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends, HTTPException

from .deps import JSONResponse, authorised, get_service
from .schemas import RecordRequest

if TYPE_CHECKING:
    from ..live_service import TactileService

router = APIRouter()


@router.post("/record/start", dependencies=[Depends(authorised)])
def record_start(request: RecordRequest | None = None, service: TactileService = Depends(get_service)) -> JSONResponse:
    """Record into the recordings directory; the API never takes a path."""
    try:
        return JSONResponse(service.start_recording(None if request is None else request.name))
    except (RuntimeError, FileExistsError) as exc:
        raise HTTPException(409, str(exc)) from None
    except ValueError as exc:
        raise HTTPException(422, f"name: {exc}") from None
    except OSError as exc:
        raise HTTPException(500, f"the recordings directory cannot be written: {exc}") from None


@router.post("/record/stop", dependencies=[Depends(authorised)])
def record_stop(service: TactileService = Depends(get_service)) -> JSONResponse:
    status = service.stop_recording()
    if status is None:
        raise HTTPException(409, "not recording")
    return JSONResponse(status)


@router.get("/record")
def record_status(service: TactileService = Depends(get_service)) -> JSONResponse:
    return JSONResponse(None if service.recorder is None else service.recorder.status())

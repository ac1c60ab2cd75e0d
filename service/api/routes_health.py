"""GET /health: link, rates, counters, reconstruction and latency."""
from __future__ import annotations

from typing import TYPE_CHECKING

from fastapi import APIRouter, Depends

from .deps import JSONResponse, get_service

if TYPE_CHECKING:
    from ..live_service import TactileService

router = APIRouter()


@router.get("/health")
def health(service: TactileService = Depends(get_service)) -> JSONResponse:
    return JSONResponse(service.health())

"""The dashboard: its page at / and its files under /static.

Where its files are is looked up when an app is created (``create_app``), not
when this module is imported: importing the API touches no file.
"""
from __future__ import annotations

import site
import sys
from pathlib import Path

from fastapi import APIRouter, FastAPI, Request
from fastapi.responses import FileResponse
from fastapi.staticfiles import StaticFiles

router = APIRouter()


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


@router.get("/", include_in_schema=False)
def index(request: Request) -> FileResponse:
    return FileResponse(request.app.state.web_dir / "index.html")


def add_dashboard(app: FastAPI) -> None:
    """Serve the dashboard from the first candidate directory that has it
    (RuntimeError naming them all when none has)."""
    app.state.web_dir = web_dir = find_web_dir(web_dir_candidates())
    app.include_router(router)
    app.mount("/static", StaticFiles(directory=web_dir), name="static")

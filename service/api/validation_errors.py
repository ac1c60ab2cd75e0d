"""422 answers that name what was wrong without sending the request back.

FastAPI's default answer to a body that fails validation repeats the whole
input in every error (once per member of a union): a 15 KB upload came back
as 52 KB. Here each error keeps its type, location and message, and the bad
value only where it is short (a number, a short string); a long or nested
one is described (``<list of 2000 items>``). At most MAX_ERRORS are listed,
with how many more there were.
"""
from __future__ import annotations

from fastapi import Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

MAX_ERRORS = 20
MAX_INPUT_CHARS = 80


def described(value: object) -> object:
    """``value`` itself where short and flat, else a description of it."""
    if value is None or isinstance(value, (bool, int, float)):
        return value
    if isinstance(value, str):
        return value if len(value) <= MAX_INPUT_CHARS else f"<text of {len(value)} characters>"
    if isinstance(value, dict):
        return f"<object with {len(value)} keys>"
    if isinstance(value, (list, tuple)):
        return f"<list of {len(value)} items>"
    return f"<{type(value).__name__}>"


async def validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    """The 422 answer: each error's type, loc, msg and (described) input."""
    errors = exc.errors()
    detail = [{key: described(error[key]) if key == "input" else error[key]
               for key in ("type", "loc", "msg", "input") if key in error} for error in errors[:MAX_ERRORS]]
    body: dict = {"detail": detail}
    if len(errors) > MAX_ERRORS:
        body["more_errors"] = len(errors) - MAX_ERRORS
    return JSONResponse(body, status_code=422)

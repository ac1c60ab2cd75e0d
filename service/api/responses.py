"""The API's default response class."""
from __future__ import annotations

import orjson
from fastapi.responses import Response


class JSONResponse(Response):
    """orjson with numpy support: NaN (no value) becomes null."""

    media_type = "application/json"

    def render(self, content) -> bytes:
        return orjson.dumps(content, option=orjson.OPT_SERIALIZE_NUMPY)

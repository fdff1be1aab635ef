"""HTTP errors: the application's refusals mapped to statuses, request validation errors in
the API's 422 format, Redis outages as 503 with ``Retry-After`` (never a 500 or a traceback),
and a generic 500 for genuine bugs (logged with the traceback)."""
from __future__ import annotations

import logging
import math

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse

from service.application.errors import (AppError, Conflict, Forbidden, Invalid, NotFound, TooManyRequests,
                                        Unavailable)
from service.storage.redis import UNAVAILABLE, StorageError

log = logging.getLogger("tryon")

STATUS = {NotFound: 404, Conflict: 409, Forbidden: 403, TooManyRequests: 429, Unavailable: 503}
STORAGE_RETRY_AFTER_S = 1
# Redis answers that mean "not now" rather than a bug: loading its data, read-only replica,
# persistence failing (disk full).
_UNAVAILABLE_REPLIES = ("LOADING", "READONLY", "MISCONF", "MASTERDOWN", "TRYAGAIN")


def invalid(loc: tuple, message: str) -> RequestValidationError:
    """A 422 in the API's format for ``loc`` (``("body", "mesh")``)."""
    return RequestValidationError([{"loc": loc, "msg": message, "type": "value_error"}])


def retry_after(seconds: float) -> dict[str, str]:
    """The ``Retry-After`` header (whole seconds, at least 1)."""
    return {"Retry-After": str(max(1, math.ceil(seconds)))}


async def app_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, AppError)
    if isinstance(exc, Invalid):
        return await validation_error(request, invalid(exc.loc, exc.message))
    status = next((code for cls, code in STATUS.items() if isinstance(exc, cls)), 400)
    headers = retry_after(exc.retry_after) if isinstance(exc, (TooManyRequests, Unavailable)) else None
    return JSONResponse({"detail": exc.message}, status_code=status, headers=headers)


async def validation_error(request: Request, exc: Exception) -> JSONResponse:
    """422 ``{"detail": [{"loc", "msg", "type"}]}``. The offending ``input`` is not echoed (it
    may be NaN/inf, which JSON cannot carry, or large)."""
    errors = exc.errors() if isinstance(exc, RequestValidationError) else []
    detail = []
    for err in errors:
        msg = str(err.get("msg", ""))
        if err.get("type") == "value_error" and msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        detail.append({"loc": [p if isinstance(p, int) else str(p) for p in err.get("loc", ())],
                       "msg": msg, "type": str(err.get("type", "value_error"))})
    return JSONResponse({"detail": detail}, status_code=422)


def storage_unavailable_response() -> JSONResponse:
    return JSONResponse({"detail": "storage is unavailable right now; retry shortly"}, status_code=503,
                        headers=retry_after(STORAGE_RETRY_AFTER_S))


async def storage_error(request: Request, exc: Exception) -> JSONResponse:
    """Redis unreachable (or refusing writes for now): 503 + Retry-After, one log line; the
    connection pool reconnects by itself once it is back."""
    if isinstance(exc, UNAVAILABLE) or str(exc).split(" ", 1)[0] in _UNAVAILABLE_REPLIES:
        log.warning("storage unavailable on %s %s: %s", request.method, request.url.path,
                    " ".join(str(exc).split())[:200])
        return storage_unavailable_response()
    return await unhandled_error(request, exc)


async def unhandled_error(request: Request, exc: Exception) -> JSONResponse:
    """Genuine bugs only: log with traceback, answer a generic 500."""
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": "internal server error"}, status_code=500)


def install(app: FastAPI) -> None:
    app.add_exception_handler(AppError, app_error)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(StorageError, storage_error)
    app.add_exception_handler(Exception, unhandled_error)

"""HTTP errors: the application's refusals mapped to statuses, request validation errors in
the API's 422 format (a body that is not JSON, or nested too deep to read, too: one status for
one kind of error on every route), messages cut to a short excerpt of the input they quote,
Redis outages as 503 with ``Retry-After`` (never a 500 or a traceback), a client gone mid-request
or a request body too slow as one log line, and a generic 500 for genuine bugs (logged with the
traceback)."""
from __future__ import annotations

import logging
import math

from fastapi import FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from service.api.middleware import BodyTimeout
from service.application.errors import (AppError, Conflict, Forbidden, Invalid, NotFound, TooLarge,
                                        TooManyRequests, Unavailable)
from service.storage.redis import UNAVAILABLE, StorageError

log = logging.getLogger("tryon")

STATUS = {NotFound: 404, Conflict: 409, Forbidden: 403, TooLarge: 413, TooManyRequests: 429, Unavailable: 503}
MAX_MESSAGE_CHARS = 300  # an error message quotes at most this much (a 10 MB JSON key is not echoed)
MAX_LOC_CHARS = 64
UNREADABLE_BODY = "There was an error parsing the body"  # FastAPI's 400 for a body json cannot read
STORAGE_RETRY_AFTER_S = 1
# Redis answers that mean "not now" rather than a bug: loading its data, read-only replica,
# persistence failing (disk full).
_UNAVAILABLE_REPLIES = ("LOADING", "READONLY", "MISCONF", "MASTERDOWN", "TRYAGAIN")


def invalid(loc: tuple, message: str) -> RequestValidationError:
    """A 422 in the API's format for ``loc`` (``("body", "mesh")``)."""
    return RequestValidationError([{"loc": loc, "msg": message, "type": "value_error"}])


def short(text: str, limit: int = MAX_MESSAGE_CHARS) -> str:
    """``text`` cut to ``limit`` characters (an excerpt of whatever input it quotes)."""
    return text if len(text) <= limit else text[:limit - 3] + "..."


def retry_after(seconds: float) -> dict[str, str]:
    """The ``Retry-After`` header (whole seconds, at least 1)."""
    return {"Retry-After": str(max(1, math.ceil(seconds)))}


async def app_error(request: Request, exc: Exception) -> JSONResponse:
    assert isinstance(exc, AppError)
    if isinstance(exc, Invalid):
        return await validation_error(request, invalid(exc.loc, exc.message))
    status = next((code for cls, code in STATUS.items() if isinstance(exc, cls)), 400)
    headers = retry_after(exc.retry_after) if isinstance(exc, (TooManyRequests, Unavailable)) else None
    return JSONResponse({"detail": short(exc.message)}, status_code=status, headers=headers)


async def validation_error(request: Request, exc: Exception) -> JSONResponse:
    """422 ``{"detail": [{"loc", "msg", "type"}]}``. The offending ``input`` is not echoed (it
    may be NaN/inf, which JSON cannot carry, or large)."""
    errors = exc.errors() if isinstance(exc, RequestValidationError) else []
    detail = []
    for err in errors:
        msg = str(err.get("msg", ""))
        if err.get("type") == "value_error" and msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        detail.append({"loc": [p if isinstance(p, int) else short(str(p), MAX_LOC_CHARS) for p in err.get("loc", ())],
                       "msg": short(msg), "type": short(str(err.get("type", "value_error")), MAX_LOC_CHARS)})
    return JSONResponse({"detail": detail}, status_code=422)


async def http_error(request: Request, exc: Exception) -> Response:
    """Starlette's and FastAPI's HTTP errors as they are, but a body FastAPI could not read as
    JSON (nested too deep for the parser) is the same 422 as any other bad JSON."""
    assert isinstance(exc, StarletteHTTPException)
    if exc.status_code == 400 and exc.detail == UNREADABLE_BODY:
        return await validation_error(request, invalid(("body",), "the body is not valid JSON (or nested too deep)"))
    return await http_exception_handler(request, exc)


async def client_gone(request: Request, exc: Exception) -> Response:
    """The client went away while its request was read: one log line (nobody reads the answer)."""
    log.info("client disconnected during %s %s", request.method, request.url.path)
    return Response(status_code=400)


async def body_timeout(request: Request, exc: Exception) -> Response:
    """A request body too slow or stalled (see ``TimedReceive``): 408, the connection closed."""
    log.info("request body timed out on %s %s", request.method, request.url.path)
    return JSONResponse({"detail": "request body too slow or stalled; send it at once"}, status_code=408,
                        headers={"Connection": "close"})


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
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(ClientDisconnect, client_gone)
    app.add_exception_handler(BodyTimeout, body_timeout)
    app.add_exception_handler(RequestValidationError, validation_error)
    app.add_exception_handler(StorageError, storage_error)
    app.add_exception_handler(Exception, unhandled_error)

"""ASGI middleware of the API: the request-body limit (413), back-pressure (503 + Retry-After
when a process is saturated or reads too many uploads at once, instead of queueing for
seconds), memory given back after large uploads, and methods: ``OPTIONS`` on any path answers
204 with the path's ``Allow``, and a 405 carries the path's full ``Allow`` (Starlette's names
only the first route that matched the path)."""
from __future__ import annotations

import ctypes
import logging
from collections.abc import Iterable

from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.routing import Match, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("tryon")

OVERLOAD_RETRY_AFTER_S = 1
TRIM_AFTER_BYTES = 4 * 1024 * 1024  # uploads at least this large give their memory back afterwards


def _header(scope: Scope, name: bytes) -> bytes | None:
    for key, value in scope.get("headers") or []:
        if key == name:
            return value
    return None


def _content_length(scope: Scope) -> int | None:
    raw = _header(scope, b"content-length")
    try:
        return int(raw) if raw is not None else None
    except ValueError:
        return None


def trim_memory() -> None:
    """Give freed heap memory back to the system (glibc ``malloc_trim``; a no-op elsewhere):
    a large upload's parse leaves hundreds of MB free in malloc arenas otherwise."""
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):  # pragma: no cover - not glibc
        pass


async def _drain(receive: Receive) -> None:
    """Read and drop a request body (so that the client, still sending, reads our answer)."""
    while True:
        message = await receive()
        if message["type"] != "http.request" or not message.get("more_body", False):
            return


class BodySizeLimitMiddleware:
    """Answers 413 to request bodies larger than ``max_bytes`` (declared or streamed)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        if _header(scope, b"content-length") is not None:
            declared = _content_length(scope)
            if declared is not None and declared > self.max_bytes:
                await self._reject(scope, receive, send)
                return
            await self.app(scope, receive, send)
            return
        # No Content-Length (chunked): buffer up to the limit, then replay.
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            body = message.get("body", b"")
            size += len(body)
            if size > self.max_bytes:
                await self._reject(scope, receive, send)
                return
            chunks.append(body)
            if not message.get("more_body", False):
                break
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": b"".join(chunks), "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    async def _reject(self, scope: Scope, receive: Receive, send: Send) -> None:
        response = JSONResponse(
            {"detail": f"request body larger than {self.max_bytes} bytes"}, status_code=413
        )
        await response(scope, receive, send)


class BackPressureMiddleware:
    """Per process: at most ``max_inflight`` API requests (``/v1/...``) at once and, among them,
    at most ``max_uploads`` multipart uploads; beyond that an immediate 503 with
    ``Retry-After`` (a rejected upload's body is read and dropped first, never kept). After a
    large upload, freed memory is given back to the system."""

    def __init__(self, app: ASGIApp, max_inflight: int, max_uploads: int) -> None:
        self.app = app
        self.max_inflight = max_inflight
        self.max_uploads = max_uploads
        self.inflight = 0
        self.uploads = 0

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].startswith("/v1/"):
            await self.app(scope, receive, send)
            return
        upload = scope["method"] == "POST" and (_header(scope, b"content-type") or b"").lower().startswith(
            b"multipart/form-data")
        if self.inflight >= self.max_inflight or (upload and self.uploads >= self.max_uploads):
            what = "uploads" if upload and self.uploads >= self.max_uploads else "requests"
            if upload:
                await _drain(receive)
            response = JSONResponse({"detail": f"the server is busy ({what}); retry shortly"}, status_code=503,
                                    headers={"Retry-After": str(OVERLOAD_RETRY_AFTER_S)})
            await response(scope, receive, send)
            return
        self.inflight += 1
        self.uploads += upload
        try:
            await self.app(scope, receive, send)
        finally:
            self.inflight -= 1
            self.uploads -= upload
            if upload and (_content_length(scope) or TRIM_AFTER_BYTES) >= TRIM_AFTER_BYTES:
                await run_in_threadpool(trim_memory)


CANDIDATE_METHODS = ("GET", "POST", "PUT", "PATCH", "DELETE")


def allowed_methods(routes: Iterable, path: str) -> set[str] | None:
    """The methods the app answers on ``path``, asked of the routes themselves (included
    routers count as the router counts them); a mount (static files: GET) only when no API
    route serves the path. None when nothing serves it."""
    methods: set[str] = set()
    mounted = False
    routes = list(routes)
    for method in CANDIDATE_METHODS:
        scope = {"type": "http", "path": path, "method": method, "root_path": "", "headers": []}
        for route in routes:
            try:
                match, _ = route.matches(scope)
            except Exception:  # pragma: no cover - a route that cannot judge this scope
                continue
            if match == Match.FULL:
                if isinstance(route, Mount):
                    mounted = True
                else:
                    methods.add(method)
                break
    if not methods and mounted:
        methods.add("GET")
    if not methods:
        return None
    if "GET" in methods:
        methods.add("HEAD")
    return methods | {"OPTIONS"}


def allow_header(methods: set[str]) -> str:
    return ", ".join(sorted(methods))


class MethodsMiddleware:
    """``OPTIONS`` (not a CORS preflight, which the CORS middleware answers) on a served path:
    204 with ``Allow``; on an unknown path: 404. A 405 gets the path's full ``Allow``."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        routes = getattr(scope.get("app"), "routes", ())
        if scope["method"] == "OPTIONS":
            methods = allowed_methods(routes, scope["path"])
            if methods is None:
                response = JSONResponse({"detail": "Not Found"}, status_code=404)
            else:
                response = Response(status_code=204, headers={"Allow": allow_header(methods)})
            await response(scope, receive, send)
            return

        async def send_with_allow(message: Message) -> None:
            if message["type"] == "http.response.start" and message["status"] == 405:
                methods = allowed_methods(routes, scope["path"]) or {"OPTIONS"}
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"allow"]
                headers.append((b"allow", allow_header(methods).encode()))
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_allow)

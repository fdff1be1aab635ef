"""ASGI middleware of the API: the client's address (``X-Forwarded-For`` from trusted proxies
only), the request-body limit (413), slow or stalled bodies (408), back-pressure (503 +
Retry-After when a process is saturated or reads too many uploads at once, instead of queueing
for seconds; an upload takes its slot only once its body is in), memory given back after large
uploads, and methods: ``OPTIONS`` on any path answers 204 with the path's ``Allow``, and a 405
carries the path's full ``Allow`` (Starlette's names only the first route that matched the path)."""
from __future__ import annotations

import asyncio
import ctypes
import ipaddress
import logging
import socket
import tempfile
import time
from collections.abc import Iterable

from fastapi.responses import JSONResponse, Response
from starlette.concurrency import run_in_threadpool
from starlette.routing import Match, Mount
from starlette.types import ASGIApp, Message, Receive, Scope, Send

log = logging.getLogger("tryon")

OVERLOAD_RETRY_AFTER_S = 1
TRIM_AFTER_BYTES = 256 * 1024  # uploads at least this large give their memory back afterwards (~1 ms)
SPOOL_MEMORY_BYTES = 1024 * 1024  # an upload's body is kept in memory up to this, then in a temporary file
REPLAY_CHUNK_BYTES = 64 * 1024
PROXY_RESOLVE_S = 30.0  # trusted proxies named by host name are resolved again after this


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


class TrustedProxyMiddleware:
    """The client's address (``scope["client"]``) from ``X-Forwarded-For`` when, and only when,
    the connection comes from a trusted proxy: the right-most address not itself a trusted
    proxy. Proxies are IP addresses, networks or host names (a compose service: resolved every
    :data:`PROXY_RESOLVE_S`). Without trusted proxies the socket's address stands."""

    def __init__(self, app: ASGIApp, proxies: list[str]) -> None:
        self.app = app
        self.networks = []
        self.names = []
        for p in proxies:
            try:
                self.networks.append(ipaddress.ip_network(p, strict=False))
            except ValueError:
                self.names.append(p)
        self.resolved: set[str] = set()
        self.resolved_at = -PROXY_RESOLVE_S

    async def _resolve(self) -> None:
        if not self.names or time.monotonic() - self.resolved_at < PROXY_RESOLVE_S:
            return
        self.resolved_at = time.monotonic()
        found: set[str] = set()
        loop = asyncio.get_running_loop()
        for name in self.names:
            try:
                for info in await loop.getaddrinfo(name, None, type=socket.SOCK_STREAM):
                    found.add(str(info[4][0]))
            except OSError:
                log.warning("trusted proxy %r does not resolve", name[:100])
        self.resolved = found

    def _trusted(self, addr: str) -> bool:
        if addr in self.resolved:
            return True
        try:
            ip = ipaddress.ip_address(addr)
        except ValueError:
            return False
        return any(ip in net for net in self.networks)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] in ("http", "websocket") and (self.networks or self.names) and scope.get("client"):
            await self._resolve()
            peer = scope["client"][0]
            forwarded = _header(scope, b"x-forwarded-for")
            if forwarded and self._trusted(peer):
                client = peer
                for hop in reversed([h.strip() for h in forwarded.decode("latin-1").split(",")]):
                    try:
                        client = str(ipaddress.ip_address(hop))
                    except ValueError:
                        break
                    if not self._trusted(client):
                        break
                scope = {**scope, "client": (client, 0)}
        await self.app(scope, receive, send)


class BodyTimeout(Exception):
    """A request body that stalled, or came in slower than the minimum rate."""


class TimedReceive:
    """``receive`` of a request body with deadlines: each message within ``timeout`` seconds,
    and after the first ``timeout`` seconds the body's average at least ``min_rate`` bytes/s
    (0: no minimum); :class:`BodyTimeout` otherwise. Once the body is in, plain ``receive``."""

    def __init__(self, receive: Receive, timeout: float, min_rate: int) -> None:
        self.receive = receive
        self.timeout = timeout
        self.min_rate = min_rate
        self.start = time.monotonic()
        self.received = 0
        self.done = False
        self.timed_out = False

    async def __call__(self) -> Message:
        if self.done:
            return await self.receive()
        wait = self.timeout
        if self.min_rate:
            wait = min(wait, self.start + self.timeout + self.received / self.min_rate - time.monotonic())
        try:
            if wait <= 0:
                raise asyncio.TimeoutError
            message = await asyncio.wait_for(self.receive(), wait)
        except asyncio.TimeoutError:
            self.timed_out = True
            raise BodyTimeout(f"request body too slow: {self.received} bytes in "
                              f"{time.monotonic() - self.start:.1f} s") from None
        if message["type"] == "http.request":
            self.received += len(message.get("body", b""))
            self.done = not message.get("more_body", False)
        else:
            self.done = True
        return message


async def _answer_timeout(scope: Scope, receive: Receive, send: Send, timed: TimedReceive) -> None:
    log.info("request body timed out on %s %s (%d bytes in %.1f s)", scope["method"], scope["path"],
             timed.received, time.monotonic() - timed.start)
    response = JSONResponse({"detail": "request body too slow or stalled; send it at once"}, status_code=408,
                            headers={"Connection": "close"})
    await response(scope, receive, send)


class BodySizeLimitMiddleware:
    """Answers 413 to request bodies larger than ``max_bytes`` (declared or streamed)."""

    def __init__(self, app: ASGIApp, max_bytes: int, body_timeout: float = 5.0, body_min_rate: int = 0) -> None:
        self.app = app
        self.max_bytes = max_bytes
        self.body_timeout = body_timeout
        self.body_min_rate = body_min_rate

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
        # No Content-Length (chunked): buffer up to the limit (with the body deadlines), then replay.
        chunks: list[bytes] = []
        size = 0
        timed = TimedReceive(receive, self.body_timeout, self.body_min_rate)
        while True:
            try:
                message = await timed()
            except BodyTimeout:
                await _answer_timeout(scope, receive, send, timed)
                return
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
    at most ``max_uploads`` multipart uploads being parsed; beyond that an immediate 503 with
    ``Retry-After``. Request bodies have deadlines (:class:`TimedReceive`: 408 when stalled or too
    slow); an upload's body is read whole (spooled to a temporary file past
    :data:`SPOOL_MEMORY_BYTES`) before it takes an upload slot, so slow senders cannot hold the
    slots. A client that goes away mid-body is one log line. After a large upload, freed memory
    is given back to the system."""

    def __init__(self, app: ASGIApp, max_inflight: int, max_uploads: int, body_timeout: float = 5.0,
                 body_min_rate: int = 0) -> None:
        self.app = app
        self.max_inflight = max_inflight
        self.max_uploads = max_uploads
        self.body_timeout = body_timeout
        self.body_min_rate = body_min_rate
        self.inflight = 0
        self.uploads = 0

    def _busy(self, what: str) -> JSONResponse:
        return JSONResponse({"detail": f"the server is busy ({what}); retry shortly"}, status_code=503,
                            headers={"Retry-After": str(OVERLOAD_RETRY_AFTER_S)})

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or not scope["path"].startswith("/v1/"):
            await self.app(scope, receive, send)
            return
        upload = scope["method"] == "POST" and (_header(scope, b"content-type") or b"").lower().startswith(
            b"multipart/form-data")
        timed = TimedReceive(receive, self.body_timeout, self.body_min_rate)
        if scope["method"] in ("GET", "HEAD", "DELETE", "OPTIONS") and not _content_length(scope):
            timed.done = True
        if self.inflight >= self.max_inflight:
            await self._refuse(scope, timed, send, "requests", upload)
            return
        self.inflight += 1
        try:
            if upload:
                await self._upload(scope, timed, send)
            else:
                await self._request(scope, timed, send)
        finally:
            self.inflight -= 1

    async def _refuse(self, scope: Scope, timed: TimedReceive, send: Send, what: str, drain: bool) -> None:
        if drain and not timed.done:  # read and drop the body, so that the client reads our answer
            try:
                await _drain(timed)
            except BodyTimeout:
                pass
        await self._busy(what)(scope, timed, send)

    async def _request(self, scope: Scope, timed: TimedReceive, send: Send) -> None:
        started = False

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if timed.timed_out and not started:
                return  # the app's answer to a body it could not read: replaced by the 408
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, timed, guarded_send)
        except Exception:
            if not timed.timed_out or started:
                raise
        if timed.timed_out and not started:
            await _answer_timeout(scope, timed, send, timed)

    async def _upload(self, scope: Scope, timed: TimedReceive, send: Send) -> None:
        with tempfile.SpooledTemporaryFile(max_size=SPOOL_MEMORY_BYTES) as spool:
            try:
                while not timed.done:
                    message = await timed()
                    if message["type"] != "http.request":
                        log.info("client disconnected during the upload of %s %s (%d bytes in)", scope["method"],
                                 scope["path"], timed.received)
                        return
                    spool.write(message.get("body", b""))
            except BodyTimeout:
                await _answer_timeout(scope, timed, send, timed)
                return
            if self.uploads >= self.max_uploads:
                await self._busy("uploads")(scope, timed, send)
                return
            size = spool.tell()
            spool.seek(0)
            left = size

            async def replay() -> Message:
                nonlocal left
                if left <= 0 and left != -1:
                    left = -1
                    return {"type": "http.request", "body": b"", "more_body": False}
                if left == -1:
                    return await timed()
                chunk = spool.read(min(REPLAY_CHUNK_BYTES, left))
                left -= len(chunk)
                if left <= 0:
                    left = -1
                    return {"type": "http.request", "body": chunk, "more_body": False}
                return {"type": "http.request", "body": chunk, "more_body": True}

            self.uploads += 1
            try:
                await self.app(scope, replay, send)
            finally:
                self.uploads -= 1
                if size >= TRIM_AFTER_BYTES:
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

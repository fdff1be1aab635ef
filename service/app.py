"""The FastAPI application factory (``uvicorn --factory service.app:create_app``)."""
from __future__ import annotations

import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service import __version__
from service.api.jobs_routes import router as jobs_router
from service.api.routes import router
from service.api.tryon_routes import router as tryon_router
from service.model.body import load_body_model
from service.settings import Settings, get_settings

log = logging.getLogger("tryon")

REPO_ROOT = Path(__file__).resolve().parent.parent


def web_client_dir() -> Path | None:
    """The customer page directory: ``web_client/`` next to the package (repo checkout or
    editable install), else ``./web_client`` (the Docker image's working directory)."""
    for candidate in (REPO_ROOT / "web_client", Path.cwd() / "web_client"):
        if (candidate / "index.html").is_file():
            return candidate
    return None


class BodySizeLimitMiddleware:
    """Answers 413 to request bodies larger than ``max_bytes`` (declared or streamed)."""

    def __init__(self, app: ASGIApp, max_bytes: int) -> None:
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None:
            try:
                too_big = int(declared) > self.max_bytes
            except ValueError:
                too_big = False
            if too_big:
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


async def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    """422 ``{"detail": [{"loc", "msg", "type"}]}``. The offending ``input`` is not echoed (it
    may be NaN/inf, which JSON cannot carry, or large)."""
    errors = exc.errors() if isinstance(exc, RequestValidationError) else []
    detail = []
    for err in errors:
        msg = str(err.get("msg", ""))
        if err.get("type") == "value_error" and msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        detail.append(
            {"loc": [p if isinstance(p, int) else str(p) for p in err.get("loc", ())],
             "msg": msg, "type": str(err.get("type", "value_error"))}
        )
    return JSONResponse({"detail": detail}, status_code=422)


async def _unhandled_error(request: Request, exc: Exception) -> JSONResponse:
    """Genuine bugs only: log with traceback, answer a generic 500."""
    log.exception("unhandled error on %s %s", request.method, request.url.path, exc_info=exc)
    return JSONResponse({"detail": "internal server error"}, status_code=500)


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app. The body model is loaded once, in the lifespan (``app.state.body_model``),
    so building the app (e.g. for the OpenAPI document) needs no model file."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
        path = str(settings.body_model_path) if settings.body_model_path else None
        model = load_body_model(path)
        log.info("body model loaded from %s (%d components)", model.path, model.n_components)
        app.state.body_model = model
        from service import storage as storage_mod
        from service.catalogue import BodyCache, ensure_demo_garments

        storage = storage_mod.Storage(settings)
        app.state.storage = storage
        app.state.body_cache = BodyCache()
        storage_mod.set_default(storage)
        worker = storage_mod.EmbeddedWorker.start(settings) if settings.runs_embedded_worker() else None
        try:
            ids = ensure_demo_garments(model, storage)
            log.info("storage ready (%s); demo garments: %s",
                     settings.redis_url or f"embedded redis under {settings.data_dir}", ", ".join(ids))
            yield
        finally:
            if worker is not None:
                worker.stop()
            storage_mod.set_default(None)
            storage.close()

    app = FastAPI(
        title="tryon",
        version=__version__,
        description="Online 3D clothes try-on: avatars from body measurements or meshes, retailers' garments "
        "as clothing bases, garments and outfits fitted to each customer, as JSON or GLB.",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_upload_bytes)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(Exception, _unhandled_error)
    app.include_router(router)
    app.include_router(tryon_router)
    app.include_router(jobs_router)
    three = next((c for c in (REPO_ROOT / "node_modules" / "three", Path.cwd() / "node_modules" / "three")
                  if c.is_dir()), None)
    if three is not None:  # three.js from the npm lockfile (npm ci), for the customer page
        app.mount("/vendor/three", StaticFiles(directory=three), name="three")
    static = web_client_dir()
    if static is not None:  # mounted last: API routes take precedence
        app.mount("/", StaticFiles(directory=static, html=True), name="web_client")
    return app

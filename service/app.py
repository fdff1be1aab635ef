"""The FastAPI application factory (``uvicorn --factory service.app:create_app``)."""
from __future__ import annotations

import logging
import os
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

from fastapi import FastAPI
from fastapi.middleware.cors import CORSMiddleware
from fastapi.staticfiles import StaticFiles

from service import __version__
from service.api import body, customers, errors, examples, garments, health, jobs, tryon
from service.api import responses as R
from service.api.middleware import (
    BackPressureMiddleware,
    BodySizeLimitMiddleware,
    MethodsMiddleware,
    TrustedProxyMiddleware,
)
from service.api.logs import install_redaction
from service.api.schemas import attribute_ranges, document_measurements
from service.application.context import Context
from service.model.body import shape
from service.model.body.model import load_body_model
from service.settings import SERVE_PID_ENV, Settings, get_settings
from service.storage.redis import die_with_parent
from service.storage.supervise import DemoDrape, EmbeddedWorker

log = logging.getLogger("tryon")

REPO_ROOT = Path(__file__).resolve().parent.parent
CORS_HEADERS = ["Authorization", "Content-Type", "X-API-Key", "If-None-Match", "Accept"]
CORS_EXPOSED = ["ETag", "Location", "Retry-After"]


def web_client_dir() -> Path | None:
    """The customer page directory: ``web_client/`` next to the package (repo checkout or
    editable install), else ``./web_client`` (the Docker image's working directory)."""
    for candidate in (REPO_ROOT / "web_client", Path.cwd() / "web_client"):
        if (candidate / "index.html").is_file():
            return candidate
    return None


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app. The body model is loaded once, in the lifespan (``app.state.body_model``),
    so building the app (e.g. for the OpenAPI document) needs no model file."""
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        serve_pid = os.environ.get(SERVE_PID_ENV)
        if serve_pid and serve_pid.isdigit() and int(serve_pid) != os.getpid():
            die_with_parent(int(serve_pid))  # a server process of `tryon serve --workers N`: no orphan
        Path(settings.data_dir).mkdir(parents=True, exist_ok=True)
        model = load_body_model(settings.body_model_path)
        shape.precompute(model)  # the per-model data of measurements -> avatar, built once
        log.info("body model %s loaded from %s (%d components)", model.version, model.path, model.n_components)
        ctx = Context.open(settings, model)
        app.state.body_model = model
        app.state.context = ctx
        worker = EmbeddedWorker.start(settings) if settings.runs_embedded_worker() else None
        demo_drape = None
        try:
            ids = ctx.garments.ensure_demo()
            log.info("storage ready (%s); demo garments: %s",
                     settings.redis_url or f"embedded redis under {settings.data_dir}", ", ".join(ids))
            if settings.runs_demo_drape() and ctx.garments.demo_to_drape():
                demo_drape = DemoDrape.start(settings)
            yield
        finally:
            if demo_drape is not None:
                demo_drape.stop()
            if worker is not None:
                worker.stop()
            app.state.context = None
            ctx.close()

    app = FastAPI(
        title="tryon",
        version=__version__,
        description="Online 3D clothes try-on: avatars from body measurements or meshes, retailers' garments "
        "as clothing bases, garments and outfits fitted to each customer, as JSON or GLB.",
        lifespan=lifespan,
        responses=R.UNAVAILABLE,
    )
    app.state.settings = settings
    generate = app.openapi

    def openapi() -> dict:
        """FastAPI's document, with ``measurements`` described as the body model checks it."""
        if app.openapi_schema is None:
            app.openapi_schema = document_measurements(generate(), attribute_ranges(settings.body_model_path))
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
    # outermost last: trusted proxies, CORS (preflights, headers on every answer), methods
    # (OPTIONS, 405's Allow), the body limit (413), back-pressure (503) and body deadlines
    # (408), then the routes
    body_limits = {"body_timeout": settings.body_timeout, "body_min_rate": settings.body_min_rate}
    app.add_middleware(BackPressureMiddleware, max_inflight=settings.max_inflight, max_uploads=settings.max_uploads,
                       **body_limits)
    app.add_middleware(BodySizeLimitMiddleware, max_bytes=settings.max_upload_bytes, **body_limits)
    app.add_middleware(MethodsMiddleware)
    origins = settings.cors_origin_list()
    if origins:
        app.add_middleware(CORSMiddleware, allow_origins=origins, allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=CORS_HEADERS, expose_headers=CORS_EXPOSED, max_age=600)
    # outermost: the client's address from trusted proxies only (rate limits and caps count by it)
    app.add_middleware(TrustedProxyMiddleware, proxies=settings.trusted_proxy_list())
    errors.install(app)
    install_redaction()
    for module in (health, body, examples, customers, garments, tryon, jobs):
        app.include_router(module.router)
    three = next((c for c in (REPO_ROOT / "node_modules" / "three", Path.cwd() / "node_modules" / "three")
                  if c.is_dir()), None)
    if three is not None:  # three.js from the npm lockfile (npm ci), for the customer page
        app.mount("/vendor/three", StaticFiles(directory=three), name="three")
    static = web_client_dir()
    if static is not None:  # mounted last: API routes take precedence
        app.mount("/", StaticFiles(directory=static, html=True), name="web_client")
    return app

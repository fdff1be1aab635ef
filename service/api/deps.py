"""Every FastAPI dependency of the routes: settings, the body model, the application context and
its use cases, the retailer's API key, the customer's credentials (``Authorization: Bearer
<token>`` or the owning retailer's key), the rate limit of the expensive routes, the GLB
compression parameter and ``If-None-Match``. All async and override-free on purpose: a sync or
overridden dependency costs a thread-pool hop or a signature analysis on every request."""
from __future__ import annotations

import hmac
from collections.abc import AsyncIterator
from typing import Annotated, Literal

from fastapi import Depends, HTTPException, Query, Request, WebSocket
from fastapi.concurrency import run_in_threadpool
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer
from starlette.requests import HTTPConnection

from service.application.auth import Credentials
from service.application.context import Context
from service.application.customers import CustomerService
from service.application.drapes import ExactDrapes
from service.application.editing import EditingService
from service.application.garments import GarmentService
from service.application.jobs import JobService
from service.application.limits import Limits, Requester, current_requester
from service.application.tryon import TryOnService
from service.model.body.model import BodyModel, load_body_model
from service.settings import Settings, get_settings


async def get_app_settings(request: HTTPConnection) -> Settings:
    """This app's settings (``create_app(settings)`` stores them in ``app.state``)."""
    settings = getattr(request.app.state, "settings", None)
    return settings if settings is not None else get_settings()


SettingsDep = Annotated[Settings, Depends(get_app_settings)]


async def get_body_model(request: Request, settings: SettingsDep) -> BodyModel:
    """The body model loaded once at startup; without a lifespan (an in-process test client)
    the process-wide cached model for ``settings``."""
    model = getattr(request.app.state, "body_model", None)
    return model if model is not None else load_body_model(settings.body_model_path)


async def get_context(request: HTTPConnection) -> Context:
    ctx = getattr(request.app.state, "context", None)
    if ctx is None:  # pragma: no cover - the lifespan always sets it
        raise HTTPException(503, "storage is not available")
    return ctx


ContextDep = Annotated[Context, Depends(get_context)]
BodyModelDep = Annotated[BodyModel, Depends(get_body_model)]


async def get_customers(ctx: ContextDep) -> CustomerService:
    return ctx.customers


async def get_garments(ctx: ContextDep) -> GarmentService:
    return ctx.garments


async def get_tryon(ctx: ContextDep) -> TryOnService:
    return ctx.tryon


async def get_drapes(ctx: ContextDep) -> ExactDrapes:
    return ctx.drapes


async def get_jobs(ctx: ContextDep) -> JobService:
    return ctx.jobs


async def get_editing(ctx: ContextDep) -> EditingService:
    return ctx.editing


async def get_limits(ctx: ContextDep) -> Limits:
    return ctx.limits


CustomersDep = Annotated[CustomerService, Depends(get_customers)]
GarmentsDep = Annotated[GarmentService, Depends(get_garments)]
TryOnDep = Annotated[TryOnService, Depends(get_tryon)]
JobsDep = Annotated[JobService, Depends(get_jobs)]
DrapesDep = Annotated[ExactDrapes, Depends(get_drapes)]
EditingDep = Annotated[EditingService, Depends(get_editing)]
LimitsDep = Annotated[Limits, Depends(get_limits)]

api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False, description="Retailer API key (TRYON_RETAILER_KEYS)")


bearer_scheme = HTTPBearer(auto_error=False, description="A customer's token, from POST /v1/customers")
KeyDep = Annotated[str | None, Depends(api_key_header)]


def retailer_of(settings: Settings, key: str) -> str | None:
    """The retailer whose API key ``key`` is, or None."""
    found = None
    for known, name in settings.retailers().items():
        if hmac.compare_digest(known.encode(), key.encode()):
            found = name
    return found


async def get_retailer(settings: SettingsDep, key: KeyDep = None) -> str:
    """The retailer name of the request's ``X-API-Key`` (401 without one, 403 if unknown)."""
    if not key:
        raise HTTPException(401, "missing X-API-Key header (retailer API key)", headers={"WWW-Authenticate": "ApiKey"})
    name = retailer_of(settings, key)
    if name is None:
        raise HTTPException(403, "invalid API key")
    return name


async def get_optional_retailer(settings: SettingsDep, key: KeyDep = None) -> str | None:
    """The retailer of ``X-API-Key`` when one is sent (403 if unknown), else None."""
    return await get_retailer(settings, key) if key else None


async def get_credentials(
        retailer: Annotated[str | None, Depends(get_optional_retailer)],
        bearer: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer_scheme)] = None) -> Credentials:
    """What the request presents to open a customer: its token and/or its retailer's key."""
    return Credentials(token=bearer.credentials if bearer else None, retailer=retailer)


def credentials_of(websocket: WebSocket, settings: Settings) -> Credentials | None:
    """A WebSocket's credentials (browsers cannot set headers on one): ``Authorization: Bearer``
    or the ``token`` query parameter, and/or ``X-API-Key``. None: an unknown API key."""
    auth = websocket.headers.get("authorization", "")
    token = auth[7:].strip() if auth.lower().startswith("bearer ") else websocket.query_params.get("token")
    key = websocket.headers.get("x-api-key")
    retailer = retailer_of(settings, key) if key else None
    if key and retailer is None:
        return None
    return Credentials(token=token or None, retailer=retailer)


RetailerDep = Annotated[str, Depends(get_retailer)]
OptionalRetailerDep = Annotated[str | None, Depends(get_optional_retailer)]
CredentialsDep = Annotated[Credentials, Depends(get_credentials)]


def requester_of(request: Request, settings: Settings, key: str | None) -> Requester:
    """Who the request counts against: its retailer (valid ``X-API-Key``) or its client address
    (the socket's, or the one trusted proxies forwarded)."""
    retailer = retailer_of(settings, key) if key else None
    return Requester(client=request.client.host if request.client else None, retailer=retailer)


async def expensive(request: Request, limits: LimitsDep, settings: SettingsDep,
                    key: KeyDep = None) -> AsyncIterator[None]:
    """An expensive request holds one of its requester's ``TRYON_MAX_EXPENSIVE_CLIENT`` slots of
    this process until it is answered (429 with ``Retry-After`` when all are taken)."""
    requester = requester_of(request, settings, key)
    current_requester.set(requester)
    with limits.slot(requester):
        yield


async def rate_limited(request: Request, limits: LimitsDep, settings: SettingsDep,
                       key: KeyDep = None) -> AsyncIterator[None]:
    """Counts an expensive request against its retailer's (valid ``X-API-Key``) or its client's
    rate limit: 429 with ``Retry-After`` when spent (the Redis call runs off the event loop);
    then holds a slot as :func:`expensive` does. The use cases that queue jobs count them
    against the same requester."""
    requester = requester_of(request, settings, key)
    await run_in_threadpool(limits.check, requester.client, requester.retailer)
    current_requester.set(requester)
    with limits.slot(requester):
        yield


RateLimited = Depends(rate_limited)
Expensive = Depends(expensive)


async def get_if_none_match(request: Request) -> list[str] | None:
    """The request's ``If-None-Match`` tags (``W/`` dropped), or None."""
    inm = request.headers.get("if-none-match")
    return [t.strip().removeprefix("W/") for t in inm.split(",")] if inm else None


IfNoneMatchDep = Annotated[list[str] | None, Depends(get_if_none_match)]

Compression = Annotated[
    Literal["quantize", "meshopt"] | None,
    Query(description="GLB compression: quantize (KHR_mesh_quantization) or meshopt "
                      "(EXT_meshopt_compression); omitted: plain float32"),
]

# The avatar's look (issue 11) on avatar.glb, outfit.glb and POST /v1/avatars.
Hair = Annotated[
    str | None,
    Query(max_length=64, description="The avatar's hair: a hair id of `GET /v1/looks`, or `none` for no hair; "
                                     "omitted: the default style of the avatar's gender (its `gender` "
                                     "measurement, given or estimated). An unknown id is a 422"),
]
Underwear = Annotated[
    bool,
    Query(description="Dress the avatar in its gender's base layer (underwear; the body under it is not "
                      "drawn). Default true: nobody is shown nude; false shows the bare body"),
]
# Pose-corrective morph targets (issue 11) on the try-on GLBs.
PoseCorrectives = Annotated[
    bool,
    Query(description="Give each garment one morph target per page pose (`pose:<name>`, the presets of "
                      "`GET /v1/customers/{cid}/poses`): rest-space POSITION deltas (sparse accessors) that "
                      "keep the skinned garment outside the body in that pose; a viewer sets the current "
                      "pose's target influence to 1, the others to 0. Computing them costs ~40-160 ms per garment "
                      "and pose (2k-8k vertices), plus ~0.6 s once per customer to adapt the poses; they are "
                      "then cached per process (the same customer and garments again: ~1 ms). Default false: "
                      "no targets"),
]

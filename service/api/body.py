"""The body model: its description, avatars from measurements, the template topology."""
from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Header, Response

from service.api import responses as R
from service.api.deps import BodyModelDep, Compression, Hair, RateLimited, Underwear
from service.api.schemas import AttributeOut, AvatarRequest, AvatarResponse, BodyModelResponse, LooksResponse
from service.application import avatars, scenes
from service.application import look as looks
from service.model.body.model import BONES

router = APIRouter(tags=["body"])


@router.get("/v1/body-model", response_model=BodyModelResponse)
async def get_body_model_info(model: BodyModelDep) -> BodyModelResponse:
    """The attributes accepted by ``POST /v1/avatars`` (with ranges), bones and components."""
    return BodyModelResponse(
        attributes=[AttributeOut(name=a.name, unit=a.unit, min=a.min, max=a.max, description=a.description)
                    for a in model.attributes],
        bones=list(BONES), components=model.n_components)


@router.post("/v1/avatars", response_model=AvatarResponse, dependencies=[RateLimited],
             openapi_extra={"security": [{}]},
             responses={200: {"description": "The avatar: JSON, or GLB when `Accept: model/gltf-binary`.",
                              "content": {R.GLB_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}}},
                        **R.JSON_BODY, **R.RATE_LIMITED})
def create_avatar(request: AvatarRequest, model: BodyModelDep,
                  accept: Annotated[str | None, Header()] = None, hair: Hair = None,
                  underwear: Underwear = True, compression: Compression = None) -> Any:
    """Fit an avatar to the given measurements; the attributes not given are estimated. As GLB:
    the skinned body (node ``avatar``) with ``eyes``, ``eyebrows``, ``hair`` and ``underwear``
    nodes, like ``GET /v1/customers/{cid}/avatar.glb`` (``hair`` and ``underwear`` choose;
    ``compression`` as on every GLB route)."""
    avatar = avatars.from_measurements(model, dict(request.measurements))
    if R.wants_glb(accept):
        look = looks.resolve(looks.gender_of(avatar.measurements), hair, underwear)
        return R.glb(scenes.avatar_glb(model, avatar.vertices, compression, look=look))
    return AvatarResponse(weights=[float(w) for w in np.asarray(avatar.weights).ravel()],
                          measurements={k: (v if isinstance(v, str) else float(v))
                                        for k, v in avatar.measurements.items()},
                          estimated=list(avatar.estimated))


@router.get("/v1/looks", response_model=LooksResponse)
def get_looks() -> LooksResponse:
    """The avatar's look choices for the page: the hair styles (``hair=`` on ``avatar.glb``,
    ``outfit.glb`` and ``POST /v1/avatars``; ``none`` for no hair) and, per gender, the default
    hair and whether underwear is worn by default (it is: ``underwear=false`` shows the bare
    body)."""
    return LooksResponse.model_validate({"hair": looks.hair_choices(), "defaults": looks.defaults()})


@router.get("/v1/body-model/template.obj", response_class=Response, responses=R.OBJ_RESPONSE)
def template_obj(model: BodyModelDep) -> Response:
    """The template topology (the mean avatar's body surface): deform it and upload it to
    ``POST /v1/customers`` (any unit, pose-free: vertex order is what matters)."""
    return R.obj(avatars.template_obj(model))


@router.get("/v1/body-model/template.glb", response_class=Response, responses=R.GLB_RESPONSE)
def template_glb(model: BodyModelDep, compression: Compression = None) -> Response:
    """The template topology (mean avatar body surface) as a skinned GLB."""
    return R.glb(scenes.avatar_glb(model, model.mean, compression))

"""HTTP routes (thin: validation in schemas, work in service.model)."""
from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from fastapi import APIRouter, Depends, Header, Response
from fastapi.exceptions import RequestValidationError

from service.api.deps import get_body_model
from service.api.schemas import (
    AttributeOut,
    AvatarRequest,
    AvatarResponse,
    BodyModelResponse,
    HealthResponse,
)
from service.model.body import BONES, BodyModel
from service.model.gltf import mesh_to_glb

GLB_MEDIA_TYPE = "model/gltf-binary"
JSON_MEDIA_TYPE = "application/json"

router = APIRouter()
BodyModelDep = Annotated[BodyModel, Depends(get_body_model)]


def _accept_quality(accept: str | None, media_type: str) -> float:
    """The q-value ``accept`` gives ``media_type`` (exact > type/* > */*); 0 if not accepted."""
    if not accept:
        return 1.0 if media_type == JSON_MEDIA_TYPE else 0.0
    best, best_rank = 0.0, -1
    main = media_type.split("/")[0]
    for part in accept.split(","):
        fields = [f.strip() for f in part.split(";")]
        rng = fields[0].lower()
        q = 1.0
        for p in fields[1:]:
            if p.lower().startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        rank = 2 if rng == media_type else 1 if rng == f"{main}/*" else 0 if rng == "*/*" else -1
        if rank > best_rank:
            best, best_rank = q, rank
    return best if best_rank >= 0 else 0.0


def wants_glb(accept: str | None) -> bool:
    """True when the Accept header prefers GLB strictly over JSON."""
    return _accept_quality(accept, GLB_MEDIA_TYPE) > _accept_quality(accept, JSON_MEDIA_TYPE)


def avatar_glb(model: BodyModel, vertices: np.ndarray, compression: str | None = None) -> bytes:
    """The customer-visible skinned body surface of a (V, 3) avatar as GLB bytes
    (``compression``: None, "quantize" or "meshopt")."""
    n_body = model.n_body_vertices
    return mesh_to_glb(
        model.body_vertices(vertices),
        model.body_faces,
        name="avatar",
        skin={
            "joints": model.joints(vertices),
            "parents": np.asarray(model.bone_parents),
            "joint_names": list(BONES),
            "vertex_joints": model.lbs_indices[:n_body],
            "vertex_weights": model.lbs_weights[:n_body],
        },
        compression=compression,
    )


@router.get("/healthz", response_model=HealthResponse, tags=["ops"])
async def healthz() -> HealthResponse:
    """Liveness probe."""
    return HealthResponse()


@router.get("/v1/body-model", response_model=BodyModelResponse, tags=["body"])
async def get_body_model_info(model: BodyModelDep) -> BodyModelResponse:
    """The attributes accepted by ``POST /v1/avatars`` (with ranges), bones and components."""
    return BodyModelResponse(
        attributes=[
            AttributeOut(name=a.name, unit=a.unit, min=a.min, max=a.max, description=a.description)
            for a in model.attributes
        ],
        bones=list(BONES),
        components=model.n_components,
    )


@router.post(
    "/v1/avatars",
    response_model=AvatarResponse,
    tags=["body"],
    responses={
        200: {
            "description": "The avatar: JSON, or GLB when `Accept: model/gltf-binary`.",
            "content": {GLB_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}},
        }
    },
)
def create_avatar(
    request: AvatarRequest,
    model: BodyModelDep,
    accept: Annotated[str | None, Header()] = None,
) -> Any:
    """Fit an avatar to the given measurements; the attributes not given are estimated."""
    from service.model.shape import MeasurementError, avatar_from_measurements

    try:
        avatar = avatar_from_measurements(model, dict(request.measurements))
    except MeasurementError as exc:
        field = str(getattr(exc, "field", ""))
        msg = str(getattr(exc, "message", "") or exc)
        raise RequestValidationError(
            [{"loc": ("body", "measurements", field), "msg": msg, "type": "value_error"}]
        ) from exc
    if wants_glb(accept):
        return Response(content=avatar_glb(model, avatar.vertices), media_type=GLB_MEDIA_TYPE)
    return AvatarResponse(
        weights=[float(w) for w in np.asarray(avatar.weights).ravel()],
        measurements={
            k: (v if isinstance(v, str) else float(v)) for k, v in avatar.measurements.items()
        },
        estimated=list(avatar.estimated),
    )

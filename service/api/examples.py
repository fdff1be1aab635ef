"""The example avatars retailers fit garments to."""
from __future__ import annotations

from typing import Any

from fastapi import APIRouter, Response

from service.api import responses as R
from service.api.deps import BodyModelDep, Compression, GarmentsDep
from service.api.schemas import ExampleAvatarOut
from service.application import scenes

router = APIRouter(tags=["garments"])


@router.get("/v1/example-avatars", response_model=list[ExampleAvatarOut])
async def list_example_avatars(garments: GarmentsDep) -> list[dict[str, Any]]:
    """The example avatars, in the order ``POST /v1/garments`` expects its ``meshes``: the
    mean, then mean +/- c sqrt(var_i) U_i for each component i."""
    return garments.examples.listing


@router.get("/v1/example-avatars/{example_id}.glb", response_class=Response, responses=R.GLB_RESPONSE)
def example_avatar_glb(example_id: str, model: BodyModelDep, garments: GarmentsDep,
                       compression: Compression = None) -> Response:
    """An example avatar's body surface (skinned GLB), the surface to fit garments to."""
    return R.glb(scenes.avatar_glb(model, garments.example(example_id), compression))


@router.get("/v1/example-avatars/{example_id}.obj", response_class=Response, responses=R.OBJ_RESPONSE)
def example_avatar_obj(example_id: str, model: BodyModelDep, garments: GarmentsDep) -> Response:
    """An example avatar's body surface as OBJ (metres, Y up): fit the garment to it."""
    X = garments.example(example_id)
    return R.obj(scenes.obj_text(model.body_vertices(X), model.body_faces, f"tryon example avatar {example_id}"))

"""HTTP routes of customers, example avatars, garments and try-on (work in service.catalogue)."""
from __future__ import annotations

import hmac
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Depends, File, Form, HTTPException, Query, Request, Response, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.security import APIKeyHeader
from pydantic import ValidationError
from starlette.datastructures import UploadFile as StarletteUploadFile

from service import catalogue as C
from service.api.deps import SettingsDep, get_body_model
from service.api.routes import GLB_MEDIA_TYPE, avatar_glb
from service.api.schemas import AvatarRequest, CustomerResponse, ExampleAvatarOut, GarmentResponse
from service.model.body import BodyModel
from service.storage import Storage, new_id

router = APIRouter()
BodyModelDep = Annotated[BodyModel, Depends(get_body_model)]
OBJ_MEDIA_TYPE = "model/obj"
BASIS_MAX_AGE = 86400
MAX_OUTFIT_GARMENTS = 12

Compression = Annotated[
    Literal["quantize", "meshopt"] | None,
    Query(description="GLB compression: quantize (KHR_mesh_quantization) or meshopt "
                      "(EXT_meshopt_compression); omitted: plain float32"),
]
GLB_RESPONSE = {200: {"description": "GLB (glTF 2.0 binary)",
                      "content": {GLB_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}}},
                404: {"description": "Unknown id"}}
CUSTOMER_GLB_RESPONSE = {**GLB_RESPONSE, 409: {"description": "The customer's scan is being fitted, or its fit failed"}}
OBJ_RESPONSE = {200: {"description": "Wavefront OBJ (metres, Y up)",
                      "content": {OBJ_MEDIA_TYPE: {"schema": {"type": "string"}}}},
                404: {"description": "Unknown id"}}


async def get_storage(request: Request) -> Storage:
    storage = getattr(request.app.state, "storage", None)
    if storage is None:  # pragma: no cover - the lifespan always sets it
        raise HTTPException(503, "storage is not available")
    return storage


async def get_body_cache(request: Request) -> C.BodyCache:
    cache = getattr(request.app.state, "body_cache", None)
    if cache is None:
        cache = request.app.state.body_cache = C.BodyCache()
    return cache


StorageDep = Annotated[Storage, Depends(get_storage)]
BodyCacheDep = Annotated[C.BodyCache, Depends(get_body_cache)]
api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False,
                              description="Retailer API key (TRYON_RETAILER_KEYS)")


async def get_retailer(settings: SettingsDep, key: Annotated[str | None, Depends(api_key_header)] = None) -> str:
    """The retailer name of the request's ``X-API-Key`` (401 without one, 403 if unknown)."""
    if not key:
        raise HTTPException(401, "missing X-API-Key header (retailer API key)",
                            headers={"WWW-Authenticate": "ApiKey"})
    for known, name in settings.retailers().items():
        if hmac.compare_digest(known.encode(), key.encode()):
            return name
    raise HTTPException(403, "invalid API key")


RetailerDep = Annotated[str, Depends(get_retailer)]


def _invalid(exc: C.UploadError) -> RequestValidationError:
    return RequestValidationError([{"loc": exc.loc, "msg": exc.message, "type": "value_error"}])


def _glb(data: bytes, **headers: str) -> Response:
    return Response(content=data, media_type=GLB_MEDIA_TYPE, headers=headers or None)


def _customer(storage: Storage, cid: str) -> dict[str, Any]:
    rec = storage.get_customer(cid)
    if rec is None:
        raise HTTPException(404, f"customer '{cid}' not found")
    return C.customer_view(storage, rec)


def _ready_customer(storage: Storage, cid: str) -> dict[str, Any]:
    """The customer, if its avatar exists (404 unknown; 409 while its scan is being fitted or
    when the fit failed)."""
    rec = _customer(storage, cid)
    if rec.get("status", "ready") == "ready":
        return rec
    job = (rec.get("job") or {}).get("id", "")
    if rec["status"] == "fitting":
        raise HTTPException(409, f"customer '{cid}' is not ready: its scan is being fitted "
                                 f"(job '{job}', GET /v1/jobs/{job}); try again when it is done")
    raise HTTPException(409, f"customer '{cid}' has no avatar: fitting the scan failed: "
                             f"{rec.get('error') or 'unknown error'}. Delete it and upload another scan")


def _garment(storage: Storage, gid: str) -> tuple[dict[str, Any], Any]:
    rec = storage.get_garment(gid)
    basis = storage.load_basis(gid, rec) if rec is not None else None
    if rec is None or basis is None:
        raise HTTPException(404, f"garment '{gid}' not found")
    return rec, basis


# -- body model template and example avatars ---------------------------------------------------
@router.get("/v1/body-model/template.obj", tags=["body"], response_class=Response, responses=OBJ_RESPONSE)
def template_obj(model: BodyModelDep) -> Response:
    """The template topology (the mean avatar's body surface): deform it and upload it to
    ``POST /v1/customers`` (any unit, pose-free: vertex order is what matters)."""
    text = C.obj_text(model.body_vertices(model.mean), model.body_faces,
                      "tryon body template: mean avatar body surface, metres, Y up, facing +Z")
    return Response(text, media_type=OBJ_MEDIA_TYPE)


@router.get("/v1/body-model/template.glb", tags=["body"], response_class=Response, responses=GLB_RESPONSE)
def template_glb(model: BodyModelDep, compression: Compression = None) -> Response:
    """The template topology (mean avatar body surface) as a skinned GLB."""
    return _glb(avatar_glb(model, model.mean, compression))


@router.get("/v1/example-avatars", response_model=list[ExampleAvatarOut], tags=["garments"])
async def list_example_avatars(model: BodyModelDep) -> list[dict[str, Any]]:
    """The example avatars, in the order ``POST /v1/garments`` expects its ``meshes``: the
    mean, then mean +/- c sqrt(var_i) U_i for each component i."""
    return C.examples(model).listing


def _example(model: BodyModel, example_id: str) -> np.ndarray:
    ex = C.examples(model)
    i = ex.index(example_id)
    if i is None:
        raise HTTPException(404, f"example avatar '{example_id}' not found (see /v1/example-avatars)")
    return ex.vertices[i]


@router.get("/v1/example-avatars/{example_id}.glb", tags=["garments"], response_class=Response,
            responses=GLB_RESPONSE)
def example_avatar_glb(example_id: str, model: BodyModelDep, compression: Compression = None) -> Response:
    """An example avatar's body surface (skinned GLB), the surface to fit garments to."""
    return _glb(avatar_glb(model, _example(model, example_id), compression))


@router.get("/v1/example-avatars/{example_id}.obj", tags=["garments"], response_class=Response,
            responses=OBJ_RESPONSE)
def example_avatar_obj(example_id: str, model: BodyModelDep) -> Response:
    """An example avatar's body surface as OBJ (metres, Y up): fit the garment to it."""
    X = _example(model, example_id)
    return Response(C.obj_text(model.body_vertices(X), model.body_faces, f"tryon example avatar {example_id}"),
                    media_type=OBJ_MEDIA_TYPE)


# -- customers ---------------------------------------------------------------------------------
CUSTOMER_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/AvatarRequest"}},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["mesh"],
                    "properties": {
                        "mesh": {"type": "string", "format": "binary",
                                 "description": "An avatar mesh in the template topology (/v1/body-model/"
                                                "template.obj: the body or full vertex count; OBJ/PLY/GLB) -> "
                                                "201, ready; or any other 3D scan, clothed avatar or point "
                                                f"cloud ({C.SCAN_FORMATS}; at most 500,000 points) -> 202, "
                                                "fitted by a job. Any unit (m, cm, mm), any up axis"},
                        "gender": {"type": "string", "enum": ["female", "male"],
                                   "description": "Optional; estimated from the shape if omitted"},
                        "clothed": {"type": "boolean", "default": True,
                                    "description": "Scans: the person wears clothes (the body is fitted "
                                                   "inside them); false for a scan of the bare body"},
                    },
                }
            },
        },
    }
}
TRUE_WORDS, FALSE_WORDS = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


@router.post("/v1/customers", status_code=201, response_model=CustomerResponse, tags=["customers"],
             openapi_extra=CUSTOMER_BODY,
             responses={202: {"description": "A scan was accepted: the customer is 'fitting' until its job "
                                             "(job.url, also the Location header) is done",
                              "model": CustomerResponse},
                        413: {"description": "Upload too large"}, 422: {"description": "Invalid input"}})
async def create_customer(request: Request, response: Response, model: BodyModelDep, storage: StorageDep,
                          settings: SettingsDep) -> dict[str, Any]:
    """Create a customer from measurements (JSON ``{"measurements": {...}}``, as
    ``POST /v1/avatars``), from an avatar mesh in the template topology (multipart file
    ``mesh``: 201) or from a scan of any topology (multipart file ``mesh``: 202; the scan is
    validated now, then fitted by a job: poll ``job.url``)."""
    ctype = request.headers.get("content-type", "").lower()
    if ctype.startswith("multipart/form-data"):
        form = await request.form(max_files=2, max_fields=8)
        upload = form.get("mesh")
        if not isinstance(upload, StarletteUploadFile):
            raise _invalid(C.UploadError(("body", "mesh"), f"a file field 'mesh' ({C.SCAN_FORMATS}) is required"))
        gender = form.get("gender")
        if gender is not None and gender not in ("female", "male"):
            raise _invalid(C.UploadError(("body", "gender"), "gender must be 'female' or 'male'"))
        clothed_field = form.get("clothed")
        clothed = True
        if clothed_field is not None:
            word = str(clothed_field).strip().lower()
            if word not in TRUE_WORDS + FALSE_WORDS:
                raise _invalid(C.UploadError(("body", "clothed"), "clothed must be true or false"))
            clothed = word in TRUE_WORDS
        data = await upload.read()
        try:
            scan = await run_in_threadpool(C.read_upload, model, data, upload.filename)
            if scan is None:
                record = await run_in_threadpool(C.customer_from_mesh, model, data, upload.filename, gender)
            else:
                record = C.scan_customer(scan, gender, clothed)
        except C.UploadError as exc:
            raise _invalid(exc) from exc
        if scan is not None:
            await run_in_threadpool(C.submit_scan, storage, record, scan, settings.fit_timeout)
            response.status_code = 202
            response.headers["Location"] = record["job"]["url"]
            return {**record, "job": {**record["job"], "status": "queued"}}
    else:
        body = await request.body()
        try:
            req = AvatarRequest.model_validate_json(body or b"")
        except ValidationError as exc:
            raise RequestValidationError(
                [{**e, "loc": ("body", *e.get("loc", ()))} for e in exc.errors(include_input=False)]
            ) from exc
        record = await run_in_threadpool(_customer_from_measurements, model, dict(req.measurements))
    await run_in_threadpool(storage.put_customer, record)
    return record


def _customer_from_measurements(model: BodyModel, measurements: dict[str, Any]) -> dict[str, Any]:
    from service.model.shape import MeasurementError, avatar_from_measurements

    try:
        avatar = avatar_from_measurements(model, measurements)
    except MeasurementError as exc:
        raise RequestValidationError(
            [{"loc": ("body", "measurements", str(exc.field)), "msg": str(exc.message), "type": "value_error"}]
        ) from exc
    return {
        "id": new_id(), "status": "ready", "source": "measurements", "created": C.now_iso(),
        "weights": [float(w) for w in np.asarray(avatar.weights).ravel()],
        "measurements": {k: (v if isinstance(v, str) else float(v)) for k, v in avatar.measurements.items()},
        "estimated": list(avatar.estimated),
    }


@router.get("/v1/customers/{cid}", response_model=CustomerResponse, tags=["customers"],
            responses={404: {"description": "Unknown customer"}})
async def get_customer(cid: str, storage: StorageDep) -> dict[str, Any]:
    """A stored customer (a scan customer: ``fitting``, then ``ready`` or ``failed``)."""
    return _customer(storage, cid)


@router.get("/v1/customers/{cid}/avatar.glb", tags=["customers"], response_class=Response,
            responses=CUSTOMER_GLB_RESPONSE)
def customer_avatar_glb(cid: str, model: BodyModelDep, storage: StorageDep, bodies: BodyCacheDep,
                        compression: Compression = None) -> Response:
    """The customer's avatar: the skinned body surface (409 while its scan is being fitted)."""
    rec = _ready_customer(storage, cid)
    body = bodies.get(model, cid, rec["weights"])
    return _glb(avatar_glb(model, body.vertices, compression))


@router.delete("/v1/customers/{cid}", status_code=204, response_class=Response, tags=["customers"],
               responses={404: {"description": "Unknown customer"}})
def delete_customer(cid: str, storage: StorageDep, bodies: BodyCacheDep) -> Response:
    """Delete a customer and everything derived from it (at any time: a waiting scan and its
    fitting job too; a running fit is stopped)."""
    bodies.drop(cid)
    if not storage.delete_customer(cid):
        raise HTTPException(404, f"customer '{cid}' not found")
    bodies.drop(cid)
    return Response(status_code=204)


# -- garments ----------------------------------------------------------------------------------
@router.get("/v1/garments", response_model=list[GarmentResponse], tags=["garments"])
async def list_garments(storage: StorageDep) -> list[dict[str, Any]]:
    """Every stored garment (the demo catalogue included), oldest first."""
    return storage.list_garments()


@router.post("/v1/garments", status_code=201, response_model=GarmentResponse, tags=["garments"],
             responses={401: {"description": "Missing X-API-Key"}, 403: {"description": "Unknown API key"},
                        413: {"description": "Upload too large"}, 422: {"description": "Invalid upload"}})
async def create_garment(
    retailer: RetailerDep,
    model: BodyModelDep,
    storage: StorageDep,
    name: Annotated[str, Form(min_length=1, max_length=200, description="Garment name")],
    meshes: Annotated[list[UploadFile] | None, File(
        description="One fitted garment mesh per example avatar, in the order of /v1/example-avatars "
                    "(OBJ/PLY/GLB; same vertices and faces in every file; metres, or cm/mm detected)")] = None,
    mhclo: Annotated[UploadFile | None, File(description="MakeHuman .mhclo binding (with obj)")] = None,
    obj: Annotated[UploadFile | None, File(description="The MakeHuman garment's .obj (with mhclo)")] = None,
    color: Annotated[str | None, Form(pattern=r"^#?[0-9a-fA-F]{6}$", description="sRGB colour #rrggbb")] = None,
    layer: Annotated[int, Form(ge=0, le=9, description="Outfit layer (0 innermost)")] = C.DEFAULT_LAYER,
) -> dict[str, Any]:
    """Upload a garment: either ``meshes`` (fitted to each example avatar) or a MakeHuman
    ``mhclo`` + ``obj`` pair. Its clothing basis is built and stored."""
    has_meshes = bool(meshes)
    has_mh = mhclo is not None or obj is not None
    if has_meshes == has_mh:
        raise _invalid(C.UploadError(("body",), "send either files 'meshes' (one per example avatar) or "
                                                "files 'mhclo' and 'obj' (a MakeHuman garment)"))
    common = {"name": name, "owner": retailer, "color": C.parse_color(color), "layer": layer}
    try:
        if has_meshes:
            files = [(f.filename or f"mesh{i}", await f.read()) for i, f in enumerate(meshes or [])]
            fits, faces, unit = await run_in_threadpool(C.fits_from_meshes, model, files)
            return await run_in_threadpool(lambda: C.build_and_store(
                model, storage, fits, faces, source="meshes", extra={"unit": unit}, **common))
        if mhclo is None or obj is None:
            missing = "mhclo" if mhclo is None else "obj"
            raise C.UploadError(("body", missing), f"a MakeHuman garment needs both files 'mhclo' and 'obj'; "
                                                   f"'{missing}' is missing")
        mh_data, obj_data = await mhclo.read(), await obj.read()
        fits, faces = await run_in_threadpool(C.fits_from_mhclo, model, mh_data, obj_data)
        return await run_in_threadpool(lambda: C.build_and_store(
            model, storage, fits, faces, source="mhclo", **common))
    except C.UploadError as exc:
        raise _invalid(exc) from exc


@router.get("/v1/garments/{gid}", response_model=GarmentResponse, tags=["garments"],
            responses={404: {"description": "Unknown garment"}})
async def get_garment(gid: str, storage: StorageDep) -> dict[str, Any]:
    """A stored garment."""
    rec = storage.get_garment(gid)
    if rec is None:
        raise HTTPException(404, f"garment '{gid}' not found")
    return rec


@router.delete("/v1/garments/{gid}", status_code=204, response_class=Response, tags=["garments"],
               responses={401: {"description": "Missing X-API-Key"},
                          403: {"description": "Unknown API key, or another retailer's garment"},
                          404: {"description": "Unknown garment"}})
def delete_garment(gid: str, retailer: RetailerDep, storage: StorageDep) -> Response:
    """Delete one of the retailer's garments (its basis files too)."""
    rec = storage.get_garment(gid)
    if rec is None:
        raise HTTPException(404, f"garment '{gid}' not found")
    if rec.get("owner") != retailer:
        raise HTTPException(403, f"garment '{gid}' belongs to another retailer")
    storage.delete_garment(gid)
    return Response(status_code=204)


@router.get("/v1/garments/{gid}/basis.glb", tags=["garments"], response_class=Response,
            responses={**GLB_RESPONSE, 304: {"description": "Not modified (If-None-Match)"}})
def garment_basis_glb(gid: str, request: Request, storage: StorageDep,
                      compression: Compression = None) -> Response:
    """The clothing basis: the mean garment with one morph target per basis row (a viewer
    applies the customer's weights as morph weights). Strong ``ETag``; honours
    ``If-None-Match``."""
    rec, basis = _garment(storage, gid)
    tag = basis.etag() or rec.get("etag", "")
    etag = f'"{tag}-{compression}"' if compression else f'"{tag}"'
    headers = {"ETag": etag, "Cache-Control": f"public, max-age={BASIS_MAX_AGE}"}
    inm = request.headers.get("if-none-match")
    if inm:
        tags = [t.strip().removeprefix("W/") for t in inm.split(",")]
        if "*" in tags or etag in tags:
            return Response(status_code=304, headers=headers)
    return _glb(C.basis_glb(basis, rec, compression), **headers)


# -- try-on ------------------------------------------------------------------------------------
@router.get("/v1/customers/{cid}/garments/{gid}.glb", tags=["try-on"], response_class=Response,
            responses=CUSTOMER_GLB_RESPONSE)
async def try_on_glb(cid: str, gid: str, model: BodyModelDep, storage: StorageDep, bodies: BodyCacheDep,
               compression: Compression = None) -> Response:
    """The garment fitted to the customer, skinned with the customer's skeleton."""
    crec = _ready_customer(storage, cid)
    grec, basis = _garment(storage, gid)
    body = bodies.get(model, cid, crec["weights"])
    mesh = C.garment_mesh(basis, grec, body, layer=0)
    return _glb(C.single_mesh_glb(mesh, C.skin_of(model, body), compression))


@router.get("/v1/customers/{cid}/outfit.glb", tags=["try-on"], response_class=Response,
            responses=CUSTOMER_GLB_RESPONSE)
async def outfit_glb(cid: str, model: BodyModelDep, storage: StorageDep, bodies: BodyCacheDep,
               garments: Annotated[str, Query(description="Comma-separated garment ids")] = "",
               compression: Compression = None) -> Response:
    """The customer's avatar wearing the garments (one scene, one skeleton), layered: inner
    garments (lower layer) first, each outer one pushed over the ones below."""
    crec = _ready_customer(storage, cid)
    ids = list(dict.fromkeys(g.strip() for g in garments.split(",") if g.strip()))
    if len(ids) > MAX_OUTFIT_GARMENTS:
        raise RequestValidationError([{"loc": ("query", "garments"), "type": "value_error",
                                       "msg": f"at most {MAX_OUTFIT_GARMENTS} garments per outfit"}])
    loaded = [_garment(storage, gid) for gid in ids]
    order = sorted(range(len(loaded)), key=lambda i: (int(loaded[i][0].get("layer", C.DEFAULT_LAYER)), i))
    body = bodies.get(model, cid, crec["weights"])
    meshes = [C.avatar_mesh(model, body)]
    for rank, i in enumerate(order):
        rec, basis = loaded[i]
        meshes.append(C.garment_mesh(basis, rec, body, layer=rank))
    return _glb(C.scene_glb(meshes, C.skin_of(model, body), compression))


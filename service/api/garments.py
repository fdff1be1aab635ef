"""The garment catalogue: list, upload (retailers), read, delete, and the clothing basis."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, File, Form, Query, Response, UploadFile
from fastapi.concurrency import run_in_threadpool

from service.api import responses as R
from service.api.deps import Compression, GarmentsDep, IfNoneMatchDep, RateLimited, RetailerDep
from service.api.errors import invalid
from service.api.schemas import GarmentResponse
from service.application.garments import DEFAULT_LAYER
from service.records import Garment

router = APIRouter(tags=["garments"])
BASIS_MAX_AGE = 86400


@router.get("/v1/garments", response_model=list[GarmentResponse])
def list_garments(garments: GarmentsDep) -> list[Garment]:
    """Every stored garment (the demo catalogue included), oldest first."""
    return garments.list()


@router.post("/v1/garments", status_code=201, response_model=GarmentResponse, dependencies=[RateLimited],
             responses={202: {"description": "A draped garment (or, with the drape on, a MakeHuman garment) was "
                                             "accepted: it is listed with status 'building' until its job (job.url, "
                                             "also the Location header) has draped it on every example avatar",
                                  "model": GarmentResponse},
                        401: {"description": "Missing X-API-Key"}, 403: {"description": "Unknown API key"},
                        **R.UPLOAD, **R.RATE_LIMITED, 422: {"description": "Invalid upload"}})
async def create_garment(
    response: Response,
    retailer: RetailerDep,
    garments: GarmentsDep,
    name: Annotated[str, Form(min_length=1, max_length=200,
                              description="Garment name (printable characters; surrounding whitespace is "
                                          "dropped; control characters or only whitespace: 422)")],
    garment: Annotated[list[UploadFile] | None, File(
        description="One garment mesh draped on one body (OBJ, GLB/glTF with embedded buffers, PLY, STL), as "
                    "exported from a design tool: on an example avatar (`on`) or on your own `avatar`; with a "
                    "`size_chart` it is the `base_size`, graded to every size. Graded meshes: one file per size "
                    "(same vertices and faces), all draped on the same body, with `garment_sizes`")] = None,
    garment_sizes: Annotated[list[str] | None, Form(
        description="Graded meshes: the size label of each file 'garment', in the same order (repeated, or "
                    "comma-separated); every size of the `size_chart` once")] = None,
    size_chart: Annotated[str | None, Form(
        description='The size chart: a JSON object size label -> body measurements that size is made for, in '
                    'chart order, e.g. {"S": {"chest_cm": 88, "waist_cm": 76, "hip_cm": 94}, "M": {...}} (names '
                    'as in /v1/customers: chest_cm, waist_cm, hip_cm, height_cm, inseam_cm, ...; every size the '
                    'same names, increasing in each). A value may be an interval [low, high] as printed charts '
                    'give it: the size is made for its middle. Without it the garment is one size')] = None,
    base_size: Annotated[str | None, Form(
        description="With `size_chart`: the size of the uploaded mesh (default: the middle size)")] = None,
    fabric: Annotated[str | None, Form(description=(
        "The cloth: woven (default; shirting, suiting: barely stretches), knit (jersey) or stretch (elastane); "
        "how far the drape lets the garment stretch on each body, and the fit verdicts' thresholds"))] = None,
    on: Annotated[str | None, Form(description="With `garment`: the example avatar it was draped on (an id of "
                                               "/v1/example-avatars; default mean)")] = None,
    avatar: Annotated[UploadFile | None, File(
        description="With `garment`: the body it was draped on, of any topology, unit and up axis, in the "
                    "garment's frame (fitted unclothed by the build job)")] = None,
    meshes: Annotated[list[UploadFile] | None, File(
        description="One fitted garment mesh per example avatar, in the order of /v1/example-avatars "
                    "(OBJ/PLY/GLB; same vertices and faces in every file; metres, or cm/mm detected)")] = None,
    mhclo: Annotated[UploadFile | None, File(description="MakeHuman .mhclo binding (with obj)")] = None,
    obj: Annotated[UploadFile | None, File(description="The MakeHuman garment's .obj (with mhclo)")] = None,
    texture: Annotated[UploadFile | None, File(
        description="Optional base-colour texture (PNG or JPEG, at most 8 MiB and 8192 px a side) for an OBJ with "
                    "texture coordinates (vt): the 'garment', the first of 'meshes', or the mhclo's 'obj'")] = None,
    color: Annotated[str | None, Form(pattern=r"^#?[0-9a-fA-F]{6}$", description="sRGB colour #rrggbb")] = None,
    layer: Annotated[int, Form(ge=0, le=9, description="Outfit layer (0 innermost)")] = DEFAULT_LAYER,
    gender: Annotated[str | None, Form(pattern="^(female|male|unisex)$", description=(
        "Who the garment is made for: female, male or unisex (default). With a `size_chart`, the sizes' bodies "
        "are of this gender; with the drape, the population bodies its clothing basis is fitted over are "
        "three quarters of this gender (half each for unisex)"))] = None,
) -> Garment:
    """Upload a garment: ``meshes`` (fitted to each example avatar: 201, its clothing basis is
    built and stored now), a MakeHuman ``mhclo`` + ``obj`` pair, or one ``garment`` draped on an
    example avatar (``on``) or on your own ``avatar`` (202: a job drapes it on every example
    avatar; poll ``job.url`` or the garment's ``status`` and ``progress``). A ``mhclo`` is 201,
    built now, where the server runs with the drape off (``TRYON_DRAPE=false``)."""
    has_meshes = bool(meshes)
    garment_files = list(garment or [])
    ways = [has_meshes, mhclo is not None or obj is not None, bool(garment_files)]
    if sum(ways) != 1:
        raise invalid(("body",), "send one of: files 'meshes' (one per example avatar), files 'mhclo' and 'obj' "
                                 "(a MakeHuman garment), or a file 'garment' (draped on one body, with 'on' or a "
                                 "file 'avatar')")
    if not garment_files and (on is not None or avatar is not None):
        raise invalid(("body", "on" if on is not None else "avatar"), "'on' and 'avatar' go with a file 'garment'")
    if not garment_files and garment_sizes:
        raise invalid(("body", "garment_sizes"), "'garment_sizes' goes with files 'garment' (graded meshes)")
    chart = garments.chart(size_chart, base_size, fabric)
    common = {"name": name, "owner": retailer, "color": color, "layer": layer, "chart": chart, "gender": gender,
              "texture": (await texture.read(), texture.filename) if texture is not None else None}
    if garment_files:
        files = [(await f.read(), f.filename) for f in garment_files]
        labels = None if garment_sizes is None else [x.strip() for v in garment_sizes for x in v.split(",")]
        a_data = await avatar.read() if avatar is not None else None
        a_name = avatar.filename if avatar is not None else None
        record = await run_in_threadpool(lambda: garments.create_draped(
            files[0][0], files[0][1], on=on, avatar=a_data, avatar_name=a_name, graded=files[1:],
            garment_sizes=labels, **common))
        response.status_code = 202
        if record.job is not None:
            response.headers["Location"] = record.job.url
        return record
    if has_meshes:
        files = [(f.filename or f"mesh{i}", await f.read()) for i, f in enumerate(meshes or [])]
        return await run_in_threadpool(lambda: garments.create_from_meshes(files, **common))
    if mhclo is None or obj is None:
        missing = "mhclo" if mhclo is None else "obj"
        raise invalid(("body", missing), f"a MakeHuman garment needs both files 'mhclo' and 'obj'; '{missing}' is "
                                         "missing")
    mh_data, obj_data = await mhclo.read(), await obj.read()
    record = await run_in_threadpool(lambda: garments.create_from_mhclo(mh_data, obj_data, **common))
    if record.job is not None:  # with the drape on: a queued build
        response.status_code = 202
        response.headers["Location"] = record.job.url
    return record


@router.get("/v1/garments/{gid}", response_model=GarmentResponse, responses={404: {"description": "Unknown garment"}})
def get_garment(gid: str, garments: GarmentsDep) -> Garment:
    """A stored garment."""
    return garments.get(gid)


@router.delete("/v1/garments/{gid}", status_code=204, response_class=Response,
               responses={401: {"description": "Missing X-API-Key"},
                          403: {"description": "Unknown API key, or another retailer's garment"},
                          404: {"description": "Unknown garment"}})
def delete_garment(gid: str, retailer: RetailerDep, garments: GarmentsDep) -> Response:
    """Delete one of the retailer's garments (its basis files too)."""
    garments.delete(gid, retailer)
    return Response(status_code=204)


@router.get("/v1/garments/{gid}/basis.glb", response_class=Response,
            responses={**R.CUSTOMER_GLB_RESPONSE, 200: {**R.GLB_RESPONSE[200], "headers": R.ETAG}, **R.NOT_MODIFIED})
def garment_basis_glb(gid: str, garments: GarmentsDep, if_none_match: IfNoneMatchDep,
                      compression: Compression = None,
                      components: Annotated[int | None, Query(
                          ge=0, le=1000, description="at most this many basis rows as morph targets "
                          "(the first ones); 0: the mean garment alone (a preview or thumbnail)")] = None
                      ) -> Response:
    """The clothing basis: the mean garment with one morph target per basis row (a viewer
    applies the customer's weights as morph weights). Strong ``ETag``; honours
    ``If-None-Match``."""
    data, etag = garments.basis_glb(gid, compression, if_none_match, components)
    headers = {"ETag": etag, "Cache-Control": f"public, max-age={BASIS_MAX_AGE}"}
    if data is None:
        return Response(status_code=304, headers=headers)
    return R.glb(data, **headers)

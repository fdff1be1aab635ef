"""Pydantic request/response schemas of the public API."""
from __future__ import annotations

import copy
import json
import math
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from service.model.body.model import model_path
from service.model.body.measurements import ATTRIBUTES
from service.model.formats.mesh_io import KEPT_SCAN_POINTS


def _measurement_value(value: Any) -> float | str:
    """Accept JSON numbers (finite, as float) and strings (only ``gender`` is categorical; the
    model rejects strings elsewhere with its own message); reject booleans, null, arrays,
    objects and non-finite numbers."""
    if isinstance(value, bool) or value is None:
        raise ValueError("must be a number (or 'female'/'male' for gender)")
    if isinstance(value, int):
        try:
            value = float(value)
        except OverflowError as exc:
            raise ValueError("number is too large") from exc
    if isinstance(value, float):
        if not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value
    if isinstance(value, str):
        return value
    raise ValueError("must be a number (or 'female'/'male' for gender)")


MeasurementValue = Annotated[float | str, BeforeValidator(_measurement_value)]


class HealthResponse(BaseModel):
    """Liveness probe answer."""

    status: Literal["ok"] = "ok"


class AttributeOut(BaseModel):
    """One biometric attribute the avatar endpoint accepts."""

    name: str = Field(examples=["height_cm"])
    unit: str | None = Field(description='"cm", "kg", or null for the categorical gender')
    min: float | None = Field(description="Smallest accepted value (null for gender)")
    max: float | None = Field(description="Largest accepted value (null for gender)")
    description: str


class BodyModelResponse(BaseModel):
    """The parametric body model's public description."""

    attributes: list[AttributeOut]
    bones: list[str] = Field(description="The 17 skeleton bones, in skin joint order")
    components: int = Field(description="Number of PCA shape components (length of weights)")


class AvatarRequest(BaseModel):
    """Measurements of the customer; any subset of the attributes (the rest is estimated)."""

    model_config = ConfigDict(
        json_schema_extra={
            "examples": [{"measurements": {"gender": "female", "height_cm": 168.0, "weight_kg": 62.0}}]
        }
    )

    measurements: dict[str, MeasurementValue] = Field(
        default_factory=dict,
        description='Attribute name -> value (cm/kg numbers; gender is "female" or "male").',
    )


class EditRequest(BaseModel):
    """An edit of a customer's avatar: absolute target values of any of the 12 attributes (the
    others held), and rotations of any of the 17 bones (the others as fitted)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={
        "examples": [{"measurements": {"weight_kg": 70.0}, "pose": {"forearm_l": [0.0, 0.0, 0.6]}}]})

    measurements: dict[str, MeasurementValue] = Field(
        default_factory=dict, description="Attribute name -> target value (cm/kg); gender cannot change")
    pose: dict[str, list[float]] = Field(
        default_factory=dict, description="Bone name -> axis-angle rotation [x, y, z] in radians (angle <= pi), "
                                          "local to the parent bone; see /v1/body-model for the bones")


class AvatarResponse(BaseModel):
    """The fitted avatar: shape weights and the measurements re-taken on the avatar."""

    weights: list[float] = Field(description="PCA shape weights (components,)")
    measurements: dict[str, float | str] = Field(
        description="All 12 attributes measured on the avatar (gender as female/male)"
    )
    estimated: list[str] = Field(description="Attributes that were not given, hence estimated")


class JobRef(BaseModel):
    """A record's job (a customer's fit, a garment's build)."""

    id: str = Field(description="Job id (fit-<customer id>, build-<garment id>, or drape-<digest> for a "
                                "customer's exact drape of a garment)")
    url: str = Field(description="Where to poll it: /v1/jobs/{id}")
    status: Literal["queued", "running", "done", "failed"] | None = Field(
        default=None, description="The job's status now (null once the job record has expired)")


class FitStats(BaseModel):
    """How the scan fit went."""

    outer_iterations: int
    inner_iterations: int
    seconds: float = Field(description="Fitting time on the worker")
    points_fitted: int | None = Field(
        default=None, description="The scan's points the fit used once its floor and stray clusters were dropped: "
        "all of them, or 100,000 drawn at random from a denser scan")
    flat_cap_points: int | None = Field(
        default=None, description="Points of a flat cap closing the top of the head (a scanner's software filling "
        "the opening where its view ended below the crown), left out of the fit so that the head's top is the body "
        "model's; 0 when the scan has none")
    face_shape_from_body: bool | None = Field(
        default=None, description="True when the scan showed too little of the head (the face in a hole, the top cut "
        "off, hair) to trust the face for the body's shape: the face's points then set the head's pose only, and the "
        "face takes its shape from the rest of the body")
    head_shape_from_body: bool | None = Field(
        default=None, description="True when, for such a poorly seen head, a second fit in which the whole head and "
        "neck set their pose only (their height and size following the rest of the body) left less of the scan "
        "unexplained than the first and was kept (face_shape_from_body is then true as well)")


class ScanInfo(BaseModel):
    """The uploaded scan as read."""

    format: str = Field(description="obj, ply, stl, glb, gltf or xyz")
    points: int = Field(description="Vertices or points used (kept for the fit and for editing)")
    faces: int | None = Field(description="Triangles (null: a point cloud)")
    points_uploaded: int | None = Field(
        default=None, description=f"The file's vertices or points when there were more than {KEPT_SCAN_POINTS:,}: the "
                                  "scan was then simplified to `points` by vertex clustering (each kept point one of "
                                  "the file's); null otherwise")


class CustomerResponse(BaseModel):
    """A stored customer: the avatar's shape weights and its measurements. Customers from a
    scan are ``fitting`` until their job is done (then ``ready``, or ``failed`` with ``error``);
    ``weights`` and ``measurements`` are null until ready."""

    id: str = Field(description="Random URL-safe id")
    token: str | None = Field(
        default=None, description="Only in the answer to POST /v1/customers: the customer's secret, to send as "
                                  "`Authorization: Bearer <token>` on every customer route. Only its hash is "
                                  "stored: keep it (it cannot be shown again)")
    owner: str | None = Field(default=None, description="The retailer whose X-API-Key created it (null: "
                                                        "nobody's); that key opens it too")
    status: Literal["ready", "fitting", "failed"] = Field(
        default="ready", description="ready: the avatar exists; fitting: a job fits the uploaded scan; "
                                     "failed: the scan could not be fitted (see error)")
    source: Literal["measurements", "mesh", "scan"] = Field(
        description="How the avatar was made: measurements, a mesh in the template topology, or "
                    "a scan / clothed avatar / point cloud fitted by a job")
    weights: list[float] | None = Field(default=None, description="PCA shape weights (components,)")
    measurements: dict[str, float | str] | None = Field(
        default=None, description="The 12 attributes measured on the avatar")
    estimated: list[str] = Field(default_factory=list, description="Attributes that were estimated")
    entered: dict[str, float | str] | None = Field(
        default=None, description="The measurements as entered: a measurement customer's, or those given with a "
                                  "scan (height_cm, weight_kg, ...), which the fitted body keeps")
    created: str = Field(description="ISO 8601 UTC time of creation")
    unit: str | None = Field(default=None, description="Mesh and scan uploads: detected unit of the file (m, cm, mm)")
    residual_mm: float | None = Field(
        default=None, description="Mesh uploads: mean distance between the upload and its projection (mm); "
                                  "scans: mean distance between the fitted posed body and the scan (mm)")
    up: str | None = Field(default=None, description="Scans: the file's detected up axis, e.g. +y, +z")
    pose: dict[str, list[float]] | None = Field(
        default=None, description="Scans: the scanned pose, bone name -> local rotation (axis-angle, "
                                  "radians, [x, y, z]) for each of the 17 bones of /v1/body-model")
    translation: list[float] | None = Field(
        default=None, description="Scans: root translation of the posed body (metres, model frame)")
    clothed: bool | None = Field(default=None, description="Scans: the scan was declared clothed")
    frame: list[float] | None = Field(
        default=None, description="Scans: the 4 x 4 similarity (16 numbers, row-major) taking the uploaded file's "
                                  "coordinates to the model frame (metres, Y up); GET .../avatar.glb?pose=scan "
                                  "undoes it")
    partial: bool | None = Field(
        default=None, description="Scans: true when a side of the body (front, back, left or right) had almost no "
                                  "scan surface (a single-view scan): that side of the avatar is the shape "
                                  "prior's guess, not measured")
    coverage: dict[str, float] | None = Field(
        default=None, description="Scans: share of the fitted body's front, back, left and right with scan surface "
                                  "within 5 cm")
    unseen: list[str] | None = Field(
        default=None, description="Scans: bones of /v1/body-model whose part the scan hardly showed (bare scans: "
                                  "under 30 % of its surface near a scan point, e.g. a hand in a hole; any scan: "
                                  "\"head\" when it has no head at all): their posture is pulled towards the rest "
                                  "pose, not measured (a missing head's size too is the shape prior's)")
    scan: ScanInfo | None = Field(default=None, description="Scans: the uploaded file as read")
    job: JobRef | None = Field(default=None, description="Scans: the fitting job")
    fit: FitStats | None = Field(default=None, description="Scans: fitting statistics")
    editable: bool = Field(default=False, description="Scans uploaded as a mesh: the scan itself, clothes and "
                                                      "all, is what POST /v1/customers/{id}/edit reshapes")
    error: str | None = Field(default=None, description="Failed scans: why the scan could not be fitted")


class JobResponse(BaseModel):
    """A background job (a scan fit), from the queue."""

    id: str
    kind: str | None = Field(default=None, description="What the job does: fit (a customer's scan), garment "
                                                        "(a draped garment's build) or drape (a customer's exact "
                                                        "drape of a garment, ?drape=exact)")
    status: Literal["queued", "running", "done", "failed"] = Field(
        description="queued (waiting, or waiting for a retry), running, done, failed (see error)")
    progress: float = Field(ge=0.0, le=1.0, description="Fraction done, 0..1")
    message: str | None = Field(default=None, description="What the job is doing")
    error: str | None = Field(default=None, description="Failed jobs: why, in one line")
    customer_id: str | None = Field(default=None, description="The customer the job fits (or drapes on)")
    garment_id: str | None = Field(default=None, description="The garment the job builds (or drapes)")
    created: str | None = Field(default=None, description="ISO 8601 UTC time the job was created")
    started: str | None = Field(default=None, description="... it last started running")
    ended: str | None = Field(default=None, description="... it ended")


class ExampleAvatarOut(BaseModel):
    """One example avatar: the mean (``component`` null) or mean +/- c sqrt(var) U_component."""

    id: str = Field(examples=["pc00-plus"])
    component: int | None
    sign: int = Field(description="+1, -1, or 0 for the mean")
    coefficient: float = Field(description="Weight of the component (metres-scale PCA units)")


class GarmentSizeResponse(BaseModel):
    label: str
    measurements: dict[str, float] = Field(description="Body measurements the size is made for (API names, cm; "
                                                       "the middle of an interval the chart gave)")
    intervals: dict[str, list[float]] | None = Field(
        default=None, description="The measurements the chart gave as intervals [low, high] (null: none)")


class GarmentResponse(BaseModel):
    """A stored garment (its clothing basis is at /v1/garments/{id}/basis.glb)."""

    id: str
    name: str
    owner: str = Field(description='Retailer that uploaded it ("demo" for the built-in catalogue)')
    source: Literal["meshes", "mhclo", "demo", "draped"] = Field(
        description="How it came: meshes fitted to every example avatar, a MakeHuman mhclo, the demo "
                    "catalogue, or one mesh draped on one body and fitted to every example by a job")
    status: Literal["ready", "building", "failed"] = Field(
        default="ready", description="ready: it can be tried on; building: its job fits it to the example "
                                     "avatars (see progress, job); failed: see error")
    progress: float | None = Field(default=None, ge=0.0, le=1.0, description="Building garments: 0..1")
    error: str | None = Field(default=None, description="Failed garments: why, in one line")
    job: JobRef | None = Field(default=None, description="Draped garments: the build job")
    color: list[float] = Field(description="Linear RGBA base colour")
    layer: int = Field(description="Layer order in an outfit (inner garments first)")
    created: str
    n_vertices: int = Field(description="Vertices of the garment's cloth (a draped upload joined at its seams, "
                                        "without vertices on no face: its GLBs' texture seams split them again)")
    n_faces: int
    n_components: int = Field(description="Number of basis rows (PCA components covered; 0 while building)")
    etag: str = Field(description="Content hash of the basis (empty while building)")
    unit: str | None = Field(default=None, description="Mesh uploads: detected unit of the files")
    up: str | None = Field(default=None, description="Garments draped on an example avatar: the file's up axis")
    on: str | None = Field(default=None, description="Garments draped on an example avatar: its id")
    textured: bool = Field(default=False, description="Whether its GLBs carry texture coordinates and a texture")
    category: str | None = Field(default=None, description="Demo catalogue: top, bottom, suit, shoes, hat")
    gender: str | None = Field(default=None, description="Who it is made for: female, male or unisex (the upload's "
                                                         "`gender`, or the demo catalogue's); null: unisex")
    catalogue_id: str | None = Field(default=None, description="Demo catalogue: the compiled item's id")
    swatch: str | None = Field(default=None, description="Demo catalogue: thumbnail colour #rrggbb (sRGB)")
    sizes: list[GarmentSizeResponse] = Field(default_factory=list, description=(
        "The size chart in chart order: each size's label and the body measurements it is made for (one "
        "entry, empty measurements, for a garment without a chart)"))
    base_size: str | None = Field(default=None, description="The size of the uploaded mesh")
    fabric: Literal["woven", "knit", "stretch"] = Field(
        default="woven", description="The cloth it is draped as: woven (barely stretches), knit (jersey) or "
                                     "stretch (elastane); see docs/drape.md and docs/sizes.md")
    example_fits: Literal["drape", "warp", "meshes"] | None = Field(
        default=None, description="How its fits to the example avatars (its clothing basis) were made: 'drape' "
                                  "(the cloth drape engine: it keeps its size on every body), 'warp' (carried with the "
                                  "body: it follows the body, as if made to measure; the demo catalogue until its "
                                  "background drape reaches it), 'meshes' (your own fits); none while building")

    @model_validator(mode="before")
    @classmethod
    def _one_size(cls, data):
        """A garment without a chart shows as one size."""
        if isinstance(data, BaseModel):
            data = data.model_dump()
        if isinstance(data, dict) and not data.get("sizes"):
            data = dict(data)
            data["sizes"] = [{"label": data.get("base_size") or "one size", "measurements": {}}]
            data["base_size"] = data["sizes"][0]["label"]
        return data


def attribute_ranges(body_model_path: Path | None) -> dict[str, list[float]] | None:
    """The accepted ranges of the body model's attributes (its ``meta_json`` alone is read, not
    the model), or None when the file cannot be read."""
    try:
        with np.load(model_path(body_model_path), allow_pickle=False) as z:
            return dict(json.loads(str(z["meta_json"]))["attribute_ranges"])
    except (OSError, KeyError, ValueError):
        return None


def measurements_schema(ranges: dict[str, list[float]]) -> dict[str, Any]:
    """The JSON schema of ``measurements`` as the service checks it: the 12 attributes (no
    other key), gender female/male, the others numbers in their accepted ranges."""
    props: dict[str, Any] = {}
    for name in ATTRIBUTES:
        if name == "gender":
            props[name] = {"type": "string", "enum": ["female", "male"]}
        elif name in ranges:
            lo, hi = ranges[name]
            unit = "kg" if name == "weight_kg" else "cm"
            props[name] = {"type": "number", "minimum": float(lo), "maximum": float(hi),
                           "description": f"{unit}, {float(lo):g} to {float(hi):g}"}
    return {"type": "object", "properties": props, "additionalProperties": False,
            "title": "Measurements",
            "description": "Any subset of the attributes of GET /v1/body-model (cm/kg numbers within their "
                           "ranges; gender female or male); the rest is estimated."}


def document_measurements(doc: dict[str, Any], ranges: dict[str, list[float]] | None) -> dict[str, Any]:
    """The OpenAPI document (a deep copy: FastAPI shares ``openapi_extra``'s dicts with the
    routes) with the precise ``measurements`` schema: the JSON body's, and the accepted range of
    each measurement form field of a scan upload."""
    doc = copy.deepcopy(doc)
    if ranges:
        req = doc.get("components", {}).get("schemas", {}).get("AvatarRequest")
        if req is not None:
            req["properties"]["measurements"] = measurements_schema(ranges)
        fields = measurements_schema(ranges)["properties"]
        upload = (doc.get("paths", {}).get("/v1/customers", {}).get("post", {}).get("requestBody", {})
                  .get("content", {}).get("multipart/form-data", {}).get("schema", {}).get("properties", {}))
        for name, prop in upload.items():
            if name != "gender" and name in fields:
                prop.update({k: fields[name][k] for k in ("minimum", "maximum")})
    return doc


class HairOut(BaseModel):
    id: str = Field(description="Pass as `hair=` to avatar.glb, outfit.glb or POST /v1/avatars")
    name: str
    gender: str = Field(description="The gender the style was made for (female, male or unisex); any avatar "
                                    "may wear any style")
    color: str = Field(description="Swatch colour '#rrggbb' (sRGB)")


class LookDefaults(BaseModel):
    hair: str = Field(description="The hair id used when `hair` is omitted")
    underwear: bool = Field(description="Whether the base layer is worn when `underwear` is omitted")


class LooksResponse(BaseModel):
    hair: list[HairOut] = Field(description="The hair styles; `none` (no hair) is always accepted too")
    defaults: dict[str, LookDefaults] = Field(description="Per gender (female, male): the default look")


class RegionFit(BaseModel):
    region: Literal["chest", "waist", "hip", "thigh", "upper_arm", "shoulders", "sleeve", "inseam", "hem"] = Field(
        description="A girth (chest ... shoulders) or a length (sleeve, inseam, hem; see docs/sizes.md)")
    ease_cm: float = Field(description="Girths: garment girth minus body girth there (cm; negative: the cloth is "
                                       "stretched). Lengths: garment length minus body length (cm; negative: the "
                                       "garment ends short of the body's landmark)")
    strain_pct: float = Field(description="How far the body stretches the cloth there (%; 0 when looser; always 0 "
                                          "for a length)")
    verdict: Literal["too_tight", "tight", "fit", "loose", "too_loose"]


class SizeFitResponse(BaseModel):
    label: str
    verdict: Literal["too_tight", "tight", "fit", "loose", "too_loose"] = Field(
        description="The tightest region's verdict when any is tight, else the loosest region's")
    regions: list[RegionFit]


class FitResponse(BaseModel):
    """How each size of a garment fits one customer."""

    garment_id: str
    fabric: Literal["woven", "knit", "stretch"]
    base_size: str
    recommended: str = Field(description="The size with no region tight or too tight whose ease is closest to the "
                                         "garment's design ease; if every size is tight somewhere, the loosest")
    sizes: list[SizeFitResponse] = Field(description="In chart order")

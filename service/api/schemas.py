"""Pydantic request/response schemas of the public API."""
from __future__ import annotations

import math
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field


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


class AvatarResponse(BaseModel):
    """The fitted avatar: shape weights and the measurements re-taken on the avatar."""

    weights: list[float] = Field(description="PCA shape weights (components,)")
    measurements: dict[str, float | str] = Field(
        description="All 12 attributes measured on the avatar (gender as female/male)"
    )
    estimated: list[str] = Field(description="Attributes that were not given, hence estimated")


class JobRef(BaseModel):
    """A customer's fitting job."""

    id: str = Field(description="Job id (fit-<customer id>)")
    url: str = Field(description="Where to poll it: /v1/jobs/{id}")
    status: Literal["queued", "running", "done", "failed"] | None = Field(
        default=None, description="The job's status now (null once the job record has expired)")


class FitStats(BaseModel):
    """How the scan fit went."""

    outer_iterations: int
    inner_iterations: int
    seconds: float = Field(description="Fitting time on the worker")


class ScanInfo(BaseModel):
    """The uploaded scan as read."""

    format: str = Field(description="obj, ply, stl, glb, gltf or xyz")
    points: int = Field(description="Vertices or points used")
    faces: int | None = Field(description="Triangles (null: a point cloud)")


class CustomerResponse(BaseModel):
    """A stored customer: the avatar's shape weights and its measurements. Customers from a
    scan are ``fitting`` until their job is done (then ``ready``, or ``failed`` with ``error``);
    ``weights`` and ``measurements`` are null until ready."""

    id: str = Field(description="Random URL-safe id")
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
    scan: ScanInfo | None = Field(default=None, description="Scans: the uploaded file as read")
    job: JobRef | None = Field(default=None, description="Scans: the fitting job")
    fit: FitStats | None = Field(default=None, description="Scans: fitting statistics")
    error: str | None = Field(default=None, description="Failed scans: why the scan could not be fitted")


class JobResponse(BaseModel):
    """A background job (a scan fit), from the queue."""

    id: str
    status: Literal["queued", "running", "done", "failed"] = Field(
        description="queued (waiting, or waiting for a retry), running, done, failed (see error)")
    progress: float = Field(ge=0.0, le=1.0, description="Fraction done, 0..1")
    message: str | None = Field(default=None, description="What the job is doing")
    error: str | None = Field(default=None, description="Failed jobs: why, in one line")
    customer_id: str | None = Field(default=None, description="The customer the job fits")
    created: str | None = Field(default=None, description="ISO 8601 UTC time the job was created")
    started: str | None = Field(default=None, description="... it last started running")
    ended: str | None = Field(default=None, description="... it ended")


class ExampleAvatarOut(BaseModel):
    """One example avatar: the mean (``component`` null) or mean +/- c sqrt(var) U_component."""

    id: str = Field(examples=["pc00-plus"])
    component: int | None
    sign: int = Field(description="+1, -1, or 0 for the mean")
    coefficient: float = Field(description="Weight of the component (metres-scale PCA units)")


class GarmentResponse(BaseModel):
    """A stored garment (its clothing basis is at /v1/garments/{id}/basis.glb)."""

    id: str
    name: str
    owner: str = Field(description='Retailer that uploaded it ("demo" for the built-in catalogue)')
    source: Literal["meshes", "mhclo", "demo"]
    color: list[float] = Field(description="Linear RGBA base colour")
    layer: int = Field(description="Layer order in an outfit (inner garments first)")
    created: str
    n_vertices: int
    n_faces: int
    n_components: int = Field(description="Number of basis rows (PCA components covered)")
    etag: str = Field(description="Content hash of the basis")
    unit: str | None = Field(default=None, description="Mesh-set uploads: detected unit of the files")

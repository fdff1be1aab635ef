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


class CustomerResponse(BaseModel):
    """A stored customer: the avatar's shape weights and its measurements."""

    id: str = Field(description="Random URL-safe id")
    status: Literal["ready"] = "ready"
    source: Literal["measurements", "mesh"] = Field(description="How the avatar was made")
    weights: list[float] = Field(description="PCA shape weights (components,)")
    measurements: dict[str, float | str] = Field(description="The 12 attributes measured on the avatar")
    estimated: list[str] = Field(default_factory=list, description="Attributes that were estimated")
    created: str = Field(description="ISO 8601 UTC time of creation")
    unit: str | None = Field(default=None, description="Mesh uploads: detected unit of the file (m, cm, mm)")
    residual_mm: float | None = Field(
        default=None, description="Mesh uploads: mean distance between the upload and its projection (mm)"
    )


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

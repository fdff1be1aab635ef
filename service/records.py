"""Typed records of what the service stores: customers, garments and jobs (pydantic models,
stored as JSON). Every stored record carries its schema version and the version of the body
model it was made with (``BodyModel.version``): a record of another body model is recognised
as stale instead of silently giving a wrong avatar or garment.

No web, queue or storage imports: the repositories (``service.storage``) store these, the use
cases (``service.application``) work on them, the routes turn them into API responses.
"""
from __future__ import annotations

from datetime import datetime, timezone
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

SCHEMA_VERSION = 1

CustomerStatus = Literal["ready", "fitting", "failed"]
CustomerSource = Literal["measurements", "mesh", "scan"]
GarmentStatus = Literal["ready", "building", "failed"]
GarmentSource = Literal["meshes", "mhclo", "demo", "draped"]
JobStatus = Literal["queued", "running", "done", "failed"]


def now_iso() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


class Record(BaseModel):
    """Fields every stored record has."""

    model_config = ConfigDict(extra="ignore")

    id: str
    schema_version: int = SCHEMA_VERSION
    body_model: str | None = Field(default=None, description="BodyModel.version it was made with")
    owner: str | None = Field(default=None, description="The retailer it belongs to (None: nobody's)")
    created: str = Field(default_factory=now_iso)

    def is_current(self, body_model_version: str) -> bool:
        """Made by this schema and this body model."""
        return self.schema_version == SCHEMA_VERSION and self.body_model == body_model_version


class JobRef(BaseModel):
    """The job that builds or fits a record, and where to poll it; ``status`` is filled in when
    the record is shown (never stored)."""

    id: str
    url: str
    status: JobStatus | None = None


class ScanInfo(BaseModel):
    """An uploaded scan as read: format, points (vertices) and faces (None: a point cloud)."""

    format: str
    points: int
    faces: int | None = None
    points_uploaded: int | None = None  # the file's points when it was simplified to ``points``


class FitStats(BaseModel):
    outer_iterations: int
    inner_iterations: int
    seconds: float
    points_fitted: int | None = None  # the scan's points the fit used (None: fitted before 2026-11-27)
    flat_cap_points: int | None = None  # a flat cap over the head, left out of the fit (None: before 2026-11-28)
    face_shape_from_body: bool | None = None  # a poorly seen head's face shaped by the body (None: before 2026-11-28)
    head_shape_from_body: bool | None = None  # ... its whole head and neck, a second hypothesis kept (None: before 2026-11-28)


class Customer(Record):
    """A customer: the avatar's PCA weights and its 12 measurements, and how it was made."""

    status: CustomerStatus = "ready"
    source: CustomerSource
    weights: list[float] | None = None
    measurements: dict[str, float | str] | None = None
    estimated: list[str] = Field(default_factory=list)
    entered: dict[str, float | str] | None = Field(default=None, description="measurements as entered")
    gender_given: str | None = None
    unit: str | None = None
    residual_mm: float | None = None
    up: str | None = None
    pose: dict[str, list[float]] | None = None
    translation: list[float] | None = None
    clothed: bool | None = None
    frame: list[float] | None = Field(default=None, description="scans: the 4 x 4 similarity (row-major) taking "
                                                                "the file's coordinates to the model frame")
    partial: bool | None = Field(default=None, description="scans: a side of the body had no scan surface")
    coverage: dict[str, float] | None = None
    unseen: list[str] | None = Field(default=None, description="scans: bones the scan hardly showed, posture "
                                                               "left to the prior")
    scan: ScanInfo | None = None
    job: JobRef | None = None
    fit: FitStats | None = None
    editable: bool = Field(default=False, description="the uploaded clothed mesh is kept for editing")
    error: str | None = None
    token_hash: str | None = Field(default=None, description="SHA-256 of the customer's token (the token "
                                                             "itself is never stored)")


class GarmentSize(BaseModel):
    """One size of a garment's size chart: its label and the body measurements it is made for
    (API attribute names and units; empty for a garment without a chart; the middle of an
    interval the chart gave), and those intervals ``[low, high]`` as given."""

    label: str
    measurements: dict[str, float] = Field(default_factory=dict)
    intervals: dict[str, list[float]] | None = None

    def chart_entry(self) -> dict:
        """This size as ``sizing.validate_chart`` gives it: {label, measurements[, intervals]}."""
        return self.model_dump(exclude_none=True)


class Garment(Record):
    """A garment of the catalogue; its clothing basis is stored beside it (basis files)."""

    name: str
    source: GarmentSource
    color: list[float]
    layer: int
    status: GarmentStatus = "ready"
    n_vertices: int = 0
    n_faces: int = 0
    n_components: int = 0
    etag: str = ""
    unit: str | None = None
    up: str | None = None
    on: str | None = Field(default=None, description="draped garments: the example avatar it was draped on")
    job: JobRef | None = None
    error: str | None = None
    progress: float | None = Field(default=None, description="building garments: the build's progress (not stored)")
    textured: bool = False
    category: str | None = None
    gender: str | None = None
    catalogue_id: str | None = None
    swatch: str | None = None
    sizes: list[GarmentSize] | None = Field(default=None, description="the size chart in chart order (None: one size)")
    base_size: str | None = None
    fabric: str = Field(default="woven", description="the cloth the drape uses: woven, knit or stretch")
    fit: dict | None = Field(default=None, description="sizing.SizeFit.to_meta(): the girths of every size")
    example_fits: Literal["drape", "warp", "meshes"] | None = Field(
        default=None, description="how its fits to the example avatars (its clothing basis) were made: 'drape' (the "
                                  "cloth drape engine: the garment keeps its size on every body), 'warp' (carried with "
                                  "the body: it follows the body, as if made to measure), 'meshes' (the retailer's own)")

    def size_labels(self) -> list[str]:
        """The garment's size labels in chart order (one size without a chart)."""
        from service.model.garments.sizing import ONE_SIZE

        return [s.label for s in self.sizes] if self.sizes else [self.base_size or ONE_SIZE]

    def base_index(self) -> int:
        labels = self.size_labels()
        return labels.index(self.base_size) if self.base_size in labels else 0


class Job(BaseModel):
    """A background job as the API shows it (built from the queue's own record)."""

    id: str
    kind: str | None = None
    status: JobStatus
    progress: float = 0.0
    message: str | None = None
    error: str | None = None
    customer_id: str | None = None
    garment_id: str | None = None
    owner: str | None = None
    created: str | None = None
    started: str | None = None
    ended: str | None = None

"""``GET /healthz``."""
from __future__ import annotations

from fastapi import APIRouter

from service.api.schemas import HealthResponse

router = APIRouter(tags=["ops"])


@router.get("/healthz", response_model=HealthResponse)
async def healthz() -> HealthResponse:
    """Liveness probe."""
    return HealthResponse()

"""HTTP routes of background jobs (scan fits): ``GET /v1/jobs/{id}``."""
from __future__ import annotations

from typing import Any

from fastapi import APIRouter, HTTPException

from service.api.schemas import JobResponse
from service.api.tryon_routes import StorageDep
from service.storage import job_state

router = APIRouter()


@router.get("/v1/jobs/{job_id}", response_model=JobResponse, tags=["jobs"],
            responses={404: {"description": "Unknown job (or its record expired: 7 days after it ended)"}})
async def get_job(job_id: str, storage: StorageDep) -> dict[str, Any]:
    """A job's state: ``queued`` (also while waiting for a retry), ``running`` (``progress``
    0..1, ``message``), ``done`` or ``failed`` (``error``: why, in one line)."""
    job = storage.get_job(job_id)
    if job is None:
        raise HTTPException(404, f"job '{job_id}' not found")
    return job_state(job)

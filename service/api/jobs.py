"""Background jobs: ``GET /v1/jobs/{id}``."""
from __future__ import annotations

from fastapi import APIRouter

from service.api import responses as R
from service.api.deps import CredentialsDep, JobsDep
from service.api.schemas import JobResponse
from service.records import Job

router = APIRouter(tags=["jobs"])


@router.get("/v1/jobs/{job_id}", response_model=JobResponse,
            responses={**R.INVALID_KEY,
                       404: {"description": "Unknown job (or its record expired: 7 days after it ended); a "
                                            "customer's job without the customer's token or retailer key; a garment's build job without "
                                            "its retailer's key"}})
def get_job(job_id: str, jobs: JobsDep, creds: CredentialsDep) -> Job:
    """A job's state: ``queued`` (also while waiting for a retry), ``running`` (``progress``
    0..1, ``message``), ``done`` or ``failed`` (``error``: why, in one line). A customer's
    fitting job needs the customer's token (or its retailer's key), as the customer does; a
    garment's build job its retailer's key."""
    return jobs.get(job_id, creds)

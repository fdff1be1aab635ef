"""Background jobs as the API shows them. A job about a customer (its scan's fit) is that
customer's data: it opens with the customer's token or its retailer's key, like the customer. A
garment's build job is its retailer's: it opens with that retailer's key."""
from __future__ import annotations

from typing import TYPE_CHECKING

from service.records import Job

from .auth import ANONYMOUS, Credentials
from .errors import NotFound

if TYPE_CHECKING:
    from .context import Context


class JobService:
    def __init__(self, ctx: "Context"):
        self.ctx = ctx

    def get(self, job_id: str, creds: Credentials = ANONYMOUS) -> Job:
        job = self.ctx.queue.get(job_id)
        if job is None:
            raise NotFound(f"job '{job_id}' not found")
        if job.customer_id is not None:
            record = self.ctx.customers_repo.get(job.customer_id)
            try:
                self.ctx.customers.open(record, job.customer_id, creds)
            except NotFound:
                raise NotFound(f"job '{job_id}' not found") from None
        elif job.garment_id is not None and (creds.retailer is None or creds.retailer != job.owner):
            raise NotFound(f"job '{job_id}' not found")
        return job

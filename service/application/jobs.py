"""Background jobs as the API shows them. A job about a customer (its scan's fit) is that
customer's data: it opens with the customer's token or its retailer's key, like the customer. A
garment's build job is its retailer's: it opens with that retailer's key."""
from __future__ import annotations

from service.records import Job
from service.storage.queue import JobQueue
from service.storage.records import CustomerRepo

from .auth import ANONYMOUS, Credentials
from .customers import CustomerService
from .errors import NotFound


class JobService:
    def __init__(self, queue: JobQueue, customers_repo: CustomerRepo, customers: CustomerService):
        self.queue = queue
        self.customers_repo = customers_repo
        self.customers = customers

    def get(self, job_id: str, creds: Credentials = ANONYMOUS) -> Job:
        job = self.queue.get(job_id)
        if job is None:
            raise NotFound(f"job '{job_id}' not found")
        if job.customer_id is not None:
            record = self.customers_repo.get(job.customer_id)
            try:
                self.customers.open(record, job.customer_id, creds)
            except NotFound:
                raise NotFound(f"job '{job_id}' not found") from None
        elif job.garment_id is not None and (creds.retailer is None or creds.retailer != job.owner):
            raise NotFound(f"job '{job_id}' not found")
        return job

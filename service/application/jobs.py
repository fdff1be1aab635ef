"""Background jobs as the API shows them. A job about a customer (its scan's fit) is that
customer's data: it opens with the customer's token or its retailer's key, like the customer. A
garment's build job is its retailer's: it opens with that retailer's key."""
from __future__ import annotations

from service.records import Customer, Job
from service.storage.queue import JobQueue
from service.storage.records import CustomerRepo

from .auth import ANONYMOUS, Credentials, may_open
from .customers import CustomerService
from .errors import NotFound


# the record an unknown job id is checked against: no token or retailer opens it
UNOPENABLE = Customer(id="unknown", source="measurements", token_hash="0" * 64)


class JobService:
    def __init__(self, queue: JobQueue, customers_repo: CustomerRepo, customers: CustomerService):
        self.queue = queue
        self.customers_repo = customers_repo
        self.customers = customers

    def get(self, job_id: str, creds: Credentials = ANONYMOUS) -> Job:
        """The job, if ``creds`` may see it. An unknown id is refused on the path of a forbidden
        one (the same record lookup and credential check, the same 404), so that neither the
        answer nor its time tells whether the id exists."""
        job = self.queue.get(job_id)
        if job is None or job.customer_id is not None:
            cid = job.customer_id if job is not None and job.customer_id is not None else job_id
            record = self.customers_repo.get(cid)
            try:
                if job is None:
                    may_open(record or UNOPENABLE, creds)
                    raise NotFound(cid)
                self.customers.open(record, cid, creds)
            except NotFound:
                raise NotFound(f"job '{job_id}' not found") from None
        elif job.garment_id is not None and (creds.retailer is None or creds.retailer != job.owner):
            raise NotFound(f"job '{job_id}' not found")
        return job

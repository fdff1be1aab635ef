"""Limits per client (its IP address, as the server sees it behind trusted proxies) and, for
requests with a valid ``X-API-Key``, per retailer instead: rate limits on the expensive routes
(an avatar fit, a new customer, an upload; Redis counters shared across processes and hosts),
caps on the jobs one of them may have queued or running (Redis), expensive requests one of
them may have in progress in one process, and the process's memory budget for decoding
uploads."""
from __future__ import annotations

import math
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass
from service.model.garments.sizing import MAX_SIZES
from service.settings import Settings
from service.storage.limits import JobTracker, RateLimiter

from .errors import TooLarge, TooManyRequests, Unavailable

BURST_FACTOR = 2.0  # a client may send this many seconds' worth of requests at once
JOBS_RETRY_AFTER_S = 10  # Retry-After of a refusal for too many queued jobs
BUSY_RETRY_AFTER_S = 1  # Retry-After of a refusal for too many expensive requests at once
MEMORY_RETRY_AFTER_S = 2  # Retry-After when uploads being decoded hold the memory budget
JOB_TRACK_FACTOR = 4  # a tracked job is forgotten after this many job timeouts (its retries included)


@dataclass(frozen=True)
class Requester:
    """Who a request counts against: its retailer (a valid API key) or else its client address."""

    client: str | None
    retailer: str | None

    @property
    def bucket(self) -> str:
        return f"retailer:{self.retailer}" if self.retailer is not None else f"client:{self.client or 'unknown'}"

    @property
    def who(self) -> str:
        return f"retailer '{self.retailer}'" if self.retailer is not None else "this client"


# set by the expensive routes' dependency; read by the use cases that queue jobs
current_requester: ContextVar[Requester | None] = ContextVar("current_requester", default=None)


class Limits:
    def __init__(self, settings: Settings, rate_limiter: RateLimiter, jobs: JobTracker):
        self.settings = settings
        self.rate_limiter = rate_limiter
        self.jobs = jobs
        self._lock = threading.Lock()
        self._running: dict[str, int] = {}
        self._memory = 0

    def check(self, client: str | None, retailer: str | None) -> None:
        """Count one expensive request; :class:`TooManyRequests` (429 + Retry-After) when the
        client's or retailer's budget is spent."""
        s = self.settings
        if retailer is not None:
            bucket, rate, who = f"retailer:{retailer}", s.rate_limit_retailer, f"retailer '{retailer}'"
        else:
            bucket, rate, who = f"client:{client or 'unknown'}", s.rate_limit_client, "this client"
        if rate <= 0:
            return
        wait = self.rate_limiter.hit(bucket, rate, max(BURST_FACTOR * rate, 1.0))
        if wait > 0:
            raise TooManyRequests(f"rate limit of {rate:g} requests/s for {who} on this route reached; retry in "
                                  f"{math.ceil(wait)} s", retry_after=wait)

    # -- expensive requests at once (per process) ------------------------------------------------
    @contextmanager
    def slot(self, requester: Requester) -> Iterator[None]:
        """Hold one of the requester's ``TRYON_MAX_EXPENSIVE_CLIENT`` slots of this process while
        an expensive request runs; :class:`TooManyRequests` when all are taken."""
        cap = self.settings.max_expensive_client
        with self._lock:
            n = self._running.get(requester.bucket, 0)
            if n >= cap:
                raise TooManyRequests(f"{requester.who} already has {n} expensive requests in progress; at most "
                                      f"{cap} at once", retry_after=BUSY_RETRY_AFTER_S)
            self._running[requester.bucket] = n + 1
        try:
            yield
        finally:
            with self._lock:
                left = self._running.get(requester.bucket, 1) - 1
                if left > 0:
                    self._running[requester.bucket] = left
                else:
                    self._running.pop(requester.bucket, None)

    # -- queued jobs (all processes: Redis) ------------------------------------------------------
    def _track_age_s(self) -> float:
        """How long a tracked job counts at most (its retries included)."""
        return JOB_TRACK_FACTOR * max(self.settings.fit_timeout, self.settings.garment_timeout * MAX_SIZES,
                                      self.settings.drape_timeout)  # a build's timeout is per size

    def check_jobs(self) -> None:
        """Before an upload that queues a job is parsed: :class:`TooManyRequests` (429 +
        Retry-After) when the requester of this request already has its cap of jobs queued or
        running (``TRYON_MAX_QUEUED_CLIENT`` / ``TRYON_MAX_QUEUED_RETAILER``)."""
        requester = current_requester.get()
        if requester is None:
            return
        s = self.settings
        cap = s.max_queued_retailer if requester.retailer is not None else s.max_queued_client
        live = self.jobs.live(requester.bucket, self._track_age_s())
        if live >= cap:
            raise TooManyRequests(f"{requester.who} has {live} jobs queued or running; at most {cap}: retry when "
                                  "one is done", retry_after=JOBS_RETRY_AFTER_S)

    def track_job(self, job_id: str) -> None:
        """Count a job just queued against this request's requester."""
        requester = current_requester.get()
        if requester is None:
            return
        self.jobs.track(requester.bucket, job_id, self._track_age_s())

    # -- memory for decoding uploads (per process) -----------------------------------------------
    @contextmanager
    def memory(self, nbytes: int) -> Iterator[None]:
        """Reserve ``nbytes`` of the process's ``TRYON_MEMORY_BUDGET_MB`` while an upload is
        decoded: :class:`TooLarge` (413) when one upload alone needs more, :class:`Unavailable`
        (503 + Retry-After) when uploads being decoded hold too much of it now."""
        budget = self.settings.memory_budget_mb * 1024 * 1024
        if nbytes > budget:
            raise TooLarge(f"this upload needs about {nbytes // 2**20} MiB to read; this server reads at most "
                           f"{budget // 2**20} MiB at once (decimate the mesh or split the upload)")
        with self._lock:
            if self._memory + nbytes > budget:
                raise Unavailable("the server is reading other uploads; retry shortly", retry_after=MEMORY_RETRY_AFTER_S)
            self._memory += nbytes
        try:
            yield
        finally:
            with self._lock:
                self._memory -= nbytes

"""The job queue: an rq ``Queue("tryon")`` on the service's Redis connection, and the jobs'
state as typed records (:class:`service.records.Job`).

Jobs are enqueued by dotted path (``worker.jobs.fit_customer``: the service never imports the
worker package), retried (:data:`JOB_RETRIES`), time-limited, with progress in ``job.meta``
(:func:`report_progress`) and, in ``job.meta`` too, what the job is about (``kind``,
``customer_id``/``garment_id``, ``owner``, ``schema_version``, ``body_model``).

Recovery: a job whose worker dies (SIGKILL, lost machine) stops getting heartbeats; its entry
in rq's StartedJobRegistry expires ``worker_ttl`` seconds after the last one (rq's own margin is
60 s, see :func:`service.storage.supervise.worker_class`) and the next registry clean-up of any
live worker (every ``maintenance_interval`` s) re-enqueues it at once while it has retries left,
else moves it to the failed registry. Jobs must therefore be idempotent.
"""
from __future__ import annotations

import logging
import time
from datetime import datetime
from typing import Any

import redis
from rq import Queue, Retry, get_current_job
from rq.command import send_stop_job_command
from rq.exceptions import InvalidJobOperation, NoSuchJobError
from rq.job import Job as RqJob
from rq.job import JobStatus

from service.records import SCHEMA_VERSION, Job
from service.storage.records import valid_id

log = logging.getLogger("tryon.storage.queue")

QUEUE_NAME = "tryon"
# rq worker timings (seconds): how long a worker's heartbeat key lives, how often a running
# job's heartbeat is refreshed, how often a worker cleans registries of dead workers/jobs.
# `tryon worker`'s defaults.
WORKER_TTL = 30
JOB_MONITORING_INTERVAL = 5
MAINTENANCE_INTERVAL = 15
# Retries: the first at once (a job abandoned by a dead worker runs again without waiting for
# an rq scheduler, whose lock a killed worker holds for 60 s more), then after 30 s and 120 s
# (scheduled: every worker runs rq's scheduler).
JOB_RETRIES = {"max": 3, "interval": [0, 30, 120]}
JOB_RESULT_TTL = 7 * 86400  # seconds rq keeps a finished job and its result
JOB_FAILURE_TTL = 7 * 86400  # ... a failed one
JOB_STATES = {"queued": "queued", "deferred": "queued", "scheduled": "queued", "created": "queued",
              "rate_limited": "queued", "ready_to_enqueue": "queued", "started": "running",
              "finished": "done", "failed": "failed", "stopped": "failed", "canceled": "failed"}


def report_progress(fraction: float, message: str = "") -> None:
    """Inside an rq job: store progress in the job's meta (``progress``, ``message``)."""
    job = get_current_job()
    if job is not None:
        job.meta["progress"] = float(fraction)
        job.meta["message"] = message
        job.save_meta()


def ping_job(value: Any = None) -> dict[str, Any]:
    """A trivial job (``service.storage.queue.ping_job``) to check that a worker runs."""
    report_progress(1.0, "done")
    return {"pong": value}


def current_connection() -> redis.Redis | None:
    """Inside an rq job: the job's Redis connection."""
    job = get_current_job()
    return None if job is None else job.connection


class JobQueue:
    """The ``tryon`` queue on one connection."""

    def __init__(self, conn: redis.Redis):
        self.conn = conn
        self.queue = Queue(QUEUE_NAME, connection=conn)

    def enqueue(self, dotted_path: str, *args: Any, job_id: str, kind: str, timeout: int,
                body_model: str, meta: dict[str, Any] | None = None, description: str | None = None) -> RqJob:
        """Enqueue ``dotted_path(*args)`` under a deterministic ``job_id``, retried (see
        :data:`JOB_RETRIES`), its result kept 7 days."""
        full_meta = {"kind": kind, "schema_version": SCHEMA_VERSION, "body_model": body_model, "progress": 0.0,
                     "message": "waiting for a worker", **(meta or {})}
        return self.queue.enqueue(dotted_path, *args, job_id=job_id, job_timeout=timeout, meta=full_meta,
                                  description=description, retry=Retry(**JOB_RETRIES),
                                  result_ttl=JOB_RESULT_TTL, failure_ttl=JOB_FAILURE_TTL)

    def fetch(self, job_id: str) -> RqJob | None:
        """The rq job of this queue with that id, or None."""
        if not valid_id(job_id):
            return None
        try:
            job = RqJob.fetch(job_id, connection=self.conn)
        except NoSuchJobError:
            return None
        return job if job.origin == QUEUE_NAME else None

    def get(self, job_id: str) -> Job | None:
        """The job as a typed record, or None."""
        job = self.fetch(job_id)
        return None if job is None else job_record(job)

    def cancel(self, job_id: str, wait: float = 3.0) -> None:
        """Forget a job: deleted when waiting or ended; when running, its worker is told to stop
        it (the work-horse is killed; rq marks the job stopped, not retried), and it is deleted
        once stopped (after ``wait`` seconds it is left: a dead worker's job is re-run by the
        recovery, which must then find nothing to do)."""
        job = self.fetch(job_id)
        if job is None:
            return
        if job.get_status(refresh=False) == JobStatus.STARTED:
            try:
                send_stop_job_command(self.conn, job.id)
            except InvalidJobOperation:  # it has just ended
                pass
            deadline = time.monotonic() + wait
            try:
                while job.get_status(refresh=True) == JobStatus.STARTED:
                    if time.monotonic() > deadline:
                        log.warning("job %s did not stop in %.0f s; left to the recovery", job.id, wait)
                        return
                    time.sleep(0.05)
            except InvalidJobOperation:  # gone already
                return
        job.delete()


def _last_line(text: str | None) -> str | None:
    """The last non-empty line of a traceback ('ValueError: ...'), never the traceback."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    if not lines:
        return None
    line = lines[-1]
    return line if len(line) <= 500 else line[:497] + "..."


def _iso(value: datetime | None) -> str | None:
    return value.isoformat(timespec="seconds") if value is not None else None


def job_record(job: RqJob) -> Job:
    """An rq job as a :class:`Job`: status queued|running|done|failed, progress, message, error,
    what it is about. A finished job whose result is ``{"status": "failed", "error": ...}`` (a
    deterministic failure, not retried) is failed."""
    rq_status = job.get_status(refresh=False)
    rq_status = getattr(rq_status, "value", rq_status) or "queued"
    status = JOB_STATES.get(str(rq_status), "queued")
    meta = job.meta or {}
    error = None
    result = job.latest_result() if status in ("done", "failed") else None
    if status == "done":
        value = result.return_value if result is not None else None
        if isinstance(value, dict) and value.get("status") == "failed":
            status, error = "failed", str(value.get("error") or "the job failed")
    elif status == "failed":
        if rq_status == "stopped":
            error = "the job was stopped"
        elif rq_status == "canceled":
            error = "the job was canceled"
        else:
            text = getattr(result, "exc_string", None) or ""
            error = ("its worker died and no retries were left" if "AbandonedJobError" in text
                     else _last_line(text) or "the job failed")
    progress = float(meta.get("progress", 0.0) or 0.0)
    return Job(
        id=job.id, kind=meta.get("kind"), status=status,  # type: ignore[arg-type]
        progress=1.0 if status == "done" else min(max(progress, 0.0), 1.0),
        message=meta.get("message") or None, error=error,
        customer_id=meta.get("customer_id"), garment_id=meta.get("garment_id"), owner=meta.get("owner"),
        created=_iso(job.created_at), started=_iso(job.started_at), ended=_iso(job.ended_at),
    )

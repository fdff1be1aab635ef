"""The body-fitting job (rq, run by ``tryon worker``): a customer's uploaded scan -> avatar.

``POST /v1/customers`` with a scan stores the parsed scan in Redis (``scan:<customer id>``),
the customer with ``status: fitting`` and enqueues :func:`fit_customer` (job id
``fit-<customer id>``, see ``service.catalogue.submit_scan``). Any worker on any machine can
run it. At-least-once delivery (a job of a killed worker runs again), hence idempotent:

* the customer is gone (deleted meanwhile): nothing to do;
* already ``ready`` or ``failed``: its recorded outcome, nothing recomputed;
* :class:`~service.model.fitting.FitError` (the scan cannot be fitted, deterministic): the
  customer becomes ``failed`` with the message, the job *returns* ``{"status": "failed"}``
  (no retry); any other exception propagates (rq retries the job);
* success: the customer becomes ``ready`` (weights, measurements, pose, ...), written only if
  it still exists (WATCH: a delete during the fit wins), and the stored scan is dropped.
"""
from __future__ import annotations

import logging
from typing import Any

from service import catalogue as C
from service.model.body import load_body_model
from service.model.fitting import FitError, fit_body
from service.model.scan_io import scan_from_npz_bytes
from service.settings import get_settings
from service.storage import Storage, default_storage, report_progress

log = logging.getLogger("tryon.worker.fitting")

FIT_SHARE = 0.95  # of the job's progress; the rest: loading, measuring, storing


def body_model():
    """The process's body model (``tryon worker`` loads it before forking its work-horses)."""
    settings = get_settings()
    return load_body_model(settings.body_model_path)


def _storage() -> Storage:
    """The storage on the running job's connection (else the process default)."""
    from rq import get_current_job

    job = get_current_job()
    if job is None:
        return default_storage()
    return Storage(get_settings(), connection=job.connection)


class _Progress:
    """``fit_body``'s progress callback -> the job's meta, monotone, scaled to the fit's share."""

    def __init__(self, start: float = 0.02):
        self.value = start

    def __call__(self, fraction: float, message: str = "") -> None:
        value = min(max(0.02 + FIT_SHARE * float(fraction), self.value), 0.99)
        if value > self.value or message:
            self.value = value
            report_progress(value, message or "fitting")


def _outcome(record: dict[str, Any]) -> dict[str, Any]:
    if record["status"] == "failed":
        return {"status": "failed", "customer_id": record["id"], "error": record.get("error")}
    return {"status": "done", "customer_id": record["id"], "residual_mm": record.get("residual_mm")}


def _fail(storage: Storage, record: dict[str, Any], message: str) -> dict[str, Any]:
    failed = {**record, "status": "failed", "error": message}
    if not storage.put_customer_if_exists(failed, drop_scan=True):
        return {"status": "deleted", "customer_id": record["id"]}
    report_progress(1.0, "failed")
    log.info("customer %s: the scan cannot be fitted: %s", record["id"], message)
    return _outcome(failed)


def fit_customer(customer_id: str) -> dict[str, Any]:
    """Fit the body model to the customer's stored scan (the rq job; see the module docstring).
    Returns ``{"status": "done"|"failed"|"deleted", "customer_id", ...}``."""
    storage = _storage()
    record = storage.get_customer(customer_id)
    if record is None:
        storage.delete_scan(customer_id)
        return {"status": "deleted", "customer_id": customer_id}
    if record.get("status") in ("ready", "failed"):
        return _outcome(record)
    report_progress(0.0, "loading the scan")
    raw = storage.get_scan(customer_id)
    if raw is None:
        return _fail(storage, record, "the uploaded scan expired before it was fitted; upload it again")
    scan = scan_from_npz_bytes(raw)
    model = body_model()
    progress = _Progress()
    report_progress(progress.value, "fitting the body model")
    try:
        fit = fit_body(model, scan.points, scan.normals, scan.faces,
                       clothed=bool(record.get("clothed", True)), progress=progress)
    except FitError as exc:
        return _fail(storage, record, str(exc))
    report_progress(max(progress.value, FIT_SHARE), "measuring the avatar")
    ready = C.customer_from_fit(model, record, fit)
    if not storage.put_customer_if_exists(ready, drop_scan=True):
        log.info("customer %s was deleted during its fit: result dropped", customer_id)
        return {"status": "deleted", "customer_id": customer_id}
    report_progress(1.0, "done")
    log.info("customer %s fitted: residual %.1f mm, %.1f s", customer_id, fit.residual_mm, fit.seconds)
    return _outcome(ready)

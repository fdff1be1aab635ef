"""The queued jobs' entry points (rq runs them by dotted path in ``tryon worker`` processes).
Each is thin: it calls the same use cases as the routes, on a context of the worker process
(:func:`service.application.context.worker_context`), and reports progress in the job's meta.

* :func:`fit_customer` (job id ``fit-<customer id>``): a customer's uploaded scan -> avatar
  (``CustomerService.run_fit``: idempotent, deterministic failures recorded, not retried).
* :func:`build_garment` (job id ``build-<garment id>``): one draped garment -> fitted to every
  example avatar -> its clothing basis (``GarmentService.run_build``, likewise).
* :func:`drape_garment` (job id ``drape-<digest>``): a customer's exact drape of one garment
  (``ExactDrapes.run``, likewise).
"""
from __future__ import annotations

from typing import Any

from service.application.context import worker_context
from service.storage.queue import report_progress


def fit_customer(customer_id: str) -> dict[str, Any]:
    """Fit the body model to the customer's stored scan. Returns ``{"status": "done"|"failed"|
    "deleted", "customer_id", ...}``."""
    return worker_context().customers.run_fit(customer_id, report_progress)


def build_garment(garment_id: str) -> dict[str, Any]:
    """Build a draped garment's clothing basis. Returns ``{"status": "done"|"failed"|"deleted",
    "garment_id", ...}``."""
    return worker_context().garments.run_build(garment_id, report_progress)


def drape_garment(customer_id: str, garment_id: str, size: str | None, iterations: int, key: str) -> dict[str, Any]:
    """Drape a garment on a customer's body (``?drape=exact``). Returns ``{"status": "done"|
    "failed"|"deleted"|"stale", "customer_id", "garment_id", ...}``."""
    return worker_context().drapes.run(customer_id, garment_id, size, iterations, key, report_progress)


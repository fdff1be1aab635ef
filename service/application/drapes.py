"""Per-customer exact drapes (``?drape=exact`` on a garment's try-on): the garment settled on the
customer's own body by the cloth drape engine (``service.model.drape``), at the garment's own size
and in its fabric, from where the build's drapes started (``tryon.drape_start``: a drape basis's
start channel at the customer's weights, else the basis try-on). One queued job per (customer, garment, size, customer
shape); its result is stored as files (``storage.drapes``) and then served in the try-on's GLB
layout, the draped vertices in place of the basis try-on's.

The garment's size is its basis' rest shape (``GarmentBasis.rest``: the garment as uploaded, per
size for a garment in sizes). Bases built without one (the demo catalogue and ``.mhclo``
uploads without ``TRYON_DRAPE``, pre-fitted ``meshes``, older garments) use the mean garment
``g``: the garment fitted to the ``mean`` example avatar, which is exactly the size of a
``.mhclo`` or catalogue garment (as bound to ``mean``) and the retailer's own fit for
pre-fitted meshes. The basis try-on on another example avatar is not used: it is the garment
already reshaped to that body, not its size."""
from __future__ import annotations

import hashlib
import json
import logging
from typing import Any

import numpy as np

from service.model.body.model import BodyModel
from service.model.drape import Config, DrapeError, precompute
from service.model.garments.draped import DRAPE_CLEARANCE_M
from service.model.garments.tryon import GarmentBasis, drape_start
from service.records import Customer, Garment, JobRef
from service.settings import Settings
from service.storage.drapes import DrapeStore
from service.storage.queue import JobQueue
from service.storage.records import CustomerRepo, GarmentRepo

from . import scenes
from .auth import Credentials
from .customers import CustomerService
from .errors import Conflict, NotFound, TooManyRequests
from .garments import GarmentService
from .limits import Limits
from .progress import MonotoneProgress, Progress
from .tryon import TryOnService

log = logging.getLogger("tryon.drapes")

DRAPE_JOB = "worker.jobs.drape_garment"  # the rq job, by dotted path (the service never imports worker)
# bump when what a drape is made of changes (its method, its start): every key, job id and ETag changes
DRAPE_VERSION = 3
DRAPE_START = 0.05  # a drape job's progress once the records are loaded and the start made


def drape_key(model_version: str, cid: str, weights: list[float], gid: str, garment_etag: str,
              basis_etag: str, size: str | None, fabric: str, iterations: int) -> str:
    """The digest (32 hex) of everything a customer's drape of a garment is made of."""
    h = hashlib.sha256(np.asarray(weights, np.float64).tobytes())
    h.update(json.dumps([DRAPE_VERSION, model_version, cid, gid, garment_etag, basis_etag, size, fabric,
                         iterations]).encode())
    return h.hexdigest()[:32]


def drape_job_id(key: str) -> str:
    """The deterministic id of the drape job of ``key`` (:func:`drape_key`)."""
    return f"drape-{key}"


def drape_rest(basis: GarmentBasis) -> np.ndarray:
    """The garment's size (M, 3): its rest shape, or the mean garment without one (module doc)."""
    return np.asarray(basis.rest if basis.rest is not None else basis.g, np.float64)


class ExactDrapes:
    def __init__(self, settings: Settings, model: BodyModel, customers_repo: CustomerRepo,
                 garments_repo: GarmentRepo, customers: CustomerService, garments: GarmentService,
                 tryon: TryOnService, queue: JobQueue, limits: Limits, store: DrapeStore):
        self.settings = settings
        self.model = model
        self.customers_repo = customers_repo
        self.garments_repo = garments_repo
        self.customers = customers
        self.garments = garments
        self.tryon = tryon
        self.queue = queue
        self.limits = limits
        self.store = store

    def _key(self, record: Customer, garment: Garment, basis: GarmentBasis, iterations: int) -> str:
        assert record.weights is not None
        return drape_key(self.model.version, record.id, record.weights, garment.id, garment.etag or "",
                         basis.etag(), basis.meta.get("size"), garment.fabric, iterations)

    # -- the try-on --------------------------------------------------------------------------
    def garment_glb(self, cid: str, gid: str, creds: Credentials, compression: str | None,
                    if_none_match: list[str] | None = None, pose_correctives: bool = False,
                    size: str | None = None, fitmap: str | None = None) -> tuple[bytes | None, str] | JobRef:
        """The garment draped on the customer, in the layout of ``TryOnService.garment_glb``, and
        its ETag (``None`` bytes when ``if_none_match`` matches); while the drape is not done, its
        job (queued at the first request; the same job while it is queued or running). 409 when
        the drape failed (its reason); 429 when the requester has its cap of queued jobs."""
        record, loaded = self.tryon.load(cid, [gid], creds, [size])
        garment, basis = loaded[0]
        key = self._key(record, garment, basis, self.settings.drape_iterations)
        draped = self.store.load(cid, gid, key)
        if draped is None or draped.shape != (basis.n_vertices, 3):
            return self._job(record, garment, basis, key)
        tag = scenes.etag(f"garment|exact:{key}" + ("|poses" if pose_correctives else "")
                          + (f"|fitmap:{fitmap}" if fitmap else ""), self.model.version, record.weights,
                          compression, [(gid, basis.etag() or garment.etag)])
        if scenes.etag_matches(tag, if_none_match):
            return None, tag
        body = self.customers.body(record)
        return scenes.outfit_glb(self.model, body, loaded, compression, with_avatar=False,
                                 poses=self.tryon.page_poses(record, pose_correctives), fitmap=fitmap,
                                 worn=[draped]), tag

    def outfit_worn(self, record: Customer, layered: list[tuple[Garment, GarmentBasis]]
                    ) -> tuple[list[np.ndarray | None], str] | JobRef:
        """An outfit's garments as the customer's exact drapes (``TryOnService.outfit_glb``'s
        ``worn``): each garment's drape when it is done, None (its basis try-on) where the drape
        failed; while any drape is queued or running, the first such job instead (each missing
        drape is queued at the first request, as many as the requester's cap of queued jobs
        allows, the rest at the requests after). Also the ETag part naming the drapes used."""
        worn: list[np.ndarray | None] = []
        keys: list[str] = []
        pending: JobRef | None = None
        capped: TooManyRequests | None = None
        for garment, basis in layered:
            key = self._key(record, garment, basis, self.settings.drape_iterations)
            draped = self.store.load(record.id, garment.id, key)
            if draped is not None and draped.shape == (basis.n_vertices, 3):
                worn.append(draped)
                keys.append(key)
                continue
            try:
                ref = self._job(record, garment, basis, key)
            except Conflict:  # this garment cannot be draped on this body: its basis try-on
                worn.append(None)
                keys.append("basis")
                continue
            except TooManyRequests as exc:  # at the requester's cap: queued when one of the others is done
                capped = capped or exc
                continue
            pending = pending or ref
        if pending is not None:
            return pending
        if capped is not None:
            raise capped
        return worn, "|exact:" + ",".join(keys)

    def _job(self, record: Customer, garment: Garment, basis: GarmentBasis, key: str) -> JobRef:
        """The drape's job: the one queued or running, else a new one (a done job whose result
        is missing is replaced). A failed one: 409 with its reason, until the customer's shape
        or the garment changes (a new key) or the job record expires."""
        job_id = drape_job_id(key)
        ref = JobRef(id=job_id, url=f"/v1/jobs/{job_id}")
        job = self.queue.get(job_id)
        if job is not None and job.status in ("queued", "running"):
            return ref.model_copy(update={"status": job.status})
        if job is not None and job.status == "failed":
            raise Conflict(f"the exact drape of garment '{garment.id}' on customer '{record.id}' failed: "
                           f"{job.error or 'unknown error'} (job '{job_id}')")
        self.limits.check_jobs()
        if job is not None:
            self.queue.cancel(job_id)
        self.queue.enqueue(DRAPE_JOB, record.id, garment.id, basis.meta.get("size"),
                           self.settings.drape_iterations, key, job_id=job_id,
                           kind="drape", timeout=self.settings.drape_timeout, body_model=self.model.version,
                           description=f"drape garment {garment.id} on customer {record.id}",
                           meta={"customer_id": record.id, "garment_id": garment.id, "owner": record.owner})
        self.limits.track_job(job_id)
        return ref.model_copy(update={"status": "queued"})

    # -- the drape job -----------------------------------------------------------------------
    def run(self, cid: str, gid: str, size: str | None, iterations: int, key: str,
            progress: Progress) -> dict[str, Any]:
        """The drape job: the garment (size ``size``) settled on the customer's body from its
        start there (``tryon.drape_start``; at most ``iterations``, as the API's settings asked),
        stored under ``key``. Idempotent: a drape already stored is done; a customer or garment deleted, or changed since (another key), leaves nothing; a
        :class:`DrapeError` (the garment cannot be draped on this body) fails the job with the
        reason and is not retried; anything else raises (the queue retries). A delete during the
        drape wins (its file is removed)."""
        out = {"customer_id": cid, "garment_id": gid}
        customer, garment = self.customers_repo.get(cid), self.garments_repo.get(gid)
        if customer is None or garment is None:
            return {"status": "deleted", **out}
        try:
            record = self.customers.require_ready(customer, cid)
            labels = garment.size_labels()
            idx = labels.index(size) if size is not None and size in labels and len(labels) > 1 else None
            garment, basis = self.garments.require_ready(garment, gid, idx)
        except (NotFound, Conflict) as exc:
            return {"status": "failed", "error": exc.message, **out}
        if self._key(record, garment, basis, iterations) != key:
            return {"status": "stale", **out}
        if self.store.load(cid, gid, key) is not None:
            return {"status": "done", **out}
        progress = MonotoneProgress(progress)
        progress(0.0, "placing the garment on the body")
        body = self.customers.body(record)
        start = drape_start(basis, body)
        progress(DRAPE_START, "draping the garment on the customer's body")
        try:
            draper = precompute(drape_rest(basis), np.asarray(basis.faces, np.int64), garment.fabric,
                                Config(max_iterations=int(iterations), clearance_m=DRAPE_CLEARANCE_M,
                                       proxy_max_vertices=self.settings.drape_max_vertices or None))
            result = draper.solve(self.model.body_vertices(body.vertices).astype(np.float64),
                                  self.model.body_faces, start)
        except DrapeError as exc:
            progress(1.0, "failed")
            log.info("drape of garment %s on customer %s failed: %s", gid, cid, exc)
            return {"status": "failed", "error": f"the garment cannot be draped on this customer: {exc}", **out}
        self.store.save(cid, gid, key, result.vertices)
        if self.customers_repo.get(cid) is None or self.garments_repo.get(gid) is None:
            self.store.delete(cid, gid, key)
            return {"status": "deleted", **out}
        progress(1.0, "done")
        stats = result.stats
        log.info("garment %s draped on customer %s: %d iterations, %.1f s, settled %s", gid, cid,
                 stats["iterations"], stats["seconds"], stats["settled"])
        return {"status": "done", **out, "iterations": int(stats["iterations"]), "settled": bool(stats["settled"]),
                "seconds": round(float(stats["seconds"]), 3)}

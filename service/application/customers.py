"""Customers: from measurements, from an avatar mesh in the template topology, or from a scan
fitted by a queued job (:meth:`CustomerService.run_fit`, run by ``worker.jobs.fit_customer``);
their avatars."""
from __future__ import annotations

import logging
from datetime import datetime, timezone
from typing import Any

import numpy as np

from service.model.formats import gltf
from service.model.body.model import BONES, BodyModel
from service.model.formats.frames import rotation_to_y
from service.model.geometry.mesh import vertex_normals
from service.model.fitting.checks import FitError
from service.model.fitting.fit import FitResult, fit_body
from service.model.formats.mesh_io import Scan, scan_from_npz_bytes, scan_to_npz_bytes
from service.model.fitting.scan_cleanup import kept_faces
from service.model.body.shape import MeasurementError, avatar_from_measurements, estimate_gender
from service.model.garments.tryon import CustomerBody
from service.records import Customer, FitStats, JobRef, ScanInfo
from service.storage.drapes import DrapeStore
from service.storage.meshes import MeshStore
from service.storage.queue import JobQueue
from service.storage.records import CustomerRepo, new_id

from . import look as looks
from . import scenes
from .bodies import BodyCache
from .editors import Editors, build_editor
from .auth import ANONYMOUS, Credentials, may_open, new_token
from .errors import Conflict, Invalid, NotFound
from .progress import MonotoneProgress, Progress
from .limits import Limits
from .poses import Poses
from .uploads import TemplateAvatar, read_body_upload, upload_memory

log = logging.getLogger("tryon.customers")

FIT_JOB = "worker.jobs.fit_customer"  # the rq job, by dotted path (the service never imports worker)
MISSING_JOB_GRACE_S = 60  # a fitting customer without its job for this long has failed
FIT_START, FIT_SHARE = 0.02, 0.95  # a fitting job's progress: loading, then fit_body, then measuring, storing



def fit_job_id(cid: str) -> str:
    """The deterministic id of a customer's fitting job."""
    return f"fit-{cid}"


class CustomerService:
    def __init__(self, model: BodyModel, repo: CustomerRepo, queue: JobQueue, meshes: MeshStore, bodies: BodyCache,
                 editors: Editors, poses: Poses, limits: Limits, fit_timeout: int, drapes: DrapeStore):
        self.model = model
        self.repo = repo
        self.queue = queue
        self.meshes = meshes
        self.bodies = bodies
        self.editors = editors
        self.poses = poses
        self.limits = limits
        self.fit_timeout = fit_timeout
        self.drapes = drapes

    # -- records -----------------------------------------------------------------------------
    def _new(self, **fields: Any) -> tuple[Customer, str]:
        """A new record and its token (only the token's hash is in the record)."""
        token, digest = new_token()
        return Customer(id=new_id(), body_model=self.model.version, token_hash=digest, **fields), token

    def open(self, record: Customer | None, cid: str, creds: Credentials) -> Customer:
        """The record if ``creds`` may open it; else the 404 of an unknown id (ids cannot be
        probed: a wrong or missing token looks exactly like no such customer)."""
        if record is None or not may_open(record, creds):
            raise NotFound(f"customer '{cid}' not found")
        return record

    def _shape_fields(self, weights: np.ndarray, gender: str | None) -> dict[str, Any]:
        """``weights``, ``measurements`` (the 12 attributes measured on the avatar) and
        ``estimated`` (``["gender"]`` when not given: estimated from the shape)."""
        w = np.asarray(weights, np.float64).ravel()
        estimated = [] if gender else ["gender"]
        gender = gender or estimate_gender(self.model, w)
        measured = self.model.measure(self.model.vertices(w), gender)
        return {"weights": [float(x) for x in w],
                "measurements": {k: (v if isinstance(v, str) else float(v)) for k, v in measured.items()},
                "estimated": estimated}

    # -- creating ----------------------------------------------------------------------------
    def create_from_measurements(self, measurements: dict[str, Any],
                                 owner: str | None = None) -> tuple[Customer, str]:
        """A ready customer from measurements, and its token (``owner``: the retailer whose
        key created it, which opens it too)."""
        try:
            avatar = avatar_from_measurements(self.model, measurements)
        except MeasurementError as exc:
            raise Invalid(("body", "measurements", str(exc.field)), exc.message) from exc
        record, token = self._new(status="ready", source="measurements", owner=owner,
                                  weights=[float(w) for w in np.asarray(avatar.weights).ravel()],
                                  measurements={k: (v if isinstance(v, str) else float(v))
                                                for k, v in avatar.measurements.items()},
                                  estimated=list(avatar.estimated), entered=dict(measurements))
        self.repo.put(record)
        return record, token

    def create_from_upload(self, data: bytes, filename: str | None, gender: str | None, clothed: bool,
                           owner: str | None = None, known: dict[str, float] | None = None) -> tuple[Customer, str]:
        """An avatar mesh in the template topology -> a ready customer (``status`` ready);
        any other mesh or point cloud -> a customer being fitted by a queued job (``status``
        fitting, ``job``), with ``known`` measurements of the person (checked, API units) kept
        by the fit; with its token. Bad files raise :class:`Invalid` before anything is stored;
        a requester at its cap of queued jobs gets :class:`TooManyRequests`, a file that needs
        more memory to read than the process's budget :class:`TooLarge` (before it is parsed)."""
        self.limits.check_jobs()
        with self.limits.memory(upload_memory(data, filename)):
            upload = read_body_upload(self.model, data, filename)
        if isinstance(upload, TemplateAvatar):
            if known:
                raise Invalid(("body", next(iter(known))),
                              "measurements are for scans: this mesh is in the template topology, its shape is "
                              "read exactly (leave the measurements out, or create the customer from them)")
            p = upload.projection
            record, token = self._new(status="ready", source="mesh", owner=owner, gender_given=gender,
                                      **self._shape_fields(p.weights, gender), unit=p.unit,
                                      residual_mm=float(p.residual_mm))
            self.repo.put(record)
            return record, token
        return self._submit_scan(upload, gender, clothed, owner, known)

    def _submit_scan(self, scan: Scan, gender: str | None, clothed: bool,
                     owner: str | None, known: dict[str, float] | None = None) -> tuple[Customer, str]:
        """Store the scan (``scan:<id>``, for any worker) with the customer (``known``
        measurements as ``entered``), then enqueue its fitting job (deterministic id, retried);
        on failure nothing is left behind."""
        record, token = self._new(status="fitting", source="scan", owner=owner, gender_given=gender,
                                  clothed=bool(clothed), entered=dict(known) if known else None,
                                  scan=ScanInfo(format=scan.kind, points=int(len(scan.points)),
                                                faces=None if scan.faces is None else int(len(scan.faces)),
                                                points_uploaded=scan.source_points))
        cid = record.id
        job_id = fit_job_id(cid)
        record = record.model_copy(update={"job": JobRef(id=job_id, url=f"/v1/jobs/{job_id}")})
        self.repo.put_with_scan(record, scan_to_npz_bytes(scan))
        try:
            self.queue.enqueue(FIT_JOB, cid, job_id=job_id, kind="fit", timeout=self.fit_timeout,
                                   body_model=self.model.version, description=f"fit the scan of customer {cid}",
                                   meta={"customer_id": cid, "owner": owner})
        except BaseException:
            self.repo.delete(cid)
            raise
        self.limits.track_job(job_id)
        assert record.job is not None
        return record.model_copy(update={"job": record.job.model_copy(update={"status": "queued"})}), token

    # -- reading -----------------------------------------------------------------------------
    def get(self, cid: str, creds: Credentials = ANONYMOUS) -> Customer:
        """A customer as the API shows it (404 unknown, or not opened by ``creds``). A
        ``fitting`` customer whose job failed (retries exhausted) or vanished shows as failed
        (the queue is consulted only then)."""
        record = self.open(self.repo.get(cid), cid, creds)
        return self._with_job_outcome(record, show_job=True)

    def _with_job_outcome(self, record: Customer, show_job: bool = False) -> Customer:
        if record.job is None or (record.status != "fitting" and not show_job):
            return record
        job = self.queue.get(record.job.id)
        record = record.model_copy(update={"job": record.job.model_copy(update={"status": job and job.status})})
        if record.status != "fitting":
            return record
        if job is not None and job.status == "failed":
            return record.model_copy(update={"status": "failed", "error": job.error or "the fitting job failed"})
        if job is None:
            created = datetime.fromisoformat(record.created)
            if (datetime.now(timezone.utc) - created).total_seconds() > MISSING_JOB_GRACE_S:
                return record.model_copy(update={"status": "failed",
                                                 "error": "the fitting job was lost; upload the scan again"})
        return record

    def require_ready(self, record: Customer | None, cid: str) -> Customer:
        """The customer if it has an avatar of this body model: 404 unknown; 409 while its scan
        is being fitted, when the fit failed, or when it was made with another body model."""
        if record is None:
            raise NotFound(f"customer '{cid}' not found")
        if record.status != "ready":
            record = self._with_job_outcome(record)
            job = record.job.id if record.job else ""
            if record.status == "fitting":
                raise Conflict(f"customer '{cid}' is not ready: its scan is being fitted (job '{job}', "
                               f"GET /v1/jobs/{job}); try again when it is done")
            raise Conflict(f"customer '{cid}' has no avatar: fitting the scan failed: "
                           f"{record.error or 'unknown error'}. Delete it and upload another scan")
        if not record.is_current(self.model.version) or record.weights is None:
            raise Conflict(f"customer '{cid}' was made with another body model ({record.body_model or 'unversioned'}; "
                           f"this service runs {self.model.version}): delete it and create it again")
        return record

    def body(self, record: Customer) -> CustomerBody:
        assert record.weights is not None
        return self.bodies.get(record.id, record.weights)

    def page_poses(self, cid: str, creds: Credentials) -> dict[str, dict[str, list[float]]]:
        """{preset name: {bone: [x, y, z] axis-angle radians (local rotation, rest frames = world
        axes)}} for every bone, in ``BONES`` order (404 unknown customer, 409 not ready)."""
        return self.poses.record_poses(self.require_ready(self.open(self.repo.get(cid), cid, creds), cid))

    def avatar_glb(self, cid: str, creds: Credentials, compression: str | None,
                   if_none_match: list[str] | None = None, hair: str | None = None,
                   underwear: bool = True, pose: str = "rest") -> tuple[bytes | None, str]:
        """The customer's skinned avatar wearing its look (``hair``: a catalogue hair id,
        ``none`` or None for the default of the customer's gender; ``underwear``) and its ETag
        (from the weights, the look and the options); ``None`` bytes when one of
        ``if_none_match`` matches (not modified). ``pose="scan"``: the bare body as fitted in
        the scan, in the scan's frame (:meth:`scan_posed_vertices`), not skinned; 422 for
        customers not fitted from a scan."""
        record = self.require_ready(self.open(self.repo.get(cid), cid, creds), cid)
        if pose == "scan":
            V = self.scan_posed_vertices(record)
            etag = scenes.etag("avatar-scan", self.model.version,
                               [*record.weights, *np.ravel(list(record.pose.values())), *record.translation,
                                *record.frame], compression)
            if scenes.etag_matches(etag, if_none_match):
                return None, etag
            mesh = scenes.avatar_mesh(self.model, V, vertex_normals(V, self.model.body_faces), template=False)
            mesh = {k: v for k, v in mesh.items() if k not in ("vertex_joints", "vertex_weights")}  # unskinned
            return gltf.scene_to_glb([mesh], compression=compression), etag
        look = looks.resolve(looks.gender_of(record.measurements), hair, underwear)
        etag = scenes.etag(f"avatar|{look.key}", self.model.version, record.weights, compression)
        if scenes.etag_matches(etag, if_none_match):
            return None, etag
        body = self.body(record)
        return scenes.avatar_glb(self.model, body.vertices, compression, normals=body.normals, look=look), etag

    def scan_posed_vertices(self, record: Customer) -> np.ndarray:
        """The body (V, 3) float64 posed as fitted and placed where the scan was, in the scan's
        frame in glTF conventions: metres, the scan's up axis as +Y (the fit's ``frame`` undone,
        then the file's up axis turned to +Y). :class:`Invalid` for customers not fitted from a
        scan; :class:`Conflict` for scan customers fitted before the frame was stored."""
        if record.source != "scan":
            raise Invalid(("query", "pose"), f"pose=scan needs a customer fitted from a scan; this one was made "
                                             f"from {'measurements' if record.source == 'measurements' else 'a mesh in the template topology'}"
                                             " (use pose=rest)")
        if record.frame is None or record.pose is None or record.translation is None or record.up is None:
            raise Conflict(f"customer '{record.id}' was fitted before scan poses were stored: upload the scan again")
        rot = np.array([record.pose[b] for b in BONES], np.float64)
        V = self.model.forward(np.asarray(record.weights, np.float64), rot,
                               np.asarray(record.translation, np.float64)).vertices[: self.model.n_body_vertices]
        T = np.asarray(record.frame, np.float64).reshape(4, 4)
        scale = float(np.cbrt(np.linalg.det(T[:3, :3])))  # metres per file unit
        R0 = T[:3, :3] / scale  # file axes -> model axes
        file_m = (V - T[:3, 3]) @ R0  # R0^T (v - t): the file's axes, metres
        up = np.zeros(3)
        up["xyz".index(record.up[1])] = 1.0 if record.up[0] == "+" else -1.0
        return file_m @ rotation_to_y(up).T

    def delete(self, cid: str, creds: Credentials = ANONYMOUS) -> None:
        """Delete a customer and everything derived from it (at any time: a waiting scan and its
        fitting job too, a running fit is stopped; its exact drapes: a drape job still running
        finds the customer gone and drops its result)."""
        self.open(self.repo.get(cid), cid, creds)
        self.bodies.drop(cid)
        record = self.repo.delete(cid)
        if record is None:
            raise NotFound(f"customer '{cid}' not found")
        if record.job is not None:
            self.queue.cancel(record.job.id)
        self.meshes.delete(cid)
        self.drapes.delete_customer(cid)
        self.editors.forget(cid)
        self.bodies.drop(cid)
        if record.weights:
            self.poses.forget(record)

    # -- the fitting job ---------------------------------------------------------------------
    def run_fit(self, cid: str, progress: Progress) -> dict[str, Any]:
        """Fit the body model to the customer's stored scan (the queued job). Idempotent, as
        at-least-once delivery needs: a deleted customer -> nothing to do; already ready or
        failed -> its recorded outcome; :class:`FitError` (the scan cannot be fitted,
        deterministic) -> the customer is failed with the message and the job *returns*
        ``{"status": "failed"}`` (no retry); any other exception propagates (the queue retries);
        success -> the customer becomes ready, written only if it still exists (a delete during
        the fit wins), and the stored scan is dropped."""
        record = self.repo.get(cid)
        if record is None:
            self.repo.delete(cid)
            return {"status": "deleted", "customer_id": cid}
        if record.status in ("ready", "failed"):
            return _outcome(record)
        progress = MonotoneProgress(progress)
        progress(0.0, "loading the scan")
        raw = self.repo.get_scan(cid)
        if raw is None:
            return self._fail(record, "the uploaded scan expired before it was fitted; upload it again", progress)
        scan = scan_from_npz_bytes(raw)
        fitting = progress.scaled(FIT_START, FIT_SHARE)
        fitting(0.0, "fitting the body model")
        try:
            known = {k: float(v) for k, v in (record.entered or {}).items() if k != "gender"}
            fit = fit_body(self.model, scan.points, scan.normals, scan.faces, clothed=bool(record.clothed),
                           progress=lambda f, m: fitting(f, m or "fitting"), known=known or None,
                           gender=record.gender_given)
        except FitError as exc:
            return self._fail(record, str(exc), progress)
        progress(FIT_SHARE, "measuring the avatar")
        ready = self._fitted(record, fit)
        if scan.faces is not None:  # a mesh: kept for editing, with its warping graph checked
            progress(FIT_SHARE, "building the warping graph for editing")
            T = np.asarray(fit.to_model, np.float64)
            kept = np.ones(len(scan.points), bool) if fit.kept is None else fit.kept  # without the floor
            arrays = {"vertices": (scan.points[kept] @ T[:3, :3].T + T[:3, 3]).astype(np.float32),
                      "faces": kept_faces(scan.faces, kept).astype(np.int32)}
            ready = ready.model_copy(update={"editable": True})
            build_editor(self.model, ready, arrays)  # fails here, in the job, rather than at the first edit
            self.meshes.save(cid, arrays)
        if not self.repo.complete(ready):
            self.meshes.delete(cid)
            log.info("customer %s was deleted during its fit: result dropped", cid)
            return {"status": "deleted", "customer_id": cid}
        progress(1.0, "done")
        log.info("customer %s fitted: residual %.1f mm, %.1f s", cid, fit.residual_mm, fit.seconds)
        return _outcome(ready)

    def _fitted(self, record: Customer, fit: FitResult) -> Customer:
        rotvecs = np.asarray(fit.rotvecs, np.float64).reshape(len(BONES), 3)
        return record.model_copy(update={
            "status": "ready", "error": None, "body_model": self.model.version,
            **self._shape_fields(fit.weights, record.gender_given),
            "pose": {bone: [float(x) for x in r] for bone, r in zip(BONES, rotvecs)},
            "translation": [float(x) for x in np.asarray(fit.translation, np.float64).ravel()],
            "unit": str(fit.unit), "up": str(fit.up), "residual_mm": float(fit.residual_mm),
            "frame": [float(x) for x in np.asarray(fit.to_model, np.float64).ravel()],
            "partial": bool(fit.partial), "coverage": {k: float(v) for k, v in fit.coverage.items()},
            "unseen": [str(b) for b in fit.unseen],
            "fit": FitStats(outer_iterations=int(fit.outer_iterations), inner_iterations=int(fit.inner_iterations),
                            seconds=round(float(fit.seconds), 3), points_fitted=int(fit.stats["points"]["fitted"]),
                            flat_cap_points=int(fit.stats["points"].get("flat_cap", 0)),
                            face_shape_from_body=bool(fit.stats.get("face_shape_from_body", False)),
                            head_shape_from_body=bool(fit.stats.get("head_shape_from_body", False))),
        })

    def _fail(self, record: Customer, message: str, progress: Progress) -> dict[str, Any]:
        failed = record.model_copy(update={"status": "failed", "error": message})
        if not self.repo.complete(failed):
            return {"status": "deleted", "customer_id": record.id}
        progress(1.0, "failed")
        log.info("customer %s: the scan cannot be fitted: %s", record.id, message)
        return _outcome(failed)


def _outcome(record: Customer) -> dict[str, Any]:
    if record.status == "failed":
        return {"status": "failed", "customer_id": record.id, "error": record.error}
    return {"status": "done", "customer_id": record.id, "residual_mm": record.residual_mm}

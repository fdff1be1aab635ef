"""Customers and garments between the HTTP layer and the model: upload parsing and validation,
garment builds (mesh sets, MakeHuman ``.mhclo``, the demo catalogue), try-on GLBs.

No FastAPI imports: errors are :class:`UploadError` (``loc`` + message) that the routes turn
into 422 answers. Shapes follow ``service.model``: avatar vertices (V, 3) metres, garment
vertices (M, 3), faces (F, 3).
"""
from __future__ import annotations

import functools
import io
import logging
import threading
import time
from datetime import datetime, timezone
from typing import Any

import numpy as np

from service.model.body import BONES, BodyModel
from service.storage import Storage, VersionedLRU, new_id

log = logging.getLogger("tryon.catalogue")

MAX_GARMENT_VERTICES = 100_000
MAX_GARMENT_FACES = 400_000
NEAR_MEDIAN_M = 0.08  # median distance of a fitted garment to its example body
NEAR_MAX_M = 0.40  # largest distance of any garment vertex to its example body
ORDER_MIN_BODY_RMS_M = 0.005  # components that barely move the body under the garment are skipped
ORDER_SWAP_COS = -0.3  # a +/- pair whose garment moves against its body: swapped files
ORDER_MIN_COS = 0.3  # body-motion-weighted mean cosine below this: files in the wrong order
UNIT_SCALES = (("m", 1.0), ("cm", 0.01), ("mm", 0.001))
DEFAULT_COLOR = (0.55, 0.55, 0.58, 1.0)
DEFAULT_LAYER = 1
DEMO_OWNER = "demo"
MESH_TYPES = ("obj", "ply", "glb")


class UploadError(ValueError):
    """An unusable upload: ``loc`` (as in a 422 detail entry) and a message saying why."""

    def __init__(self, loc: tuple[Any, ...], message: str):
        super().__init__(message)
        self.loc = loc
        self.message = message


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


# -- example avatars --------------------------------------------------------------------------
class Examples:
    """The example avatars of a model (listing order) and KD-trees of their body surfaces."""

    def __init__(self, model: BodyModel):
        from service.model.tryon import example_set, example_vertices

        self.model = model
        self.set = example_set(model)
        self.vertices = example_vertices(model, self.set)  # (1 + 2N, V, 3)
        self.listing = self.set.listing()
        self.ids = [e["id"] for e in self.listing]
        self._trees: dict[int, Any] = {}
        self._lock = threading.Lock()

    def tree(self, i: int):
        from scipy.spatial import cKDTree

        with self._lock:
            if i not in self._trees:
                self._trees[i] = cKDTree(self.model.body_vertices(self.vertices[i]).astype(np.float64))
            return self._trees[i]

    def index(self, example_id: str) -> int | None:
        try:
            return self.ids.index(example_id)
        except ValueError:
            return None


@functools.lru_cache(maxsize=4)
def examples(model: BodyModel) -> Examples:
    return Examples(model)


# -- mesh files --------------------------------------------------------------------------------
def mesh_type(data: bytes, filename: str | None) -> str:
    """'glb', 'ply' or 'obj' from the file's magic bytes, else its extension, else 'obj'."""
    if data[:4] == b"glTF":
        return "glb"
    if data[:3].lower() == b"ply":
        return "ply"
    ext = (filename or "").rsplit(".", 1)[-1].lower() if filename and "." in filename else ""
    if ext in MESH_TYPES:
        return ext
    return "obj"


def read_mesh(data: bytes, filename: str | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) float64 and faces (F, 3) of an OBJ/PLY/GLB file, in the file's vertex
    order (trimesh, ``process=False``). Raises ValueError with a reason."""
    import trimesh

    if not data:
        raise ValueError("the file is empty")
    kind = mesh_type(data, filename)
    kwargs: dict[str, Any] = {"process": False}
    if kind == "obj":
        kwargs["maintain_order"] = True
    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=kind, force="mesh", **kwargs)
    except Exception as exc:  # trimesh raises many kinds of errors on garbage
        raise ValueError(f"cannot read the file as {kind.upper()}: {exc or type(exc).__name__}") from exc
    vertices = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0:
        raise ValueError(f"no vertices found in the {kind.upper()} file")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"no triangle faces found in the {kind.upper()} file")
    if not np.all(np.isfinite(vertices)):
        raise ValueError("the mesh has non-finite vertex coordinates")
    return vertices, faces


def obj_text(vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> str:
    """A minimal OBJ (``v`` and 1-based ``f`` lines)."""
    out = io.StringIO()
    if comment:
        for line in comment.splitlines():
            out.write(f"# {line}\n")
    np.savetxt(out, np.asarray(vertices, np.float64), fmt="v %.6f %.6f %.6f")
    np.savetxt(out, np.asarray(faces, np.int64) + 1, fmt="f %d %d %d")
    return out.getvalue()


# -- customers ------------------------------------------------------------------------------
def estimate_gender(model: BodyModel, weights: np.ndarray) -> str:
    """The population's more likely gender for a shape (Gaussian conditioning on weights)."""
    try:
        from service.model import measurements as M
        from service.model.shape import _prior

        prior = _prior(model)
        n_attr = len(M.ATTRIBUTES)
        w = np.asarray(weights, np.float64)
        cond = {n_attr + k: float(w[k]) for k in range(len(w))}
        mean, _ = prior.condition(cond, {i: 1e-6 for i in cond})
        return "male" if mean[0] >= 0.5 else "female"
    except Exception:  # pragma: no cover - an estimate only
        log.exception("gender estimate failed")
        return "female"


def customer_from_mesh(model: BodyModel, data: bytes, filename: str | None,
                       gender: str | None) -> dict[str, Any]:
    """A customer record from an uploaded avatar mesh (template topology)."""
    from service.model.avatar_io import AvatarMeshError, project_mesh

    try:
        vertices, _ = read_mesh(data, filename)
    except ValueError as exc:
        raise UploadError(("body", "mesh"), str(exc)) from exc
    try:
        proj = project_mesh(model, vertices)
    except AvatarMeshError as exc:
        raise UploadError(("body", "mesh"), str(exc)) from exc
    return {
        "id": new_id(), "status": "ready", "source": "mesh", "created": now_iso(),
        **shape_fields(model, proj.weights, gender),
        "unit": proj.unit, "residual_mm": float(proj.residual_mm),
    }


def shape_fields(model: BodyModel, weights: np.ndarray, gender: str | None) -> dict[str, Any]:
    """A customer's ``weights``, ``measurements`` (the 12 attributes measured on the avatar)
    and ``estimated`` (``["gender"]`` when not given: estimated from the shape)."""
    w = np.asarray(weights, np.float64).ravel()
    estimated = [] if gender else ["gender"]
    gender = gender or estimate_gender(model, w)
    measured = model.measure(model.vertices(w), gender)
    return {
        "weights": [float(x) for x in w],
        "measurements": {k: (v if isinstance(v, str) else float(v)) for k, v in measured.items()},
        "estimated": estimated,
    }


# -- customers from scans (fitted by a job: worker.fitting.fit_customer) ---------------------
FIT_JOB = "worker.fitting.fit_customer"
SCAN_FORMATS = "OBJ, PLY, STL, GLB/glTF (embedded buffers only) or XYZ"
MISSING_JOB_GRACE_S = 60  # a fitting customer without its job for this long has failed


def fit_job_id(cid: str) -> str:
    """The deterministic id of a customer's fitting job."""
    return f"fit-{cid}"


def read_upload(model: BodyModel, data: bytes, filename: str | None) -> Any | None:
    """Parse and validate an uploaded ``mesh`` file: None for an avatar in the template
    topology (a mesh with the template's body or full vertex count: :func:`customer_from_mesh`),
    else the :class:`~service.model.scan_io.Scan` to fit. Raises :class:`UploadError`."""
    from service.model.scan_io import ScanError, read_scan

    counts = (model.n_body_vertices, int(model.mean.shape[0]))
    try:
        scan = read_scan(data, filename)
    except ScanError as exc:
        message = str(exc)
        try:  # a template-topology mesh the scan reader refuses still takes the template path
            vertices, _ = read_mesh(data, filename)
        except ValueError:
            raise UploadError(("body", "mesh"), message) from exc
        if len(vertices) in counts:
            return None
        raise UploadError(("body", "mesh"), f"{message} (an avatar in the template topology has "
                                            f"{counts[0]} vertices: /v1/body-model/template.obj)") from exc
    if scan.faces is not None and len(scan.points) in counts:
        return None
    from service.model.fitting import FitError, detect_scan_unit

    try:  # a file that is no person in m, cm or mm would only become a failed job
        detect_scan_unit(scan.points)
    except FitError as exc:
        raise UploadError(("body", "mesh"), str(exc)) from exc
    return scan


def scan_customer(scan: Any, gender: str | None, clothed: bool) -> dict[str, Any]:
    """The record of a customer whose scan waits for its fitting job (``status: fitting``)."""
    cid = new_id()
    job_id = fit_job_id(cid)
    return {
        "id": cid, "status": "fitting", "source": "scan", "created": now_iso(),
        "gender_given": gender, "clothed": bool(clothed),
        "scan": {"format": scan.kind, "points": int(len(scan.points)),
                 "faces": None if scan.faces is None else int(len(scan.faces))},
        "job": {"id": job_id, "url": f"/v1/jobs/{job_id}"},
    }


def submit_scan(storage: Storage, record: dict[str, Any], scan: Any, timeout: int) -> Any:
    """Store the scan (``scan:<id>``, for any worker) and the customer, then enqueue its
    fitting job (deterministic id, retried); on failure nothing is left behind. The rq job."""
    from service.model.scan_io import scan_to_npz_bytes

    cid = record["id"]
    storage.put_scan(cid, scan_to_npz_bytes(scan))
    try:
        storage.put_customer(record)
        return storage.enqueue(FIT_JOB, cid, job_id=record["job"]["id"], job_timeout=timeout,
                               description=f"fit the scan of customer {cid}",
                               meta={"customer_id": cid, "progress": 0.0, "message": "waiting for a worker"})
    except BaseException:
        storage.delete_customer(cid)
        raise


def customer_from_fit(model: BodyModel, record: dict[str, Any], fit: Any) -> dict[str, Any]:
    """The ready customer from its fitting record and a ``FitResult``: shape fields, ``pose``
    (bone -> local axis-angle radians, ``BONES`` order), ``translation`` (metres, model
    frame), ``unit`` and ``up`` of the file, ``residual_mm``, ``fit`` statistics."""
    rotvecs = np.asarray(fit.rotvecs, np.float64).reshape(len(BONES), 3)
    out = {k: v for k, v in record.items() if k != "error"}
    out.update({
        "status": "ready", **shape_fields(model, fit.weights, record.get("gender_given")),
        "pose": {bone: [float(x) for x in r] for bone, r in zip(BONES, rotvecs)},
        "translation": [float(x) for x in np.asarray(fit.translation, np.float64).ravel()],
        "unit": str(fit.unit), "up": str(fit.up), "residual_mm": float(fit.residual_mm),
        "fit": {"outer_iterations": int(fit.outer_iterations), "inner_iterations": int(fit.inner_iterations),
                "seconds": round(float(fit.seconds), 3)},
    })
    return out


def customer_view(storage: Storage, record: dict[str, Any]) -> dict[str, Any]:
    """A customer as the API shows it: a scan customer's job with its live status; a
    ``fitting`` customer whose job failed (retries exhausted) or vanished shows as failed."""
    job_ref = record.get("job")
    if not job_ref:
        return record
    from service.storage import job_state

    out = dict(record)
    job = storage.get_job(job_ref["id"])
    state = job_state(job) if job is not None else None
    out["job"] = {**job_ref, "status": state["status"] if state else None}
    if out.get("status") == "fitting":
        if state is not None and state["status"] == "failed":
            out.update(status="failed", error=state["error"] or "the fitting job failed")
        elif state is None:
            created = datetime.fromisoformat(record["created"])
            if (datetime.now(timezone.utc) - created).total_seconds() > MISSING_JOB_GRACE_S:
                out.update(status="failed", error="the fitting job was lost; upload the scan again")
    return out


class BodyCache:
    """LRU of ``customer_body`` per customer id, valid while the customer's weights are
    unchanged (dropped on delete)."""

    def __init__(self, size: int = 64):
        self._lru = VersionedLRU(size)

    def get(self, model: BodyModel, cid: str, weights: list[float]):
        from service.model.tryon import customer_body

        key = tuple(weights)
        body = self._lru.get(cid, key)
        if body is None:
            body = customer_body(model, np.asarray(weights, np.float64))
            self._lru.put(cid, key, body)
        return body

    def drop(self, cid: str) -> None:
        self._lru.drop(cid)


# -- garments ----------------------------------------------------------------------------------
def parse_color(value: str | None) -> tuple[float, float, float, float]:
    """'#rrggbb' (sRGB) -> linear RGBA; None -> the default grey."""
    if not value:
        return DEFAULT_COLOR
    h = value.lstrip("#")
    srgb = np.array([int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return (float(lin[0]), float(lin[1]), float(lin[2]), 1.0)


def check_near_bodies(ex: Examples, fits: np.ndarray, labels: list[str], locs: list[tuple]) -> None:
    """Every fitted garment must lie near its example avatar's body surface."""
    for i, F in enumerate(fits):
        d, _ = ex.tree(i).query(np.asarray(F, np.float64))
        med, mx = float(np.median(d)), float(d.max())
        where = f"{labels[i]} (example avatar {ex.ids[i]})"
        if med > NEAR_MEDIAN_M:
            raise UploadError(locs[i], f"{where}: the garment is not fitted to this example avatar: its vertices "
                                       f"are {100 * med:.1f} cm from the body surface (median; limit "
                                       f"{100 * NEAR_MEDIAN_M:.0f} cm). Fit it to /v1/example-avatars/"
                                       f"{ex.ids[i]}.obj, in metres, Y up")
        if mx > NEAR_MAX_M:
            raise UploadError(locs[i], f"{where}: a vertex is {100 * mx:.1f} cm from the body surface (limit "
                                       f"{100 * NEAR_MAX_M:.0f} cm)")


def check_order(ex: Examples, fits: np.ndarray, labels: list[str]) -> None:
    """The garment must follow the example avatars: for each component i, the change of the
    garment between E(i,+) and E(i,-) must point the way the body under it changes (cosine),
    weighted by how much the body changes there. Catches files in the wrong order."""
    near = ex.tree(0).query(np.asarray(fits[0], np.float64))[1]
    cos, wts = [], []
    for i in range(ex.set.n):
        p, m = 1 + 2 * i, 2 + 2 * i
        dg = np.asarray(fits[p] - fits[m], np.float64)
        db = np.asarray(ex.vertices[p][near] - ex.vertices[m][near], np.float64)
        rms = float(np.sqrt((db ** 2).sum(axis=1).mean()))
        ng, nbd = np.linalg.norm(dg), np.linalg.norm(db)
        if rms < ORDER_MIN_BODY_RMS_M or ng == 0 or nbd == 0:
            continue
        c = float((dg * db).sum() / (ng * nbd))
        if c < ORDER_SWAP_COS:
            raise UploadError(("body", "meshes", p), f"{labels[p]} and {labels[m]} look swapped: the garment "
                                                     f"changes against the body between {ex.ids[p]} and {ex.ids[m]}")
        cos.append(c)
        wts.append(rms)
    if wts and float(np.average(cos, weights=wts)) < ORDER_MIN_COS:
        raise UploadError(("body", "meshes"), "the meshes do not follow the example avatars' shapes: send them in "
                                              "the order of /v1/example-avatars, each fitted to its avatar")


def detect_scale(ex: Examples, vertices: np.ndarray) -> tuple[str, float]:
    """The unit (m, cm, mm) that puts a garment closest to the mean example body."""
    best = None
    for name, scale in UNIT_SCALES:
        d, _ = ex.tree(0).query(vertices * scale)
        med = float(np.median(d))
        if best is None or med < best[2]:
            best = (name, scale, med)
    return best[0], best[1]


def fits_from_meshes(model: BodyModel, files: list[tuple[str, bytes]]) -> tuple[np.ndarray, np.ndarray, str]:
    """(fits (1 + 2N, M, 3), faces (F, 3), unit) from one mesh per example avatar."""
    ex = examples(model)
    n = len(ex.ids)
    if len(files) != n:
        raise UploadError(("body", "meshes"), f"expected {n} meshes, one per example avatar in the order of "
                                              f"/v1/example-avatars; got {len(files)}")
    fits: list[np.ndarray] = []
    faces0: np.ndarray | None = None
    labels = [f"file {i + 1} '{name}'" for i, (name, _) in enumerate(files)]
    locs = [("body", "meshes", i) for i in range(n)]
    unit, scale = "m", 1.0
    for i, (name, data) in enumerate(files):
        try:
            v, f = read_mesh(data, name)
        except ValueError as exc:
            raise UploadError(locs[i], f"{labels[i]}: {exc}") from exc
        if len(v) > MAX_GARMENT_VERTICES:
            raise UploadError(locs[i], f"{labels[i]}: {len(v)} vertices; at most {MAX_GARMENT_VERTICES} per garment")
        if len(f) > MAX_GARMENT_FACES:
            raise UploadError(locs[i], f"{labels[i]}: {len(f)} faces; at most {MAX_GARMENT_FACES} per garment")
        if faces0 is None:
            faces0 = f
            unit, scale = detect_scale(ex, v)
        else:
            if len(v) != len(fits[0]):
                raise UploadError(locs[i], f"{labels[i]}: {len(v)} vertices, but file 1 has {len(fits[0])}: every "
                                           "mesh must be the same garment (same vertices and faces)")
            if f.shape != faces0.shape or not np.array_equal(f, faces0):
                raise UploadError(locs[i], f"{labels[i]}: its faces differ from file 1's: every mesh must be the "
                                           "same garment (same vertices and faces, in the same order)")
        fits.append(v * scale)
    assert faces0 is not None
    F = np.stack(fits)
    check_near_bodies(ex, F, labels, locs)
    check_order(ex, F, labels)
    return F, faces0.astype(np.int32), unit


def fits_from_mhclo(model: BodyModel, mhclo: bytes, obj: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(fits (1 + 2N, M, 3), faces) of a MakeHuman garment (``.mhclo`` binding + its ``.obj``)."""
    from service.model.mhclo import MhcloError, parse_mhclo, parse_obj_faces

    texts = []
    for field, data in (("mhclo", mhclo), ("obj", obj)):
        if not data:
            raise UploadError(("body", field), f"the {field} file is empty")
        try:
            texts.append(data.decode("utf-8"))
        except UnicodeDecodeError:
            try:
                texts.append(data.decode("latin-1"))
            except UnicodeDecodeError as exc:  # pragma: no cover - latin-1 decodes anything
                raise UploadError(("body", field), f"the {field} file is not text") from exc
    try:
        binding = parse_mhclo(texts[0], model.mean.shape[0])
    except MhcloError as exc:
        raise UploadError(("body", "mhclo"), f"mhclo: {exc}") from exc
    try:
        n_v, faces = parse_obj_faces(texts[1])
    except MhcloError as exc:
        raise UploadError(("body", "obj"), f"obj: {exc}") from exc
    n_b = len(binding.indices)
    if n_v != n_b:
        raise UploadError(("body", "obj"), f"the OBJ has {n_v} vertices but the mhclo binds {n_b}: "
                                           "they are not the same garment")
    if n_v > MAX_GARMENT_VERTICES:
        raise UploadError(("body", "obj"), f"{n_v} vertices; at most {MAX_GARMENT_VERTICES} per garment")
    if len(faces) > MAX_GARMENT_FACES:
        raise UploadError(("body", "obj"), f"{len(faces)} faces; at most {MAX_GARMENT_FACES} per garment")
    ex = examples(model)
    fits = np.stack([binding.fit(E) for E in ex.vertices])
    if not np.all(np.isfinite(fits)):
        raise UploadError(("body", "mhclo"), "the binding gives non-finite vertex positions")
    check_near_bodies(ex, fits, ["the fitted garment"] * len(fits), [("body", "mhclo")] * len(fits))
    return fits, faces.astype(np.int32)


def build_and_store(model: BodyModel, storage: Storage, fits: np.ndarray, faces: np.ndarray, *,
                    name: str, owner: str, source: str, color: tuple[float, ...], layer: int,
                    extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """Build the clothing basis, store it (files, then metadata) and return the record."""
    from service.model.tryon import build_garment_basis

    ex = examples(model)
    gid = new_id()
    meta = {"name": name, "owner": owner, "source": source, "color": [float(c) for c in color],
            "layer": int(layer), "created": now_iso()}
    basis = build_garment_basis(model, fits, faces, ex.set, meta=meta)
    record = {"id": gid, **meta, **(extra or {}),
              "n_vertices": int(basis.meta["n_vertices"]), "n_faces": int(basis.meta["n_faces"]),
              "n_components": int(basis.meta["n_components"]), "etag": basis.etag()}
    basis.meta["id"] = gid
    storage.put_garment(record, basis)
    return record


def ensure_demo_garments(model: BodyModel, storage: Storage) -> list[str]:
    """Build and store the demo garments that are missing (idempotent; one process builds,
    the others wait on the Redis lock). Returns the ids of the demo garments."""
    from service.model.demo_garments import COLORS, LAYER, make_demo_garments

    ids: list[str] = []
    with storage.lock("demo-garments", ttl=120, wait=120) as held:
        if not held:
            log.warning("demo garments: lock not obtained; not building them")
        templates = None
        for name in ("tshirt", "trousers", "skirt"):
            gid = storage.get_str(f"demo:{name}")
            if gid and storage.get_garment(gid) is not None:
                ids.append(gid)
                continue
            if not held:
                continue
            if templates is None:
                templates = make_demo_garments(model)
            t0 = time.perf_counter()
            ex = examples(model)
            fits = np.stack([templates[name].fit(model, E) for E in ex.vertices])
            rec = build_and_store(model, storage, fits, templates[name].faces, name=name, owner=DEMO_OWNER,
                                  source="demo", color=COLORS[name], layer=LAYER[name])
            storage.set_str(f"demo:{name}", rec["id"])
            ids.append(rec["id"])
            log.info("demo garment %s built (%s) in %.2fs", name, rec["id"], time.perf_counter() - t0)
    return ids


# -- GLB ---------------------------------------------------------------------------------------
def skin_of(model: BodyModel, body: Any) -> dict[str, Any]:
    """The customer's skeleton (rest joints of their body) for GLB skins."""
    return {"joints": model.joints(body.vertices), "parents": np.asarray(model.bone_parents),
            "joint_names": list(BONES)}


def garment_mesh(basis: Any, record: dict[str, Any], body: Any, layer: int) -> dict[str, Any]:
    """The garment tried on ``body`` as a scene mesh dict (skinned with the basis' skinning)."""
    from service.model.tryon import try_on

    v, _moved = try_on(basis, body, layer=layer)
    return {"vertices": np.asarray(v, np.float32), "faces": np.asarray(basis.faces),
            "normals": basis.normals(v, body.weights), "color": tuple(record.get("color") or DEFAULT_COLOR),
            "name": str(record.get("name") or "garment"), "double_sided": True,
            "vertex_joints": np.asarray(basis.skin_idx), "vertex_weights": np.asarray(basis.skin_w)}


def avatar_mesh(model: BodyModel, body: Any) -> dict[str, Any]:
    nb = model.n_body_vertices
    return {"vertices": model.body_vertices(body.vertices), "faces": model.body_faces,
            "normals": body.normals, "color": (0.8, 0.7, 0.62, 1.0), "name": "avatar",
            "vertex_joints": model.lbs_indices[:nb], "vertex_weights": model.lbs_weights[:nb]}


def single_mesh_glb(mesh: dict[str, Any], skin: dict[str, Any], compression: str | None) -> bytes:
    from service.model import gltf

    return gltf.scene_to_glb([mesh], skin=skin, compression=compression)


def scene_glb(meshes: list[dict[str, Any]], skin: dict[str, Any], compression: str | None) -> bytes:
    """Several meshes sharing one skin (avatar and garments)."""
    from service.model import gltf

    return gltf.scene_to_glb(meshes, skin=skin, compression=compression)


def basis_glb(basis: Any, record: dict[str, Any], compression: str | None) -> bytes:
    """The mean garment with the clothing basis rows as morph targets."""
    from service.model import gltf

    B = np.asarray(basis.B)
    return gltf.basis_to_glb(np.asarray(basis.g), B, np.asarray(basis.faces),
                             color=tuple(record.get("color") or DEFAULT_COLOR),
                             name=str(record.get("name") or "garment"),
                             target_names=[f"pc{i:02d}" for i in range(B.shape[0])], compression=compression)

"""Garments: the catalogue, retailers' uploads (one mesh fitted to each example avatar, or a
MakeHuman ``.mhclo``), their clothing bases, and the demo catalogue built at the first start."""
from __future__ import annotations

import hashlib
import logging
from collections.abc import Callable

import numpy as np

from typing import Any

from service.model.body.model import BodyModel
from service.model.garments.autofit import fit_to_examples
from service.model.drape import DrapeError
from service.model.garments.draped import DrapedFits, draped_example_fits
from service.model.garments.catalogue import Material, RenderLayout, Texture
from service.model.fitting.checks import FitError
from service.model.fitting.fit import fit_body
from service.model.formats.mesh_io import scan_type
from service.model.formats.frames import UNITS, unit_against
from service.model.garments import sizing as SZ
from service.model.garments.tryon import GarmentBasis, build_garment_basis, refresh_skinning
from service.records import Garment, JobRef
from service.settings import Settings
from service.storage.bases import BasisStore
from service.storage.drapes import DrapeStore
from service.storage.queue import JobQueue
from service.storage.records import GarmentRepo, new_id

from . import scenes
from . import sizes as sizing
from .sizes import Chart
from .errors import Conflict, Forbidden, Invalid, NotFound
from .demo import DemoCatalogue
from .examples import Examples
from .limits import Limits
from .progress import MonotoneProgress, Progress
from .uploads import (GARMENT_UPS, DrapedGarment, MhcloUpload, clean_name, is_textured, glb_look, obj_layout, one_cloth, parse_color, place_on_body, read_draped_avatar,
                      read_garment_mesh, read_mhclo_layout, read_texture, upload_memory)


log = logging.getLogger("tryon.garments")

NEAR_MEDIAN_M = 0.08  # median distance of a fitted garment to its example body
NEAR_MAX_M = 0.40  # largest distance of any garment vertex to its example body
ORDER_MIN_BODY_RMS_M = 0.005  # components that barely move the body under the garment are skipped
ORDER_SWAP_COS = -0.3  # a +/- pair whose garment moves against its body: swapped files
ORDER_MIN_COS = 0.3  # body-motion-weighted mean cosine below this: files in the wrong order
DEFAULT_LAYER = 1
UPLOAD_METALLIC, UPLOAD_ROUGHNESS = 0.0, 0.85  # cloth: dielectric, rough
BUILD_JOB = "worker.jobs.build_garment"  # the rq job, by dotted path
# shares of a build job's progress
BUILD_SHARES = {"avatar_fit": 0.3, "autofit": 0.6, "basis": 0.1}


def build_job_id(gid: str) -> str:
    """The deterministic id of a draped garment's build job."""
    return f"build-{gid}"


def build_timeout(settings: Settings, sizes: int) -> int:
    """Seconds a garment's build job may run: ``TRYON_GARMENT_TIMEOUT`` per size (a garment in 5
    sizes drapes 5 garments on every example avatar and population body)."""
    return settings.garment_timeout * max(1, sizes)


class GarmentService(DemoCatalogue):
    def __init__(self, settings: Settings, model: BodyModel, repo: GarmentRepo, bases: BasisStore, queue: JobQueue,
                 limits: Limits, examples: Callable[[], Examples], drapes: DrapeStore):
        self.settings = settings
        self.model = model
        self.repo = repo
        self.bases = bases
        self.queue = queue
        self.limits = limits
        self._examples = examples  # the example avatars, built on first use
        self.drapes = drapes  # customers' exact drapes of the garments

    @property
    def examples(self) -> Examples:
        return self._examples()

    # -- reading -----------------------------------------------------------------------------
    def list(self) -> list[Garment]:
        """The catalogue, oldest first; garments being built with their build's progress."""
        return [self._view(g) for g in self.repo.list()]

    def get(self, gid: str) -> Garment:
        record = self.repo.get(gid)
        if record is None:
            raise NotFound(f"garment '{gid}' not found")
        return self._view(record)

    def _view(self, record: Garment) -> Garment:
        """A garment being built shows its job's status and progress; one whose job failed
        (retries exhausted) shows as failed."""
        if record.status != "building" or record.job is None:
            return record
        job = self.queue.get(record.job.id)
        update: dict[str, Any] = {"job": record.job.model_copy(update={"status": job and job.status}),
                                  "progress": job.progress if job else 0.0}
        if job is not None and job.status == "failed":
            update.update(status="failed", error=job.error or "the build job failed")
        return record.model_copy(update=update)

    def require_ready(self, record: Garment | None, gid: str, size: int | None = None) -> tuple[Garment, GarmentBasis]:
        """A garment that can be tried on, with its basis (``size``: that size's, by index in
        the chart; None: the base size's): 404 unknown; 409 while it is being built, when its
        build failed, or when it was built for another body model."""
        if record is None:
            raise NotFound(f"garment '{gid}' not found")
        if record.status == "building":
            raise Conflict(f"garment '{gid}' is not ready: it is being built"
                           + (f" (job '{record.job.id}', GET {record.job.url})" if record.job else ""))
        if record.status == "failed":
            raise Conflict(f"garment '{gid}' could not be built: {record.error or 'unknown error'}")
        if not record.is_current(self.model.version):
            raise Conflict(f"garment '{gid}' was built for another body model ({record.body_model or 'unversioned'}; "
                           f"this service runs {self.model.version}): upload it again")
        sized = bool(record.sizes) and len(record.sizes) > 1
        basis = self.bases.load(gid, record.etag, (record.base_index() if size is None else size) if sized else None)
        if basis is None:
            raise NotFound(f"garment '{gid}' not found (its basis files are missing)")
        if sized:  # built with sizes: the skinning is current
            return record, basis
        return self._current_skinning(record, basis)

    def size_fit(self, record: Garment, basis: GarmentBasis) -> SZ.SizeFit:
        """The garment's girths per size (``sizing.SizeFit``)."""
        return sizing.garment_fit(self.model, record, basis)

    def _current_skinning(self, record: Garment, basis: GarmentBasis) -> tuple[Garment, GarmentBasis]:
        """A basis whose skin weights an older version of the service made gets them recomputed
        (``tryon.refresh_skinning``, once: written atomically beside the record, whose ETag
        changes with it; concurrent refreshes write the same files)."""
        fresh = refresh_skinning(self.model, basis)
        if fresh is None:
            return record, basis
        updated = record.model_copy(update={"etag": fresh.etag()})
        self.bases.save(record.id, fresh)
        if not self.repo.replace_if_exists(updated):  # deleted meanwhile
            self.bases.delete(record.id)
            raise NotFound(f"garment '{record.id}' not found")
        log.info("garment %s: skin weights recomputed (skinning version %s)", record.id, fresh.meta["skinning"])
        return updated, fresh

    def basis_glb(self, gid: str, compression: str | None, if_none_match: list[str] | None = None,
                  components: int | None = None) -> tuple[bytes | None, str]:
        """The clothing basis as GLB (its first ``components`` rows as morph targets; None: all)
        and its strong ETag (quoted); ``None`` bytes when one of ``if_none_match`` (quoted tags,
        or ``*``) matches: not modified."""
        record, basis = self.require_ready(self.repo.get(gid), gid)
        rows = len(basis.B)
        n = rows if components is None else min(components, rows)
        tag = basis.etag() or record.etag
        etag = '"' + "-".join([tag, *([compression] if compression else []), *([f"c{n}"] if n < rows else [])]) + '"'
        if scenes.etag_matches(etag, if_none_match):
            return None, etag
        return scenes.basis_glb(basis, record, compression, n), etag

    def example(self, example_id: str) -> np.ndarray:
        """An example avatar's vertices (V, 3) (404 unknown)."""
        i = self.examples.index(example_id)
        if i is None:
            raise NotFound(f"example avatar '{example_id}' not found (see /v1/example-avatars)")
        return self.examples.vertices[i]

    # -- creating ----------------------------------------------------------------------------
    def chart(self, size_chart: str | None, base_size: str | None, fabric: str | None) -> Chart | None:
        """The upload's ``size_chart``, ``base_size`` and ``fabric`` checked (422)."""
        return sizing.parse_chart(self.model, size_chart, base_size, fabric)

    def create_from_meshes(self, files: list[tuple[str, bytes]], *, name: str, owner: str, color: str | None,
                           layer: int, texture: tuple[bytes, str | None] | None = None,
                           chart: Chart | None = None, gender: str | None = None) -> Garment:
        """:meth:`_create_from_meshes` within the process's memory budget for decoding uploads."""
        need = sum(upload_memory(data, fname) for fname, data in files) + (upload_memory(*texture) if texture else 0)
        with self.limits.memory(need):
            return self._create_from_meshes(files, name=name, owner=owner, color=color, layer=layer, texture=texture,
                                            chart=chart, gender=gender)

    def _create_from_meshes(self, files: list[tuple[str, bytes]], *, name: str, owner: str, color: str | None,
                            layer: int, texture: tuple[bytes, str | None] | None = None,
                            chart: Chart | None = None, gender: str | None = None) -> Garment:
        """A garment fitted by the retailer to every example avatar: one mesh per example, in
        the order of ``/v1/example-avatars``, same vertices and faces in each. The first file's
        OBJ texture coordinates (``vt``) and the optional ``texture`` (bytes, filename) give
        its look."""
        name = clean_name(name)
        rgba = parse_color(color, scenes.DEFAULT_GARMENT_COLOR)
        tex = read_texture(*texture) if texture is not None else None
        if chart is not None and chart.sizes:
            raise Invalid(("body", "size_chart"), "'meshes' are one size fitted to every example avatar: a size "
                                                  "chart goes with a 'garment' (graded by the service, or graded "
                                                  "meshes with 'garment_sizes') or an 'mhclo'")
        fits, faces, unit = self._fits_from_meshes(files)
        faces, layout = _file_layout(*files[0], faces)
        # pre-fitted meshes are the retailer's own example fits: used as they are (not draped)
        return self._build_and_store(fits, faces, name=name, owner=owner, source="meshes", color=rgba, layer=layer,
                                     fabric=chart.fabric if chart is not None else SZ.DEFAULT_FABRIC,
                                     unit=unit, layout=layout, material=_upload_material(tex, rgba, color, layout),
                                     gender=gender)

    def create_from_mhclo(self, mhclo: bytes, obj: bytes, *, name: str, owner: str, color: str | None,
                          layer: int, texture: tuple[bytes, str | None] | None = None,
                          chart: Chart | None = None, gender: str | None = None) -> Garment:
        """A MakeHuman garment, fitted to every example avatar through its binding; the OBJ's
        texture coordinates and the optional ``texture`` (bytes, filename) give its look. With a
        size ``chart``: the garment as bound to the mean avatar is the base size, graded to
        every size of the chart. Built now (``TRYON_DRAPE`` off: the binding's fits, seconds),
        or with the drape on checked now and built by a queued job (:meth:`run_build`: the
        record is listed with ``status: building``)."""
        name = clean_name(name)
        rgba = parse_color(color, scenes.DEFAULT_GARMENT_COLOR)
        tex = read_texture(*texture) if texture is not None else None
        binding, faces, layout = read_mhclo_layout(self.model, mhclo, obj)
        material = _upload_material(tex, rgba, color, layout)
        fits = self._bound_fits(binding)  # 422 now when it does not sit on the example avatars
        record = Garment(id=new_id(), body_model=self.model.version, owner=owner, name=name, source="mhclo",
                         color=[float(c) for c in rgba], layer=int(layer), textured=is_textured(material, layout),
                         n_vertices=int(fits.shape[1]), n_faces=int(len(faces)),
                         gender=gender,
                         **(chart.record_fields() if chart is not None and chart.sizes
                            else {"fabric": chart.fabric if chart is not None else SZ.DEFAULT_FABRIC}))
        if self.settings.drape:  # draping on every example takes minutes: a queued build job
            self.limits.check_jobs()
            return self._queue_build(record.model_copy(update={"status": "building"}),
                                     MhcloUpload(mhclo, obj, texture, color).to_bytes())
        built = self._from_binding(record, binding, faces, layout, material, drape=False, fits=fits)
        self._publish_built(built)
        return built

    def _from_binding(self, record: Garment, binding: Any, faces: np.ndarray, layout: RenderLayout | None,
                      material: Material | None, drape: bool, progress: Progress | None = None,
                      fits: np.ndarray | None = None) -> Garment:
        """A garment bound to the body mesh (``.mhclo``, the demo catalogue): its example fits
        by its binding (with ``drape``: then draped at its own size, its fit to the mean example
        avatar), in the sizes of its chart (graded: :meth:`_store_sizes`) or one; the bases
        stored, the record with its counts returned (not yet published). ``fits``: its
        :meth:`_bound_fits`, when already made. Raises ``Invalid`` (it does not sit on the
        bodies) or ``DrapeError``."""
        mean = self.examples.index("mean") or 0
        if record.sizes and len(record.sizes) > 1:
            chart = Chart([sz.chart_entry() for sz in record.sizes], record.base_size or "", record.fabric)
            source = np.asarray(self.examples.vertices[mean], np.float64)
            g0 = np.asarray(binding.fit(source), np.float64)
            if not np.all(np.isfinite(g0)):
                raise Invalid(("body", "mhclo"), "the binding gives non-finite vertex positions")
            rests, on, bodies = sizing.graded(self.model, g0, faces, source, chart, record.gender)
            return self._store_sizes(record, rests, faces, on, bodies[chart.base], chart, layout, material,
                                     progress, bound=binding.fit, drape=drape)
        fits = self._bound_fits(binding) if fits is None else fits
        rest = strains = starts = None
        if drape:  # its size: the garment as bound to the mean example avatar
            rest = fits[mean]
            d = self.drape_to_examples(rest, faces, fits, record.fabric, progress, record.gender)
            fits, strains, starts = d.fits, d.strain_fits, fits
        return self._store_one_size(record, fits, faces, layout, material, rest=rest, drape=drape, strain_fits=strains,
                                    start_fits=starts)

    def _bound_fits(self, binding: Any) -> np.ndarray:
        """(E, N, 3) a bound garment's fit to every example avatar, checked (``Invalid``)."""
        fits = np.stack([binding.fit(E) for E in self.examples.vertices])
        if not np.all(np.isfinite(fits)):
            raise Invalid(("body", "mhclo"), "the binding gives non-finite vertex positions")
        self._check_near_bodies(fits, ["the fitted garment"] * len(fits), [("body", "mhclo")] * len(fits))
        return fits

    def _store_sizes(self, record: Garment, rests: np.ndarray, faces: np.ndarray, bodies_on: np.ndarray,
                     base_body: np.ndarray, chart: Chart, layout: RenderLayout | None, material: Material | None,
                     progress: Progress | None = None, bound: Callable[[np.ndarray], np.ndarray] | None = None,
                     drape: bool = False) -> Garment:
        """Every size's example fits and basis, stored together; the record with its counts,
        combined ETag and girths per size (``fit``). The example fits: carried by the warp
        (``sizes.size_example_fits``), or for a garment bound to the body (``bound``: its
        binding's fit, avatar -> garment) by its binding (``sizing.bound_size_fits``,
        milliseconds a size); with ``drape`` each size then keeps its own size: its rest shape
        settled on every example (:meth:`drape_to_examples`)."""
        progress = MonotoneProgress(progress or (lambda f, m: None))
        if bound is not None:
            fits = SZ.bound_size_fits(bound, self.examples.vertices, rests, bodies_on)
        else:
            fits = sizing.per_size_fits(self.model, rests, faces, bodies_on,
                                        progress.scaled(0.0, 0.1 if drape else 0.9))
        strains: list = [None] * len(fits)
        starts: list = [None] * len(fits)
        if drape:
            n = len(fits)
            starts = fits
            draped = [self.drape_to_examples(rests[s], faces, f, chart.fabric,
                                             progress.scaled(0.1 + 0.8 * s / n, 0.8 / n, f"size {chart.labels[s]}: "),
                                             record.gender)
                      for s, f in enumerate(fits)]
            fits, strains = [d.fits for d in draped], [d.strain_fits for d in draped]
        progress(0.9, "building the clothing bases")
        bases = []
        for s, f in enumerate(fits):
            meta = {"name": record.name, "owner": record.owner, "source": record.source, "color": record.color,
                    "layer": record.layer, "created": record.created, "id": record.id, "body_model": self.model.version,
                    "size": chart.labels[s]}
            bases.append(build_garment_basis(self.model, f, faces, self.examples.set, meta=meta, layout=layout,
                                             material=material, rest=rests[s], strain_fits=strains[s],
                                             start_fits=starts[s]))
        fit = SZ.sized_garment_fit(self.model, rests, faces, bodies_on, chart.labels, chart.base, base_body,
                                   chart.fabric, list(chart.sizes[0]["measurements"]))
        self.bases.save_sizes(record.id, bases)
        etag = hashlib.sha256("-".join(b.etag() for b in bases).encode()).hexdigest()[:32]
        b0 = bases[chart.base]
        return record.model_copy(update={"n_vertices": int(b0.meta["n_vertices"]), "n_faces": int(b0.meta["n_faces"]),
                                         "n_components": int(b0.meta["n_components"]), "etag": etag,
                                         "fit": fit.to_meta(), "example_fits": "drape" if drape else "warp"})

    def drape_to_examples(self, rest: np.ndarray, faces: np.ndarray, warp_fits: np.ndarray, fabric: str,
                          progress: Progress | None = None, gender: str | None = None) -> DrapedFits:
        """The garment at its own size (``rest`` (N, 3), as uploaded on its body) settled on every
        example avatar by the cloth drape engine, each solve started from the warp fit there
        (``warp_fits`` (E, N, 3)), and on ``settings.drape_population`` population bodies
        (started from the warp fits' basis there; of the garment's ``gender`` mostly, where it has
        one: ``tryon.population_sample``): the example fits (E, N, 3) of its clothing
        basis, those of the least-squares basis through all the drapes when there are population
        bodies, and those of its strain channel (``garments.draped.draped_example_fits``). The one place a garment meets the
        examples (per size, for graded garments). Raises ``DrapeError`` (degenerate rest shape,
        a drape that cannot settle)."""
        ex = self.examples
        cb = None if progress is None else (lambda f, msg: progress(f, msg))
        d = draped_example_fits(self.model, ex.set, ex.vertices, rest, faces, warp_fits, fabric,
                                self.settings.drape_population, progress=cb, workers=self.settings.drape_workers,
                                gender=gender, max_vertices=self.settings.drape_max_vertices or None)
        log.info("draped on %d bodies: %.1fs, %d of them settled, %d population bodies left out (it would end "
                 "inside them without friction in the soft levels)", len(d.stats),
                 sum(s["seconds"] for s in d.stats), sum(bool(s["settled"]) for s in d.stats),
                 sum("failed" in s for s in d.stats))
        return d

    def _fits_from_meshes(self, files: list[tuple[str, bytes]]) -> tuple[np.ndarray, np.ndarray, str]:
        ex = self.examples
        n = len(ex.ids)
        if len(files) != n:
            raise Invalid(("body", "meshes"), f"expected {n} meshes, one per example avatar in the order of "
                                              f"/v1/example-avatars; got {len(files)}")
        fits: list[np.ndarray] = []
        faces0: np.ndarray | None = None
        labels = [f"file {i + 1} '{fname}'" for i, (fname, _) in enumerate(files)]
        locs = [("body", "meshes", i) for i in range(n)]
        unit, scale = "m", 1.0
        for i, (fname, data) in enumerate(files):
            v, f = read_garment_mesh(data, fname, locs[i], labels[i])
            if faces0 is None:
                faces0 = f
                unit, scale, _ = unit_against(v, ex.tree(0))
            else:
                if len(v) != len(fits[0]):
                    raise Invalid(locs[i], f"{labels[i]}: {len(v)} vertices, but file 1 has {len(fits[0])}: every "
                                           "mesh must be the same garment (same vertices and faces)")
                if f.shape != faces0.shape or not np.array_equal(f, faces0):
                    raise Invalid(locs[i], f"{labels[i]}: its faces differ from file 1's: every mesh must be the "
                                           "same garment (same vertices and faces, in the same order)")
            fits.append(v * scale)
        assert faces0 is not None
        F = np.stack(fits)
        self._check_near_bodies(F, labels, locs)
        self._check_order(F, labels)
        return F, faces0, unit

    def _check_near_bodies(self, fits: np.ndarray, labels: list[str], locs: list[tuple]) -> None:
        """Every fitted garment must lie near its example avatar's body surface."""
        ex = self.examples
        for i, F in enumerate(fits):
            d, _ = ex.tree(i).query(np.asarray(F, np.float64))
            med, mx = float(np.median(d)), float(d.max())
            where = f"{labels[i]} (example avatar {ex.ids[i]})"
            if med > NEAR_MEDIAN_M:
                raise Invalid(locs[i], f"{where}: the garment is not fitted to this example avatar: its vertices "
                                       f"are {100 * med:.1f} cm from the body surface (median; limit "
                                       f"{100 * NEAR_MEDIAN_M:.0f} cm). Fit it to /v1/example-avatars/"
                                       f"{ex.ids[i]}.obj, in metres, Y up")
            if mx > NEAR_MAX_M:
                raise Invalid(locs[i], f"{where}: a vertex is {100 * mx:.1f} cm from the body surface (limit "
                                       f"{100 * NEAR_MAX_M:.0f} cm)")

    def _check_order(self, fits: np.ndarray, labels: list[str]) -> None:
        """The garment must follow the example avatars: for each component i, the change of the
        garment between E(i,+) and E(i,-) must point the way the body under it changes (cosine),
        weighted by how much the body changes there. Catches files in the wrong order."""
        ex = self.examples
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
                raise Invalid(("body", "meshes", p), f"{labels[p]} and {labels[m]} look swapped: the garment changes "
                                                     f"against the body between {ex.ids[p]} and {ex.ids[m]}")
            cos.append(c)
            wts.append(rms)
        if wts and float(np.average(cos, weights=wts)) < ORDER_MIN_COS:
            raise Invalid(("body", "meshes"), "the meshes do not follow the example avatars' shapes: send them in the "
                                              "order of /v1/example-avatars, each fitted to its avatar")

    def _build_and_store(self, fits: np.ndarray, faces: np.ndarray, *, name: str, owner: str, source: str,
                         color: tuple[float, ...], layer: int, unit: str | None = None,
                         layout: RenderLayout | None = None, material: Material | None = None,
                         **extra: Any) -> Garment:
        """Build the clothing basis, store its files, then publish the record (nothing is
        visible until the basis is complete; on failure nothing is left behind). ``extra``:
        further record fields (catalogue metadata)."""
        record = Garment(id=new_id(), body_model=self.model.version, owner=owner, name=name, source=source,  # type: ignore[arg-type]
                         color=[float(c) for c in color], layer=int(layer), unit=unit,
                         textured=is_textured(material, layout), **extra)
        record = self._store_one_size(record, fits, faces, layout, material,
                                      example_fits="meshes" if source == "meshes" else "warp")
        self._publish_built(record)
        return record

    def _store_one_size(self, record: Garment, fits: np.ndarray, faces: np.ndarray, layout: RenderLayout | None,
                        material: Material | None, rest: np.ndarray | None = None, drape: bool = False,
                        example_fits: str | None = None, strain_fits: np.ndarray | None = None,
                        start_fits: np.ndarray | None = None) -> Garment:
        """A one-size garment's clothing basis from its example fits (E, N, 3) (and those of its
        strain channel (E, N), and the fits they were draped from (E, N, 3), for drapes) built and
        stored; the record with its counts, ETag, girths (``fit``) and how its fits were made."""
        meta = {"name": record.name, "owner": record.owner, "source": record.source, "color": record.color,
                "layer": record.layer, "created": record.created, "id": record.id, "body_model": self.model.version}
        basis = build_garment_basis(self.model, fits, faces, self.examples.set, meta=meta, layout=layout,
                                    material=material, rest=rest, strain_fits=strain_fits, start_fits=start_fits)
        fit = SZ.sized_garment_fit(self.model, np.asarray(fits[0])[None], faces, self.examples.vertices[0],
                                   record.size_labels(), 0, self.examples.vertices[0], record.fabric)
        self.bases.save(record.id, basis)
        return record.model_copy(update={"n_vertices": int(basis.meta["n_vertices"]),
                                         "n_faces": int(basis.meta["n_faces"]),
                                         "n_components": int(basis.meta["n_components"]), "etag": basis.etag(),
                                         "fit": fit.to_meta(),
                                         "example_fits": example_fits or ("drape" if drape else "warp")})

    def _publish_built(self, record: Garment) -> None:
        """List a garment whose bases are stored (its files removed if that fails)."""
        try:
            self.repo.publish(record)
        except BaseException:
            self.bases.delete(record.id)
            raise

    def _queue_build(self, record: Garment, upload: bytes) -> Garment:
        """List a garment with ``status: building`` and its upload, and queue its build job
        (:meth:`run_build`); the record as the API shows it (job queued, progress 0)."""
        job_id = build_job_id(record.id)
        record = record.model_copy(update={"status": "building", "job": JobRef(id=job_id, url=f"/v1/jobs/{job_id}")})
        self.repo.publish(record, upload)
        try:
            self.queue.enqueue(BUILD_JOB, record.id, job_id=job_id, kind="garment",
                               timeout=build_timeout(self.settings, len(record.sizes or ())),
                               body_model=self.model.version,
                               description=f"fit garment {record.id} to the example avatars",
                               meta={"garment_id": record.id, "owner": record.owner})
        except BaseException:
            self.repo.delete(record.id)
            raise
        self.limits.track_job(job_id)
        return record.model_copy(update={"job": record.job.model_copy(update={"status": "queued"}),  # type: ignore[union-attr]
                                         "progress": 0.0})

    def create_draped(self, garment: bytes, garment_name: str | None, *, on: str | None, avatar: bytes | None,
                      avatar_name: str | None, name: str, owner: str, color: str | None, layer: int,
                      texture: tuple[bytes, str | None] | None = None, chart: Chart | None = None,
                      graded: list[tuple[bytes, str | None]] | None = None,
                      garment_sizes: list[str] | None = None, gender: str | None = None) -> Garment:
        """:meth:`_create_draped` for a requester under its cap of queued jobs, within the
        process's memory budget for decoding uploads (both checked before anything is parsed)."""
        self.limits.check_jobs()
        need = upload_memory(garment, garment_name) + (upload_memory(avatar, avatar_name) if avatar else 0) \
            + (upload_memory(*texture) if texture else 0) + sum(upload_memory(d, n) for d, n in graded or [])
        with self.limits.memory(need):
            return self._create_draped(garment, garment_name, on=on, avatar=avatar, avatar_name=avatar_name,
                                       name=name, owner=owner, color=color, layer=layer, texture=texture,
                                       chart=chart, graded=graded, garment_sizes=garment_sizes, gender=gender)

    def _create_draped(self, garment: bytes, garment_name: str | None, *, on: str | None, avatar: bytes | None,
                       avatar_name: str | None, name: str, owner: str, color: str | None, layer: int,
                       texture: tuple[bytes, str | None] | None = None, chart: Chart | None = None,
                       graded: list[tuple[bytes, str | None]] | None = None,
                       garment_sizes: list[str] | None = None, gender: str | None = None) -> Garment:
        """One garment draped on one body (an example avatar ``on``, default ``mean``, or the
        retailer's own ``avatar`` of any topology): checked now (422 before any job), then
        carried to every example avatar by a queued build job (:meth:`run_build`). The garment
        is listed at once with ``status: building``; its basis appears when complete.

        Sizes: with a size ``chart`` the garment is the base size, graded by the job to every
        size; or ``graded`` further files (the retailer's graded meshes, same vertices and faces)
        with ``garment_sizes`` the labels of all files (``garment`` first) in the chart."""
        name = clean_name(name)
        files = [(garment, garment_name), *(graded or [])]
        order = _graded_order(files, garment_sizes, chart)
        if order is not None:  # the base size's file places the garment; the others follow it
            assert chart is not None
            garment, garment_name = files[order[chart.base]]
        rgba = parse_color(color, scenes.DEFAULT_GARMENT_COLOR)
        if on is not None and avatar is not None:
            raise Invalid(("body", "on"), "send either 'on' (an example avatar id) or a file 'avatar', not both")
        tex = read_texture(*texture) if texture is not None else None
        v, faces = read_garment_mesh(garment, garment_name, ("body", "garment"), "garment")
        n_file = len(v)
        faces, layout = _file_layout(garment_name or "garment", garment, faces)
        if layout is None and len(garment) >= 4 and garment[:4] == b"glTF":  # GLB: uv + embedded texture
            look = glb_look(garment, faces)
            if look is not None and len(look[0].vertex) == len(v):
                layout, embedded = look
                tex = tex or embedded
        file_faces = faces
        v, faces, layout, first = one_cloth(v, faces, layout)
        if avatar is None:
            on = on or "mean"
            i = self.examples.index(on)
            if i is None:
                raise Invalid(("body", "on"), f"unknown example avatar '{on}' (see /v1/example-avatars)")
            placed, unit, up = place_on_body(v, self.examples.tree(i), ("body", "garment"))
            upload = DrapedGarment(placed, faces, on=on, unit=unit, up=up)
        else:
            scan, unit = read_draped_avatar(avatar, avatar_name, v)
            upload = DrapedGarment(v, faces, on=None, unit=unit, up=None, avatar=scan)
        upload.layout, upload.texture = layout, tex
        if order is not None:
            upload.graded = self._read_graded(files, order, upload, file_faces, first, n_file)
        record = Garment(id=new_id(), body_model=self.model.version, owner=owner, name=name, source="draped",
                         **(chart.record_fields() if chart is not None and chart.sizes
                            else {"fabric": chart.fabric if chart is not None else SZ.DEFAULT_FABRIC}),
                         color=[float(c) for c in rgba], layer=int(layer), unit=unit,
                         textured=is_textured(_upload_material(tex, rgba, color, layout), layout),
                         gender=gender,
                         up=upload.up, on=upload.on, n_vertices=int(len(v)), n_faces=int(len(faces)))
        return self._queue_build(record, upload.to_bytes())

    def _read_graded(self, files: list[tuple[bytes, str | None]], order: list[int], upload: DrapedGarment,
                     faces: np.ndarray, first: np.ndarray, n_file: int) -> np.ndarray:
        """(S, M, 3) every size's mesh in chart order, in the base file's frame as placed (its
        unit and up axis), one cloth as the base file's (``first`` (M,): the base file's vertex
        of each cloth vertex, :func:`one_cloth`; ``faces`` (F, 3) and ``n_file`` the base file's
        faces and vertex count): 422 when a file is not the same garment (vertices and faces)."""
        out = []
        scale = UNITS[upload.unit] if upload.on is not None else 1.0
        R = GARMENT_UPS[upload.up] if upload.up is not None else np.eye(3)
        for k in order:
            data, fname = files[k]
            loc, label = ("body", "garment", k), f"garment file {k + 1} '{fname or 'garment'}'"
            v, f = read_garment_mesh(data, fname, loc, label)
            if len(v) != n_file or f.shape != faces.shape or not np.array_equal(f, faces):
                raise Invalid(loc, f"{label}: not the same mesh as the base size's file ({len(v)} vertices, "
                                   f"{len(f)} faces; the base size has {n_file} and {len(faces)}): graded "
                                   "meshes must share vertices and faces, in the same order")
            out.append((v[first] * scale) @ R.T)
        return np.stack(out)

    def run_build(self, gid: str, progress: Progress) -> dict[str, Any]:
        """The build job of a draped garment: (fit the retailer's avatar, unclothed, when one was
        given), carry the garment to every example avatar (``autofit.fit_to_examples``: the
        warping graph, collisions, edge lengths), build and store the basis, then mark the
        garment ready -- only if it still exists (a delete during the build wins; its files are
        removed). Idempotent: a ready or failed garment returns its outcome; a deterministic
        failure (the avatar cannot be fitted, a degenerate garment) fails the garment with the
        reason and is not retried; anything else raises (the queue retries)."""
        record = self.repo.get(gid)
        if record is None:
            self.bases.delete(gid)
            return {"status": "deleted", "garment_id": gid}
        if record.status in ("ready", "failed"):
            return _build_outcome(record)
        raw = self.repo.get_upload(gid)
        if raw is None:
            return self._fail_build(record, "the uploaded garment expired before it was built; upload it again", progress)
        progress = MonotoneProgress(progress)
        if record.source == "mhclo":
            return self._run_mhclo_build(record, MhcloUpload.from_bytes(raw), progress)
        upload = DrapedGarment.from_bytes(raw)
        share = BUILD_SHARES
        garment, faces = upload.vertices, upload.faces
        if upload.avatar is not None:
            progress(0.01, "fitting the avatar the garment was draped on")
            scan = upload.avatar
            try:
                fit = fit_body(self.model, scan.points, scan.normals, scan.faces, clothed=False,
                               progress=progress.scaled(0.01, share["avatar_fit"] - 0.01, "avatar: "))
            except FitError as exc:
                return self._fail_build(record, f"the avatar could not be fitted: {exc}", progress)
            T = np.asarray(fit.to_model, np.float64)
            garment = garment @ T[:3, :3].T + T[:3, 3]
            source = np.asarray(fit.posed_vertices, np.float64)
            start = share["avatar_fit"]
        else:
            i = self.examples.index(upload.on or "mean")
            if i is None:  # the example set changed since the upload
                return self._fail_build(record, f"the example avatar '{upload.on}' no longer exists; upload it again",
                                        progress)
            source = self.examples.vertices[i]
            start = 0.0
        span = share["autofit"] + (share["avatar_fit"] - start)
        if record.sizes and len(record.sizes) > 1:
            return self._run_sized_build(record, upload, garment, faces, source,
                                         T if upload.avatar is not None else None, progress, start)
        progress(start, "carrying the garment to the example avatars")
        try:
            result = fit_to_examples(self.model, garment, faces, source_body=source,
                                     progress=progress.scaled(start, span))
        except ValueError as exc:
            return self._fail_build(record, f"the garment could not be fitted: {exc}", progress)
        fits, strains, starts = result.fits, None, None
        if self.settings.drape:
            # its size: the garment as uploaded on the body it was draped on (in the model's frame)
            progress(1.0 - share["basis"], "draping the garment on the example avatars")
            try:
                d = self.drape_to_examples(garment, faces, fits, record.fabric,
                                           progress.scaled(1.0 - share["basis"], 0.8 * share["basis"], "draping: "),
                                           record.gender)
                fits, strains, starts = d.fits, d.strain_fits, fits
            except DrapeError as exc:
                return self._fail_build(record, f"the garment could not be draped: {exc}", progress)
        progress(1.0 - share["basis"], "building the clothing basis")
        rgba = tuple(record.color) if record.color else scenes.DEFAULT_GARMENT_COLOR
        material = _upload_material(upload.texture, rgba, None, upload.layout)
        built = self._store_one_size(record, fits, faces, upload.layout, material, rest=garment,
                                     drape=self.settings.drape, strain_fits=strains, start_fits=starts)
        return self._complete_build(built, progress)

    def _run_mhclo_build(self, record: Garment, upload: MhcloUpload, progress: MonotoneProgress) -> dict[str, Any]:
        """The build job of a MakeHuman garment uploaded with the drape on: its files read again,
        draped on every example avatar at its own size (in its sizes), bases stored, the garment
        marked ready (as :meth:`run_build`)."""
        progress(0.01, "reading the MakeHuman garment")
        try:
            binding, faces, layout = read_mhclo_layout(self.model, upload.mhclo, upload.obj)
            tex = read_texture(*upload.texture) if upload.texture is not None else None
            rgba = tuple(record.color) if record.color else scenes.DEFAULT_GARMENT_COLOR
            material = _upload_material(tex, rgba, upload.color, layout)
            built = self._from_binding(record, binding, faces, layout, material, drape=self.settings.drape,
                                       progress=progress.scaled(0.02, 0.98))
        except (Invalid, DrapeError) as exc:
            self.bases.delete(record.id)
            return self._fail_build(record, f"the garment could not be draped: {exc}", progress)
        return self._complete_build(built, progress)

    def _complete_build(self, built: Garment, progress: Progress) -> dict[str, Any]:
        """A build job's garment, its bases stored, marked ready -- only if it still exists (a
        delete during the build wins: its files are removed)."""
        ready = built.model_copy(update={"status": "ready", "error": None, "progress": None})
        if not self.repo.complete(ready):
            self.bases.delete(ready.id)
            log.info("garment %s was deleted during its build: result dropped", ready.id)
            return {"status": "deleted", "garment_id": ready.id}
        progress(1.0, "done")
        log.info("garment %s built (%s)", ready.id, ready.source)
        return _build_outcome(ready)

    def _run_sized_build(self, record: Garment, upload: DrapedGarment, garment: np.ndarray, faces: np.ndarray,
                         source: np.ndarray, T: np.ndarray | None, progress: MonotoneProgress,
                         start: float) -> dict[str, Any]:
        """The build of a garment in sizes: graded by the service (one mesh) or by the retailer
        (``upload.graded``, all on the same body), each size fitted to every example avatar,
        the bases stored, the garment marked ready (as :meth:`run_build`)."""
        chart = Chart([s.chart_entry() for s in record.sizes or []], record.base_size or "", record.fabric)
        progress(start, f"grading {len(chart.sizes)} sizes")
        try:
            bodies = sizing.chart_bodies(self.model, chart, record.gender)
            if upload.graded is not None:
                rests = np.asarray(upload.graded, np.float64)
                if T is not None:
                    rests = rests @ T[:3, :3].T + T[:3, 3]
                on = np.broadcast_to(np.asarray(source, np.float64), (len(rests), *np.shape(source)))
            else:
                rests = SZ.grade(self.model, garment, faces, source, bodies, chart.base)
                on = SZ.size_bodies_on(source, bodies, chart.base)
            rgba = tuple(record.color) if record.color else scenes.DEFAULT_GARMENT_COLOR
            material = _upload_material(upload.texture, rgba, None, upload.layout)
            built = self._store_sizes(record, rests, faces, on, bodies[chart.base], chart, upload.layout, material,
                                      progress.scaled(start + 0.05, 0.95 - start), drape=self.settings.drape)
        except (ValueError, Invalid, DrapeError) as exc:
            self.bases.delete(record.id)
            return self._fail_build(record, f"the garment could not be graded or fitted: {exc}", progress)
        return self._complete_build(built, progress)

    def _fail_build(self, record: Garment, message: str, progress: Progress) -> dict[str, Any]:
        failed = record.model_copy(update={"status": "failed", "error": message, "progress": None})
        if not self.repo.complete(failed):
            return {"status": "deleted", "garment_id": record.id}
        progress(1.0, "failed")
        log.info("garment %s cannot be built: %s", record.id, message)
        return _build_outcome(failed)

    # -- deleting ----------------------------------------------------------------------------
    def delete(self, gid: str, retailer: str) -> None:
        """Delete one of the retailer's garments: its record, basis files, waiting upload, build
        job (a running build is stopped) and every customer's exact drape of it."""
        record = self.repo.get(gid)
        if record is None:
            raise NotFound(f"garment '{gid}' not found")
        if record.owner != retailer:
            raise Forbidden(f"garment '{gid}' belongs to another retailer")
        self.repo.delete(gid)
        if record.job is not None:
            self.queue.cancel(record.job.id)
        self.bases.delete(gid)
        self.drapes.delete_garment(gid)


def _graded_order(files: list[tuple[bytes, str | None]], garment_sizes: list[str] | None,
                  chart: Chart | None) -> list[int] | None:
    """For graded meshes: the index of each size's file, in chart order; None for one file.
    422 when the labels do not match the files or the chart."""
    if garment_sizes is None:
        if len(files) > 1:
            raise Invalid(("body", "garment_sizes"), f"{len(files)} files 'garment': graded meshes need "
                                                     "'garment_sizes', their size labels in the same order")
        return None
    if chart is None or not chart.sizes:
        raise Invalid(("body", "size_chart"), "'garment_sizes' needs a 'size_chart' giving those sizes")
    if len(garment_sizes) != len(files):
        raise Invalid(("body", "garment_sizes"), f"{len(garment_sizes)} labels in 'garment_sizes' for {len(files)} "
                                                 "files 'garment': one label per file, in the same order")
    if len(set(garment_sizes)) != len(garment_sizes) or set(garment_sizes) != set(chart.labels):
        raise Invalid(("body", "garment_sizes"), f"'garment_sizes' {garment_sizes} must name each size of the "
                                                 f"chart once ({', '.join(chart.labels)})")
    return [garment_sizes.index(lb) for lb in chart.labels]


def _file_layout(filename: str, data: bytes, faces: np.ndarray) -> tuple[np.ndarray, RenderLayout | None]:
    """(faces, render layout) of an uploaded OBJ garment with texture coordinates (the same
    triangles, in the OBJ's order); (faces, None) otherwise."""
    try:
        kind = scan_type(data, filename)
    except ValueError:
        return faces, None
    found = obj_layout(data, faces) if kind == "obj" else None
    return (faces, None) if found is None else found


def _upload_material(texture: Texture | None, rgba: tuple[float, ...], color: str | None,
                     layout: RenderLayout | None) -> Material | None:
    """A retailer's garment look: its texture (when the mesh has texture coordinates) times the
    colour (white when a texture came without a colour); None without a texture (the record's
    colour is used)."""
    if texture is None:
        return None
    if layout is None:
        raise Invalid(("body", "texture"), "a texture needs texture coordinates: the OBJ has no 'vt' on every face "
                                           "corner (export the garment with UVs)")
    factor = tuple(float(c) for c in rgba) if color else (1.0, 1.0, 1.0, 1.0)
    return Material(factor, texture, None, "OPAQUE", None, True, UPLOAD_METALLIC, UPLOAD_ROUGHNESS)  # type: ignore[arg-type]


def _build_outcome(record: Garment) -> dict[str, Any]:
    if record.status == "failed":
        return {"status": "failed", "garment_id": record.id, "error": record.error}
    return {"status": "done", "garment_id": record.id}

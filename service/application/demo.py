"""The demo catalogue: the compiled MakeHuman garments (``service.model.garments.catalogue``)
built at the first start through the path a retailer's ``.mhclo`` upload takes, in the sizes
of their EN 13402-3 charts (``service.model.garments.demo_sizes``) or one size.

A mixin of :class:`~service.application.garments.GarmentService` (it builds with the
service's own upload path)."""
from __future__ import annotations

import logging
import time
from typing import Any

import numpy as np

from service.model.body.measurements import measure_attributes
from service.model.garments import sizing as SZ
from service.model.garments.catalogue import CatalogueItem, load_catalogue
from service.model.garments.demo_sizes import demo_chart
from service.model.garments.tryon import GarmentBasis
from service.model.drape import DrapeError
from service.records import Garment
from service.storage.records import new_id

from . import scenes
from .sizes import Chart
from .uploads import is_textured, parse_color

log = logging.getLogger("tryon.garments")

DEMO_OWNER = "demo"
# the lock's time: the first build of the whole catalogue in sizes on a loaded machine, with room
DEMO_LOCK_S = 600
# the demo catalogue's cloth, by catalogue id (jersey tops, elastane sportswear; the rest woven)
DEMO_FABRICS = {"womens-tshirt": "knit", "cropped-tee": "knit", "mens-tshirt": "knit", "longsleeve-tee": "knit",
                "white-tshirt": "knit", "sports-trousers": "stretch"}
GENDERS = ("female", "male")
# demo items that are not cloth (a felt hat, leather shoes): not draped, they keep their binding's basis (the cloth
# drape would let a hat's crown and brim fall onto the head like a knitted cap)
NOT_CLOTH = ("shoes", "hat")
# the lock's time: one demo garment draped in its 5 sizes on every example avatar (~13 min for a
# 1,700-vertex garment on 2 cores, the ~7,500-vertex suit about an hour), with room
DEMO_DRAPE_LOCK_S = 4 * 3600


class DemoCatalogue:
    """The demo catalogue's part of the garment service (a mixin of ``GarmentService``: it uses
    its settings, model, repo, bases, drapes, examples and its ``.mhclo`` build path)."""

    def demo_items(self) -> list[CatalogueItem]:
        """The catalogue garments served as the demo catalogue (``TRYON_DEMO_ITEMS``: 'all',
        or comma-separated catalogue ids; '' none), in catalogue order."""
        items = load_catalogue().garments()
        want = self.settings.demo_items.strip()
        if want == "all":
            return items
        ids = [w.strip() for w in want.split(",") if w.strip()]
        unknown = sorted(set(ids) - {it.id for it in items})
        if unknown:
            raise ValueError(f"TRYON_DEMO_ITEMS: unknown catalogue items {unknown}")
        return [it for it in items if it.id in ids]

    def demo_chart(self, item: CatalogueItem, body_cm: dict[str, dict[str, float]] | None = None
                   ) -> Chart | None:
        """The size chart a demo garment is built in (``demo_sizes.demo_chart``: EN 13402-3
        letter sizes XS-XL), its base size the one nearest the body the garment is bound to
        (the mean example avatar, measured for the garment's gender), its fabric
        (``DEMO_FABRICS``); None for one-size items or with ``TRYON_DEMO_SIZES`` off.
        ``body_cm``: gender -> the mean avatar's measurements, filled on first use."""
        found = demo_chart(item.category, item.gender) if self.settings.demo_sizes else None
        if found is None:
            return None
        table = found[1]
        gender = "female" if item.gender == "female" else "male"
        cache = {} if body_cm is None else body_cm
        if gender not in cache:
            X = self.examples.vertices[self.examples.index("mean") or 0]
            cache[gender] = {k: float(v) for k, v in measure_attributes(self.model.measurement_spec, X, gender).items()
                             if k in SZ.CHART_MEASUREMENTS}
        sizes, base = SZ.validate_chart(table, SZ.nearest_size(table, cache[gender]))
        return Chart(sizes, base, DEMO_FABRICS.get(item.id, SZ.DEFAULT_FABRIC))

    def _current_demo(self, old: Garment | None, chart: Chart | None) -> GarmentBasis | None:
        """The stored basis of a demo garment that needs no rebuild: built for this body model
        in the sizes the catalogue defines now (``chart``; None: one size); else None."""
        if old is None or not old.is_current(self.model.version):
            return None
        sized = bool(old.sizes) and len(old.sizes) > 1
        if chart is None:
            return None if sized else self.bases.load(old.id, old.etag)
        have = [s.chart_entry() for s in old.sizes or []]
        if not sized or have != chart.sizes or old.base_size != chart.base_size or old.fabric != chart.fabric:
            return None
        return self.bases.load(old.id, old.etag, old.base_index())

    def ensure_demo(self) -> list[str]:
        """Build and store the demo catalogue where missing, built for another body model or
        in other sizes than the catalogue defines now, through the path a retailer's ``.mhclo``
        upload takes: in the sizes of its chart (:meth:`demo_chart`: graded, one basis per
        size, girths per size) or one size (fitted to every example avatar by its binding,
        checked, basis built); keyed by catalogue item id, with its UVs, material, category,
        gender and layer (idempotent; one process builds, the others wait on the Redis lock).
        Returns their ids."""
        ids: list[str] = []
        with self.repo.lock("demo-garments", ttl=DEMO_LOCK_S, wait=DEMO_LOCK_S) as held:
            if not held:
                log.warning("demo garments: lock not obtained; not building them")
            t_all = time.perf_counter()
            body_cm: dict[str, dict[str, float]] = {}
            for item in self.demo_items():
                gid = self.repo.demo_id(item.id)
                old = self.repo.get(gid) if gid else None
                chart = self.demo_chart(item, body_cm)
                basis = self._current_demo(old, chart)
                if basis is not None and old is not None:
                    if held and chart is None:
                        self._current_skinning(old, basis)
                    ids.append(old.id)
                    continue
                if not held:
                    continue
                t0 = time.perf_counter()
                rec = self._build_demo(item, chart)
                self.repo.set_demo_id(item.id, rec.id)
                if old is not None:  # built for another body model or in other sizes: replaced
                    self.repo.delete(old.id)
                    self.bases.delete(old.id)
                    self.drapes.delete_garment(old.id)
                ids.append(rec.id)
                log.info("demo garment %s built (%s, %s) in %.2fs", item.id, rec.id,
                         f"{len(chart.sizes)} sizes, base {chart.base_size}" if chart else "one size",
                         time.perf_counter() - t0)
            log.info("demo catalogue: %d garments ready in %.2fs", len(ids), time.perf_counter() - t_all)
        return ids

    def _build_demo(self, item: CatalogueItem, chart: Chart | None) -> Garment:
        """One demo garment built through its binding (seconds; draped later in the background
        where the drape is on: :meth:`drape_demo`) and published: graded to ``chart`` (as an
        ``.mhclo`` upload with a size chart) or one size (as one without)."""
        record = self._demo_record(item, chart)
        built = self._from_binding(record, item.binding, item.faces.astype(np.int32), item.render_layout(),
                                   item.material, drape=False)
        self._publish_built(built)
        return built

    def _demo_record(self, item: CatalogueItem, chart: Chart | None) -> Garment:
        fields: dict[str, Any] = chart.record_fields() if chart is not None else {
            "fabric": DEMO_FABRICS.get(item.id, SZ.DEFAULT_FABRIC)}
        color = parse_color(item.color, scenes.DEFAULT_GARMENT_COLOR)
        material, layout = item.material, item.render_layout()
        return Garment(id=new_id(), body_model=self.model.version, name=item.name, owner=DEMO_OWNER, source="demo",
                       color=[float(c) for c in color], layer=int(item.layer or 0), category=item.category,
                       gender=item.gender, catalogue_id=item.id, swatch=item.color,
                       textured=is_textured(material, layout),
                       **fields)

    def demo_to_drape(self) -> list[tuple[CatalogueItem, Garment]]:
        """The demo garments (catalogue item, record) not yet built through the drape: tops and
        bottoms first (a useful catalogue for both genders soonest), the smallest meshes first;
        not the items that are not cloth (``NOT_CLOTH``: shoes, hats)."""
        out = []
        for item in self.demo_items():
            if item.category in NOT_CLOTH:
                continue
            gid = self.repo.demo_id(item.id)
            rec = self.repo.get(gid) if gid else None
            if rec is not None and rec.example_fits != "drape" and rec.is_current(self.model.version):
                out.append((item, rec))
        return sorted(out, key=lambda ir: (ir[0].category not in ("top", "bottom"), ir[1].n_vertices))

    def drape_demo(self) -> list[str]:
        """The demo garments built through their binding (:meth:`ensure_demo`) re-built through
        the cloth drape, one after the other (:meth:`demo_to_drape`'s order), each size's rest shape settled
        on every example avatar (``TRYON_DRAPE``'s build): their bases replaced in place and
        their records marked ``example_fits: "drape"``. Run by ``tryon drape-demo`` in a
        background process after the first start; each garment under a Redis lock (one process
        drapes it; a garment already draped, or being draped elsewhere, is skipped). A garment
        that cannot be draped keeps its binding's basis (logged). Returns the ids draped."""
        done: list[str] = []
        for item, rec in self.demo_to_drape():
            with self.repo.lock(f"demo-drape:{item.id}", ttl=DEMO_DRAPE_LOCK_S, wait=0) as held:
                rec = self.repo.get(rec.id) if held else None  # again, under the lock
                if rec is None or rec.example_fits == "drape":
                    continue
                t0 = time.perf_counter()
                try:
                    built = self._from_binding(rec, item.binding, item.faces.astype(np.int32), item.render_layout(),
                                               item.material, drape=True)
                except (ValueError, DrapeError) as exc:
                    log.warning("demo garment %s could not be draped (it keeps its binding's basis): %s", item.id, exc)
                    continue
                if not self.repo.replace_if_exists(built):  # replaced by a rebuild meanwhile
                    continue
                done.append(rec.id)
                log.info("demo garment %s draped (%s) in %.1fs", item.id, rec.id, time.perf_counter() - t0)
        return done

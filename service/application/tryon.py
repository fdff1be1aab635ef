"""Try-on: a garment, or an outfit, fitted to a customer, as GLB. When warm, one Redis round
trip (the customer and the garments together), then in-process caches: the customer's body
(per weights) and the garments' memory-mapped bases (per etag)."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

from service.model.body.model import BodyModel
from service.model.garments import sizing as SZ
from service.model.garments.tryon import GarmentBasis
from service.records import Customer, Garment, JobRef
from service.storage.records import CustomerRepo, GarmentRepo, fetch

from . import look as looks
from . import poses as _poses
from . import scenes
from . import sizes as sizing
from .auth import Credentials
from .customers import CustomerService
from .errors import Invalid
from .garments import GarmentService

MAX_OUTFIT_GARMENTS = 12
# CPU budget of one outfit request (measured on one core, issue 42: 12 garments with pose
# targets cost 11-14 s): layering one garment over the others, and one pose target of one
# garment (doc of pose_correctives: 40-160 ms per garment and pose; the upper end here).
LAYER_CPU_S = 0.3
POSE_TARGET_CPU_S = 0.16
PAGE_POSES = 4  # the page's pose presets (web_client/poses.json)
MAX_REQUEST_CPU_S = 6.0


def outfit_cpu_s(n_garments: int, pose_correctives: bool) -> float:
    """Estimated CPU seconds of an outfit of ``n_garments`` not cached yet."""
    return n_garments * (LAYER_CPU_S + (PAGE_POSES * POSE_TARGET_CPU_S if pose_correctives else 0.0))


class TryOnService:
    def __init__(self, model: BodyModel, customers_repo: CustomerRepo, garments_repo: GarmentRepo,
                 customers: CustomerService, garments: GarmentService, poses: _poses.Poses):
        self.model = model
        self.customers_repo = customers_repo
        self.garments_repo = garments_repo
        self.customers = customers
        self.garments = garments
        self.poses = poses

    def load(self, cid: str, gids: list[str], creds: Credentials, sizes: list[str | None] | None = None,
              query: str = "size", refuse: str | None = None):
        """The customer and each garment with the basis of its size: ``sizes[i]`` (a label of
        garment i's chart; 422 listing them when unknown) or, where None, the size recommended
        for this customer (:meth:`fit_report`)."""
        customer, garments = fetch(self.customers_repo, cid, self.garments_repo, gids)
        record = self.customers.require_ready(self.customers.open(customer, cid, creds), cid)
        sizes = list(sizes or [])
        loaded = []
        for i, (g, gid) in enumerate(zip(garments, gids)):
            want = sizes[i] if i < len(sizes) else None
            g, basis = self.garments.require_ready(g, gid)
            labels = g.size_labels()
            if len(labels) > 1:
                if want is None:
                    idx = self._report(record, g, basis).recommended
                else:
                    try:
                        idx = SZ.size_index(labels, want, 0)
                    except SZ.ChartError as exc:
                        raise Invalid(("query", query),
                                      f"garment '{gid}': {exc.message}") from exc
                if idx != g.base_index():
                    g, basis = self.garments.require_ready(g, gid, idx)
            elif want is not None and want not in labels:
                raise Invalid(("query", query),
                              f"garment '{gid}': unknown size '{want}'; this garment's sizes: {', '.join(labels)}")
            loaded.append((g, basis))
        if refuse is not None:
            raise Invalid(("query", query), refuse)
        return record, loaded

    def _report(self, record, garment: Garment, basis: GarmentBasis) -> SZ.FitReport:
        """Every size of ``garment`` on the customer ``record``'s body."""
        body = self.customers.body(record)
        return SZ.fit_report(self.garments.size_fit(garment, basis), sizing.customer_girths(self.model, body))

    def fit_report(self, cid: str, gid: str, creds: Credentials) -> dict:
        """How each size of a garment fits the customer: ``{recommended, sizes: [{label,
        verdict, regions: [{region, ease_cm, strain_pct, verdict}]}]}`` in chart order
        (``sizing.fit_report``)."""
        customer, garments = fetch(self.customers_repo, cid, self.garments_repo, [gid])
        record = self.customers.require_ready(self.customers.open(customer, cid, creds), cid)
        g, basis = self.garments.require_ready(garments[0], gid)
        out = self._report(record, g, basis).to_dict()
        return {"garment_id": gid, "fabric": g.fabric, "base_size": g.base_size or g.size_labels()[0], **out}

    def _etag(self, kind: str, record, loaded: list[tuple[Garment, GarmentBasis]], compression: str | None) -> str:
        return scenes.etag(kind, self.model.version, record.weights, compression,
                           [(g.id, basis.etag() or g.etag) for g, basis in loaded])

    def page_poses(self, record, on: bool):
        """The page's poses adapted to the customer (cached per body), when ``on``: a function
        that gets them, for ``scenes.outfit_glb`` to call once the outfit is layered. The page
        asks for ``/poses`` together with its first outfit: when the two requests reach
        different server processes, one adapts the poses while the other layers the outfit,
        then waits for them (``Poses.record_poses``' lock) instead of adapting them first."""
        return (lambda: _poses.pose_arrays(self.poses.record_poses(record))) if on else None

    def garment_glb(self, cid: str, gid: str, creds: Credentials, compression: str | None,
                    if_none_match: list[str] | None = None, pose_correctives: bool = False,
                    size: str | None = None, fitmap: str | None = None) -> tuple[bytes | None, str]:
        """The garment fitted to the customer, skinned with the customer's skeleton, and its
        ETag (customer weights, garment etag, options); ``None`` bytes when ``if_none_match``
        matches (not modified: nothing is computed)."""
        record, loaded = self.load(cid, [gid], creds, [size])
        tag = self._etag("garment" + ("|poses" if pose_correctives else "") + (f"|fitmap:{fitmap}" if fitmap else ""),
                         record, loaded, compression)
        if scenes.etag_matches(tag, if_none_match):
            return None, tag
        body = self.customers.body(record)
        return scenes.outfit_glb(self.model, body, loaded, compression, with_avatar=False,
                                 poses=self.page_poses(record, pose_correctives), fitmap=fitmap), tag

    def outfit_glb(self, cid: str, gids: list[str], creds: Credentials, compression: str | None,
                   if_none_match: list[str] | None = None, hair: str | None = None,
                   underwear: bool = True, pose_correctives: bool = False,
                   sizes: list[str] | None = None, fitmap: str | None = None,
                   worn: Callable[[Customer, list[tuple[Garment, GarmentBasis]]], Any] | None = None
                   ) -> tuple[bytes | None, str] | JobRef:
        """The customer's avatar wearing its look (``hair``, ``underwear``: see
        ``CustomerService.avatar_glb``) and the garments (one scene, one skeleton), layered:
        inner garments (lower layer) first, each outer one pushed over the ones below; and its
        ETag. ``pose_correctives``: each garment with one morph target per page pose.
        ``worn(record, layered)``: the garments' vertices from elsewhere (a customer's exact
        drapes: ``ExactDrapes.outfit_worn``) as (list of (M_i, 3) or None for the basis try-on,
        an ETag part), or a job to answer instead (202) while one is being computed."""
        given = [g.strip() for g in gids if g.strip()]
        ids = list(dict.fromkeys(given))
        if len(ids) > MAX_OUTFIT_GARMENTS:
            raise Invalid(("query", "garments"), f"at most {MAX_OUTFIT_GARMENTS} garments per outfit")
        cost = outfit_cpu_s(len(ids), pose_correctives)
        if cost > MAX_REQUEST_CPU_S:
            most = int(MAX_REQUEST_CPU_S // outfit_cpu_s(1, pose_correctives))
            raise Invalid(("query", "garments"), f"{len(ids)} garments with pose_correctives cost about {cost:.0f} s "
                                                 f"of CPU; at most {most} garments per outfit with pose_correctives")
        chosen: list[str | None] = [None] * len(ids)
        refuse = None
        if sizes is not None and ids:  # without garments there is nothing to size
            if len(sizes) != len(given):
                refuse = (f"{len(sizes)} sizes for {len(given)} garments: one size label per garment, in the same "
                          "order (empty: the recommended size)")
            else:
                for gid, sz in zip(given, sizes):
                    chosen[ids.index(gid)] = sz.strip() or None
        record, loaded = self.load(cid, ids, creds, chosen, "sizes", refuse)
        look = looks.resolve(looks.gender_of(record.measurements), hair, underwear)
        order = sorted(range(len(loaded)), key=lambda i: (loaded[i][0].layer, i))
        layered: list[tuple[Garment, GarmentBasis]] = [loaded[i] for i in order]
        vertices, part = None, ""
        if worn is not None:
            got = worn(record, layered)
            if isinstance(got, JobRef):
                return got
            vertices, part = got
        tag = self._etag(f"outfit|{look.key}" + part + ("|poses" if pose_correctives else "")
                         + (f"|fitmap:{fitmap}" if fitmap else ""), record, layered, compression)
        if scenes.etag_matches(tag, if_none_match):
            return None, tag
        return scenes.outfit_glb(self.model, self.customers.body(record), layered, compression,
                                 look=look, poses=self.page_poses(record, pose_correctives), fitmap=fitmap,
                                 worn=vertices), tag

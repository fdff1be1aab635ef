"""Try-on: a garment, or an outfit, fitted to a customer, as GLB. When warm, one Redis round
trip (the customer and the garments together), then in-process caches: the customer's body
(per weights) and the garments' memory-mapped bases (per etag)."""
from __future__ import annotations

from typing import TYPE_CHECKING

from service.model.garments.tryon import GarmentBasis
from service.records import Garment
from service.storage.records import fetch

from . import look as looks
from . import poses as _poses
from . import scenes
from .auth import Credentials
from .errors import Invalid

if TYPE_CHECKING:
    from .context import Context

MAX_OUTFIT_GARMENTS = 12


class TryOnService:
    def __init__(self, ctx: "Context"):
        self.ctx = ctx

    def _load(self, cid: str, gids: list[str], creds: Credentials):
        customer, garments = fetch(self.ctx.customers_repo, cid, self.ctx.garments_repo, gids)
        record = self.ctx.customers.require_ready(self.ctx.customers.open(customer, cid, creds), cid)
        loaded = [self.ctx.garments.require_ready(g, gid) for g, gid in zip(garments, gids)]
        return record, loaded

    def _etag(self, kind: str, record, loaded: list[tuple[Garment, GarmentBasis]], compression: str | None) -> str:
        return scenes.etag(kind, self.ctx.model.version, record.weights, compression,
                           [(g.id, basis.etag() or g.etag) for g, basis in loaded])

    def _page_poses(self, record, on: bool):
        """The page's poses adapted to the customer (cached per body), when ``on``: a function
        that gets them, for ``scenes.outfit_glb`` to call once the outfit is layered. The page
        asks for ``/poses`` together with its first outfit: when the two requests reach
        different server processes, one adapts the poses while the other layers the outfit,
        then waits for them (``poses.record_poses``' lock) instead of adapting them first."""
        return (lambda: _poses.pose_arrays(_poses.record_poses(self.ctx.customers, record))) if on else None

    def garment_glb(self, cid: str, gid: str, creds: Credentials, compression: str | None,
                    if_none_match: list[str] | None = None, pose_correctives: bool = False) -> tuple[bytes | None, str]:
        """The garment fitted to the customer, skinned with the customer's skeleton, and its
        ETag (customer weights, garment etag, options); ``None`` bytes when ``if_none_match``
        matches (not modified: nothing is computed)."""
        record, loaded = self._load(cid, [gid], creds)
        tag = self._etag("garment" + ("|poses" if pose_correctives else ""), record, loaded, compression)
        if scenes.etag_matches(tag, if_none_match):
            return None, tag
        body = self.ctx.customers.body(record)
        return scenes.outfit_glb(self.ctx.model, body, loaded, compression, with_avatar=False,
                                 poses=self._page_poses(record, pose_correctives)), tag

    def outfit_glb(self, cid: str, gids: list[str], creds: Credentials, compression: str | None,
                   if_none_match: list[str] | None = None, hair: str | None = None,
                   underwear: bool = True, pose_correctives: bool = False) -> tuple[bytes | None, str]:
        """The customer's avatar wearing its look (``hair``, ``underwear``: see
        ``CustomerService.avatar_glb``) and the garments (one scene, one skeleton), layered:
        inner garments (lower layer) first, each outer one pushed over the ones below; and its
        ETag. ``pose_correctives``: each garment with one morph target per page pose."""
        ids = list(dict.fromkeys(g.strip() for g in gids if g.strip()))
        if len(ids) > MAX_OUTFIT_GARMENTS:
            raise Invalid(("query", "garments"), f"at most {MAX_OUTFIT_GARMENTS} garments per outfit")
        record, loaded = self._load(cid, ids, creds)
        look = looks.resolve(looks.gender_of(record.measurements), hair, underwear)
        order = sorted(range(len(loaded)), key=lambda i: (loaded[i][0].layer, i))
        layered: list[tuple[Garment, GarmentBasis]] = [loaded[i] for i in order]
        tag = self._etag(f"outfit|{look.key}" + ("|poses" if pose_correctives else ""), record, layered, compression)
        if scenes.etag_matches(tag, if_none_match):
            return None, tag
        return scenes.outfit_glb(self.ctx.model, self.ctx.customers.body(record), layered, compression,
                                 look=look, poses=self._page_poses(record, pose_correctives)), tag

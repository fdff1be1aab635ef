"""Try-on: a garment or an outfit fitted to a customer."""
from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response

from service.api import responses as R
from service.api.deps import (Compression, CredentialsDep, Expensive, Hair, IfNoneMatchDep, PoseCorrectives, TryOnDep,
                              Underwear)

router = APIRouter(tags=["try-on"])


@router.get("/v1/customers/{cid}/garments/{gid}.glb", response_class=Response, dependencies=[Expensive],
            responses=R.CUSTOMER_SCENE_RESPONSE)
def try_on_glb(cid: str, gid: str, tryon: TryOnDep, creds: CredentialsDep, if_none_match: IfNoneMatchDep,
               compression: Compression = None, pose_correctives: PoseCorrectives = False) -> Response:
    """The garment fitted to the customer, skinned with the customer's skeleton. ``ETag`` from
    (customer weights, garment etag, options); ``If-None-Match`` -> 304 without computing.
    ``pose_correctives=true``: one morph target per page pose (``pose:<name>``) that keeps the
    garment outside the body in that pose (influence 1 in that pose, 0 otherwise)."""
    return R.private_glb(*tryon.garment_glb(cid, gid, creds, compression, if_none_match, pose_correctives))


@router.get("/v1/customers/{cid}/outfit.glb", response_class=Response, dependencies=[Expensive],
            responses=R.CUSTOMER_SCENE_RESPONSE)
def outfit_glb(cid: str, tryon: TryOnDep, creds: CredentialsDep, if_none_match: IfNoneMatchDep,
               garments: Annotated[str, Query(description="Comma-separated garment ids")] = "",
               compression: Compression = None, hair: Hair = None, underwear: Underwear = True,
               pose_correctives: PoseCorrectives = False) -> Response:
    """The customer's avatar wearing the garments (one scene, one skeleton), layered: inner
    garments (lower layer) first, each outer one pushed over the ones below. The avatar as in
    ``avatar.glb`` (nodes ``avatar``, ``eyes``, ``eyebrows``, ``hair``, ``underwear``; the same
    ``hair`` and ``underwear`` choices), then one node per garment. ``ETag`` and
    ``If-None-Match`` as for one garment; ``pose_correctives`` as for one garment (the page
    asks for them: it sets the current pose's target influence), and the ``avatar`` node gets
    ``pose:<name>`` targets too where skin would show through the posed clothes (pulled under
    them). The body under opaque garments is left out of the ``avatar`` mesh (its vertices
    stay)."""
    return R.private_glb(*tryon.outfit_glb(cid, garments.split(","), creds, compression, if_none_match,
                                           hair, underwear, pose_correctives))

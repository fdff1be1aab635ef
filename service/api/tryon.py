"""Try-on: a garment or an outfit fitted to a customer."""
from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from fastapi.responses import JSONResponse

from service.api import responses as R
from service.api.schemas import FitResponse, JobRef
from service.api.deps import (Compression, CredentialsDep, DrapesDep, Expensive, Hair, IfNoneMatchDep, PoseCorrectives,
                              TryOnDep, Underwear)
from service.records import JobRef as JobRefRecord

router = APIRouter(tags=["try-on"])
FitMap = Annotated[Literal["strain", "ease"] | None, Query(description=(
    "Colour the garments by their fit (COLOR_0 on a white material): strain, blue at rest to red at the "
    "fabric's stretch limit (as CLO's strain map); ease, red where the cloth presses the body, green at the "
    "fabric's designed ease, blue where it hangs"))]
Drape = Annotated[Literal["basis", "exact"], Query(description=(
    "basis (default): the garment from its clothing basis, in milliseconds. exact: the garment draped on "
    "this customer's own body by the cloth drape engine (its own size and fabric), computed once by a queued "
    "job: the first request answers 202 with the job (also the Location header; the same job while it is "
    "queued or running), then the draped garment, cached until the customer's body or the garment changes; "
    "409 with the reason when the drape failed"))]
EXACT_DRAPE_RESPONSES = {
    202: {"description": "drape=exact: the customer's drape is being computed: poll the job (`url`, also the "
                         "`Location` header), then ask again", "model": JobRef},
    409: {"description": R.CUSTOMER_GLB_RESPONSE[409]["description"] + "; drape=exact: the customer's drape "
                                                                         "failed (`detail`: why)"},
    429: {"description": "drape=exact: the requester already has its cap of queued jobs", "headers": R.RETRY_AFTER},
}


@router.get("/v1/customers/{cid}/garments/{gid}.glb", response_class=Response, dependencies=[Expensive],
            responses={**R.CUSTOMER_SCENE_RESPONSE, **EXACT_DRAPE_RESPONSES})
def try_on_glb(cid: str, gid: str, tryon: TryOnDep, drapes: DrapesDep, creds: CredentialsDep,
               if_none_match: IfNoneMatchDep, compression: Compression = None,
               pose_correctives: PoseCorrectives = False,
               size: Annotated[str | None, Query(max_length=64, description=(
                   "A size label of the garment's chart (default: the size recommended for this customer, "
                   "see /fit); unknown: 422 listing the garment's sizes"))] = None,
               fitmap: FitMap = None, drape: Drape = "basis") -> Response:
    """The garment fitted to the customer, skinned with the customer's skeleton. ``ETag`` from
    (customer weights, garment etag, options); ``If-None-Match`` -> 304 without computing.
    ``pose_correctives=true``: one morph target per page pose (``pose:<name>``) that keeps the
    garment outside the body in that pose (influence 1 in that pose, 0 otherwise).
    ``drape=exact``: the customer's own drape of the garment (202 with its job until it is
    done; then the same GLB layout with the draped garment, its own ``ETag``)."""
    if drape == "exact":
        out = drapes.garment_glb(cid, gid, creds, compression, if_none_match, pose_correctives, size, fitmap)
        if isinstance(out, JobRefRecord):
            return JSONResponse(out.model_dump(), status_code=202, headers={"Location": out.url})
        return R.private_glb(*out)
    return R.private_glb(*tryon.garment_glb(cid, gid, creds, compression, if_none_match, pose_correctives, size,
                                            fitmap))


OutfitDrape = Annotated[Literal["basis", "exact"], Query(description=(
    "basis (default): the garments from their clothing bases, in milliseconds. exact: each garment draped on "
    "this customer's own body (as `drape=exact` on one garment), then layered: 202 with a job while any "
    "garment's drape is queued or running (each missing drape is queued at the first request; poll the job, "
    "then ask again), then the outfit; a garment whose drape failed is worn from its basis"))]


@router.get("/v1/customers/{cid}/outfit.glb", response_class=Response, dependencies=[Expensive],
            responses={**R.CUSTOMER_SCENE_RESPONSE, 202: EXACT_DRAPE_RESPONSES[202], 429: EXACT_DRAPE_RESPONSES[429]})
def outfit_glb(cid: str, tryon: TryOnDep, drapes: DrapesDep, creds: CredentialsDep, if_none_match: IfNoneMatchDep,
               garments: Annotated[str, Query(description="Comma-separated garment ids")] = "",
               compression: Compression = None, hair: Hair = None, underwear: Underwear = True,
               pose_correctives: PoseCorrectives = False,
               sizes: Annotated[str | None, Query(max_length=2000, description=(
                   "Comma-separated size labels, one per garment in the order of `garments` (empty: the "
                   "recommended size); default: each garment's recommended size"))] = None,
               fitmap: FitMap = None, drape: OutfitDrape = "basis") -> Response:
    """The customer's avatar wearing the garments (one scene, one skeleton), layered: inner
    garments (lower layer) first, each outer one pushed over the ones below. The avatar as in
    ``avatar.glb`` (nodes ``avatar``, ``eyes``, ``eyebrows``, ``hair``, ``underwear``; the same
    ``hair`` and ``underwear`` choices), then one node per garment. ``ETag`` and
    ``If-None-Match`` as for one garment; ``pose_correctives`` as for one garment (the page
    asks for them: it sets the current pose's target influence), and the ``avatar`` node gets
    ``pose:<name>`` targets too where skin would show through the posed clothes (pulled under
    them). The body under opaque garments is left out of the ``avatar`` mesh (its vertices
    stay). ``drape=exact``: each garment as the customer's own drape (202 with a job until
    they are all done or failed)."""
    out = tryon.outfit_glb(cid, garments.split(","), creds, compression, if_none_match, hair, underwear,
                           pose_correctives, None if sizes is None else sizes.split(","), fitmap,
                           worn=drapes.outfit_worn if drape == "exact" else None)
    if isinstance(out, JobRefRecord):
        return JSONResponse(out.model_dump(), status_code=202, headers={"Location": out.url})
    return R.private_glb(*out)


@router.get("/v1/customers/{cid}/garments/{gid}/fit", response_model=FitResponse,
            responses={k: v for k, v in R.CUSTOMER_SCENE_RESPONSE.items() if k not in (200, 304)})
def garment_fit(cid: str, gid: str, tryon: TryOnDep, creds: CredentialsDep) -> dict:
    """How each size of the garment fits the customer: per size a verdict and, per region
    (girths chest, waist, hip, thigh, upper arm, shoulders; lengths sleeve, inseam, hem: those
    the garment has), the ease (garment girth minus body girth, or garment length minus body
    length, cm), the strain of cloth tighter than the body (%, 0 for a length) and a verdict
    (too_tight, tight, fit, loose, too_loose; girth thresholds per fabric, a too short length is
    tight, a too long one loose); ``recommended``: the size with no tight region whose ease is
    closest to the garment's design ease (its ease on the base size's body), else the loosest.
    Sizes in chart order."""
    return tryon.fit_report(cid, gid, creds)

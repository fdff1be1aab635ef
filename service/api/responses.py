"""Response helpers shared by the routes: media types, GLB/OBJ responses, content negotiation,
and the OpenAPI descriptions of the answers."""
from __future__ import annotations

from fastapi import Response

GLB_MEDIA_TYPE = "model/gltf-binary"
JSON_MEDIA_TYPE = "application/json"
OBJ_MEDIA_TYPE = "model/obj"

RETRY_AFTER = {"Retry-After": {"description": "Seconds after which to retry", "schema": {"type": "integer"}}}
# Any API route: Redis unreachable, or the process saturated (back-pressure).
UNAVAILABLE = {503: {"description": "Storage unavailable or server busy: retry after `Retry-After` seconds",
                     "headers": RETRY_AFTER}}
RATE_LIMITED = {429: {"description": "Rate limit of the client or retailer reached: retry after `Retry-After` "
                                     "seconds", "headers": RETRY_AFTER}}
JSON_BODY = {400: {"description": "Malformed body"}, 413: {"description": "Request body too large"}}
UPLOAD = {400: {"description": "Malformed multipart body"}, 413: {"description": "Upload too large"}}
INVALID_KEY = {403: {"description": "Unknown X-API-Key"}}
ETAG = {"ETag": {"description": "Strong validator of the content (send it as If-None-Match)",
                 "schema": {"type": "string"}}}
NOT_MODIFIED = {304: {"description": "Not modified (If-None-Match matched the ETag)", "headers": ETAG}}
CUSTOMER_404 = {404: {"description": "Unknown customer, or no valid `Authorization: Bearer <token>` (nor the "
                                     "owning retailer's X-API-Key): the two are not told apart"}}

GLB_RESPONSE = {200: {"description": "GLB (glTF 2.0 binary)",
                      "content": {GLB_MEDIA_TYPE: {"schema": {"type": "string", "format": "binary"}}}},
                404: {"description": "Unknown id"}}
CUSTOMER_GLB_RESPONSE = {**GLB_RESPONSE, 409: {"description": "The customer's scan is being fitted or its fit "
                                                              "failed, a garment is not ready, or a record was "
                                                              "made with another body model"}}
# A scene made for one customer: token-protected, with an ETag.
CUSTOMER_SCENE_RESPONSE = {**CUSTOMER_GLB_RESPONSE, 200: {**GLB_RESPONSE[200], "headers": ETAG},
                           **NOT_MODIFIED, **INVALID_KEY,
                           404: {"description": CUSTOMER_404[404]["description"] + "; or an unknown garment"}}
PRIVATE_CACHE = "private, no-cache"  # a customer's data: browsers revalidate (ETag), shared caches keep nothing
OBJ_RESPONSE = {200: {"description": "Wavefront OBJ (metres, Y up)",
                      "content": {OBJ_MEDIA_TYPE: {"schema": {"type": "string"}}}},
                404: {"description": "Unknown id"}}


def glb(data: bytes, **headers: str) -> Response:
    return Response(content=data, media_type=GLB_MEDIA_TYPE, headers=headers or None)


def private_glb(data: bytes | None, etag: str) -> Response:
    """A customer's scene with its ETag, or 304 when ``data`` is None (not modified)."""
    headers = {"ETag": etag, "Cache-Control": PRIVATE_CACHE, "Vary": "Authorization, X-API-Key"}
    if data is None:
        return Response(status_code=304, headers=headers)
    return glb(data, **headers)


def obj(text: str) -> Response:
    return Response(text, media_type=OBJ_MEDIA_TYPE)


def _accept_quality(accept: str | None, media_type: str) -> float:
    """The q-value ``accept`` gives ``media_type`` (exact > type/* > */*); 0 if not accepted."""
    if not accept:
        return 1.0 if media_type == JSON_MEDIA_TYPE else 0.0
    best, best_rank = 0.0, -1
    main = media_type.split("/")[0]
    for part in accept.split(","):
        fields = [f.strip() for f in part.split(";")]
        rng = fields[0].lower()
        q = 1.0
        for p in fields[1:]:
            if p.lower().startswith("q="):
                try:
                    q = float(p[2:])
                except ValueError:
                    q = 0.0
        rank = 2 if rng == media_type else 1 if rng == f"{main}/*" else 0 if rng == "*/*" else -1
        if rank > best_rank:
            best, best_rank = q, rank
    return best if best_rank >= 0 else 0.0


def wants_glb(accept: str | None) -> bool:
    """True when the Accept header prefers GLB strictly over JSON."""
    return _accept_quality(accept, GLB_MEDIA_TYPE) > _accept_quality(accept, JSON_MEDIA_TYPE)

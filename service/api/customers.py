"""Customers: create (measurements, template-topology avatar mesh, or a scan fitted by a job),
read, delete, and their avatar."""
from __future__ import annotations

import asyncio
from typing import Annotated, Any, Literal

import numpy as np
from fastapi import APIRouter, Query, Request, Response, WebSocket, WebSocketDisconnect
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.datastructures import UploadFile

from service.api import responses as R
from service.api.deps import (Compression, CredentialsDep, CustomersDep, EditingDep, Hair, IfNoneMatchDep,
                              OptionalRetailerDep, RateLimited, SettingsDep, Underwear, credentials_of,
                              Expensive)
from service.api.errors import invalid
from service.api.schemas import AvatarRequest, CustomerResponse, EditRequest
from service.application.errors import Conflict, Invalid, NotFound
from service.application.uploads import (KNOWN_FIELD_DOC, KNOWN_FIELDS, SCAN_FORMATS, parse_bool, parse_gender,
                                         parse_known_measurements)
from service.model.formats.mesh_io import KEPT_SCAN_POINTS, MAX_SCAN_POINTS
from service.records import Customer

router = APIRouter(tags=["customers"])

AvatarPose = Annotated[
    Literal["rest", "scan"],
    Query(description="rest (default): the skinned rest-pose avatar; scan: the body as fitted in the customer's "
                      "scan, in the scan's frame (metres, scan up = +Y), unskinned; 422 for customers not "
                      "fitted from a scan"),
]

CUSTOMER_BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/AvatarRequest"}},
            "multipart/form-data": {
                "schema": {
                    "type": "object",
                    "required": ["mesh"],
                    "properties": {
                        "mesh": {"type": "string", "format": "binary",
                                 "description": "An avatar mesh in the template topology (/v1/body-model/"
                                                "template.obj: the body or full vertex count; OBJ/PLY/GLB) -> "
                                                "201, ready; or any other 3D scan, clothed avatar or point "
                                                f"cloud ({SCAN_FORMATS}; at most {MAX_SCAN_POINTS:,} points, more "
                                                f"than {KEPT_SCAN_POINTS:,} simplified to that by vertex "
                                                "clustering) -> 202, "
                                                "fitted by a job. Any unit (m, cm, mm), any up axis"},
                        "gender": {"type": "string", "enum": ["female", "male"],
                                   "description": "Optional; estimated from the shape if omitted"},
                        "clothed": {"type": "boolean", "default": True,
                                    "description": "Scans: the person wears clothes (the body is fitted "
                                                   "inside them); false for a scan of the bare body "
                                                   "(minimal clothing; hair is expected and the head "
                                                   "is fitted inside it)"},
                        **{name: {"type": "number", "description": KNOWN_FIELD_DOC.format(name=name)}
                           for name in KNOWN_FIELDS},
                    },
                }
            },
        },
    },
    # a retailer's key is optional here (anonymous customers are the page's)
    "security": [{}],
}


def _json_measurements(body: bytes) -> dict[str, Any]:
    try:
        return dict(AvatarRequest.model_validate_json(body or b"").measurements)
    except ValidationError as exc:
        raise RequestValidationError(
            [{**e, "loc": ("body", *e.get("loc", ()))} for e in exc.errors(include_input=False)]) from exc


def _created(record: Customer, token: str) -> CustomerResponse:
    """The answer to a creation: the record as shown, with its token (given only here)."""
    return CustomerResponse.model_validate({**record.model_dump(), "token": token})


@router.post("/v1/customers", status_code=201, response_model=CustomerResponse, openapi_extra=CUSTOMER_BODY,
             dependencies=[RateLimited],
             responses={202: {"description": "A scan was accepted: the customer is 'fitting' until its job "
                                             "(job.url, also the Location header) is done",
                              "model": CustomerResponse},
                        **R.UPLOAD, **R.INVALID_KEY, **R.RATE_LIMITED, 422: {"description": "Invalid input"}})
async def create_customer(request: Request, response: Response, customers: CustomersDep,
                          retailer: OptionalRetailerDep = None) -> CustomerResponse:
    """Create a customer from measurements (JSON ``{"measurements": {...}}``, as
    ``POST /v1/avatars``), from an avatar mesh in the template topology (multipart file
    ``mesh``: 201) or from a scan of any topology (multipart file ``mesh``: 202; the scan is
    validated now, then fitted by a job: poll ``job.url``).

    The answer's ``token`` is shown only here: every customer route (and the customer's job)
    needs it as ``Authorization: Bearer <token>``. With a retailer's ``X-API-Key`` the customer
    belongs to that retailer (``owner``), whose key opens it too."""
    if not request.headers.get("content-type", "").lower().startswith("multipart/form-data"):
        measurements = _json_measurements(await request.body())
        return _created(*await run_in_threadpool(customers.create_from_measurements, measurements, retailer))
    form = await request.form(max_files=2, max_fields=8 + len(KNOWN_FIELDS))
    upload = form.get("mesh")
    if not isinstance(upload, UploadFile):
        raise invalid(("body", "mesh"), f"a file field 'mesh' ({SCAN_FORMATS}) is required")
    gender = parse_gender(form.get("gender"))
    clothed = parse_bool(form.get("clothed"), "clothed", True)
    known = parse_known_measurements(customers.model, dict(form))
    data = await upload.read()
    await form.close()
    try:
        record, token = await run_in_threadpool(customers.create_from_upload, data, upload.filename, gender,
                                                clothed, retailer, known)
    finally:
        del data
    if record.job is not None:
        response.status_code = 202
        response.headers["Location"] = record.job.url
    return _created(record, token)


@router.get("/v1/customers/{cid}", response_model=CustomerResponse,
            responses={**R.CUSTOMER_404, **R.INVALID_KEY})
def get_customer(cid: str, customers: CustomersDep, creds: CredentialsDep) -> Customer:
    """A stored customer (a scan customer: ``fitting``, then ``ready`` or ``failed``); needs its
    token (or its retailer's key)."""
    return customers.get(cid, creds)


@router.get("/v1/customers/{cid}/avatar.glb", response_class=Response,
            responses={**R.CUSTOMER_SCENE_RESPONSE,
                       422: {"description": "Unknown compression or pose, or pose=scan for a customer not fitted "
                                            "from a scan"}})
def customer_avatar_glb(cid: str, customers: CustomersDep, creds: CredentialsDep, if_none_match: IfNoneMatchDep,
                        compression: Compression = None, hair: Hair = None, underwear: Underwear = True,
                        pose: AvatarPose = "rest") -> Response:
    """The customer's avatar (409 while its scan is being fitted): the skinned body surface
    (node ``avatar``, skin-coloured) with ``eyes`` (irises), ``eyebrows``, ``hair`` (``hair``:
    a style of ``GET /v1/looks``, ``none``, or the default of the customer's gender) and
    ``underwear`` (the gender's base layer unless ``underwear=false``), one mesh node each,
    all skinned with one skeleton, in the rest pose. ``pose=scan`` (customers fitted from a
    scan): the bare body posed as fitted in the scan and placed where the scan was, in the
    scan's frame in glTF conventions (metres, the scan's up axis as +Y), not skinned, to overlay
    on the scan; 422 for customers made from measurements or a template-topology mesh (they
    have no scan), 409 for scan customers fitted before poses were stored. ``ETag`` from the
    customer's weights (and pose), the look and the options; ``If-None-Match`` -> 304."""
    return R.private_glb(*customers.avatar_glb(cid, creds, compression, if_none_match, hair, underwear, pose))


@router.get("/v1/customers/{cid}/poses", response_model=dict[str, dict[str, list[float]]],
            responses={**R.CUSTOMER_404, **R.INVALID_KEY,
                       409: {"description": "The customer's scan is being fitted or its fit failed"}})
def customer_poses(cid: str, customers: CustomersDep, creds: CredentialsDep) -> dict[str, dict[str, list[float]]]:
    """The page's pose presets (``web_client/poses.json``) adapted to the customer's body:
    ``{preset: {bone: [x, y, z]}}``, local rotations of the 17 bones as axis-angle (radians;
    the bones' rest frames are the world axes: Y up, facing +Z). Each arm's abduction is
    increased until no arm vertex is inside the torso or thighs."""
    return customers.page_poses(cid, creds)


@router.delete("/v1/customers/{cid}", status_code=204, response_class=Response,
               responses={**R.CUSTOMER_404, **R.INVALID_KEY})
def delete_customer(cid: str, customers: CustomersDep, creds: CredentialsDep) -> Response:
    """Delete a customer and everything derived from it (at any time: a waiting scan and its
    fitting job too; a running fit is stopped)."""
    customers.delete(cid, creds)
    return Response(status_code=204)


# -- editing (issue 13) ------------------------------------------------------------------------
@router.post("/v1/customers/{cid}/edit", response_class=Response, dependencies=[Expensive],
             responses={**R.CUSTOMER_GLB_RESPONSE, **R.CUSTOMER_404, **R.INVALID_KEY, **R.JSON_BODY,
                        422: {"description": "Unknown attribute or bone, or a value outside its allowed range"}})
def edit_customer(cid: str, request: EditRequest, editing: EditingDep, creds: CredentialsDep,
                  compression: Compression = None) -> Response:
    """The customer's avatar with new measurements (absolute targets, the others held) and a
    new pose (the bones not given as fitted), as GLB: for a customer fitted from a clothed mesh,
    that scan, clothes and all (its own vertices, in order; the body-aware warping graph of the
    editing paper carries it); for any other customer, the body. 409 while its scan is fitted."""
    return R.glb(editing.glb(cid, creds, request.measurements, request.pose, compression))


WS_ERRORS = {NotFound: 4404, Conflict: 4409}
WS_UNSUPPORTED_DATA = 1003  # RFC 6455: a frame of a type the endpoint cannot accept
WS_POLICY_VIOLATION = 1008
WS_MAX_MESSAGE_CHARS = 64 * 1024  # an edit message is ~1-2 KB of JSON


class WebSocketMisuse(Exception):
    """A client message the editing protocol does not allow: closes with ``code``."""

    def __init__(self, code: int, reason: str):
        super().__init__(reason)
        self.code, self.reason = code, reason


@router.websocket("/v1/customers/{cid}/edit/ws")
async def edit_customer_ws(websocket: WebSocket, cid: str, editing: EditingDep, settings: SettingsDep) -> None:
    """Live editing while a slider is dragged. After the connection opens the server sends a
    text frame ``{"vertices": n, "faces": F, "kind": "scan"|"avatar"}``, then one binary frame
    of the faces (uint32 little-endian, F x 3) and one of the current vertices (float32
    little-endian, n x 3, metres, model frame). Each text frame from the client with the body
    of ``POST .../edit`` (``{"measurements": {...}, "pose": {...}}``) is answered by a binary
    frame of the edited vertices; while an edit is computed, newer messages replace older ones
    (only the latest is answered). A bad message is answered by a text frame ``{"error": 422,
    "detail": [...]}``; an unknown customer (or missing or wrong credentials: the customer's
    token as ``Authorization: Bearer`` or, from a browser, the ``token`` query parameter; or its
    retailer's ``X-API-Key``) closes with code 4404, one not ready with 4409."""
    await websocket.accept()
    creds = credentials_of(websocket, settings)
    try:
        if creds is None:
            raise NotFound(f"customer '{cid}' not found")
        faces = await run_in_threadpool(editing.faces, cid, creds)
        first = await run_in_threadpool(editing.edit, cid, creds, None, None)
    except (NotFound, Conflict) as exc:
        await websocket.send_json({"error": 404 if isinstance(exc, NotFound) else 409, "detail": exc.message})
        await websocket.close(code=WS_ERRORS[type(exc)], reason=exc.message[:120])
        return
    await websocket.send_json({"vertices": int(len(first.vertices)), "faces": int(len(faces)), "kind": first.kind})
    await websocket.send_bytes(np.ascontiguousarray(faces, "<u4").tobytes())
    await websocket.send_bytes(np.ascontiguousarray(first.vertices, "<f4").tobytes())
    latest: list[str] = []
    wake = asyncio.Event()

    async def receive() -> None:
        while True:
            message = await websocket.receive()
            if message["type"] == "websocket.disconnect":
                raise WebSocketDisconnect(message.get("code", 1000))
            text = message.get("text")
            if text is None:  # a binary frame: this protocol has none from the client
                raise WebSocketMisuse(WS_UNSUPPORTED_DATA, "binary frames are not accepted; send JSON text")
            if len(text) > WS_MAX_MESSAGE_CHARS:
                raise WebSocketMisuse(WS_POLICY_VIOLATION, f"messages are at most {WS_MAX_MESSAGE_CHARS} characters")
            latest[:] = [text]
            wake.set()

    reader = asyncio.create_task(receive())
    try:
        while True:
            waiter = asyncio.create_task(wake.wait())
            done, _ = await asyncio.wait({reader, waiter}, return_when=asyncio.FIRST_COMPLETED)
            if reader in done:
                waiter.cancel()
                reader.result()  # re-raises the disconnect
            wake.clear()
            message = latest.pop() if latest else None
            if message is None:
                continue
            try:
                req = EditRequest.model_validate_json(message)
                out = await run_in_threadpool(editing.edit, cid, creds, req.measurements, req.pose)
            except ValidationError as exc:
                await websocket.send_json({"error": 422, "detail": [
                    {"loc": ["body", *e.get("loc", ())], "msg": e.get("msg", ""), "type": e.get("type", "")}
                    for e in exc.errors(include_input=False)]})
                continue
            except Invalid as exc:
                await websocket.send_json({"error": 422, "detail": [{"loc": list(exc.loc), "msg": exc.message,
                                                                     "type": "value_error"}]})
                continue
            except (NotFound, Conflict) as exc:
                await websocket.close(code=WS_ERRORS[type(exc)], reason=exc.message[:120])
                return
            await websocket.send_bytes(np.ascontiguousarray(out.vertices, "<f4").tobytes())
    except WebSocketDisconnect:
        pass
    except WebSocketMisuse as exc:  # the client broke the protocol: a close code, no trace
        await websocket.close(code=exc.code, reason=exc.reason)
    finally:
        reader.cancel()

"""Editing an avatar in real time (issue 13; editing paper Sec. 5): new measurements (absolute
targets of any attributes, the others held) and a new pose (axis-angle per bone, the others as
fitted) -> the edited avatar.

* A customer fitted from an uploaded clothed *mesh*: the scan itself is edited, clothes and all,
  through the body-aware warping graph between the fitted body and the scan
  (``service.model.nonrigid.editing.ClothedAvatarEditor``), built once per process per customer from the
  mesh the fitting job stored (``storage.meshes``) and cached; an edit is then one
  back-substitution and two sparse products.
* Any other customer (measurements, a template-topology avatar, a point cloud): the avatar's body
  is edited (measurements -> shape with every other attribute held, then the forward pass).

Vertices come out in the model frame (metres, Y up, glTF's), in the upload's vertex order.
"""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.model.formats import gltf
from service.model.body.model import BONES, BodyModel
from service.model.nonrigid.editing import ClothedAvatarEditor
from service.model.geometry.mesh import vertex_normals
from service.model.body.shape import MeasurementError, avatar_from_measurements, validate_measurements
from service.records import Customer

from .auth import Credentials
from .customers import CustomerService
from .editors import Editors
from .errors import Invalid

MAX_ANGLE = math.pi  # radians: the accepted range of each bone's rotation angle
SCAN_COLOR = (0.78, 0.76, 0.74, 1.0)


@dataclass
class Edited:
    """An edited avatar: vertices (n, 3) float32 in the model frame, faces (F, 3) int32, and
    what was edited ('scan': the uploaded clothed mesh; 'avatar': the body surface)."""

    vertices: np.ndarray
    faces: np.ndarray
    kind: str


def check_pose(pose: Mapping[str, Any] | None) -> dict[str, np.ndarray]:
    """A pose edit: bone name -> axis-angle (3,) radians with |angle| <= pi. :class:`Invalid`
    names the bone and the allowed range."""
    out: dict[str, np.ndarray] = {}
    for name, value in (pose or {}).items():
        loc = ("body", "pose", str(name))
        if name not in BONES:
            raise Invalid(loc, f"unknown bone; bones: {', '.join(BONES)}")
        try:
            a = np.asarray(value, np.float64)
        except (TypeError, ValueError) as exc:
            raise Invalid(loc, "must be [x, y, z]: an axis-angle rotation in radians") from exc
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise Invalid(loc, "must be [x, y, z]: three finite numbers (axis-angle, radians)")
        angle = float(np.linalg.norm(a))
        if angle > MAX_ANGLE + 1e-9:
            raise Invalid(loc, f"rotation of {angle:.3f} rad is outside the allowed range 0-{MAX_ANGLE:.4f} rad "
                               "(the length of the axis-angle vector)")
        out[name] = a
    return out


class EditingService:
    def __init__(self, model: BodyModel, customers: CustomerService, editors: Editors):
        self.model = model
        self.customers = customers
        self.editors = editors

    # -- the editable customer ---------------------------------------------------------------
    def _customer(self, cid: str, creds: Credentials) -> Customer:
        customers = self.customers
        return customers.require_ready(customers.open(customers.repo.get(cid), cid, creds), cid)

    def editor(self, record: Customer) -> ClothedAvatarEditor | None:
        return self.editors.editor(record)

    # -- edits -------------------------------------------------------------------------------
    def faces(self, cid: str, creds: Credentials) -> np.ndarray:
        record = self._customer(cid, creds)
        if self.editor(record) is not None:
            return self._scan_faces(record)
        return np.asarray(self.model.body_faces, np.int32)

    def edit(self, cid: str, creds: Credentials, measurements: Mapping[str, Any] | None,
             pose: Mapping[str, Any] | None) -> Edited:
        """The customer's avatar (its clothed scan, or its body) with new measurements and pose
        (404 unless ``creds`` open the customer)."""
        record = self._customer(cid, creds)
        bones = check_pose(pose)
        editor = self.editor(record)
        if editor is not None:
            try:
                v = editor.edit(measurements=dict(measurements or {}), pose=bones)
            except MeasurementError as exc:
                raise Invalid(("body", "measurements", str(exc.field)), exc.message) from exc
            return Edited(v.astype(np.float32), self._scan_faces(record), "scan")
        return Edited(self._edit_body(record, measurements, bones), np.asarray(self.model.body_faces, np.int32),
                      "avatar")

    def _scan_faces(self, record: Customer) -> np.ndarray:
        return self.editors.scan_faces(record)

    def _edit_body(self, record: Customer, measurements: Mapping[str, Any] | None,
                   bones: dict[str, np.ndarray]) -> np.ndarray:
        """The body avatar: every attribute it measures held, the targets replaced, refitted;
        then posed (the bones not given as fitted, or the rest pose)."""
        given = dict(measurements or {})
        current = dict(record.measurements or {})
        try:
            checked = validate_measurements(self.model, given)
            if "gender" in checked and checked["gender"] != current.get("gender"):
                raise MeasurementError("gender", f"cannot be edited (the avatar is {current.get('gender')})")
            if checked:
                avatar = avatar_from_measurements(self.model, {**current, **checked})
                weights = np.asarray(avatar.weights, np.float64)
            else:
                weights = np.asarray(record.weights, np.float64)
        except MeasurementError as exc:
            raise Invalid(("body", "measurements", str(exc.field)), exc.message) from exc
        pose = np.zeros((len(BONES), 3))
        if record.pose:
            pose = np.array([record.pose[b] for b in BONES], np.float64)
        for name, a in bones.items():
            pose[BONES.index(name)] = a
        posed = self.model.forward(weights, pose)
        return posed.vertices[: self.model.n_body_vertices].astype(np.float32)

    def glb(self, cid: str, creds: Credentials, measurements: Mapping[str, Any] | None,
            pose: Mapping[str, Any] | None, compression: str | None) -> bytes:
        """The edited avatar as GLB (one mesh, the upload's vertices in order)."""
        e = self.edit(cid, creds, measurements, pose)
        return gltf.scene_to_glb([{"vertices": e.vertices, "faces": e.faces,
                                   "normals": vertex_normals(e.vertices, e.faces), "color": SCAN_COLOR,
                                   "name": "avatar"}], compression=compression)

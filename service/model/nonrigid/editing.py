"""Reshaping and re-posing a fitted clothed scan in real time (issue 13; editing paper Sec. 5).

Once a body M* (shape weights beta*, pose theta*, translation) is fitted to a clothed scan A,
:class:`ClothedAvatarEditor` builds the warping graph between the posed M* and A once
(``warping.WarpGraph``: Poisson-disk nodes on both, 6 nearest neighbours, Eqs. 5-7 factored
once). An edit changes M*'s parameters and carries A along:

* **Shape** from measurements: absolute targets for any of the 11 numeric attributes (API
  units), the others held at the fitted body's values. A linearised solve at the fitted shape
  (the measurement Jacobian of ``measurements.measure``, computed once), with the population
  prior of ``shape.refine``: min_dbeta  sum_i ((J_i dbeta - dt_i) / tol_i)^2 + lambda |dbeta|^2_{Sigma^-1}
  (tol_i the ISO 20685-1 allowable error, Sigma the population covariance of the weights). The
  prior is on the change, so an edit that asks for the fitted values changes nothing. The
  solution is a fixed (K, 11) matrix times the target changes.
* **Pose**: axis-angle radians per bone (``body.BONES``), the bones not given as fitted.
* The body nodes of the graph are evaluated on the new body (only the vertices they read:
  shape, joints and skinning of that subset), then one back-substitution and two sparse
  products give A's vertices.

Pose edits go through the graph, not skinning of the scan. The module also has linear blend
and dual-quaternion skinning of the scan itself (``reskin_scan``), with skin weights transferred
from the fitted body, for comparison (paper Fig. 8).

Shapes: A's vertices (n, 3) metres in the model frame (the fit's ``to_model`` applied), faces
(F, 3) or None; body weights (K,); pose (17, 3) axis-angle.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from service.model.body import lbs
from service.model.body import measurements as M
from service.model.body.model import BONES
from service.model.geometry.mesh import closest_points_on_mesh
from service.model.formats.mhclo import HELPER_TIGHTS
from service.model.body.shape import REFINE, MeasurementError, validate_measurements
from service.model.nonrigid.warping import WarpGraph, WarpParams

SKINNING = ("lbs", "dqs")


@dataclass(frozen=True)
class EditParams:
    """The editor's graph and weights.

    Two choices differ from the paper's defaults, measured with ``tryon bench editing``:
    ``wp`` = 10 (paper 0.1): with Ec summed over ~16 directed edges per node, wp = 0.1 lets the
    body nodes drift from the edited body and smooths its motion over ~10 cm, so a twisted
    elbow loses about twice the volume that LBS of the scan does; wp = 10 keeps them on it
    (forward error mean 0.00027 against 0.00038 of the diagonal). ``skinning`` = 'dqs': M* is
    posed with dual quaternions over the body model's bone transforms, so twisted joints keep
    their volume (90-degree elbow twist of a closed suit: -64 cm3 against -393 with the paper's
    settings, -196 for LBS and -40 for DQS of the suit itself)."""

    warp: WarpParams = WarpParams(wp=10.0)
    prior_weight: float = REFINE.prior_weight  # lambda: the shape prior beside the ISO-normalised targets
    # how M* is posed for the graph: 'dqs' (dual quaternions over the body model's bone
    # transforms) or 'lbs' (the body model's forward pass itself)
    skinning: str = "dqs"
    # the body model's helper-tights layer (MakeHuman's skin-tight clothing surface) as further
    # body nodes, as in the garment auto-fit: clothes follow it rather than the bare skin
    follow_helper_tights: bool = True


DEFAULT_PARAMS = EditParams()


class ClothedAvatarEditor:
    """Built once per fitted clothed scan (see the module docstring); ``edit`` per update."""

    def __init__(self, model, weights: np.ndarray, pose: np.ndarray | None, translation: np.ndarray | None,
                 vertices: np.ndarray, faces: np.ndarray | None = None, gender: str = "female",
                 params: EditParams = DEFAULT_PARAMS, progress: Callable[[float, str], None] | None = None):
        if params.skinning not in SKINNING:
            raise ValueError(f"skinning must be one of {SKINNING}")
        if gender not in M.DENSITY:
            raise ValueError('gender must be "female" or "male"')
        self.model = model
        self.params = params
        self.gender = gender
        self.weights = np.asarray(weights, np.float64).copy()
        self.pose = lbs.matrix_to_axis_angle(lbs.as_rotations(pose, len(BONES)))
        self.translation = np.zeros(3) if translation is None else np.asarray(translation, np.float64).copy()
        nb = model.n_body_vertices
        posed = model.forward(self.weights, self.pose, self.translation)
        M_star = posed.vertices
        if params.skinning == "dqs":  # M* posed the way every edit poses it: no edit is no change
            M_star = dqs_skin(model.vertices(self.weights).astype(np.float64), posed.transforms, model.lbs_indices,
                              model.lbs_weights)
        helpers = None
        if params.follow_helper_tights and len(model.mean) >= HELPER_TIGHTS[1]:
            helpers = np.arange(*HELPER_TIGHTS)
        self.graph = WarpGraph.precompute(M_star if helpers is not None else M_star[:nb],
                                          model.body_faces, vertices, faces, params.warp, body_points=helpers,
                                          body_labels=lbs.main_bone(model.lbs_indices, model.lbs_weights),
                                          label_hops=lbs.bone_hops(model.bone_parents), progress=progress)
        # the body model restricted to the vertices the graph reads
        u = self.graph.body_vertex_ids
        self._mean_u = model.mean[u].astype(np.float64)
        self._comps_u = np.ascontiguousarray(model.components[:, u].reshape(model.n_components, -1), np.float64)
        jr = model.joint_regressor
        self._j0 = np.asarray(jr @ model.mean.astype(np.float64))
        comps = model.components.astype(np.float64).transpose(1, 0, 2).reshape(len(model.mean), -1)
        self._jc = np.asarray(jr @ comps).reshape(len(BONES), model.n_components, 3).transpose(1, 0, 2).reshape(
            model.n_components, -1)
        self._idx_u, self._w_u = model.lbs_indices[u], model.lbs_weights[u].astype(np.float64)
        # the measurements and their Jacobian at the fitted shape: dbeta = shape_map @ dtargets
        X = model.vertices(self.weights)
        raw, J = M.measure(model.measurement_spec, X, gender, jacobian=True, basis=model.components_T)
        self._raw0 = raw[:11]
        tol = np.array([M.ISO_TOLERANCE[n] for n in M.RAW_NAMES[:11]])
        Jw = np.asarray(J[:11]) / tol[:, None]  # (11, K) d measurements / d weights, ISO-normalised
        prior = params.prior_weight * np.diag(1.0 / model.variances)
        self._shape_map = np.linalg.solve(Jw.T @ Jw + prior, Jw.T / tol[None, :])  # (K, 11)
        self.measurements = M.to_api_units(raw, gender)

    # -- parameters ------------------------------------------------------------------------
    def weights_for(self, measurements: Mapping | None) -> np.ndarray:
        """Shape weights (K,) for absolute targets of any attributes (API units), the others
        held at the fitted body's values. Raises ``MeasurementError`` for unknown names,
        values out of range or a change of gender."""
        given = validate_measurements(self.model, dict(measurements or {}))
        if "gender" in given and given["gender"] != self.gender:
            raise MeasurementError("gender", f"cannot be edited (the avatar is {self.gender})")
        dt = np.zeros(11)
        for i, name in enumerate(M.ATTRIBUTES[1:]):
            if name in given:
                dt[i] = given[name] / M.api_scale(name) - self._raw0[i]
        return self.weights + self._shape_map @ dt

    def pose_for(self, pose) -> np.ndarray:
        """(17, 3) axis-angle: the fitted pose with the bones given replaced. ``pose``: None,
        a mapping bone name -> (3,) radians, or a (17, 3) array. Raises ValueError for unknown
        bones or non-finite values."""
        out = self.pose.copy()
        if pose is None:
            return out
        if isinstance(pose, Mapping):
            for name, v in pose.items():
                if name not in BONES:
                    raise ValueError(f"unknown bone {name!r}; bones: {', '.join(BONES)}")
                a = np.asarray(v, np.float64)
                if a.shape != (3,) or not np.all(np.isfinite(a)):
                    raise ValueError(f"bone {name!r}: expected 3 finite numbers (axis-angle radians)")
                out[BONES.index(name)] = a
            return out
        a = np.asarray(pose, np.float64)
        if a.shape != (len(BONES), 3) or not np.all(np.isfinite(a)):
            raise ValueError(f"pose must be ({len(BONES)}, 3) finite axis-angle radians")
        return a.copy()

    # -- the edit ----------------------------------------------------------------------------
    def body_subset(self, weights: np.ndarray, pose: np.ndarray) -> np.ndarray:
        """The posed body's vertices that the graph reads (u, 3): shape, joints and skinning of
        that subset only (the same numbers as ``model.forward`` there)."""
        w = np.asarray(weights, np.float64)
        X = self._mean_u + (w @ self._comps_u).reshape(-1, 3)
        J = self._j0 + (w @ self._jc).reshape(len(BONES), 3)
        G = lbs.global_transforms(J, self.model.bone_parents, lbs.as_rotations(pose, len(BONES)), self.translation)
        if self.params.skinning == "dqs":
            return dqs_skin(X, G, self._idx_u, self._w_u)
        return lbs.skin(X, G, self._idx_u, self._w_u)

    def edit(self, measurements: Mapping | None = None, pose=None, weights: np.ndarray | None = None) -> np.ndarray:
        """A's vertices (n, 3) float64 for new measurements (or shape ``weights`` (K,)) and
        pose (see ``weights_for`` / ``pose_for``)."""
        w = self.weights_for(measurements) if weights is None else np.asarray(weights, np.float64)
        return self.graph.warp_subset(self.body_subset(w, self.pose_for(pose)))


# -- skinning the scan itself (the comparison of paper Fig. 8) --------------------------------------
def dqs_skin(vertices: np.ndarray, transforms: np.ndarray, lbs_indices: np.ndarray,
             lbs_weights: np.ndarray) -> np.ndarray:
    """Dual-quaternion skinning (Kavan et al. 2008): the rigid bone transforms (J, 4, 4) as unit
    dual quaternions, blended per vertex with its weights (signs aligned with the vertex's
    first bone), normalised, applied. vertices (V, 3) -> (V, 3)."""
    G = np.asarray(transforms, np.float64)
    q = Rotation.from_matrix(G[:, :3, :3]).as_quat()  # (J, 4) x, y, z, w
    qr = np.concatenate([q[:, 3:], q[:, :3]], axis=1)  # (w, x, y, z)
    t = G[:, :3, 3]
    # dual part 0.5 (0, t) qr
    qd = 0.5 * np.concatenate([-(t * qr[:, 1:]).sum(1, keepdims=True),
                               qr[:, :1] * t + np.cross(t, qr[:, 1:])], axis=1)
    w = np.asarray(lbs_weights, np.float64)
    R, D = qr[lbs_indices], qd[lbs_indices]  # (V, k, 4)
    sign = np.where(np.einsum("vki,vi->vk", R, R[:, 0]) < 0, -1.0, 1.0)
    br = np.einsum("vk,vki->vi", w * sign, R)
    bd = np.einsum("vk,vki->vi", w * sign, D)
    n = np.linalg.norm(br, axis=1, keepdims=True)
    br, bd = br / n, bd / n
    r0, rv = br[:, :1], br[:, 1:]
    d0, dv = bd[:, :1], bd[:, 1:]
    P = np.asarray(vertices, np.float64)
    rotated = P + 2 * np.cross(rv, np.cross(rv, P) + r0 * P)
    trans = 2 * (r0 * dv - d0 * rv + np.cross(rv, dv))
    return rotated + trans


def transfer_skin_weights(points: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray,
                          lbs_indices: np.ndarray, lbs_weights: np.ndarray, n_bones: int = len(BONES),
                          k: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights for points (n, 3) near a body: the body's weights interpolated at each
    point's closest body surface point, the k largest kept and renormalised: (indices (n, k),
    weights (n, k))."""
    V = np.asarray(body_vertices, np.float64)
    F = np.asarray(body_faces, np.int64)
    face, _, bary = closest_points_on_mesh(points, V, F)
    dense = np.zeros((len(points), n_bones))
    for c in range(3):
        vid = F[face, c]
        for j in range(lbs_indices.shape[1]):
            np.add.at(dense, (np.arange(len(points)), lbs_indices[vid, j]), bary[:, c] * lbs_weights[vid, j])
    dense = np.maximum(dense, 0.0)
    idx = np.argsort(-dense, axis=1)[:, :k]
    w = np.take_along_axis(dense, idx, 1)
    w /= np.maximum(w.sum(1, keepdims=True), 1e-12)
    return idx, w


def reskin_scan(points: np.ndarray, skin_idx: np.ndarray, skin_w: np.ndarray, transforms_from: np.ndarray,
                transforms_to: np.ndarray, method: str = "lbs") -> np.ndarray:
    """Re-pose a posed scan (n, 3) by skinning it with the bone transforms that take the fitted
    pose to the new one, G_to G_from^-1 (both (J, 4, 4) from ``model.forward``): 'lbs' or
    'dqs'."""
    rel = np.einsum("jab,jbc->jac", transforms_to, np.linalg.inv(transforms_from))
    if method == "dqs":
        return dqs_skin(points, rel, skin_idx, skin_w)
    if method == "lbs":
        return lbs.skin(points, rel, skin_idx, skin_w)
    raise ValueError(f"method must be one of {SKINNING}")

"""The body model as the fit sees it (editing paper, Sec. 4.1): the posed model on a vertex subset
(:class:`_Rig`, :class:`_State`, :class:`_Sub`, :class:`_Posed`), its Jacobians in pose and
shape, the smoothness and posture-anchor terms and the joint limits. Pure numpy.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from service.model.body.model import BONES
from service.model.body.lbs import axis_angle_to_matrix, bone_hops, global_transforms, matrix_to_axis_angle
from service.model.geometry import kernels
from service.model.geometry.mesh import face_incidence
from service.model.geometry.solvers import edge_incidence
from service.model.fitting.regions import face_region, finger_region, hair_back_region, scalp_region


# -- the model as data for fitting ------------------------------------------------------------
@dataclass
class _Rig:
    """Body-surface data of the model in float64: mean (n, 3), U (K, n, 3), joint mean (17, 3)
    and joint directions (K, 17, 3), dense LBS weights W (n, 17), faces, edges, subtree
    indicator S (17, 17) with S[b, j] = 1 when j is in b's subtree, prior precisions (K,)."""

    mean: np.ndarray
    U: np.ndarray
    jmean: np.ndarray
    jdirs: np.ndarray
    W: np.ndarray
    faces: np.ndarray
    edges: np.ndarray
    incidence: sp.csr_matrix
    laplacian: sp.csc_matrix
    parents: np.ndarray
    subtree: np.ndarray
    precision: np.ndarray
    posture: np.ndarray  # (3 * 16, K): the shape's change of each bone's direction (see _posture_matrix)
    area: np.ndarray  # (n,) the mean rest body's surface area per vertex (a third of each incident face's), m^2
    hops: np.ndarray  # (17, 17) int: bones between two bones in the skeleton (bone_hops)
    scalp: np.ndarray  # (n,) bool: where hair may stand off the skin (scalp_region)
    face: np.ndarray  # (n,) bool: the head's vertices but the scalp (FitParams.face_shape_min_seen)
    hair_back: np.ndarray  # (n,) bool: where long hair may cover the back (hair_back_region)
    fingers: np.ndarray  # (n,) bool: the fingers, beyond the knuckles (finger_region)
    stature_ids: tuple  # (top vertex, sole vertices (m,)): the stature's ends (measurements)
    subsets: dict = field(default_factory=dict)


@functools.lru_cache(maxsize=4)
def _rig(model) -> _Rig:
    n = model.n_body_vertices
    K = model.n_components
    full_mean = model.mean.astype(np.float64)
    comps = model.components.astype(np.float64)
    jreg = model.joint_regressor
    jmean = np.asarray(jreg @ full_mean)
    jdirs = np.stack([np.asarray(jreg @ comps[k]) for k in range(K)])
    W = np.zeros((n, len(model.bone_parents)))
    np.add.at(W, (np.repeat(np.arange(n), 4), model.lbs_indices[:n].ravel()),
              model.lbs_weights[:n].astype(np.float64).ravel())
    faces = np.asarray(model.body_faces, np.int64)
    edges, B = edge_incidence(faces, n)
    parents = np.asarray(model.bone_parents)
    J = len(parents)
    subtree = np.eye(J)
    for j in range(J - 1, 0, -1):  # children follow parents: accumulate bottom-up
        subtree[parents[j]] += subtree[j]
    return _Rig(mean=full_mean[:n], U=comps[:, :n], jmean=jmean, jdirs=jdirs, W=W, faces=faces,
                edges=edges, incidence=face_incidence(faces, n), laplacian=(B.T @ B).tocsc(),
                parents=parents, subtree=(subtree > 0).astype(np.float64),
                precision=1.0 / np.maximum(model.variances.astype(np.float64), 1e-12),
                posture=_posture_matrix(jmean, jdirs, parents), area=vertex_areas(full_mean[:n], faces),
                hops=bone_hops(parents), scalp=scalp_region(full_mean[:n], faces, W),
                face=face_region(full_mean[:n], faces, W),
                hair_back=hair_back_region(full_mean[:n], faces, W, jmean),
                fingers=finger_region(full_mean[:n], W, jmean),
                stature_ids=(int(model.measurement_spec.top), np.asarray(model.measurement_spec.soles, np.int64)))


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) a third of the area of each face incident to each vertex; vertices (n, 3), faces (F, 3)."""
    v = vertices[faces]
    a = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    out = np.zeros(len(vertices))
    np.add.at(out, faces.ravel(), np.repeat(a / 3.0, 3))
    return out


def _posture_matrix(jmean: np.ndarray, jdirs: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(3 (J - 1), K): A beta stacks, for every bone j with a parent p, the part of the rest bone
    vector's change (joint j - joint p, linear in beta: jdirs) perpendicular to the mean bone
    direction. Shape weights with A beta = 0 change bone lengths, not posture: ||A beta||^2 is
    the penalty that keeps posture in the bone rotations (shape and posture decoupled)."""
    rows = []
    for j, p in enumerate(parents):
        if p < 0:
            continue
        u = jmean[j] - jmean[p]
        u = u / max(np.linalg.norm(u), 1e-12)
        rows.append((np.eye(3) - np.outer(u, u)) @ (jdirs[:, j] - jdirs[:, p]).T)
    return np.concatenate(rows)


# -- state and its Jacobians -------------------------------------------------------------------
@dataclass
class _State:
    beta: np.ndarray  # (K,)
    rot: np.ndarray  # (17, 3, 3) local rotations
    trans: np.ndarray  # (3,)

    def copy(self) -> "_State":
        return _State(self.beta.copy(), self.rot.copy(), self.trans.copy())


@dataclass
class _Sub:
    """A subset of the template's vertices with its data laid out for the updates: idx (m,),
    mean (m, 3), Ut (m, 3, K) shape directions, W (m, 17) LBS weights."""

    idx: np.ndarray
    mean: np.ndarray
    Ut: np.ndarray
    W: np.ndarray
    area: np.ndarray  # (m,) surface area per vertex over its mean (1 on average)
    region: np.ndarray  # (m,) int: the body region, the vertex's dominant bone


def _subset(rig: _Rig, idx: np.ndarray) -> _Sub:
    idx = np.asarray(idx)
    key = idx.tobytes()
    if key in rig.subsets:
        return rig.subsets[key]
    W = rig.W[idx]
    area = rig.area[idx]
    sub = _Sub(idx=idx, mean=rig.mean[idx], Ut=np.ascontiguousarray(rig.U[:, idx].transpose(1, 2, 0)),
               W=W, area=area / max(float(area.mean()), 1e-12), region=np.argmax(W, axis=1))
    if len(rig.subsets) < 8:  # the fit's fixed subsets, kept with the model
        rig.subsets[key] = sub
    return sub


@dataclass
class _Posed:
    v: np.ndarray  # (m, 3) posed vertices
    rest: np.ndarray  # (m, 3) rest vertices
    joints: np.ndarray  # (17, 3) rest joints
    G: np.ndarray  # (17, 4, 4) global transforms
    M: np.ndarray  # (m, 3, 3) blended rotations sum_j w_ij R_j
    sub: _Sub


def _flat(G: np.ndarray) -> np.ndarray:
    """(J, 4, 4) transforms -> (J, 12) rows [R.ravel(), t]."""
    return np.concatenate([G[:, :3, :3].reshape(len(G), 9), G[:, :3, 3]], axis=1)


def _pose_model(rig: _Rig, s: _State, sub: _Sub) -> _Posed:
    """M(beta, theta) on the template vertices of ``sub`` (the editing paper's Eq. 1, LBS form)."""
    rest = sub.mean + sub.Ut @ s.beta
    joints = rig.jmean + np.tensordot(s.beta, rig.jdirs, axes=1)
    G = global_transforms(joints, rig.parents, s.rot, s.trans)
    A = sub.W @ _flat(G)  # blended transforms (m, 12)
    M = A[:, :9].reshape(-1, 3, 3)
    v = (M @ rest[:, :, None])[:, :, 0] + A[:, 9:]
    return _Posed(v=v, rest=rest, joints=joints, G=G, M=M, sub=sub)


def _pose_jacobian(rig: _Rig, p: _Posed, bones: np.ndarray, comps: np.ndarray | None = None,
                   compiled: bool = True) -> np.ndarray:
    """(m, 3, 3 + 3 len(bones)): d v_i / d(translation, dw_b for b in bones), where dw_b rotates
    bone b's subtree in the world frame about its posed joint q_b, moving v_i by
    dw_b x (S_b(i) - W_b(i) q_b) with S_b(i) = sum_{j in subtree(b)} w_ij G_j(x_i).
    With ``comps``: (m, 3, 3 + 3 len(bones) + len(comps)), the shape Jacobian
    (``_shape_jacobian``) in the last columns, written in place (no concatenated copy).
    ``compiled`` (and numba there): the pose columns by ``kernels.pose_jacobian_into`` (each
    vertex visits only its non-zero weights), else the numpy reference below."""
    m = len(p.v)
    nb = len(bones)
    npz = 3 + 3 * nb
    q = np.einsum("jab,jb->ja", p.G[:, :3, :3], p.joints) + p.G[:, :3, 3]  # posed joints (17, 3)
    J = np.empty((m, 3, npz + (0 if comps is None else len(comps))))
    if compiled and kernels.AVAILABLE:
        kernels.pose_jacobian_into(np.ascontiguousarray(p.rest), np.ascontiguousarray(p.G),
                                   np.ascontiguousarray(p.sub.W), rig.subtree[bones], q[bones], J)
    else:
        per_bone = p.rest @ p.G[:, :3, :3].transpose(0, 2, 1) + p.G[:, None, :3, 3]  # (17, m, 3)
        contrib = p.sub.W.T[:, :, None] * per_bone  # w_ij G_j(x_i)
        sub = rig.subtree[bones]  # (nb, 17)
        S = np.tensordot(sub, contrib, axes=1)  # (nb, m, 3)
        arm = (S - (sub @ p.sub.W.T)[:, :, None] * q[bones][:, None, :]).transpose(1, 2, 0)  # (m, 3, nb)
        J[:, :, :3] = np.eye(3)
        J4 = J[:, :, 3:npz].reshape(m, 3, nb, 3)  # a view: (vertex, coordinate, bone, rotation axis)
        # -[arm]x, the cross-product matrix of dw x arm
        J4[:, 0, :, 0], J4[:, 0, :, 1], J4[:, 0, :, 2] = 0.0, arm[:, 2], -arm[:, 1]
        J4[:, 1, :, 0], J4[:, 1, :, 1], J4[:, 1, :, 2] = -arm[:, 2], 0.0, arm[:, 0]
        J4[:, 2, :, 0], J4[:, 2, :, 1], J4[:, 2, :, 2] = arm[:, 1], -arm[:, 0], 0.0
    if comps is not None:
        _shape_jacobian(rig, p, comps, out=J[:, :, npz:])
    return J


def _shape_jacobian(rig: _Rig, p: _Posed, comps: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(m, 3, len(comps)): d v_i / d beta_k with the rotations fixed. The rest vertex moves by
    U_k and every joint by its regressed direction, which moves each bone's translation
    t_j = R_parent p_j - R_j p_j + t_parent (forward kinematics, linear in the joints).
    ``out``: an (m, 3, len(comps)) array (a view) to write it into."""
    Rg = p.G[:, :3, :3]
    k = len(comps)  # the fits' components are a prefix: a view, not a copy (76 of them: 10 ms)
    Ut = p.sub.Ut[:, :, :k] if np.array_equal(comps, np.arange(k)) else p.sub.Ut[:, :, comps]
    dp = rig.jdirs[comps]  # (C, 17, 3)
    dt = np.zeros_like(dp)
    for j, par in enumerate(rig.parents):
        own = dp[:, j] - dp[:, j] @ Rg[j].T
        dt[:, j] = own if par < 0 else dp[:, j] @ Rg[par].T - dp[:, j] @ Rg[j].T + dt[:, par]
    out = np.matmul(p.M, Ut, out=out)  # (m, 3, C)
    out += (p.sub.W @ dt.transpose(1, 0, 2).reshape(17, -1)).reshape(-1, k, 3).transpose(0, 2, 1)
    return out


def _apply_pose(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, delta: np.ndarray) -> None:
    """Apply world-frame subtree rotations dw_b about the posed joints (first order: each local
    rotation becomes R_pg^T exp(dw_b) R_pg R_local, R_pg the parent's global rotation)."""
    s.trans = s.trans + delta[:3]
    E = axis_angle_to_matrix(delta[3:].reshape(-1, 3))
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0:
            s.rot[b] = E[c] @ s.rot[b]
        else:
            Rp = p.G[par, :3, :3]
            s.rot[b] = Rp.T @ E[c] @ Rp @ s.rot[b]


def _smoothness(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, omega: float):
    """Eq. 3's neighbouring-bone term omega sum ||theta_b - theta_parent(b)||^2 as the squared
    relative rotation r_b = rotvec(R_local_b); d r_b / d w_b = R_pg^T. Returns (H, g) over
    the pose parameters (3 + 3 len(bones))."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    a = matrix_to_axis_angle(s.rot)
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0:
            continue
        Rp = p.G[par, :3, :3]
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += omega * np.eye(3)
        g[sl] += omega * Rp @ a[b]
    return H, g


def _anchor_terms(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, rot: np.ndarray,
                  weight: float | np.ndarray):
    """A pull of each bone's local rotation towards a posture ``rot`` (17, 3, 3), the root's
    too: 1/2 sum_b weight_b ||r_b||^2 with r_b = rotvec(rot_b^T R_local_b), as Gauss-Newton
    terms with d r_b / d w_b = rot_b^T R_pg^T to first order (as ``_smoothness``; the root:
    R_pg = I); ``weight`` one for all bones or (17,) per bone. Returns (H, g) over the pose
    parameters (3 + 3 len(bones))."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    if np.all(np.asarray(weight) <= 0):
        return H, g
    r = matrix_to_axis_angle(np.einsum("bji,bjk->bik", rot, s.rot))  # rot_b^T R_b
    wb = np.broadcast_to(np.asarray(weight, np.float64), (len(rig.parents),))
    for c, b in enumerate(bones):
        if wb[b] <= 0:
            continue
        par = rig.parents[b]
        Rp = np.eye(3) if par < 0 else p.G[par, :3, :3]
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += wb[b] * np.eye(3)
        g[sl] += wb[b] * Rp @ rot[b] @ r[b]
    return H, g


# -- joint limits (issue 12): anatomical ranges per bone, hand-set ------------------------------
# Box limits (degrees) on each bone's local rotation vector (x, y, z), relative to the rest
# pose (A-pose, elbows a little bent, facing +Z, Y up, x to the body's left): for the legs x
# is flexion (thigh: negative = the leg forward; shin: positive = the knee bends), y the twist
# about the bone, z the sideways swing. The pelvis (the whole body's orientation) is free.
# Generous on purpose: they keep a fit out of impossible postures (a knee bent sideways, a
# forearm through the hip), not out of unusual ones.
JOINT_LIMITS_DEG: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "spine": ((-40, -30, -30), (40, 30, 30)),
    "chest": ((-35, -30, -30), (35, 30, 30)),
    "neck": ((-45, -60, -40), (45, 60, 40)),
    "head": ((-45, -60, -40), (45, 60, 40)),
    "upper_arm_l": ((-120, -120, -75), (120, 120, 120)),
    "upper_arm_r": ((-120, -120, -120), (120, 120, 75)),
    "forearm_l": ((-150, -150, -150), (150, 150, 150)),
    "forearm_r": ((-150, -150, -150), (150, 150, 150)),
    "hand_l": ((-80, -90, -60), (80, 90, 60)),
    "hand_r": ((-80, -90, -60), (80, 90, 60)),
    "thigh_l": ((-125, -50, -60), (40, 50, 60)),
    "thigh_r": ((-125, -50, -60), (40, 50, 60)),
    "shin_l": ((-20, -35, -20), (150, 35, 20)),
    "shin_r": ((-20, -35, -20), (150, 35, 20)),
    "foot_l": ((-50, -35, -35), (50, 35, 35)),
    "foot_r": ((-50, -35, -35), (50, 35, 35)),
}


@functools.lru_cache(maxsize=1)
def joint_limits() -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (17, 3) radians in BONES order from JOINT_LIMITS_DEG (-inf/inf: free)."""
    from service.model.body.model import BONES

    lo, hi = np.full((len(BONES), 3), -np.inf), np.full((len(BONES), 3), np.inf)
    for b, (l, h) in JOINT_LIMITS_DEG.items():
        lo[BONES.index(b)], hi[BONES.index(b)] = np.radians(l), np.radians(h)
    return lo, hi


def limit_violation(rotvecs: np.ndarray) -> np.ndarray:
    """(17, 3) radians by which each local rotation vector (17, 3) is outside its box (0 inside)."""
    lo, hi = joint_limits()
    return np.minimum(rotvecs - lo, 0.0) + np.maximum(rotvecs - hi, 0.0)


def _joint_limit_terms(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, weight: float):
    """The joint-limit penalty weight/2 sum_b ||v_b||^2 (v_b = ``limit_violation`` of the local
    rotation vector a_b) as Gauss-Newton terms (H, g) over the pose parameters (3 + 3 len(bones)),
    with d a_b / d w_b = J_l^-1(a_b) R_pg^T (the pose prior in Eq. 3)."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    if weight <= 0:
        return H, g
    a = matrix_to_axis_angle(s.rot)
    v = limit_violation(a)
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0 or not v[b].any():
            continue
        Jw = _left_jacobian_inv(a[b]) @ p.G[par, :3, :3].T  # d a_b / d w_b
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += weight * Jw.T @ np.diag((v[b] != 0).astype(float)) @ Jw
        g[sl] += weight * Jw.T @ v[b]
    return H, g


def _left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """(3, 3) d log(exp(d) R) / d d at d = 0 for R = exp(phi): the inverse left Jacobian of SO(3)."""
    t = float(np.linalg.norm(phi))
    K = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if t < 1e-6:
        return np.eye(3) - 0.5 * K
    t = min(t, np.pi - 1e-3)
    return np.eye(3) - 0.5 * K + (1 / t ** 2 - (1 + np.cos(t)) / (2 * t * np.sin(t))) * K @ K


def _bones(*names: str) -> np.ndarray:
    """(k,) int64: the bones' indices in the body model's BONES order."""
    return np.array([BONES.index(b) for b in names], np.int64)


ALL_BONES = np.arange(17)
ROOT_ONLY = _bones("pelvis")
# the coarse stage frees the skeleton from the root outwards
BONE_LEVELS = (
    _bones("pelvis"),
    _bones("pelvis", "spine", "thigh_l", "thigh_r"),
    _bones("pelvis", "spine", "chest", "thigh_l", "shin_l", "thigh_r", "shin_r"),
    _bones("pelvis", "spine", "chest", "neck", "upper_arm_l", "upper_arm_r", "thigh_l", "shin_l", "foot_l", "thigh_r",
           "shin_r", "foot_r"),
    ALL_BONES,
)


def _bone_ids(names) -> np.ndarray:
    return _bones(*names)

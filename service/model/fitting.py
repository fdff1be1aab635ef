"""Parametric body fitting of a clothed avatar, scan or point cloud (editing paper, Sec. 4.2,
Alg. 1), with an automatic initialisation and a clothing-aware data term.

Input: points (P, 3) float64 in the file's units and axes; normals (P, 3) unit or None
(estimated for point clouds); faces (F, 3) int or None (None: a point cloud). Output: the
body model's shape weights beta (K,), a pose theta (17 local bone rotations, axis-angle) and a
translation such that ``M(beta, theta)`` (the model's rest body, linear blend skinned) lies on
the scan, or just inside its clothes.

Our body model is the paper's revised SCAPE in its LBS form: rest shape ``mean + beta @ U``
(PCA, ``service.model.body``) and ``Q(theta)`` = LBS over 17 bones (``service.model.skinning``).

Stages:
1. Initialisation (the paper adjusts the pose by hand; here no human is in the loop): units
   from the size of the scan (m/cm/mm), the up axis from its principal axis (Y or Z up, either
   sign), the facing from a search over yaw angles scored by a rigid fit, then a coarse
   parametric ICP on subsamples with correspondences in both directions that frees the
   skeleton from the pelvis outwards (``BONE_LEVELS``) and then the main shape components, so
   limbs are pulled into the scan's pose; limbs caught in a local minimum are re-tried at
   discrete turns (``_limb_search``). The same ICP then refines pose and all shape components
   on more points.
2. Alg. 1: repeat { correspondences template -> scan (nearest point, rejected when normals differ
   by more than 30 degrees); repeat { update T (Eq. 2), update theta (Eq. 3), update beta (Eq. 4) }
   until 20 iterations or T moves < 1 mm } until 10 iterations or T moves < 5 mm.
   Eq. 2's matrix (edge Laplacian + correspondence weights) depends only on the correspondences,
   so it is factored once per outer iteration (``EdgeSystem``) and re-solved in the inner loop.
3. Clothing: a template vertex outside the scan (the body would poke through the clothes) keeps
   the full correspondence weight; inside (the clothes stand off the body) it gets
   ``inside_weight`` in the ICP and is dropped in Alg. 1 beyond ``alg1_inside_tol`` (Alg. 1's
   alternation is blind to weights: T, then the body, would follow loose clothes outwards); the
   shape is held by a Gaussian prior. The body ends inside the clothes, touching them where
   they are tight.
"""
from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.avatar_io import UNITS
from service.model.geometry import face_incidence, mesh_edges, vertex_normals
from service.model.skinning import axis_angle_to_matrix, global_transforms


class FitError(ValueError):
    """A scan that cannot be fitted (not a standing person, degenerate, ...); the message is
    meant for the customer."""


@dataclass(frozen=True)
class FitParams:
    """Weights and iteration limits of the fit (names follow the editing paper)."""

    # Alg. 1 loop limits and tolerances (metres)
    max_outer: int = 10
    max_inner: int = 20
    inner_tol: float = 0.001
    outer_tol: float = 0.005
    # correspondences
    normal_reject_deg: float = 30.0  # Sec. 4.2: rejected when normals differ by more
    max_corr_dist: float = 0.10  # metres; farther nearest points are not the same surface
    # Eq. 2
    alpha_point: float = 0.1
    alpha_plane: float = 1.0
    # Eq. 3: neighbouring-bone smoothness
    bone_smoothness: float = 0.1
    # clothing: weight of a correspondence whose template vertex is inside the scan
    inside_weight: float = 0.1
    # clothing in Alg. 1: correspondences more than this inside the scan are dropped there
    alg1_inside_tol: float = 0.003
    # Gaussian shape prior sum_k beta_k^2 / var_k, weighted against the data terms (sums of
    # squared metres over template vertices): s^2 makes it the posterior under per-coordinate
    # noise s
    shape_prior: float = 0.005 ** 2
    # the pose and shape updates use every n-th template vertex
    update_stride: int = 2
    # initialisation
    coarse_points: int = 2000
    coarse_iterations: int = 24
    coarse_shape_components: int = 12
    coarse_normal_reject_deg: float = 60.0
    coarse_max_dist: float = 0.25
    yaw_steps: int = 8
    robust_scale: float = 0.05  # metres: residuals beyond it are down-weighted (Huber-like)
    levenberg: float = 1e-3  # damping, relative to the mean diagonal of the normal equations
    max_rotation_step: float = 0.3  # radians per Gauss-Newton step
    min_accepted: float = 0.2  # fewer template vertices matching the scan: not a person
    coarse_candidates: int = 3
    limb_search: bool = True
    # neighbouring-bone smoothness while the pose is found (against per-point residuals
    # normalised to the subsample size): a prior that prefers the smaller of two rotations
    # that explain the scan equally well
    coarse_bone_smoothness: float = 0.1
    # refinement before Alg. 1: the same parametric ICP on more points with every component
    refine_points: int = 8000
    refine_iterations: int = 24
    run_alg1: bool = True
    damping: float = 1e-6


DEFAULT_PARAMS = FitParams()
MAX_HEIGHT_M, MIN_HEIGHT_M = 2.6, 0.9  # a standing, sitting or crouching adult


@dataclass
class FitResult:
    weights: np.ndarray  # (K,) PCA weights of the rest-pose body
    rotvecs: np.ndarray  # (17, 3) local axis-angle rotation per bone, BONES order
    translation: np.ndarray  # (3,) metres, model frame
    unit: str  # 'm' | 'cm' | 'mm' detected in the file
    up: str  # the file's up axis, e.g. '+y', '+z'
    to_model: np.ndarray  # (4, 4) similarity: file coordinates -> model frame (metres, Y up, +Z facing)
    residual_mm: float  # mean distance from the fitted posed body to the scan (accepted correspondences)
    posed_vertices: np.ndarray  # (V, 3) fitted body in the model frame
    outer_iterations: int = 0
    inner_iterations: int = 0
    seconds: float = 0.0
    stats: dict = field(default_factory=dict)


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
    edges = mesh_edges(faces)
    B = sp.csr_matrix((np.r_[np.ones(len(edges)), -np.ones(len(edges))],
                       (np.r_[np.arange(len(edges)), np.arange(len(edges))], np.r_[edges[:, 0], edges[:, 1]])),
                      shape=(len(edges), n))
    parents = np.asarray(model.bone_parents)
    J = len(parents)
    subtree = np.eye(J)
    for j in range(J - 1, 0, -1):  # children follow parents: accumulate bottom-up
        subtree[parents[j]] += subtree[j]
    return _Rig(mean=full_mean[:n], U=comps[:, :n], jmean=jmean, jdirs=jdirs, W=W, faces=faces,
                edges=edges, incidence=face_incidence(faces, n), laplacian=(B.T @ B).tocsc(),
                parents=parents, subtree=(subtree > 0).astype(np.float64),
                precision=1.0 / np.maximum(model.variances.astype(np.float64), 1e-12))


# -- state and its Jacobians -------------------------------------------------------------------
@dataclass
class _State:
    beta: np.ndarray  # (K,)
    rot: np.ndarray  # (17, 3, 3) local rotations
    trans: np.ndarray  # (3,)

    def copy(self) -> "_State":
        return _State(self.beta.copy(), self.rot.copy(), self.trans.copy())


def rotvecs_of(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> axis-angle (..., 3) radians."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R).reshape(-1, 3, 3)).as_rotvec().reshape(np.shape(R)[:-2] + (3,))


@dataclass
class _Sub:
    """A subset of the template's vertices with its data laid out for the updates: idx (m,),
    mean (m, 3), Ut (m, 3, K) shape directions, W (m, 17) LBS weights."""

    idx: np.ndarray
    mean: np.ndarray
    Ut: np.ndarray
    W: np.ndarray


def _subset(rig: _Rig, idx: np.ndarray) -> _Sub:
    idx = np.asarray(idx)
    key = idx.tobytes()
    if key in rig.subsets:
        return rig.subsets[key]
    W = rig.W[idx]
    sub = _Sub(idx=idx, mean=rig.mean[idx], Ut=np.ascontiguousarray(rig.U[:, idx].transpose(1, 2, 0)),
               W=W)
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


def _pose_jacobian(rig: _Rig, p: _Posed, bones: np.ndarray) -> np.ndarray:
    """(m, 3, 3 + 3 len(bones)): d v_i / d(translation, dw_b for b in bones), where dw_b rotates
    bone b's subtree in the world frame about its posed joint q_b, moving v_i by
    dw_b x (S_b(i) - W_b(i) q_b) with S_b(i) = sum_{j in subtree(b)} w_ij G_j(x_i)."""
    m = len(p.v)
    nb = len(bones)
    q = np.einsum("jab,jb->ja", p.G[:, :3, :3], p.joints) + p.G[:, :3, 3]  # posed joints (17, 3)
    per_bone = p.rest @ p.G[:, :3, :3].transpose(0, 2, 1) + p.G[:, None, :3, 3]  # (17, m, 3)
    contrib = p.sub.W.T[:, :, None] * per_bone  # w_ij G_j(x_i)
    sub = rig.subtree[bones]  # (nb, 17)
    S = np.tensordot(sub, contrib, axes=1)  # (nb, m, 3)
    arm = S - (p.sub.W @ sub.T).T[:, :, None] * q[bones][:, None, :]  # (nb, m, 3)
    J4 = np.zeros((m, 3, nb + 1, 3))
    J4[:, :, 0, :] = np.eye(3)
    # -[arm]x, the cross-product matrix of dw x arm
    J4[:, 0, 1:, 1], J4[:, 0, 1:, 2] = arm[..., 2].T, -arm[..., 1].T
    J4[:, 1, 1:, 0], J4[:, 1, 1:, 2] = -arm[..., 2].T, arm[..., 0].T
    J4[:, 2, 1:, 0], J4[:, 2, 1:, 1] = arm[..., 1].T, -arm[..., 0].T
    return J4.reshape(m, 3, 3 + 3 * nb)


def _shape_jacobian(rig: _Rig, p: _Posed, comps: np.ndarray) -> np.ndarray:
    """(m, 3, len(comps)): d v_i / d beta_k with the rotations fixed. The rest vertex moves by
    U_k and every joint by its regressed direction, which moves each bone's translation
    t_j = R_parent p_j - R_j p_j + t_parent (forward kinematics, linear in the joints)."""
    Rg = p.G[:, :3, :3]
    part = p.M @ p.sub.Ut[:, :, comps]  # (m, 3, C)
    dp = rig.jdirs[comps]  # (C, 17, 3)
    dt = np.zeros_like(dp)
    for j, par in enumerate(rig.parents):
        own = dp[:, j] - dp[:, j] @ Rg[j].T
        dt[:, j] = own if par < 0 else dp[:, j] @ Rg[par].T - dp[:, j] @ Rg[j].T + dt[:, par]
    return part + (p.sub.W @ dt.transpose(1, 0, 2).reshape(17, -1)).reshape(-1, len(comps), 3).transpose(0, 2, 1)


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
    a = rotvecs_of(s.rot)
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0:
            continue
        Rp = p.G[par, :3, :3]
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += omega * np.eye(3)
        g[sl] += omega * Rp @ a[b]
    return H, g


ALL_BONES = np.arange(17)
ROOT_ONLY = np.array([0])
# the coarse stage frees the skeleton from the root outwards (BONES order; see body.py)
BONE_LEVELS = (
    np.array([0]),  # pelvis
    np.array([0, 1, 11, 14]),  # + spine, thighs
    np.array([0, 1, 2, 11, 12, 14, 15]),  # + chest, shins
    np.array([0, 1, 2, 3, 5, 8, 11, 12, 13, 14, 15, 16]),  # + neck, upper arms, feet
    ALL_BONES,
)


# -- Eq. 2: the template update, factored once per correspondence set -------------------------
class EdgeSystem:
    """argmin_v' sum_edges ||(v'_a - v'_b) - e_ab||^2 + sum_i w_i (a_pt ||v'_i - c_i||^2
    + a_pl ||v'_i - pi_i||^2) (Eq. 2 of the editing paper, with its point-to-plane term
    n^T (v' - c) written as the distance to pi_i, the current v'_i projected onto c_i's tangent
    plane, and iterated in the inner loop). The matrix L + diag(w (a_pt + a_pl)) is the same
    for x, y and z and changes only with the correspondences: ``precompute`` factors it once
    (CHOLMOD when scikit-sparse is installed, else SuperLU) and ``solve`` back-substitutes."""

    def __init__(self, laplacian: sp.csc_matrix, diag: np.ndarray, eps: float = 1e-8,
                 backend: str | None = None):
        self.eps = eps
        self.diag = diag
        A = (laplacian + sp.diags(diag + eps)).tocsc()
        self.backend, self._solve = _factor(A, backend or solver_backend())

    @classmethod
    def precompute(cls, laplacian: sp.csc_matrix, diag: np.ndarray, backend: str | None = None) -> "EdgeSystem":
        return cls(laplacian, diag, backend=backend)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """rhs: (n, 3) -> v' (n, 3)."""
        return self._solve(rhs)


def _factor(A: sp.csc_matrix, backend: str):
    """A symmetric positive definite sparse matrix -> (backend, solve(rhs)): CHOLMOD's
    Cholesky (scikit-sparse) or SciPy's SuperLU."""
    if backend == "cholmod":
        from sksparse.cholmod import cholesky  # type: ignore[import-not-found]

        f = cholesky(A)
        return "cholmod", lambda b: f(np.asarray(b, np.float64))
    from scipy.sparse.linalg import splu

    lu = splu(A, permc_spec="COLAMD")
    return "superlu", lambda b: lu.solve(np.asarray(b, np.float64))


@functools.lru_cache(maxsize=1)
def solver_backend() -> str:
    """'cholmod' when scikit-sparse is importable, else 'superlu'."""
    try:
        import sksparse.cholmod  # noqa: F401  # type: ignore[import-not-found]

        return "cholmod"
    except ImportError:
        return "superlu"


# -- scan preparation and initialisation ------------------------------------------------------
def detect_scan_unit(points: np.ndarray) -> tuple[str, float]:
    """(unit, metres per unit) from the scan's largest extent: an adult standing or posed is
    0.9-2.6 m across its largest dimension."""
    ext = float(np.ptp(points, axis=0).max())
    for name, scale, _, _ in UNITS:
        if MIN_HEIGHT_M <= ext * scale <= MAX_HEIGHT_M:
            return name, scale
    raise FitError(f"cannot tell the units: the scan is {ext:g} units across (expected a person "
                   "0.9-2.6 m tall in metres, centimetres or millimetres)")


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _up_rotations(points: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Candidate rotations taking the scan's up axis to +Y: the coordinate axis closest to the
    principal axis of the points, either sign."""
    c = points - points.mean(0)
    _, _, Vt = np.linalg.svd(c[:: max(1, len(c) // 5000)], full_matrices=False)
    ax = int(np.argmax(np.abs(Vt[0])))
    out = []
    for sign in (1.0, -1.0):
        u = np.zeros(3)
        u[ax] = sign
        # the smallest rotation taking u to +Y (axis-aligned: a quarter or half turn)
        y = np.array([0.0, 1.0, 0.0])
        if np.allclose(u, y):
            R = np.eye(3)
        elif np.allclose(u, -y):
            R = np.diag([1.0, -1.0, -1.0])
        else:
            k = np.cross(u, y)
            R = axis_angle_to_matrix(k / np.linalg.norm(k) * (np.pi / 2))
        out.append(("+-"[sign < 0] + "xyz"[ax], R))
    return out


def _orient_outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Flip all normals when most point towards the scan's centre (an inside-out file)."""
    c = points.mean(0)
    return normals if np.mean(np.einsum("ij,ij->i", normals, points - c) > 0) >= 0.5 else -normals


@dataclass
class _Scan:
    points: np.ndarray  # (P, 3) model frame, metres
    normals: np.ndarray  # (P, 3)
    sub: np.ndarray  # indices of a subsample for the coarse stage
    sub_tree: cKDTree

    @functools.cached_property
    def tree(self) -> cKDTree:
        """All points (built only for the candidate that goes on to Alg. 1)."""
        return cKDTree(self.points)


def _make_scan(points: np.ndarray, normals: np.ndarray, R: np.ndarray, t: np.ndarray,
               n_sub: int, rng: np.random.Generator) -> _Scan:
    P = points @ R.T + t
    N = normals @ R.T
    sub = rng.choice(len(P), size=min(n_sub, len(P)), replace=False)
    return _Scan(P, N, sub, cKDTree(P[sub]))


def _posed_normals(rest_normals: np.ndarray, p: _Posed) -> np.ndarray:
    """Normals of posed vertices from rest normals rotated by the blended bone rotations."""
    n = (p.M @ rest_normals[:, :, None])[:, :, 0]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _clothing_weight(signed: np.ndarray, clothed: bool, params: FitParams) -> np.ndarray:
    """Weight of a correspondence by the side of the scan the body is on: ``signed`` > 0 is a
    body point outside the scan (through the clothes: full weight), < 0 inside."""
    if not clothed:
        return np.ones_like(signed)
    return np.where(signed >= 0, 1.0, params.inside_weight)


def _coarse(rig: _Rig, scan: _Scan, s: _State, sub: "_Sub", rest_normals: np.ndarray,
            schedule: list[tuple[np.ndarray, int]], clothed: bool, params: FitParams,
            omega: float | None = None) -> tuple[_State, float]:
    """Parametric ICP on subsamples: per iteration, correspondences both ways (template
    subsample -> nearest scan point, scan subsample -> nearest template vertex) rejected by
    normals and distance, point-to-plane residuals weighted for clothing, then one damped
    Gauss-Newton step on (translation, the scheduled bones, the first shape components).
    ``schedule``: [(bones, n_shape_components)] per iteration. Returns the state and the
    final trimmed mean distance (metres) both ways."""
    cos_rej = np.cos(np.radians(params.coarse_normal_reject_deg))
    Ps = scan.points[scan.sub]
    Ns = scan.normals[scan.sub]
    m = len(sub.idx)
    omega = params.coarse_bone_smoothness if omega is None else omega
    lam = params.shape_prior
    cost = np.inf
    for bones, n_shape in schedule:
        p = _pose_model(rig, s, sub)
        nv = _posed_normals(rest_normals, p)
        # template -> scan
        d1, j1 = scan.sub_tree.query(p.v)
        ok1 = (d1 < params.coarse_max_dist) & (np.einsum("ij,ij->i", nv, Ns[j1]) > cos_rej)
        # scan -> template
        d2, i2 = cKDTree(p.v).query(Ps)
        ok2 = (d2 < params.coarse_max_dist) & (np.einsum("ij,ij->i", nv[i2], Ns) > cos_rej)
        cost = 0.5 * (_trimmed_mean(d1) + _trimmed_mean(d2))
        if not (ok1.any() and ok2.any()):
            break
        a_i, a_n, a_c = np.nonzero(ok1)[0], Ns[j1[ok1]], Ps[j1[ok1]]
        b_i, b_n, b_c = i2[ok2], nv[i2[ok2]], Ps[ok2]
        vi = np.r_[a_i, b_i]
        nn = np.r_[a_n, b_n]
        cc = np.r_[a_c, b_c]
        r = np.einsum("ij,ij->i", nn, p.v[vi] - cc)
        w = _clothing_weight(r, clothed, params) * np.r_[np.full(len(a_i), m / len(a_i)),
                                                          np.full(len(b_i), m / len(b_i))]
        w = w / np.maximum(1.0, np.abs(r) / params.robust_scale)  # Huber-like: far pairs count less
        Jp = _pose_jacobian(rig, p, bones)
        comps = np.arange(n_shape)
        Jall = np.concatenate([Jp, _shape_jacobian(rig, p, comps)], axis=2) if n_shape else Jp
        H, g = _normal_equations(Jall, vi, nn, w, r)
        npz = Jp.shape[2]
        Hs, gs = _smoothness(rig, s, p, bones, omega)
        H[:npz, :npz] += Hs
        g[:npz] += gs
        if n_shape:
            H[npz:, npz:] += lam * np.diag(rig.precision[comps])
            g[npz:] += lam * rig.precision[comps] * s.beta[comps]
        H += (params.damping + params.levenberg * np.trace(H) / len(H)) * np.eye(len(H))
        delta = -np.linalg.solve(H, g)
        step = np.abs(delta[3:npz]).max(initial=0.0)
        if step > params.max_rotation_step:  # keep each rotation step small (linearisation)
            delta *= params.max_rotation_step / step
        _apply_pose(rig, s, p, bones, delta[:npz])
        if n_shape:
            s.beta[comps] += delta[npz:]
    return s, cost


def _normal_equations(Jac: np.ndarray, vi: np.ndarray, nn: np.ndarray, w: np.ndarray, r: np.ndarray):
    """Gauss-Newton normal equations of point-to-plane residuals r_k = n_k . (v_{vi_k} - c_k)
    with weights w_k: rows_k = n_k^T J_{vi_k}, H = rows^T W rows, g = rows^T W r.
    Jac: (m, 3, P)."""
    rows = sum(nn[:, a, None] * np.ascontiguousarray(Jac[:, a, :])[vi] for a in range(3))
    wr = rows * w[:, None]
    return rows.T @ wr, wr.T @ r


def _chamfer(rig: _Rig, scan: _Scan, s: _State, sub: _Sub) -> float:
    """Symmetric trimmed mean distance (m) between the template subsample and the scan's."""
    v = _pose_model(rig, s, sub).v
    d1, _ = scan.sub_tree.query(v)
    d2, _ = cKDTree(v).query(scan.points[scan.sub])
    return 0.5 * (_trimmed_mean(d1) + _trimmed_mean(d2))


# chains whose first bone is re-tried at discrete rotations (a limb caught in a local minimum)
SEARCH_BONES = (5, 8, 11, 14, 2, 6, 9, 12, 15)  # upper arms, thighs, chest, forearms, shins
SEARCH_ANGLE_DEG = 50.0


def _limb_search(rig: _Rig, scan: _Scan, s: _State, sub: _Sub, rest_normals: np.ndarray, clothed: bool,
                 params: FitParams) -> _State:
    """For each bone in SEARCH_BONES: try its local rotation turned by SEARCH_ANGLE_DEG about
    each axis (both ways), let the bone's subtree settle for a few ICP iterations, keep the
    candidate with the lowest symmetric distance to the scan."""
    best_cost = _chamfer(rig, scan, s, sub)
    for b in SEARCH_BONES:
        bones = np.nonzero(rig.subtree[b])[0]
        for axis in np.vstack([np.eye(3), -np.eye(3)]):
            cand = s.copy()
            cand.rot[b] = axis_angle_to_matrix(axis * np.radians(SEARCH_ANGLE_DEG)) @ cand.rot[b]
            cand, _ = _coarse(rig, scan, cand, sub, rest_normals, [(bones, 0)] * 3, clothed, params)
            cost = _chamfer(rig, scan, cand, sub)
            if cost < best_cost - 1e-4:
                best_cost, s = cost, cand
    return s


def _trimmed_mean(d: np.ndarray, keep: float = 0.9) -> float:
    d = np.sort(d)
    return float(d[: max(1, int(keep * len(d)))].mean())


def _initialise(rig: _Rig, points_m: np.ndarray, normals: np.ndarray, clothed: bool,
                params: FitParams, rng: np.random.Generator):
    """Up axis, facing and a coarse pose and shape (see module docstring). Returns
    (up label, R0 (3, 3), t0 (3,), scan in the model frame, state)."""
    n = len(rig.mean)
    idx = np.sort(rng.choice(n, size=min(params.coarse_points, n), replace=False))
    rest_normals = vertex_normals(rig.mean, rig.faces, rig.incidence)[idx]
    sub = _subset(rig, idx)
    model_centre = rig.mean.mean(0)
    candidates = []
    for up, Rup in _up_rotations(points_m):
        for k in range(params.yaw_steps):
            R = _yaw(2 * np.pi * k / params.yaw_steps) @ Rup
            P = points_m @ R.T
            t = np.array([model_centre[0], 0.0, model_centre[2]]) - np.array([P[:, 0].mean(), P[:, 1].min(), P[:, 2].mean()])
            candidates.append((up, R, t))
    screened = []
    for up, R, t in candidates:
        scan = _make_scan(points_m, normals, R, t, params.coarse_points, rng)
        s = _State(np.zeros(len(rig.U)), np.tile(np.eye(3), (17, 1, 1)), np.zeros(3))
        s, cost = _coarse(rig, scan, s, sub, rest_normals, [(ROOT_ONLY, 0)] * 5, clothed, params)
        screened.append((cost, up, R, t, scan, s))
    screened.sort(key=lambda x: x[0])
    best = None
    n_it = params.coarse_iterations
    per_level = max(1, n_it // (2 * len(BONE_LEVELS)))
    schedule = [(lv, 0) for lv in BONE_LEVELS for _ in range(per_level)]
    schedule += [(ALL_BONES, params.coarse_shape_components)] * max(1, n_it - len(schedule))
    for cost0, up, R, t, scan, s in screened[:params.coarse_candidates]:
        s, cost = _coarse(rig, scan, s, sub, rest_normals, schedule, clothed, params)
        if best is None or cost < best[0]:
            best = (cost, up, R, t, scan, s)
    _, up, R, t, scan, s = best
    if params.limb_search:
        s = _limb_search(rig, scan, s, sub, rest_normals, clothed, params)
        s, _ = _coarse(rig, scan, s, sub, rest_normals, schedule[-4:], clothed, params)
    return up, R, t, s, [c[0] for c in screened]


# -- Alg. 1 -----------------------------------------------------------------------------------
def _correspondences(T: np.ndarray, rig: _Rig, tree: cKDTree, points: np.ndarray, normals: np.ndarray,
                     clothed: bool, params: FitParams, cos_rej: float):
    """Nearest scan point of each template vertex, rejected when normals differ by more than
    the threshold or it is too far (Alg. 1, line 4). Returns (c, nc, weight (0 = rejected))."""
    nT = vertex_normals(T, rig.faces, rig.incidence)
    d, j = tree.query(T)
    c, nc = points[j], normals[j]
    ok = (np.einsum("ij,ij->i", nT, nc) >= cos_rej) & (d <= params.max_corr_dist)
    signed = np.einsum("ij,ij->i", T - c, nc)
    if clothed:  # Alg. 1's alternation would carry T, then the body, out to loose clothes
        ok &= signed >= -params.alg1_inside_tol
    w = ok.astype(np.float64)
    return c, nc, w


def fit_body(model, points: np.ndarray, normals: np.ndarray | None = None,
             faces: np.ndarray | None = None, *, clothed: bool = True,
             progress: Callable[[float, str], None] | None = None,
             params: FitParams = DEFAULT_PARAMS, seed: int = 0) -> FitResult:
    """Fit the body model to a scan (see the module docstring).

    points: (P, 3) file units and axes; normals: (P, 3) or None; faces: (F, 3) or None.
    Raises FitError when the scan cannot be fitted."""
    t_start = time.perf_counter()
    report = progress or (lambda f, m: None)
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 100 or not np.all(np.isfinite(pts)):
        raise FitError("the scan needs at least 100 finite 3D points")
    unit, scale = detect_scan_unit(pts)
    pts_m = pts * scale
    if normals is None:
        if faces is not None and len(faces):
            nrm = vertex_normals(pts_m, np.asarray(faces, np.int64))
        else:
            from service.model.scan_io import estimate_normals

            nrm = estimate_normals(pts_m)
    else:
        nrm = np.asarray(normals, np.float64)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    nrm = _orient_outward(pts_m, nrm)
    rig = _rig(model)
    rng = np.random.default_rng(seed)
    report(0.02, "initialising: units, up axis, facing, coarse pose")
    up, R0, t0, s, screen_costs = _initialise(rig, pts_m, nrm, clothed, params, rng)
    t_init = time.perf_counter() - t_start
    P = pts_m @ R0.T + t0
    N = nrm @ R0.T
    n = len(rig.mean)
    if params.refine_iterations:
        report(0.12, "refining pose and shape")
        scan = _make_scan(pts_m, nrm, R0, t0, params.refine_points, rng)
        ridx = np.sort(rng.choice(n, size=min(params.refine_points, n), replace=False))
        rn = vertex_normals(rig.mean, rig.faces, rig.incidence)[ridx]
        s, _ = _coarse(rig, scan, s, _subset(rig, ridx), rn,
                       [(ALL_BONES, len(rig.U))] * params.refine_iterations, clothed, params, omega=params.bone_smoothness)
        tree = scan.tree
    else:
        tree = cKDTree(P)
    t_refine = time.perf_counter() - t_start - t_init
    report(0.2, "fitting the body (Alg. 1)")

    upd = np.arange(0, n, max(1, params.update_stride))
    sw = float(params.update_stride)  # the update terms stand for all vertices
    cos_rej = np.cos(np.radians(params.normal_reject_deg))
    lam = params.shape_prior
    all_comps = np.arange(len(rig.U))
    full_sub, upd_sub = _subset(rig, np.arange(n)), _subset(rig, upd)
    T = _pose_model(rig, s, full_sub).v
    outer = inner_total = 0
    backend = None
    for outer in range(1, params.max_outer + 1 if params.run_alg1 else 1):
        T_outer = T.copy()
        c, nc, w = _correspondences(T, rig, tree, P, N, clothed, params, cos_rej)
        system = EdgeSystem.precompute(rig.laplacian, w * (params.alpha_point + params.alpha_plane))
        backend = system.backend
        for _ in range(params.max_inner):
            inner_total += 1
            T_prev = T
            # Eq. 2: update T with beta and theta fixed
            m = _pose_model(rig, s, full_sub).v
            pi = T - nc * np.einsum("ij,ij->i", T - c, nc)[:, None]
            rhs = rig.laplacian @ m + (w * params.alpha_point)[:, None] * c \
                + (w * params.alpha_plane)[:, None] * pi + system.eps * m
            T = system.solve(rhs)
            target = T[upd]
            # Eq. 3: update theta with T and beta fixed (one Gauss-Newton step)
            p = _pose_model(rig, s, upd_sub)
            Jp = _pose_jacobian(rig, p, ALL_BONES).reshape(-1, 3 + 3 * 17)
            r = (p.v - target).reshape(-1)
            H = sw * Jp.T @ Jp
            g = sw * Jp.T @ r
            Hs, gs = _smoothness(rig, s, p, ALL_BONES, params.bone_smoothness)
            delta = -np.linalg.solve(H + Hs + params.damping * np.eye(len(H)), g + gs)
            _apply_pose(rig, s, p, ALL_BONES, delta)
            # Eq. 4: update beta with T and theta fixed (linear least squares with the prior)
            p = _pose_model(rig, s, upd_sub)
            Jb = _shape_jacobian(rig, p, all_comps).reshape(-1, len(all_comps))
            r = (p.v - target).reshape(-1)
            Hb = sw * Jb.T @ Jb + lam * np.diag(rig.precision)
            gb = sw * Jb.T @ r + lam * rig.precision * s.beta
            s.beta = s.beta - np.linalg.solve(Hb, gb)
            if np.linalg.norm(T - T_prev, axis=1).max() <= params.inner_tol:
                break
        report(0.2 + 0.8 * outer / params.max_outer, f"outer iteration {outer}")
        if np.linalg.norm(T - T_outer, axis=1).max() <= params.outer_tol:
            break

    final = _pose_model(rig, s, full_sub).v
    c, nc, w = _correspondences(final, rig, tree, P, N, False, params, cos_rej)
    d = np.linalg.norm(final - c, axis=1)
    accepted = w > 0
    if accepted.mean() < params.min_accepted:
        raise FitError("the scan does not look like a person: fewer than 20 % of the body found "
                       "a matching surface")
    residual_mm = 1000 * float(d[accepted].mean())
    full = _full_posed(model, s)
    to_model = np.eye(4)
    to_model[:3, :3] = scale * R0
    to_model[:3, 3] = t0
    report(1.0, "done")
    return FitResult(
        weights=s.beta.copy(), rotvecs=rotvecs_of(s.rot), translation=s.trans.copy(), unit=unit, up=up,
        to_model=to_model, residual_mm=residual_mm, posed_vertices=full,
        outer_iterations=outer, inner_iterations=inner_total, seconds=time.perf_counter() - t_start,
        stats={"init_seconds": t_init, "refine_seconds": t_refine, "solver": backend, "accepted_fraction": float(accepted.mean()),
               "screen_costs_mm": [round(1000 * x, 1) for x in sorted(screen_costs)[:4]]},
    )


def _full_posed(model, s: _State) -> np.ndarray:
    """All V vertices of the fitted body, posed (model frame)."""
    from service.model.skinning import skin

    X = model.vertices(s.beta).astype(np.float64)
    G = global_transforms(np.asarray(model.joints(X)), np.asarray(model.bone_parents), s.rot, s.trans)
    return skin(X, G, model.lbs_indices, model.lbs_weights)

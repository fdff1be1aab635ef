"""Skin weights for garments: robust transfer from the body by weight inpainting.

Abdrashitov, Raichstat, Monsen, Hill, "Robust Skin Weights Transfer via Weight Inpainting"
(SIGGRAPH Asia 2023):

1. closest-point matching (Sec. 3.1): each garment vertex takes the body's weights
   interpolated (barycentric) at its closest point on the body surface; the match is *reliable*
   when the distance is below ``MAX_DISTANCE`` and the normals agree within ``MAX_ANGLE_DEG``
   (Eq. 1 and 2; garments are double-sided cloth, so a flipped normal counts as agreeing).
   Our addition: where neighbouring reliable matches jump (the garment bridges a crease such as
   the armpit, its vertices matched to the arm on one side and the torso on the other), the
   matches within ``JUMP_RADIUS`` are dropped too (:func:`weight_jumps`);
2. inpainting (Sec. 3.2, Eq. 3-4): the other vertices' weights W_u minimise the Dirichlet energy
   tr(W^T L W) of the garment mesh with the reliable weights W_k as constraints, i.e.
   L_uu W_u = -L_uk W_k, one factorisation for all bones;
3. the 4 largest weights per vertex are kept and renormalised (the GLB's JOINTS_0/WEIGHTS_0,
   like ``BodyModel.lbs_indices`` / ``lbs_weights``).

Nearest-vertex copying (the previous rule) makes neighbouring skirt vertices follow different
legs; the inpainted weights vary smoothly over the garment, so it stretches instead of tearing.

Shapes: garment vertices (M, 3), faces (F, 3); body vertices (V, 3), body faces (Fb, 3);
body lbs_indices / lbs_weights (V, 4); dense weights (n, J).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from service.model.geometry import closest_points_on_mesh, mesh_edges, vertex_normals
from service.model.nonrigid import factor_spd

MAX_DISTANCE = 0.02  # metres: a closest-point match farther than this is not reliable (Eq. 1)
MAX_ANGLE_DEG = 35.0  # normals must agree within this angle, up to sign (Eq. 2)
MAX_WEIGHT_GRADIENT = 40.0  # per metre: reliable matches that jump faster than this along a garment
# edge (the garment bridging a crease, e.g. the armpit, between arm and torso) are not reliable
JUMP_RADIUS = 0.04  # metres (geodesic over the garment edges) around such jumps also left to inpainting
TOP_K = 4  # joints per vertex in the GLB
REGULARISATION = 1e-9  # added to L_uu's diagonal: keeps the factorisation SPD in floating point


def dense_weights(indices: np.ndarray, weights: np.ndarray, n_joints: int) -> np.ndarray:
    """Sparse-by-rows skin weights (n, k) + (n, k) -> dense (n, J) float64."""
    n = len(indices)
    W = np.zeros((n, n_joints))
    np.add.at(W, (np.repeat(np.arange(n), indices.shape[1]), np.asarray(indices).reshape(-1)),
              np.asarray(weights, np.float64).reshape(-1))
    return W


def top_k(W: np.ndarray, k: int = TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """Dense weights (n, J) -> the k largest per row: indices (n, k) int32 (descending weight;
    index 0 where the weight is 0, as the glTF validator wants) and weights (n, k) float32
    summing to 1."""
    W = np.clip(np.asarray(W, np.float64), 0.0, None)
    idx = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, idx, axis=1)
    s = w.sum(axis=1, keepdims=True)
    empty = s[:, 0] <= 0
    w[empty] = 0.0
    w[empty, 0] = 1.0
    s[empty] = 1.0
    w = w / s
    idx = np.where(w > 0, idx, 0)
    return idx.astype(np.int32), w.astype(np.float32)


def uniform_laplacian(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """The graph Laplacian L = D - A (n, n) of the mesh edges (positive semi-definite)."""
    e = mesh_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


def closest_point_weights(vertices: np.ndarray, faces: np.ndarray, body_vertices: np.ndarray,
                          body_faces: np.ndarray, body_weights: np.ndarray, *,
                          max_distance: float = MAX_DISTANCE,
                          max_angle_deg: float = MAX_ANGLE_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: the body's dense weights (Vb, J) interpolated at each garment vertex's closest
    body point -> (weights (M, J) float64, reliable (M,) bool)."""
    X = np.asarray(vertices, np.float64)
    Vb = np.asarray(body_vertices, np.float64)
    Fb = np.asarray(body_faces, np.int64)
    face, q, bary = closest_points_on_mesh(X, Vb, Fb)
    W = np.einsum("mk,mkj->mj", bary, np.asarray(body_weights, np.float64)[Fb[face]])
    nb = vertex_normals(Vb, Fb).astype(np.float64)
    nq = np.einsum("mk,mkj->mj", bary, nb[Fb[face]])
    nq /= np.maximum(np.linalg.norm(nq, axis=1, keepdims=True), 1e-12)
    ng = vertex_normals(X, faces).astype(np.float64)
    dist = np.linalg.norm(X - q, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", ng, nq))
    reliable = (dist < max_distance) & (cos >= np.cos(np.radians(max_angle_deg)))
    return W, reliable


def weight_jumps(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, reliable: np.ndarray, *,
                 max_gradient: float = MAX_WEIGHT_GRADIENT, radius: float = JUMP_RADIUS) -> np.ndarray:
    """(M,) bool: vertices within ``radius`` (geodesic along the garment edges) of an edge
    between two reliable vertices whose weights (M, J) differ by more than ``max_gradient`` x the
    edge length (L1 norm): there the closest-point matches disagree (the garment spans a crease
    the body's weights cross over a longer path) and inpainting must decide instead."""
    X = np.asarray(vertices, np.float64)
    e = mesh_edges(faces)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    jump = np.abs(W[e[:, 0]] - W[e[:, 1]]).sum(axis=1) > max_gradient * length
    jump &= reliable[e[:, 0]] & reliable[e[:, 1]]
    seeds = np.unique(e[jump])
    if not len(seeds):
        return np.zeros(len(X), bool)
    n = len(X)
    graph = sp.coo_matrix((np.r_[length, length], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                          shape=(n, n)).tocsr()
    d = dijkstra(graph, directed=False, indices=seeds, min_only=True, limit=radius)
    return np.isfinite(d)


def inpaint(W: np.ndarray, known: np.ndarray, laplacian: sp.spmatrix) -> np.ndarray:
    """Step 2 (Eq. 3-4): weights (n, J) with rows ``known`` (n,) bool kept and the others the
    minimiser of tr(W^T L W): L_uu W_u = -L_uk W_k (factored once, J right-hand sides). Every
    connected component needs a known vertex (see :func:`transfer_skin_weights`)."""
    L = sp.csr_matrix(laplacian)
    u = np.flatnonzero(~known)
    k = np.flatnonzero(known)
    out = np.array(W, np.float64)
    if len(u) == 0:
        return out
    Luu = L[u][:, u] + sp.identity(len(u)) * REGULARISATION
    rhs = -(L[u][:, k] @ out[k])
    out[u] = factor_spd(Luu).solve(rhs)
    return out


def transfer_skin_weights(vertices: np.ndarray, faces: np.ndarray, body_vertices: np.ndarray,
                          body_faces: np.ndarray, lbs_indices: np.ndarray, lbs_weights: np.ndarray,
                          n_joints: int, *, max_distance: float = MAX_DISTANCE,
                          max_angle_deg: float = MAX_ANGLE_DEG,
                          k: int = TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """Garment skin weights from the body's: closest-point matches on reliable vertices,
    inpainted over the rest, top-k renormalised.

    vertices (M, 3), faces (F, 3): the garment on ``body_vertices`` (Vb, 3) / ``body_faces``;
    lbs_indices / lbs_weights (Vb, 4) the body's. Returns (indices (M, k) int32, weights (M, k)
    float32). A connected piece of the garment with no reliable vertex keeps the matches of its
    vertices nearest the body (its closest vertex is made reliable)."""
    faces = np.asarray(faces, np.int64)
    M = len(vertices)
    Wb = dense_weights(lbs_indices, lbs_weights, n_joints)
    W, reliable = closest_point_weights(vertices, faces, body_vertices, body_faces, Wb,
                                        max_distance=max_distance, max_angle_deg=max_angle_deg)
    reliable &= ~weight_jumps(vertices, faces, W, reliable)
    L = uniform_laplacian(faces, M)
    n_comp, labels = connected_components(L, directed=False)
    if n_comp:
        has = np.bincount(labels, weights=reliable.astype(np.float64), minlength=n_comp) > 0
        if not has.all():
            _, q, _ = closest_points_on_mesh(vertices, body_vertices, body_faces)
            d = np.linalg.norm(np.asarray(vertices, np.float64) - q, axis=1)
            for c in np.flatnonzero(~has):
                members = np.flatnonzero(labels == c)
                reliable[members[np.argmin(d[members])]] = True
    return top_k(inpaint(W, reliable, L), k)

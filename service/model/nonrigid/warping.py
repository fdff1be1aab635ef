"""The body-aware warping graph of the editing paper (Sec. 5.1-5.2, Eqs. 5-7). Pure numpy/scipy.

A graph G links a body M* (template topology: the body model's body surface) and a mesh A
attached to it (a garment draped on the body, or a clothed scan the body was fitted to). When
M* changes shape or pose, G's nodes follow it and carry A along.

Nodes: Poisson-disk samples on M* and on A (farthest-point sampling of dense area-weighted
surface samples: every pair of nodes is at least r apart and every sample is within r of a
node, i.e. a maximal Poisson-disk set), min(tau, |V_M*| + |V_A|) in all, split in proportion
to |V_M*| and |V_A|. Body nodes are stored as (face, barycentric) on M*, so the same nodes are
evaluated on any body of the same topology. Edges: each node to its 6 nearest nodes
(symmetric), bridged into one connected graph.

Unknowns: an affine map (R_j, t_j) per node; the deformed node is p_j = g_j + t_j. Eq. 5:

    argmin  Ec + wp Ep,   Ec = sum_j sum_{k in N(j)} |R_j (g_k - g_j) + g_j + t_j - (g_k + t_k)|^2   (Eq. 6)
                          Ep = sum_{j on M*} |g_j + t_j - v'_j|^2                                  (Eq. 7)

with v'_j the node's position on the new body. Written with p_j, Ec's residual is
R_j d_jk + p_j - p_k (d_jk = g_k - g_j): it has no constant term, and output coordinate r
involves only row r of each R_j and coordinate r of each p_j. So Eq. 5 splits into three
systems with the same matrix over x_j = (R_j[r, :], p_j[r]) (4 unknowns per node): the matrix
depends on the graph only and is factored once (``nonrigid.factor_spd``, CHOLMOD where
available); a new body is a new right-hand side wp S^T v' (three columns per body).

Regularisation (the only one): Ec fixes R_j only along the directions of node j's edges. On a
smooth surface those are nearly coplanar, so the column of R_j along the surface normal is
determined only through curvature, and on a flat patch not at all: the system is singular
(CHOLMOD refuses Ec + wp Ep of a real body and garment). We add

    Er = eps h^2 sum_j |R_j - F_j|_F^2          (h: mean edge length, eps = ``gradient_weight``)

F_j is the deformation gradient of the body under the node (its own face of M* for a body
node, the face of the nearest facing body node for a node of A): [e1' e2' n'] [e1 e2 n]^-1 of
the face's edge vectors and scaled normal n = (e1 x e2) / sqrt|e1 x e2| (Sumner and Popovic
2004), computed from the new body like v'. Er is zero for the identity and for any rigid
motion or uniform scaling of the body (F_j is then that motion), so it biases none of them; it
decides the direction Ec leaves free (the normal column) the way the body beneath moves; and it
makes the matrix positive definite for any connected graph with a body node.

Factoring: Er makes the R-block of the matrix block diagonal (3 x 3 per node), so the R_j are
eliminated exactly (Schur complement): the factored system has m unknowns (the node positions
p_j, one coordinate), not 4m: a quarter of the unknowns and a fifth of the fill, so one
back-substitution for three coordinates takes about a millisecond for 7,500 nodes.

A's vertices: each is a blend of the affines of its k nearest nodes (Sumner et al. 2007):
v' = sum_j w_j (R_j (v - g_j) + p_j), w_j proportional to (1 - |v - g_j| / d_max)^2, d_max
the distance to the (k+1)-th nearest node. That is linear in the unknowns: a sparse matrix D
(|V_A|, 4m) built once; with the R_j eliminated it becomes two sparse matrices over p and over
the F_j, so an update is one back-substitution and a sparse product.

Nodes whose surface normals face each other (an arm resting on the torso, the inner thighs)
are not joined and do not blend into each other's vertices (``WarpParams.min_normal_cos``):
otherwise moving the arm would drag torso cloth along. With body part labels (each vertex's
main bone and the skeleton's hops), parts that merely touch (crossed feet, a hand on the hip)
are kept apart the same way (``WarpParams.max_hops_body``). Both are additions to the paper's
plain 6 nearest neighbours (``min_normal_cos=None`` and no labels give the paper's graph).

Further body nodes without faces (``body_points``: the body model's helper-tights layer,
which clothes follow) may be added; the auto-fit and the editor use it.

Shapes: body vertices (V, 3) with faces (F, 3) into them; A's vertices (n, 3), faces (F_A, 3)
or None (a point cloud); m nodes (body nodes first); per output coordinate r the unknowns of
node j are x_j = (R_j[r, :], p_j[r]).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.model.geometry.mesh import estimate_normals, vertex_normals
from service.model.geometry.solvers import Factor, factor_spd


@dataclass(frozen=True)
class WarpParams:
    """Sizes and weights of the warping graph (names follow the editing paper, Sec. 5.1)."""

    max_nodes: int = 7500  # tau: at most this many nodes in all
    neighbours: int = 6  # edges from each node to its nearest nodes
    wp: float = 0.1  # Eq. 5: weight of the position term Ep
    blend_nodes: int = 6  # k nearest nodes blended into each vertex of A (Sumner et al. 2007 use 4)
    # Er (see the module docstring): eps of eps h^2 |R_j - F_j|^2 beside Ec (whose weight on
    # R_j along the surface is about 3 h^2 per node)
    gradient_weight: float = 1e-2
    # nodes whose normals make a larger angle are neither joined nor blended (surfaces that
    # face each other); None: the paper's plain nearest neighbours
    min_normal_cos: float | None = 0.0
    # with body labels (``precompute(body_labels=, label_hops=)``, e.g. each vertex's main bone and
    # the bones' distances in the skeleton): nodes more hops apart are neither joined nor
    # blended, so body parts that merely touch (crossed feet, a hand on the hip) stay apart.
    # Pairs with a body node allow fewer hops than pairs of A's nodes (a dress hem joins the legs)
    max_hops_body: int = 2
    max_hops_attached: int = 4
    candidates_per_node: int = 4  # dense surface samples per node for the Poisson-disk sampling
    seed: int = 0


DEFAULT_PARAMS = WarpParams()


# -- sampling ------------------------------------------------------------------------------------
def surface_samples(vertices: np.ndarray, faces: np.ndarray, n: int,
                    rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """n area-weighted uniform samples on a triangle mesh: (face (n,) int64, barycentric (n, 3))."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    cdf = np.cumsum(area)
    face = np.minimum(np.searchsorted(cdf, rng.uniform(0.0, cdf[-1], size=n), side="right"), len(F) - 1)
    r1, r2 = np.sqrt(rng.uniform(size=n)), rng.uniform(size=n)
    bary = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
    return face, bary


def farthest_point_sampling(points: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Indices (n,) of n of the points (P, 3), each the farthest from those chosen before
    (the first at random). The result is a maximal Poisson-disk set of the points with radius
    the last distance chosen. n >= P returns all of them.

    A new point can only bring closer the points within the current radius of it, so each step
    updates those (a k-d tree ball query) and a max-heap with lazy deletion finds the next."""
    import heapq

    P = np.asarray(points, np.float64)
    if n >= len(P):
        return np.arange(len(P))
    tree = cKDTree(P)
    out = np.empty(n, np.int64)
    out[0] = rng.integers(len(P))
    q = P - P[out[0]]
    d = np.einsum("ij,ij->i", q, q)
    heap = list(zip((-d).tolist(), range(len(P))))
    heapq.heapify(heap)
    for i in range(1, n):
        while True:
            negd, j = heapq.heappop(heap)
            if -negd == d[j]:
                break
        out[i] = j
        near = np.asarray(tree.query_ball_point(P[j], np.sqrt(d[j])), np.int64)
        q = P[near] - P[j]
        nd = np.einsum("ij,ij->i", q, q)
        closer = nd < d[near]
        near, nd = near[closer], nd[closer]
        d[near] = nd
        for key, idx in zip((-nd).tolist(), near.tolist()):
            heapq.heappush(heap, (key, idx))
    return out


def _orient_like_body(normals: np.ndarray, points: np.ndarray, faces: np.ndarray | None, body: np.ndarray,
                      body_normals: np.ndarray) -> np.ndarray:
    """A's normals (n, 3) flipped, per connected piece of A (all of it for a point cloud), where
    most disagree with the normal of the nearest body vertex: garments and scans come with
    either winding. Per piece, not per vertex: a loose sleeve's inner side faces the torso
    and must keep its own normal."""
    agree = np.einsum("ij,ij->i", normals, body_normals[cKDTree(body).query(points)[1]])
    if faces is not None and len(faces):
        F = np.asarray(faces, np.int64)
        n = len(points)
        A = sp.coo_matrix((np.ones(2 * len(F)), (np.r_[F[:, 0], F[:, 1]], np.r_[F[:, 1], F[:, 2]])), shape=(n, n))
        _, piece = connected_components(A, directed=False)
    else:
        piece = np.zeros(len(points), np.int64)
    vote = np.bincount(piece, weights=np.sign(agree))
    return np.where((vote[piece] < 0)[:, None], -normals, normals)


def _interpolate(values: np.ndarray, faces: np.ndarray, face: np.ndarray, bary: np.ndarray) -> np.ndarray:
    return np.einsum("nk,nkd->nd", bary, np.asarray(values, np.float64)[faces[face]])


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-12)


def barycentric_matrix(faces: np.ndarray, face: np.ndarray, bary: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(n, n_vertices) sparse: row i evaluates sample i = sum_k bary[i, k] vertices[faces[face[i], k]]."""
    n = len(face)
    return sp.csr_matrix((np.asarray(bary, np.float64).reshape(-1), (np.repeat(np.arange(n), 3),
                                                                     np.asarray(faces)[face].reshape(-1))),
                         shape=(n, n_vertices))


# -- the graph -----------------------------------------------------------------------------------
Compatible = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (i (n,), j (n, c)) -> may pair (n, c)


def knn_edges(points: np.ndarray, normals: np.ndarray, k: int, min_cos: float | None,
              compatible: Compatible | None = None) -> np.ndarray:
    """Undirected edges (E, 2) (low, high) from each point to its k nearest others, skipping
    those whose normals make a dot product below ``min_cos`` (None: no test) and pairs that
    ``compatible`` refuses."""
    m = len(points)
    filtered = min_cos is not None or compatible is not None
    kk = min(m - 1, 3 * k if filtered else k)
    if kk <= 0:
        return np.zeros((0, 2), np.int64)
    _, idx = cKDTree(points).query(points, k=kk + 1)
    idx = idx[:, 1:]
    ok = np.ones(idx.shape, bool)
    if min_cos is not None:
        ok = np.einsum("id,ikd->ik", normals, normals[idx]) >= min_cos
    if compatible is not None:
        ok &= compatible(np.arange(m), idx)
    rank = np.cumsum(ok, axis=1)
    keep = ok & (rank <= k)
    src = np.repeat(np.arange(m), kk)[keep.reshape(-1)]
    dst = idx[keep]
    e = np.sort(np.stack([src, dst], axis=1), axis=1)
    return np.unique(e, axis=0)


def bridge_components(points: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Add the shortest edge from each connected component to the rest (Boruvka steps) until
    the graph is connected. Returns all edges (E', 2)."""
    m = len(points)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    while True:
        A = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(m, m))
        n_comp, labels = connected_components(A, directed=False)
        if n_comp <= 1:
            return edges
        new = []
        for c in range(n_comp):
            inside = np.flatnonzero(labels == c)
            outside = np.flatnonzero(labels != c)
            d, j = cKDTree(points[outside]).query(points[inside])
            i = int(np.argmin(d))
            new.append(sorted((int(inside[i]), int(outside[j[i]]))))
        edges = np.unique(np.concatenate([edges, np.array(new, np.int64)]), axis=0)


def blend_weights(vertices: np.ndarray, vertex_normals_: np.ndarray, nodes: np.ndarray, node_normals: np.ndarray,
                  k: int, min_cos: float | None, compatible: Compatible | None = None,
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Sumner et al. (2007) weights of each vertex over its k nearest nodes (those facing away,
    normal dot below ``min_cos``, or refused by ``compatible`` (vertex ids, node ids), skipped):
    (node ids (n, k), weights (n, k), rows sum to 1; unused slots have weight 0)."""
    m = len(nodes)
    filtered = min_cos is not None or compatible is not None
    kk = min(m, 3 * (k + 1) if filtered else k + 1)
    d, idx = cKDTree(nodes).query(vertices, k=kk)
    d, idx = d.reshape(len(vertices), kk), idx.reshape(len(vertices), kk)
    ok = np.ones(idx.shape, bool)
    if min_cos is not None:
        ok = np.einsum("id,ikd->ik", vertex_normals_, node_normals[idx]) >= min_cos
    if compatible is not None:
        ok &= compatible(np.arange(len(vertices)), idx)
    if filtered:
        ok[~ok.any(axis=1), 0] = True  # nothing acceptable: the vertex's nearest node alone
    # the valid candidates first, in order of distance
    order = np.argsort(~ok, axis=1, kind="stable")
    d = np.take_along_axis(d, order, 1)
    idx = np.take_along_axis(idx, order, 1)
    nvalid = ok.sum(axis=1)
    kk_use = min(k, kk)
    use = np.arange(kk_use)[None, :] < np.minimum(nvalid, kk_use)[:, None]
    # d_max: the (k+1)-th valid node, else a little beyond the farthest used
    has_next = nvalid > kk_use
    dnext = np.where(has_next, d[:, min(kk_use, kk - 1)], 0.0)
    dlast = np.take_along_axis(d, (np.minimum(nvalid, kk_use) - 1)[:, None], 1)[:, 0]
    dmax = np.where(has_next, dnext, 1.5 * dlast)
    dmax = np.maximum(dmax, 1e-12)
    w = np.where(use, (1.0 - d[:, :kk_use] / dmax[:, None]) ** 2, 0.0)
    s = w.sum(axis=1)
    bad = s <= 1e-20
    w[bad] = 0.0
    w[bad, 0] = 1.0
    s[bad] = 1.0
    return idx[:, :kk_use], w / s[:, None]


def assemble_matrix(nodes: np.ndarray, edges: np.ndarray, n_body_nodes: int, wp: float,
                    reg: float) -> sp.csc_matrix:
    """The (4m, 4m) normal matrix of Ec + wp Ep + Er (Eqs. 6-7 and the regulariser) for one
    output coordinate r, unknowns x_j = (R_j[r, :], p_j[r]) at rows 4j..4j+3 (node-major).
    Ec has one residual per directed edge (j, k): R_j[r] . d_jk + p_j - p_k; Ep one per body
    node: sqrt(wp) p_j[r]; Er three per node: sqrt(reg) R_j[r, :] (reg = eps h^2)."""
    m = len(nodes)
    e = np.asarray(edges, np.int64)
    j = np.concatenate([e[:, 0], e[:, 1]])
    k = np.concatenate([e[:, 1], e[:, 0]])
    d = nodes[k] - nodes[j]  # d_jk
    nr = len(j)
    rows = np.repeat(np.arange(nr), 5)
    cols = np.stack([4 * j, 4 * j + 1, 4 * j + 2, 4 * j + 3, 4 * k + 3], axis=1).reshape(-1)
    vals = np.concatenate([d, np.ones((nr, 1)), -np.ones((nr, 1))], axis=1).reshape(-1)
    C = sp.csr_matrix((vals, (rows, cols)), shape=(nr, 4 * m))
    diag = np.zeros((m, 4))
    diag[:, :3] = reg
    diag[:n_body_nodes, 3] = wp
    return sp.csc_matrix(C.T @ C + sp.diags(diag.reshape(-1)))


def blend_matrix(vertices: np.ndarray, nodes: np.ndarray, idx: np.ndarray, w: np.ndarray) -> sp.csr_matrix:
    """D (n, 4m), node-major like :func:`assemble_matrix`:
    v'_i[r] = sum_j w_ij (R_j[r] . (v_i - g_j) + p_j[r]) = (D x_r)[i]."""
    n, k = idx.shape
    m = len(nodes)
    rel = np.asarray(vertices, np.float64)[:, None, :] - nodes[idx]  # (n, k, 3)
    vals = np.concatenate([w[..., None] * rel, w[..., None]], axis=2).reshape(-1)
    cols = (4 * idx[..., None] + np.arange(4)).reshape(-1)
    rows = np.repeat(np.arange(n), 4 * k)
    D = sp.csr_matrix((vals, (rows, cols)), shape=(n, 4 * m))
    D.eliminate_zeros()
    return D


def _block_diag(blocks: np.ndarray) -> sp.csr_matrix:
    """(m, 3, 3) -> the (3m, 3m) block-diagonal sparse matrix."""
    m = len(blocks)
    rows = np.repeat(np.arange(3 * m), 3)
    cols = (3 * np.arange(m)[:, None, None] + np.zeros((1, 3, 1), np.int64) + np.arange(3)).reshape(-1)
    return sp.csr_matrix((blocks.reshape(-1), (rows, cols)), shape=(3 * m, 3 * m))


def face_frames(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[e1 e2 n] per face (F, 3, 3) (columns): edge vectors v1 - v0, v2 - v0 and the normal
    scaled to sqrt(|e1 x e2|) (Sumner and Popovic 2004). vertices (V, 3) or (B, V, 3)."""
    V = np.asarray(vertices, np.float64)
    t = V[..., faces, :]  # (..., F, 3, 3)
    e1, e2 = t[..., 1, :] - t[..., 0, :], t[..., 2, :] - t[..., 0, :]
    c = np.cross(e1, e2)
    n = c / np.sqrt(np.maximum(np.linalg.norm(c, axis=-1, keepdims=True), 1e-30))
    return np.stack([e1, e2, n], axis=-1)


@dataclass
class WarpGraph:
    """The warping graph G between a body M* and an attached mesh A (see the module
    docstring). Build with :meth:`precompute`; then :meth:`warp` per new body (or a batch)."""

    params: WarpParams
    nodes: np.ndarray  # (m, 3) rest node positions g_j (body nodes first)
    node_normals: np.ndarray  # (m, 3)
    n_body_nodes: int  # mb
    body_face: np.ndarray  # (ms,) face of M* under each surface node (the first ms body nodes)
    body_bary: np.ndarray  # (ms, 3) its barycentric coordinates
    body_point_ids: np.ndarray  # (mb - ms,) vertex of each further body node (``body_points``)
    body_vertex_ids: np.ndarray  # (u,) the vertices of M* that the graph reads
    local_faces: np.ndarray  # (nf, 3) faces of the gradients F_j, into body_vertex_ids
    node_face: np.ndarray  # (m,) each node's gradient face (index into local_faces)
    frame_inv: np.ndarray  # (nf, 3, 3) inverse rest frames of those faces
    node_eval: sp.csr_matrix  # (mb, u): body nodes = node_eval @ body[body_vertex_ids]
    edges: np.ndarray  # (E, 2) undirected, (low, high)
    spacing: float  # h, mean edge length
    reg: float  # eps h^2
    factor: Factor  # the Schur complement S over p (m, m)
    rhs_a: sp.csr_matrix  # (m, 3m): S p = b_p - rhs_a b_a
    out_p: sp.csr_matrix  # (n, m)   A' = out_p p + out_a b_a
    out_a: sp.csr_matrix  # (n, 3m)
    r_from_p: sp.csr_matrix  # (3m, m): R rows a = r_from_b b_a - r_from_p p
    r_from_b: sp.csr_matrix  # (3m, 3m)
    blend_idx: np.ndarray  # (n, k) blend nodes of A's vertices
    blend_w: np.ndarray  # (n, k) their weights

    @property
    def n_nodes(self) -> int:
        return len(self.nodes)

    @property
    def n_attached(self) -> int:
        return self.out_p.shape[0]

    # -- build -----------------------------------------------------------------------------
    @classmethod
    def precompute(cls, body_vertices: np.ndarray, body_faces: np.ndarray, attached: np.ndarray,
                   attached_faces: np.ndarray | None = None, params: WarpParams = DEFAULT_PARAMS, *,
                   attached_normals: np.ndarray | None = None, body_points: np.ndarray | None = None,
                   body_labels: np.ndarray | None = None, label_hops: np.ndarray | None = None,
                   backend: str | None = None, progress: Callable[[float, str], None] | None = None,
                   ) -> "WarpGraph":
        """Build G on M* = (body_vertices (V, 3), body_faces (F, 3)) and A = attached (n, 3)
        with faces (F_A, 3) or None (a point cloud; normals estimated unless given), assemble
        Eq. 5 + Er, eliminate the R_j and factor. Deterministic for a given ``params.seed``.

        ``body_points``: ids of further vertices of M* that are body nodes' candidates without
        faces (the body model's ``helper-tights`` surface, which MakeHuman garments follow),
        sampled among themselves and counted with M*'s vertices.

        ``body_labels`` (V,) int and ``label_hops`` (L, L): a part label per body vertex and the
        distances between parts (see ``WarpParams.max_hops_body``); A's nodes and vertices take
        the label of their nearest facing body node."""
        report = progress or (lambda f, m: None)
        rng = np.random.default_rng(params.seed)
        BV = np.asarray(body_vertices, np.float64)
        BF = np.asarray(body_faces, np.int64)
        used = np.unique(BF)
        pts = np.zeros(0, np.int64) if body_points is None else np.asarray(body_points, np.int64)
        nV = len(used) + len(pts)  # |V_M*|: the vertices of the body surface (and extra body points)
        AV = np.asarray(attached, np.float64)
        nA = len(AV)
        total = min(params.max_nodes, nV + nA)
        mb = min(max(4, int(round(total * nV / (nV + nA)))), total - 1)
        ma = total - mb
        mp = int(round(mb * len(pts) / nV))
        ms = mb - mp

        # body nodes: Poisson-disk samples on M*, kept as (face, barycentric), then the extra
        # body points (kept as vertex ids)
        report(0.0, "sampling graph nodes")
        cf, cb = surface_samples(BV, BF, max(ms * params.candidates_per_node, ms), rng)
        pick = farthest_point_sampling(_interpolate(BV, BF, cf, cb), ms, rng)
        body_face, body_bary = cf[pick], cb[pick]
        n_body_v = vertex_normals(BV, BF).astype(np.float64)
        g_surf = _interpolate(BV, BF, body_face, body_bary)
        n_surf = _unit(_interpolate(n_body_v, BF, body_face, body_bary))
        point_ids = pts[farthest_point_sampling(BV[pts], mp, rng)] if mp else pts[:0]
        near_surf = cKDTree(g_surf).query(BV[point_ids])[1] if mp else np.zeros(0, np.int64)
        g_body = np.concatenate([g_surf, BV[point_ids]])
        nb_body = np.concatenate([n_surf, n_surf[near_surf]])
        body_face_all = np.concatenate([body_face, body_face[near_surf]])

        # A's normals, oriented like the body's (scans and garments come with either winding):
        # the facing tests compare them with body normals
        if attached_normals is not None:
            nA_v = _unit(np.asarray(attached_normals, np.float64).copy())
        elif attached_faces is not None and len(attached_faces):
            nA_v = vertex_normals(AV, np.asarray(attached_faces, np.int64)).astype(np.float64)
        else:
            nA_v = estimate_normals(AV)
        nA_v = _orient_like_body(nA_v, AV, attached_faces, BV[used], n_body_v[used])

        # A's nodes: Poisson-disk samples on A (on its faces, or among its points)
        if attached_faces is not None and len(attached_faces):
            AF = np.asarray(attached_faces, np.int64)
            af, ab = surface_samples(AV, AF, max(ma * params.candidates_per_node, ma), rng)
            cand = _interpolate(AV, AF, af, ab)
            pick = farthest_point_sampling(cand, ma, rng)
            g_att, n_att = cand[pick], _unit(_interpolate(nA_v, AF, af[pick], ab[pick]))
        else:
            pick = farthest_point_sampling(AV, ma, rng)
            g_att, n_att = AV[pick], nA_v[pick]
        nodes = np.concatenate([g_body, g_att])
        node_normals = np.concatenate([nb_body, n_att])
        m = len(nodes)

        # part labels (optional): body nodes from their vertices, A's nodes and vertices from the
        # nearest facing body node
        near_idx = blend_weights(g_att, n_att, g_body, nb_body, 1, params.min_normal_cos)[0][:, 0]
        pair_ok = vertex_ok = None
        if body_labels is not None and label_hops is not None:
            lab_b = np.asarray(body_labels)
            hops = np.asarray(label_hops)
            corner = BF[body_face, np.argmax(body_bary, axis=1)]
            node_lab = np.concatenate([lab_b[corner], lab_b[point_ids]])
            node_lab = np.concatenate([node_lab, node_lab[near_idx]])
            vert_lab = node_lab[blend_weights(AV, nA_v, g_body, nb_body, 1, params.min_normal_cos)[0][:, 0]]
            is_body = np.arange(len(node_lab)) < mb

            def pair_ok(i, j):
                lim = np.where(is_body[i][:, None] | is_body[j], params.max_hops_body, params.max_hops_attached)
                return hops[node_lab[i][:, None], node_lab[j]] <= lim

            def vertex_ok(i, j):
                lim = np.where(is_body[j], params.max_hops_body, params.max_hops_attached)
                return hops[vert_lab[i][:, None], node_lab[j]] <= lim

        # edges: the 6 nearest (facing) nodes, symmetric, bridged into one component
        report(0.3, "connecting graph nodes")
        edges = bridge_components(nodes, knn_edges(nodes, node_normals, params.neighbours, params.min_normal_cos,
                                                   pair_ok))
        h = float(np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1).mean())
        reg = params.gradient_weight * h * h

        # the gradient face of each node: its own (surface nodes), the nearest surface node's
        # (body points), the nearest facing body node's (A)
        grad_face = np.concatenate([body_face_all, body_face_all[near_idx]])
        uf, node_face = np.unique(grad_face, return_inverse=True)
        vid = np.unique(np.concatenate([BF[uf].reshape(-1), BF[body_face].reshape(-1), point_ids]))
        local_faces = np.searchsorted(vid, BF[uf])
        frame_inv = np.linalg.inv(face_frames(BV[vid], local_faces))
        node_eval = sp.vstack([barycentric_matrix(np.searchsorted(vid, BF), body_face, body_bary, len(vid)),
                               sp.csr_matrix((np.ones(mp), (np.arange(mp), np.searchsorted(vid, point_ids))),
                                             shape=(mp, len(vid)))]).tocsr()

        # Eq. 5 + Er, with the R_j eliminated (Schur complement over the p_j)
        report(0.5, "assembling and factoring Eq. 5")
        H = assemble_matrix(nodes, edges, mb, params.wp, reg).tocsr()
        ia = (4 * np.arange(m)[:, None] + np.arange(3)).reshape(-1)
        ip = 4 * np.arange(m) + 3
        Haa = H[ia][:, ia].tocoo()
        if np.any(Haa.row // 3 != Haa.col // 3):
            raise AssertionError("the R-block of Eq. 5 + Er must be block diagonal")
        blocks = np.zeros((m, 3, 3))
        np.add.at(blocks, (Haa.row // 3, Haa.row % 3, Haa.col % 3), Haa.data)
        Hinv = _block_diag(np.linalg.inv(blocks))
        Hap = H[ia][:, ip]
        Kp = (Hinv @ Hap).tocsr()  # (3m, m)
        S = (H[ip][:, ip] - Hap.T @ Kp).tocsc()
        factor = factor_spd((S + S.T) * 0.5, backend, mode="simplicial")

        report(0.8, "blend weights")
        idx, w = blend_weights(AV, nA_v, nodes, node_normals, params.blend_nodes, params.min_normal_cos, vertex_ok)
        D = blend_matrix(AV, nodes, idx, w).tocsc()
        Da, Dp = D[:, ia], D[:, ip]
        report(1.0, "warping graph ready")
        return cls(params=params, nodes=nodes, node_normals=node_normals, n_body_nodes=mb, body_face=body_face,
                   body_bary=body_bary, body_point_ids=point_ids, body_vertex_ids=vid, local_faces=local_faces, node_face=node_face,
                   frame_inv=frame_inv, node_eval=node_eval, edges=edges, spacing=h, reg=reg, factor=factor,
                   rhs_a=sp.csr_matrix(Kp.T), out_p=sp.csr_matrix(Dp - Da @ Kp), out_a=sp.csr_matrix(Da @ Hinv),
                   r_from_p=Kp, r_from_b=Hinv, blend_idx=idx, blend_w=w)

    # -- per body ----------------------------------------------------------------------------
    def body_subset(self, body_vertices: np.ndarray) -> np.ndarray:
        """The vertices the graph reads, from a full body: (V, 3) -> (u, 3); (B, V, 3) -> (B, u, 3)."""
        return np.asarray(body_vertices, np.float64)[..., self.body_vertex_ids, :]

    def body_targets(self, sub: np.ndarray) -> np.ndarray:
        """v'_j of Eq. 7, the body nodes on a new body: sub (u, 3) -> (mb, 3); (B, u, 3) -> (B, mb, 3)."""
        S = np.asarray(sub, np.float64)
        if S.ndim == 2:
            return self.node_eval @ S
        return (self.node_eval @ S.transpose(1, 0, 2).reshape(S.shape[1], -1)).reshape(
            self.n_body_nodes, len(S), 3).transpose(1, 0, 2)

    def gradients(self, sub: np.ndarray) -> np.ndarray:
        """F_j of Er, the body's deformation gradient under each node: sub (u, 3) -> (m, 3, 3);
        (B, u, 3) -> (B, m, 3, 3)."""
        F = face_frames(sub, self.local_faces) @ self.frame_inv
        return F[..., self.node_face, :, :]

    def _rhs(self, sub: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(b_a (3m, 3B), b_p (m, 3B)) for bodies sub (B, u, 3); body b in columns 3b..3b+2."""
        B, m, mb = len(sub), self.n_nodes, self.n_body_nodes
        F = self.gradients(sub)  # (B, m, 3, 3)
        b_a = self.reg * F.transpose(1, 3, 0, 2).reshape(3 * m, 3 * B)  # [3j + c, 3b + r] = F[b, j, r, c]
        b_p = np.zeros((m, 3 * B))
        b_p[:mb] = self.params.wp * self.body_targets(sub).transpose(1, 0, 2).reshape(mb, 3 * B)
        return b_a, b_p

    def solve(self, sub: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Eq. 5 + Er for new bodies: sub (B, u, 3) -> (p (m, 3B), b_a (3m, 3B))."""
        b_a, b_p = self._rhs(sub)
        return self.factor.solve(b_p - self.rhs_a @ b_a), b_a

    def warp_subset(self, sub: np.ndarray) -> np.ndarray:
        """A carried onto a new body given by its graph vertices: sub (u, 3) -> (n, 3);
        (B, u, 3) -> (B, n, 3). One back-substitution and two sparse products."""
        S = np.asarray(sub, np.float64)
        single = S.ndim == 2
        S = S[None] if single else S
        p, b_a = self.solve(S)
        Y = (self.out_p @ p + self.out_a @ b_a).reshape(self.n_attached, len(S), 3).transpose(1, 0, 2)
        return Y[0] if single else Y

    def warp(self, body_vertices: np.ndarray) -> np.ndarray:
        """A carried onto a new body of M*'s topology: (V, 3) -> (n, 3); (B, V, 3) -> (B, n, 3)."""
        return self.warp_subset(self.body_subset(body_vertices))

    def affines(self, body_vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The node affines solving Eq. 5 + Er for one body (V, 3): (R (m, 3, 3), t (m, 3)),
        p_j = g_j + t_j."""
        p, b_a = self.solve(self.body_subset(body_vertices)[None])
        a = self.r_from_b @ b_a - self.r_from_p @ p  # [3j + c, r] = R_j[r, c]
        return a.reshape(self.n_nodes, 3, 3).transpose(0, 2, 1), p - self.nodes

"""One garment draped on one body -> that garment fitted to every example avatar (issue 10).

A retailer has one 3D garment, draped on one body M* in the template topology (an example
avatar in its rest pose, or the retailer's own mannequin fitted by ``fitting.fit_body``). The
clothing basis (``tryon.build_garment_basis``) needs it fitted to each of the 1 + 2N example
avatars. Three steps, all batched over the examples:

1. **Warp** (editing paper Sec. 5.1, ``warping.WarpGraph``): the graph between M* and the
   garment A is built and factored once; each example is one more right-hand side (its body
   nodes' positions and gradients), so all examples are one back-substitution.
2. **Collisions**: no garment vertex may be inside the example's body. Each vertex keeps the
   gap it had on M* up to ``clearance`` (tight parts a small clearance; loose parts, farther
   out, are only moved if the warp took them inside): a vertex closer than that is moved to
   the closest body point plus the gap along the body normal, and the move is diffused over
   its garment neighbours (``garment.laplacian_smoother``) so the cloth stays smooth.
3. **Edge lengths**: cloth barely stretches. A few local/global iterations (as in Eq. 2's
   edge term, ``nonrigid.EdgeSystem``): locally each edge keeps its direction and has its
   length clamped to within ``edge_tolerance`` of the uploaded garment's; globally the
   vertices follow those edges and, weakly, the warped positions; then collisions again, so the
   result stays off the body. The matrix is the same for every example: factored once.

Shapes: garment vertices (M, 3), faces (F, 3); bodies in the template topology (V, 3), full or
the body surface only (``model.n_body_vertices``); metres.
"""
from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

from service.model.garments.garment import laplacian_smoother, push_out
from service.model.body.lbs import bone_hops, main_bone
from service.model.formats.mhclo import HELPER_TIGHTS
from service.model.geometry.mesh import closest_points_on_mesh, vertex_faces, vertex_normals
from service.model.geometry.solvers import EdgeSystem, edge_incidence
from service.model.nonrigid.warping import WarpGraph, WarpParams


@dataclass(frozen=True)
class AutofitParams:
    """Weights, distances (metres) and iteration limits of the fit."""

    warp: WarpParams = WarpParams()
    # the gap each vertex keeps: what it had on the draped body, clamped to [min_clearance,
    # clearance]. Small: a try-on pushes cloth out to 3 mm anyway, and a vertex that is moved
    # here is a non-linear change the clothing basis then has to interpolate
    clearance: float = 0.0015
    min_clearance: float = 0.001
    # vertices whose distance to the nearest body vertex's tangent plane exceeds their gap by
    # more than this are not tested exactly (the plane is within this of the surface there)
    contact_margin: float = 0.006
    collision_passes: int = 4
    closest_k: int = 4  # body vertices whose faces are searched for the closest point
    edge_iterations: int = 3
    # |edge strain| allowed before the projection acts. Between two bodies a garment must change
    # size somewhere (MakeHuman's own bindings stretch half the edges of a suit by more than
    # 10 % between two held-out bodies): the projection only reins in tears and spikes
    edge_tolerance: float = 0.20
    edge_anchor: float = 0.3  # weight of the collision-free warped positions beside the edges (1)
    # the body model's helper-tights surface (MakeHuman's skin-tight clothing layer, which moves
    # a little differently from the skin as the shape changes) as further body nodes
    follow_helper_tights: bool = True
    # the body farther than this from the garment gets no graph nodes (None: the whole body, as
    # in the paper): the nodes are denser where they carry the garment
    body_region: float | None = 0.05


DEFAULT_PARAMS = AutofitParams()


@dataclass
class AutofitResult:
    fits: np.ndarray  # (E, M, 3) float32 the garment on each target body
    stats: dict = field(default_factory=dict)


class BodyCollider:
    """Closest points and signed distances to one body surface (vertices (Vb, 3), faces)."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, vert_faces: np.ndarray, k: int = 8):
        self.vertices = np.asarray(vertices, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.vert_faces = vert_faces
        self.k = k
        self.tree = cKDTree(self.vertices)
        self.normals = vertex_normals(self.vertices, self.faces).astype(np.float64)

    def signed_distance(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(signed distance (P,) > 0 outside, closest points (P, 3), smooth normals there (P, 3))."""
        face, q, bary = closest_points_on_mesh(points, self.vertices, self.faces, self.k, tree=self.tree,
                                               vert_faces=self.vert_faces)
        n = np.einsum("pk,pkd->pd", bary, self.normals[self.faces[face]])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        d = np.linalg.norm(points - q, axis=1)
        side = np.einsum("pd,pd->p", points - q, n)
        return np.where(side < 0, -d, d), q, n


def resolve_collisions(x: np.ndarray, body: BodyCollider, gap: np.ndarray, smoother, params: AutofitParams,
                       exact: bool = True) -> tuple[np.ndarray, int]:
    """Move garment vertices x (M, 3) that are closer to the body than their ``gap`` (M,) (or
    inside it) out along the body normal, diffusing each move over the neighbours
    (``smoother`` (M, M)). First against the nearest body vertex's tangent plane
    (``garment.push_out``; within a fraction of a millimetre of the surface at the body's
    curvature), then, with ``exact``, against the closest surface point of the vertices near
    contact. Returns (x (M, 3) float64, number of vertices moved)."""
    x = np.asarray(x, np.float64)
    moved = np.zeros(len(x), bool)
    for _ in range(params.collision_passes):
        nn = body.tree.query(x)[1]
        plane = np.einsum("ij,ij->i", x - body.vertices[nn], body.normals[nn])
        moved |= plane < gap
        y, n = push_out(x, body.vertices, body.normals, nn[:, None], smoother, gap)
        x = np.asarray(y, np.float64)
        if n == 0:
            break
    for _ in range(params.collision_passes if exact else 0):
        nn = body.tree.query(x)[1]
        plane = np.einsum("ij,ij->i", x - body.vertices[nn], body.normals[nn])
        near = np.flatnonzero(plane < gap + params.contact_margin)
        if not len(near):
            break
        s, q, n = body.signed_distance(x[near])
        bad = s < gap[near] - 1e-5
        if not bad.any():
            break
        idx = near[bad]
        push = q[bad] + gap[idx, None] * n[bad] - x[idx]
        disp = np.asarray(smoother[:, idx] @ push)
        disp[idx] = push  # each vertex that had to move gets its whole move
        x = x + disp
        moved[idx] = True
    return x, int(moved.sum())


def edge_strain(x: np.ndarray, edges: np.ndarray, rest: np.ndarray) -> np.ndarray:
    """|x_a - x_b| / rest - 1 per edge: x (M, 3) or (B, M, 3) -> (E,) or (B, E)."""
    return np.linalg.norm(x[..., edges[:, 0], :] - x[..., edges[:, 1], :], axis=-1) / rest - 1.0


def autofit(garment: np.ndarray, garment_faces: np.ndarray, source_body: np.ndarray, targets: np.ndarray,
            body_faces: np.ndarray, params: AutofitParams = DEFAULT_PARAMS,
            progress: Callable[[float, str], None] | None = None, body_points: np.ndarray | None = None,
            body_labels: np.ndarray | None = None, label_hops: np.ndarray | None = None) -> AutofitResult:
    """The garment (M, 3) draped on ``source_body`` (V, 3) carried onto each of ``targets``
    (E, V, 3) (same topology; ``body_faces`` (F, 3) index the body surface). ``body_points``:
    further vertices of the bodies the graph follows; ``body_labels``, ``label_hops``: body
    parts that must not be joined (both as in ``WarpGraph.precompute``). Returns the
    fits (E, M, 3) float32 and statistics (times, vertices moved, edge strain)."""
    report = progress or (lambda f, m: None)
    t0 = time.perf_counter()
    G = np.asarray(garment, np.float64)
    GF = np.asarray(garment_faces, np.int64)
    BF = np.asarray(body_faces, np.int64)
    nb = int(BF.max()) + 1
    full = body_points is not None and len(body_points)
    src = np.asarray(source_body, np.float64)
    T = np.asarray(targets, np.float64)
    if not full:
        src, T = src[:nb], T[:, :nb]
    E, M = len(T), len(G)
    stats: dict = {"examples": E, "garment_vertices": M}

    # 1. the warping graph, once; every example in one back-substitution
    gface, gpts = BF, body_points
    if params.body_region is not None:
        # only the body near the garment carries it: its nodes are denser there
        tree = cKDTree(G)
        near_face = tree.query(src[BF].mean(axis=1), distance_upper_bound=params.body_region)[0] < np.inf
        gface = BF[near_face]
        if gpts is not None:
            gpts = gpts[tree.query(src[gpts], distance_upper_bound=params.body_region)[0] < np.inf]
    graph = WarpGraph.precompute(src, gface, G, GF, params.warp, body_points=gpts, body_labels=body_labels,
                                 label_hops=label_hops,
                                 progress=lambda f, m: report(0.3 * f, m))
    stats["graph"] = {"nodes": graph.n_nodes, "body_nodes": graph.n_body_nodes, "edges": len(graph.edges),
                      "spacing_mm": 1000 * graph.spacing}
    t1 = time.perf_counter()
    report(0.3, f"warping the garment onto {E} example avatars")
    X = graph.warp(T)  # (E, M, 3)
    t2 = time.perf_counter()

    # the gap each vertex keeps: what it had on the draped body, within [min_clearance, clearance]
    vf = vertex_faces(BF, nb)
    s_src = BodyCollider(src[:nb], BF, vf, params.closest_k).signed_distance(G)[0]
    gap = np.clip(s_src, params.min_clearance, params.clearance)
    smoother = laplacian_smoother(GF, M).tocsc()
    edges, Dinc = edge_incidence(GF, M)
    rest = np.linalg.norm(G[edges[:, 0]] - G[edges[:, 1]], axis=1)
    system = EdgeSystem.precompute((Dinc.T @ Dinc).tocsc(), np.full(M, params.edge_anchor))
    stats["strain_after_warp"] = _strain_stats(edge_strain(X, edges, rest))

    # 2. collisions with each example's body
    colliders = []
    moved = 0
    for e in range(E):
        colliders.append(BodyCollider(T[e, :nb], BF, vf, params.closest_k))
        X[e], n = resolve_collisions(X[e], colliders[e], gap, smoother, params,
                                     exact=params.edge_iterations == 0)
        moved += n
        report(0.3 + 0.3 * (e + 1) / E, "resolving collisions")
    stats["vertices_moved_out"] = moved
    anchor = X.copy()

    # 3. edge lengths (local/global), then off the body again
    lo, hi = rest * (1 - params.edge_tolerance), rest * (1 + params.edge_tolerance)
    for it in range(params.edge_iterations):
        vec = X[:, edges[:, 0]] - X[:, edges[:, 1]]  # (E, n_edges, 3) = Dinc x
        ln = np.maximum(np.linalg.norm(vec, axis=-1, keepdims=True), 1e-12)
        target = vec / ln * np.clip(ln, lo[:, None], hi[:, None])
        rhs = Dinc.T @ target.transpose(1, 0, 2).reshape(len(edges), -1) \
            + params.edge_anchor * anchor.transpose(1, 0, 2).reshape(M, -1)
        X = system.solve(rhs).reshape(M, E, 3).transpose(1, 0, 2)
        last = it == params.edge_iterations - 1
        for e in range(E):
            X[e], _ = resolve_collisions(X[e], colliders[e], gap, smoother, params, exact=last)
        report(0.6 + 0.4 * (it + 1) / max(params.edge_iterations, 1), "restoring edge lengths")
    t3 = time.perf_counter()
    stats["strain"] = _strain_stats(edge_strain(X, edges, rest))
    stats["seconds"] = {"graph": t1 - t0, "warp": t2 - t1, "collisions_and_edges": t3 - t2, "total": t3 - t0}
    report(1.0, "fitted to every example avatar")
    return AutofitResult(fits=X.astype(np.float32), stats=stats)


def _strain_stats(strain: np.ndarray) -> dict:
    a = np.abs(strain).reshape(-1)
    return {"within_10pct": float((a <= 0.10).mean()), "p99_abs": float(np.percentile(a, 99)),
            "max_abs": float(a.max())}


def fit_to_examples(model, garment: np.ndarray, garment_faces: np.ndarray, source_body: np.ndarray | None = None,
                    params: AutofitParams = DEFAULT_PARAMS, progress: Callable[[float, str], None] | None = None,
                    examples=None) -> AutofitResult:
    """The garment (M, 3) draped on ``source_body`` (V, 3) in the template topology (default:
    the mean avatar, the example ``mean``) fitted to the example avatars: fits (1 + 2N, M, 3) in
    the listing order of ``tryon.example_set``, ready for ``tryon.build_garment_basis``."""
    from service.model.garments import tryon

    examples = examples or tryon.example_set(model)
    EX = tryon.example_vertices(model, examples)
    src = model.mean if source_body is None else source_body
    helpers = np.arange(*HELPER_TIGHTS) if params.follow_helper_tights and len(model.mean) >= HELPER_TIGHTS[1] else None
    return autofit(garment, garment_faces, src, EX, model.body_faces, params, progress, body_points=helpers,
                   body_labels=main_bone(model.lbs_indices, model.lbs_weights), label_hops=bone_hops(model.bone_parents))

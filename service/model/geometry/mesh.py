"""Mesh helpers shared by the body model, garments, the GLB writer and the offline build.

vertices: (V, 3) float, faces: (F, 3) int (counter-clockwise seen from outside).
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, connected_components, minimum_spanning_tree
from scipy.spatial import cKDTree

from service.model.geometry import kernels


def edge_counts(faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges (E, 2) int64, each as (low, high), in lexicographic order, and the
    number of faces (F, 3) using each (E,). Edges are keyed low * n + high (n: one more than the
    largest index), a 1-D sort: ~10x faster than ``np.unique(..., axis=0)``'s structured rows."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    if not len(e):
        return e.reshape(0, 2), np.zeros(0, np.int64)
    n = int(e.max()) + 1
    keys, counts = np.unique(e[:, 0] * n + e[:, 1], return_counts=True)
    return np.stack([keys // n, keys % n], axis=1), counts


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), each as (low, high), in lexicographic order."""
    return edge_counts(faces)[0]


def boundary_vertices(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on an edge used by exactly one face."""
    edges, counts = edge_counts(faces)
    out = np.zeros(n, bool)
    out[edges[counts == 1].ravel()] = True
    return out


# a mesh's boundary vertices closer than this fraction of its median edge length are one point
# split in two (a glTF exporter splits every vertex on a UV seam; CAD and pattern tools export
# panels apart with their seams' vertices repeated): OBJ's 6 decimals in metres are 1 um apart,
# a cloth edge ~10 mm long
WELD_EDGE_FRACTION = 1e-3


def weld_seams(vertices: np.ndarray, faces: np.ndarray,
               tolerance: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Join a mesh that was split at its seams: boundary vertices (on an edge of one face) that
    lie within ``tolerance`` (default :data:`WELD_EDGE_FRACTION` x the median edge length) of
    one another become one vertex. vertices (N, 3), faces (F, 3) int -> ``index`` (N,) int64,
    each vertex's welded vertex 0..M-1 (numbered in order of first appearance; the welded
    positions are ``vertices[first]`` with ``first = np.unique(index, return_index=True)[1]``),
    and the welded faces (F, 3) int64. The mesh is returned as it is (``index`` the identity)
    when joining would collapse a face, make two faces one, or leave an edge shared by more
    than two faces that was not before (coincident layers, not a seam)."""
    X = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    n = len(X)
    identity = np.arange(n, dtype=np.int64)
    if n == 0 or not len(f):
        return identity, f
    edges, counts = edge_counts(f)
    if tolerance is None:
        lengths = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
        tolerance = WELD_EDGE_FRACTION * float(np.median(lengths))
    on_boundary = np.unique(edges[counts == 1].ravel())
    if len(on_boundary) < 2 or not tolerance > 0:
        return identity, f
    pairs = cKDTree(X[on_boundary]).query_pairs(float(tolerance), output_type="ndarray")
    if not len(pairs):
        return identity, f
    a, b = on_boundary[pairs[:, 0]], on_boundary[pairs[:, 1]]
    labels = connected_components(sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n)), directed=False)[1]
    _, first, index = np.unique(labels, return_index=True, return_inverse=True)
    # number the welded vertices in order of their first vertex (the file's order, gaps closed)
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    index = rank[index.reshape(-1)].astype(np.int64)
    welded = index[f]
    if np.any((welded[:, 0] == welded[:, 1]) | (welded[:, 1] == welded[:, 2]) | (welded[:, 2] == welded[:, 0])):
        return identity, f
    if int((edge_counts(welded)[1] > 2).sum()) > int((counts > 2).sum()):
        return identity, f
    if len(np.unique(np.sort(welded, axis=1), axis=0)) < len(np.unique(np.sort(f, axis=1), axis=0)):
        return identity, f  # two faces made one: a layer lying on its copy (a double-sided export)
    return index, welded


def edge_length_graph(vertices: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(V, V) symmetric: each edge of the mesh (vertices (V, 3), faces (F, 3)) weighted by its
    length, for distances along the surface (``scipy.sparse.csgraph.dijkstra``)."""
    X = np.asarray(vertices, np.float64)
    e = mesh_edges(faces)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    return sp.coo_matrix((np.r_[length, length], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                         shape=(len(X), len(X))).tocsr()


def vertex_components(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) the connected piece of the mesh (faces (F, 3) over n vertices) each vertex is in,
    labels 0..; a vertex in no face is a piece of its own."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    return connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                directed=False)[1]


def vertex_mean_strain(vertices: np.ndarray, edges: np.ndarray, rest_lengths: np.ndarray) -> np.ndarray:
    """(V,) per-vertex stretch: the mean over each vertex's edges (E, 2) of |edge| / rest
    length (E,) - 1 (positive stretched, negative compressed; 0 on a vertex with no edge)."""
    x = np.asarray(vertices, np.float64)
    s = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1) / np.maximum(rest_lengths, 1e-30) - 1.0
    tot = np.bincount(edges.reshape(-1), np.repeat(s, 2), minlength=len(x))
    cnt = np.bincount(edges.reshape(-1), minlength=len(x))
    return tot / np.maximum(cnt, 1)


def face_incidence(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, F) sparse vertex-face incidence: ``incidence @ face_values`` sums around vertices.
    Cache it per mesh: normals then cost one sparse product."""
    f = np.asarray(faces, np.int64)
    return sp.csr_matrix((np.ones(f.size, np.float32), (f.reshape(-1), np.repeat(np.arange(len(f)), 3))),
                         shape=(n_vertices, len(f)))


def neighbour_mean(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) row-normalised adjacency of the mesh edges: ``A @ x`` is each vertex's mean over
    its edge neighbours (a vertex on no face gets 0). Built in 32-bit indices from the faces'
    six directed edges (a 1 M-face scan: 160 MB at the peak, was 265 MB with 64-bit pairs and a
    sparse product); each row's neighbours are stored, and so summed, in descending order, the
    order of that product: smoothed garments and simplified scans stay bit for bit."""
    f = np.asarray(faces)
    index = np.int32 if n_vertices < np.iinfo(np.int32).max else np.int64
    rows, cols = np.empty((len(f), 6), index), np.empty((len(f), 6), index)
    for k, (a, b) in enumerate([(0, 1), (1, 2), (2, 0), (1, 0), (2, 1), (0, 2)]):
        rows[:, k], cols[:, k] = f[:, a], f[:, b]
    A = sp.coo_matrix((np.ones(rows.size, np.float32), (rows.reshape(-1), cols.reshape(-1))),
                      shape=(n_vertices, n_vertices))
    del rows, cols
    A = A.tocsr()  # duplicates summed, columns ascending within a row
    deg = np.diff(A.indptr)
    row = np.repeat(np.arange(n_vertices, dtype=index), deg)
    A.indices = A.indices[A.indptr[row] + A.indptr[row + 1] - 1 - np.arange(len(A.indices), dtype=index)]
    A.data = np.repeat(1.0 / np.maximum(deg, 1), deg)
    A.has_sorted_indices = False
    return A


def squared_norms(a: np.ndarray) -> np.ndarray:
    """Squared lengths (...,) of vectors (..., 3), summed x, y, z in that order (the compiled
    kernels' order: einsum's may differ in the last bit, which decides ties between faces)."""
    return a[..., 0] * a[..., 0] + a[..., 1] * a[..., 1] + a[..., 2] * a[..., 2]


def row_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise dot products (N,) of (N, 3) arrays: the same values as
    ``np.einsum("ij,ij->i", a, b)`` (same products, same left-to-right sum), ~3x faster on the
    per-request path (einsum's 3-long inner loop is slow)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix | None = None) -> np.ndarray:
    """Smooth, area-weighted unit vertex normals (V, 3) float32 (|n| = 1 within float32 eps).

    The un-normalised face cross product has length 2 x area: area weighting for free.
    Vertices on no face, or whose faces are degenerate, get +Y."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inc = incidence if incidence is not None else face_incidence(f, len(v))
    acc = np.asarray(inc @ fn, np.float64)
    length = np.sqrt(np.einsum("ij,ij->i", acc, acc))
    ok = length > 1e-20
    if not ok.all():
        acc[~ok] = (0.0, 1.0, 0.0)
        length[~ok] = 1.0
    n32 = (acc / length[:, None]).astype(np.float32)
    # re-normalise after rounding so |n| == 1 within float32 eps (the glTF validator checks)
    n64 = n32.astype(np.float64)
    return (n64 / np.sqrt(np.einsum("ij,ij->i", n64, n64))[:, None]).astype(np.float32)


COMPILED = True  # winding_numbers, closest_points_on_mesh, face_bounds: the compiled kernels (service.model.geometry.kernels) where numba is there


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Generalised winding numbers (P,) of points (P, 3) with respect to a closed triangle
    mesh: ~1 inside, ~0 outside (Jacobson et al. 2013; solid angles by Van Oosterom and
    Strackee). Exact and robust, O(P F): use it to confirm a few candidate points. With
    ``COMPILED`` (and numba there): ``kernels.winding_numbers``, ~5x faster, equal to ~1e-14."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces)
    if COMPILED and kernels.AVAILABLE:
        return kernels.winding_numbers(np.ascontiguousarray(np.asarray(points, np.float64).reshape(-1, 3)),
                                       np.ascontiguousarray(V), np.ascontiguousarray(F, np.int64))
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = np.asarray(points[s:s + chunk], np.float64)[:, None, :]
        a, b, c = V[F[:, 0]] - p, V[F[:, 1]] - p, V[F[:, 2]] - p
        la, lb, lc = (np.sqrt(np.einsum("pfi,pfi->pf", x, x)) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
               + np.einsum("pfi,pfi->pf", c, a) * lb)
        out[s:s + chunk] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return out


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (..., 3) to points p (Ericson, Real-Time Collision
    Detection 5.1.5), vectorised: the Voronoi region of each point picks its coordinates
    (v, w) along ab and ac, then one ``a + v ab + w ac`` (b, c and bc from their end points)."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom  # interior
        w = vc * denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    # the Voronoi region, the first that holds winning: 1 a, 2 b, 3 c, 4 ab, 5 ac, 6 bc, 0 inside
    region = np.select([(d1 <= 0) & (d2 <= 0), (d3 >= 0) & (d4 <= d3), (d6 >= 0) & (d5 <= d6),
                        (vc <= 0) & (d1 >= 0) & (d3 <= 0), (vb <= 0) & (d2 >= 0) & (d6 <= 0),
                        (va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0)], [1, 2, 3, 4, 5, 6], 0)
    v = np.where(region == 4, t_ab, np.where((region == 1) | (region == 5), 0.0, v))
    w = np.where(region == 5, t_ac, np.where((region == 1) | (region == 4), 0.0, w))
    res = a + ab * v[..., None] + ac * w[..., None]  # inside, vertex a, edges ab and ac
    # vertices b, c and edge bc from their own end points (the same values as Ericson's)
    res = np.where((region == 2)[..., None], b, res)
    res = np.where((region == 3)[..., None], c, res)
    bc = region == 6
    if bc.any():
        res = np.where(bc[..., None], b + (c - b) * t_bc[..., None], res)
    return res


COMPILED_PAIRS = True  # intersecting_face_pairs: the pair tests in a compiled loop (kernels.faces_cross) where numba is there
GRID_PAIRS = True  # ...and the candidate pairs from a grid inside that loop (kernels.crossing_pairs), no k-d tree


def intersecting_face_pairs(vertices: np.ndarray, faces: np.ndarray, among: np.ndarray | None = None) -> np.ndarray:
    """(K, 2) pairs of faces of one mesh that share no vertex and intersect: an edge of one
    crosses the other (Moller-Trumbore on the candidate pairs whose bounding spheres overlap).
    vertices (V, 3), faces (F, 3) int; ``among`` (S,) face indices: only the pairs with one of
    them. The same set of pairs whichever path finds them (compiled grid, compiled tests on a
    k-d tree's candidates, numpy); the compiled grid gives each pair as (a < b), sorted."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    # the compiled grid reads vertices unchecked: faces that index past them take the numpy
    # path, which raises IndexError as it always has
    if (COMPILED_PAIRS and GRID_PAIRS and kernels.AVAILABLE and np.isfinite(V).all()
            and (not F.size or (F.min() >= 0 and F.max() < len(V)))):
        return kernels.crossing_pairs(V, F, among)
    tri = V[F]
    c = tri.mean(1)
    r = np.linalg.norm(tri - c[:, None], axis=2).max(1)
    if among is None:
        pairs = cKDTree(c).query_pairs(2 * float(r.max()), output_type="ndarray")
    else:
        among = np.asarray(among, np.int64)
        ij = cKDTree(c[among]).sparse_distance_matrix(cKDTree(c), 2 * float(r.max()), output_type="ndarray")
        a, b = among[ij["i"]], ij["j"]
        in_among = np.zeros(len(F), bool)
        in_among[among] = True
        once = ~in_among[b] | (a < b)  # a pair of two of them once
        pairs = np.stack([a[once], b[once]], 1)
    if not len(pairs):
        return np.zeros((0, 2), np.int64)
    if COMPILED_PAIRS and kernels.AVAILABLE:
        hit = np.empty(len(pairs), bool)
        pairs = np.ascontiguousarray(pairs, np.int64)
        kernels.faces_cross(np.ascontiguousarray(V), np.ascontiguousarray(F), pairs, c, r, hit)
        return pairs[hit]
    a, b = pairs[:, 0], pairs[:, 1]
    near = np.linalg.norm(c[a] - c[b], axis=1) <= r[a] + r[b]
    pairs = pairs[near]
    a, b = pairs[:, 0], pairs[:, 1]
    shared = (F[a][:, :, None] == F[b][:, None, :]).any(axis=(1, 2))
    pairs = pairs[~shared]
    if not len(pairs):
        return np.zeros((0, 2), np.int64)
    hit = np.zeros(len(pairs), bool)
    for s, t in ((0, 1), (1, 0)):
        P, Q = pairs[:, s], pairs[:, t]
        T = tri[Q]
        e1, e2 = T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
        for i, j in ((0, 1), (1, 2), (2, 0)):
            o = tri[P, i]
            d = tri[P, j] - o
            h = np.cross(d, e2)
            det = (e1 * h).sum(1)
            ok = np.abs(det) > 1e-14
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            sv = o - T[:, 0]
            u = (sv * h).sum(1) * inv
            q = np.cross(sv, e1)
            v = (d * q).sum(1) * inv
            tt = (e2 * q).sum(1) * inv
            hit |= ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (tt >= 0) & (tt <= 1)
    return pairs[hit].astype(np.int64)


UNTANGLE_STILL_M = 1e-7  # untangle: a vertex moved less than this (m) in a round keeps its face pairs' test
UNTANGLE_STALL_ROUNDS = 3  # untangle: after this many rounds without fewer crossings than its best so far ...
UNTANGLE_MAX_RINGS = 6  # ... the smoothed region grows by a ring of neighbours, up to this many rings


def untangle(vertices: np.ndarray, faces: np.ndarray, rounds: int = 20, keep: np.ndarray | None = None,
             after: Callable[[np.ndarray], np.ndarray] | None = None,
             pairs: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """A mesh's self-intersections (:func:`intersecting_face_pairs`) smoothed out: each round,
    the vertices of the intersecting faces and their neighbours move halfway to the mean of
    their neighbours (uniform Laplacian smoothing, local to the tangle; a crumple, as a
    garment's armpit bound to a body, flattens in one or two rounds). Where ``after`` pushes the
    smoothed vertices back as far as they moved (two layers squeezed between an arm and the
    torso) the crossings stall: after ``UNTANGLE_STALL_ROUNDS`` rounds without fewer of them the
    smoothed region grows by a ring of neighbours (up to ``UNTANGLE_MAX_RINGS``), so that the
    layers straighten over a wider patch. ``keep`` (V,) bool: vertices that do not move;
    ``after``: applied to the vertices after each round (e.g. a body's contact, which may push
    the smoothed layers into each other again: the next round sees that); ``pairs``: the mesh's
    intersecting face pairs (K, 2) if already found. Returns the vertices (V, 3) float64 of the
    round with the fewest face pairs still intersecting (the first such), and that number."""
    V = np.array(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    P = intersecting_face_pairs(V, F) if pairs is None else np.asarray(pairs, np.int64).reshape(-1, 2)
    if not len(P):
        return V, 0
    M = neighbour_mean(F, len(V))
    A = face_incidence(F, len(V))
    best_V, best_n = V.copy(), len(P)
    rings, stall = 1, 0
    for _ in range(rounds):
        sel = np.zeros(len(F))
        sel[P.ravel()] = 1.0
        move = (A @ sel) > 0  # the faces' vertices ...
        for _ in range(rings):  # ... and their neighbours, `rings` deep
            move = (A @ (A.T @ move.astype(np.float64))) > 0
        if keep is not None:
            move &= ~keep
        if not move.any():
            break
        before = V.copy()
        V[move] = 0.5 * V[move] + 0.5 * (M @ V)[move]
        if after is not None:
            V = np.asarray(after(V), np.float64)
        # pairs of faces that did not move stay as they were; the others are tested again (a
        # vertex that ``after`` nudged by less than UNTANGLE_STILL_M counts as still: a body's
        # contact re-projects every vertex at its clearance by rounding-sized amounts)
        changed = (np.abs(V - before) > UNTANGLE_STILL_M).any(axis=1)
        moved = np.flatnonzero(A.T @ changed.astype(np.float64) > 0)
        still = ~np.isin(P, moved).any(axis=1)
        P = np.concatenate([P[still], intersecting_face_pairs(V, F, among=moved)])
        if not len(P):
            return V, 0
        if len(P) < best_n:
            best_V, best_n, stall = V.copy(), len(P), 0
        else:
            stall += 1
            if stall >= UNTANGLE_STALL_ROUNDS and rings < UNTANGLE_MAX_RINGS:
                rings, stall = rings + 1, 0
    return best_V, best_n


def face_frames(x: np.ndarray, face: np.ndarray) -> np.ndarray:
    """(K, 3, 3) orthonormal frames of the triangles ``face`` (K, 3) (vertex ids into x (N, 3)),
    rows: the first edge, the in-plane normal to it, the face normal. A point's offset from a
    triangle written in its frame (``frames @ d``) rides with the triangle when it moves and turns
    (``frames^T @ offset``)."""
    a, b, c = x[face[:, 0]], x[face[:, 1]], x[face[:, 2]]
    t1 = b - a
    t1 = t1 / np.maximum(np.linalg.norm(t1, axis=1, keepdims=True), 1e-12)
    nf = np.cross(b - a, c - a)
    nf = nf / np.maximum(np.linalg.norm(nf, axis=1, keepdims=True), 1e-12)
    return np.stack([t1, np.cross(nf, t1), nf], axis=1)


def barycentric(p, a, b, c):
    """Barycentric coordinates (..., 3) of points p (..., 3) in the planes of triangles a, b, c
    (..., 3) (for a point on the triangle: its weights; they sum to 1)."""
    v0, v1, v2 = b - a, c - a, p - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 1e-30, den, 1e-30)
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - v - w, v, w], axis=-1)


PRUNE_CANDIDATES = True  # closest_points_on_mesh: skip candidate faces that cannot be the closest (same results)
PRUNE_SLACK = kernels.PRUNE_SLACK  # relative slack on the pruning bound (rounding of the bound itself)
PRUNE_SLACK_SQ = kernels.PRUNE_SLACK_SQ  # squared metres: absolute slack (a point on a vertex ties its faces at 0)


def closest_points_on_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, k: int = 8,
                           tree: cKDTree | None = None, vert_faces: np.ndarray | None = None,
                           bounds: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
                           near: np.ndarray | None = None):
    """The closest point of a triangle mesh to each of ``points`` (P, 3): exact among the
    triangles around the k nearest vertices (pass ``tree`` over ``vertices``,
    ``vertex_faces(faces, V)`` and :func:`face_bounds` to reuse them), or around ``near`` (P, k)
    int vertex indices given instead (no nearest-vertex search: e.g. the vertices of each point's
    closest face a moment ago, for a point that has moved a little). Returns (face ids (P,) int64, closest points
    (P, 3) float64, barycentric weights (P, 3) float64 of the closest points in those faces).

    With ``PRUNE_CANDIDATES``, a candidate face is evaluated only when a lower bound of its
    distance (:func:`face_distance_bounds`) is within the distance to the nearest vertex that has
    a face (an upper bound of the answer): the same faces win, ties included, at ~1/4 the work.
    With ``COMPILED`` (and numba there), the same search one point at a time in compiled code
    (``kernels.closest_faces``: the same results, ~3x faster)."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces, np.int64)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    if not len(p):
        return np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros((0, 3))
    vert_faces = vert_faces if vert_faces is not None else vertex_faces(F, len(V))
    d1 = None  # distances to the candidate vertices (the numpy path's upper bound)
    if near is not None:
        nn = np.asarray(near, np.int64).reshape(len(p), -1)
    else:
        tree = tree if tree is not None else cKDTree(V)
        d1, nn = tree.query(p, k=min(k, len(V)))  # more than the mesh has would index past it
    if COMPILED and kernels.AVAILABLE and PRUNE_CANDIDATES:
        c, n, r = bounds if bounds is not None else face_bounds(V, F)
        face, q = kernels.closest_faces(np.ascontiguousarray(p), np.ascontiguousarray(V), np.ascontiguousarray(F),
                                        np.ascontiguousarray(nn.reshape(len(p), -1), np.int64),
                                        np.ascontiguousarray(vert_faces, np.int64),
                                        np.ascontiguousarray(c, np.float64), np.ascontiguousarray(n, np.float64),
                                        np.ascontiguousarray(r, np.float64))
        t = V[F[face]]
        return face, q, barycentric(q, t[:, 0], t[:, 1], t[:, 2])
    raw = vert_faces[nn.reshape(len(p), -1)].reshape(len(p), -1)
    if d1 is None:
        d1 = np.sqrt(((V[nn] - p[:, None, :]) ** 2).sum(-1))
    if PRUNE_CANDIDATES:
        return _closest_pruned(p, V, F, raw, np.asarray(d1).reshape(len(p), -1), np.asarray(nn).reshape(len(p), -1),
                               vert_faces, bounds if bounds is not None else face_bounds(V, F))
    cand, valid = _unique_rows(raw)
    tri = V[F[cand]]  # (P, C, 3, 3)
    q = closest_point_on_triangles(p[:, None, :], tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
    d = np.where(valid, squared_norms(q - p[:, None]), np.inf)
    j = np.argmin(d, axis=1)
    r = np.arange(len(p))
    face = cand[r, j]
    t = tri[r, j]
    return face, q[r, j], barycentric(q[r, j], t[:, 0], t[:, 1], t[:, 2])


def face_bounds(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each triangle's bounding disk: centroids (F, 3), unit normals (F, 3) (0 when degenerate)
    and radii (F,) (the largest vertex distance from the centroid). With ``COMPILED`` (and numba
    there): ``kernels.face_bounds`` (equal up to rounding; these only prune candidates)."""
    if COMPILED and kernels.AVAILABLE:
        return kernels.face_bounds(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64))
    tri = vertices[faces]  # (F, 3, 3)
    c = tri.mean(axis=1)
    r = np.sqrt(np.einsum("fki,fki->fk", tri - c[:, None], tri - c[:, None]).max(axis=1))
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return c, n, r


def face_distance_bounds(p: np.ndarray, c: np.ndarray, n: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Squared lower bounds (...,) of the distances from points p (..., 3) to triangles with
    bounding disks (:func:`face_bounds` gathered: centroids (..., 3), unit normals (..., 3),
    radii (...,)): the distance to the triangle's plane combined with the in-plane distance to
    its disk, both no larger than the true ones."""
    u = p - c
    pd2 = np.einsum("...i,...i->...", u, n) ** 2
    inplane = np.sqrt(np.maximum(np.einsum("...i,...i->...", u, u) - pd2, 0.0))
    return pd2 + np.maximum(inplane - r, 0.0) ** 2


def _closest_pruned(p, V, F, raw, d1, nn, vert_faces, bounds):
    """:func:`closest_points_on_mesh` from the raw candidates (P, C) (-1 padded, with repeats):
    each row's distinct faces (:func:`_sorted_unique_rows`), of which only those whose lower bound
    is within an upper bound of the answer (the nearest faced vertex's distance, or the distance
    to the face of the smallest lower bound if nearer) are evaluated, flattened; each row takes its
    nearest face, ties going to the face that appears first in ``raw`` (as the reference's
    first-appearance order does)."""
    P = len(p)
    cand, valid = _sorted_unique_rows(raw)
    ub = np.where(vert_faces[nn, 0] >= 0, d1, np.inf).min(axis=1)  # a vertex's faces are no farther
    c, n, r = bounds
    lb = np.where(valid, face_distance_bounds(p[:, None, :], c[cand], n[cand], r[cand]), np.inf)
    # a tighter upper bound: the distance to each row's face of the smallest lower bound
    best = cand[np.arange(P), np.argmin(lb, axis=1)]
    tb = V[F[best]]
    qb = closest_point_on_triangles(p, tb[:, 0], tb[:, 1], tb[:, 2])
    ub2 = np.where(valid.any(axis=1), np.minimum(ub * ub, np.einsum("ni,ni->n", qb - p, qb - p)), ub * ub)
    keep = lb <= ub2[:, None] * (1 + PRUNE_SLACK) + PRUNE_SLACK_SQ
    keep[:, 0] |= ~keep.any(axis=1)  # a row with no face at all keeps its padding (face 0, never valid)
    rows, cols = np.nonzero(keep)
    fc = cand[rows, cols]
    tri = V[F[fc]]  # (N, 3, 3)
    pr = p[rows]
    q = closest_point_on_triangles(pr, tri[:, 0], tri[:, 1], tri[:, 2])
    d = np.where(valid[rows, cols], squared_norms(q - pr), np.inf)
    starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    is_min = d == np.minimum.reduceat(d, starts)[np.repeat(np.arange(P), np.diff(np.r_[starts, len(rows)]))]
    m = np.flatnonzero(is_min)
    first = np.argmax(raw[rows[m]] == fc[m, None], axis=1)  # where each tying face first appears
    m = m[np.lexsort((first, rows[m]))]
    j = m[np.r_[True, rows[m][1:] != rows[m][:-1]]]  # each row's nearest face, first appearing
    t = tri[j]
    return fc[j], q[j], barycentric(q[j], t[:, 0], t[:, 1], t[:, 2])


def _sorted_unique_rows(cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate face ids (P, C) int, -1 padded, with repeats: each row's distinct ids in
    ascending order, packed to the left, (P, C') with C' the most any row has, and valid (P, C')
    bool; invalid slots hold 0. Two row sorts (no argsort): several times faster than
    :func:`_unique_rows`, whose first-appearance order the caller restores where it matters."""
    big = np.iinfo(np.int64).max
    s = np.sort(np.where(cand >= 0, cand, big).astype(np.int64), axis=1)
    rep = np.zeros_like(s, bool)
    rep[:, 1:] = s[:, 1:] == s[:, :-1]
    s = np.sort(np.where(rep, big, s), axis=1)
    valid = s != big
    s = s[:, :max(int(valid.sum(axis=1).max()), 1)]
    valid = valid[:, :s.shape[1]]
    return np.where(valid, s, 0), valid


def _unique_rows(cand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Candidate face ids (P, C) int, -1 padded, with repeats (a face is around up to 3 of the
    nearest vertices): each row's distinct ids in order of first appearance, packed to the left,
    (P, C') with C' the most any row has, and valid (P, C') bool; invalid slots repeat the row's
    first id (harmless to evaluate). The first-appearance order keeps ``argmin``'s choice among
    equally near faces; dropping the repeats saves evaluating ~2.5x the triangles."""
    P, C = cand.shape
    order = np.argsort(cand, axis=1, kind="stable")
    srt = np.take_along_axis(cand, order, axis=1)
    first = np.ones_like(srt, bool)
    first[:, 1:] = srt[:, 1:] != srt[:, :-1]
    keep = np.zeros_like(first)
    np.put_along_axis(keep, order, first & (srt >= 0), axis=1)
    pack = np.argsort(~keep, axis=1, kind="stable")[:, :max(int(keep.sum(axis=1).max()), 1)]
    c = np.take_along_axis(cand, pack, axis=1)
    valid = np.take_along_axis(keep, pack, axis=1)
    head = np.where(valid[:, :1], c[:, :1], 0)  # a row with no face at all: face 0, never valid
    return np.where(valid, c, head), valid


def vertex_faces(faces: np.ndarray, n: int) -> np.ndarray:
    """(n, max valence) face ids around each vertex, -1 padded."""
    order = np.argsort(faces.reshape(-1), kind="stable")
    vid = faces.reshape(-1)[order]
    fid = order // 3
    counts = np.bincount(vid, minlength=n)
    out = np.full((n, counts.max()), -1, np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(vid)) - start[vid]
    out[vid, pos] = fid
    return out


# -- normals of point clouds ----------------------------------------------------------------------
def estimate_normals(points: np.ndarray, k: int = 12) -> np.ndarray:
    """Unit normals (P, 3) float64 of a point cloud (P, 3), P >= 3, finite.

    PCA of each point's k nearest neighbours (the smallest principal axis), oriented
    consistently by propagation over the minimum spanning tree of the kNN graph weighted by
    1 - |n_i . n_j| (Hoppe et al. 1992), then each connected component is flipped so that
    most of its normals point away from its centroid (outward for a closed surface)."""
    P = np.asarray(points, np.float64).reshape(-1, 3)
    n_pts = len(P)
    if n_pts < 3:
        raise ValueError(f"estimate_normals needs at least 3 points, got {n_pts}")
    kk = int(min(max(k, 2), n_pts - 1))
    # work in the tree's leaf order: neighbours are then near in memory (2-3x faster)
    kd = cKDTree(P)
    order = np.asarray(kd.indices, np.int64)
    rank = np.empty(n_pts, np.int64)
    rank[order] = np.arange(n_pts)
    P = P[order]
    idx = rank[kd.query(P, k=kk + 1)[1]]  # (P, kk + 1), usually itself first
    # PCA: the eigenvector of the smallest eigenvalue of each neighbourhood's covariance
    Q = P[idx]
    Q = Q - Q.mean(axis=1, keepdims=True)
    normals = np.linalg.eigh(np.matmul(Q.transpose(0, 2, 1), Q))[1][:, :, 0]  # (P, 3) unit
    # undirected kNN graph, each edge once (low, high), weighted by 1 - |n_i . n_j| (+ eps:
    # zero weights would be missing edges)
    src = np.repeat(np.arange(n_pts), kk + 1)
    dst = idx.reshape(-1)
    keep = src != dst
    rows, cols = np.minimum(src[keep], dst[keep]), np.maximum(src[keep], dst[keep])
    w = np.maximum(1.0 - np.abs(np.einsum("ij,ij->i", normals[rows], normals[cols])), 0.0) + 1e-9
    graph = csr_matrix((w, (rows, cols)), shape=(n_pts, n_pts))  # mutual neighbours: summed twice
    graph.data /= csr_matrix((np.ones_like(w), (rows, cols)), shape=(n_pts, n_pts)).data
    tree = minimum_spanning_tree(graph)
    n_comp, labels = connected_components(tree, directed=False)
    roots = np.unique(labels, return_index=True)[1]
    # one breadth-first pass from a virtual node joined to a root of every component
    tree = tree.tocoo()
    aug = csr_matrix((np.concatenate([tree.data, np.ones(n_comp)]),
                      (np.concatenate([tree.row, np.full(n_comp, n_pts)]), np.concatenate([tree.col, roots]))),
                     shape=(n_pts + 1, n_pts + 1))
    _, pred = breadth_first_order(aug, n_pts, directed=False, return_predecessors=True)
    parent = pred[:n_pts].astype(np.int64)
    is_root = (parent == n_pts) | (parent < 0)
    parent[is_root] = np.flatnonzero(is_root)
    # flip relative to the parent, then products along the tree paths by pointer jumping
    sign = np.where(np.einsum("ij,ij->i", normals, normals[parent]) < 0, -1.0, 1.0)
    sign[is_root] = 1.0
    ptr = parent
    while not np.array_equal(ptr[ptr], ptr):
        sign = sign * sign[ptr]
        ptr = ptr[ptr]
    normals = normals * sign[:, None]
    # per component: most normals point away from the component's centroid
    counts = np.bincount(labels, minlength=n_comp).astype(np.float64)
    centroid = np.stack([np.bincount(labels, weights=P[:, ax], minlength=n_comp) for ax in range(3)], axis=1)
    centroid /= counts[:, None]
    out = np.einsum("ij,ij->i", normals, P - centroid[labels])
    vote = np.bincount(labels, weights=np.sign(out), minlength=n_comp)
    normals[vote[labels] < 0] *= -1.0
    return normals[rank]


def _cell_keys(vertices: np.ndarray, h: float, offset: np.ndarray) -> np.ndarray:
    """(V,) int64: the grid cell of voxel size ``h`` (grid shifted by ``offset`` (3,)) of each
    vertex (V, 3), one integer per cell."""
    k = np.floor((vertices - offset) / h).astype(np.int64)
    k -= k.min(0)
    return (k[:, 0] * (k[:, 1].max() + 1) + k[:, 1]) * (k[:, 2].max() + 1) + k[:, 2]


def cluster_vertices(vertices: np.ndarray, faces: np.ndarray | None, h: float, offset: np.ndarray,
                     keyed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertex clustering on a grid (Rossignac-Borrel): the vertices (V, 3) in each cell of
    voxel size ``h`` (the grid shifted by ``offset`` (3,)) become one, the member nearest to
    their mean (so it lies on the original surface). ``keyed`` (V, 3): the positions that
    decide each vertex's cell (default ``vertices``; see :func:`simplify`). Returns (the
    representatives' indices (C,) into ``vertices``, faces (F', 3) into the representatives:
    triangles that collapsed or repeat dropped, representatives on no face left out; None for
    a point cloud, whose every cell keeps its representative)."""
    vertices = np.asarray(vertices, np.float64)
    keys = _cell_keys(vertices if keyed is None else keyed, h, offset)
    _, cid, counts = np.unique(keys, return_inverse=True, return_counts=True)
    cid = cid.reshape(-1)
    C = len(counts)
    mean = np.zeros((C, 3))
    np.add.at(mean, cid, vertices)
    mean /= counts[:, None]
    d2 = np.einsum("ij,ij->i", vertices - mean[cid], vertices - mean[cid])
    order = np.lexsort((d2, cid))  # within each cluster, nearest to the mean first
    first = np.ones(len(order), bool)
    first[1:] = cid[order][1:] != cid[order][:-1]
    rep = np.empty(C, np.int64)
    rep[cid[order][first]] = order[first]
    if faces is None:
        return rep, None
    F = cid[np.asarray(faces, np.int64)]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 2] != F[:, 0])]
    S = np.sort(F, axis=1)
    _, uniq = np.unique((S[:, 0] * C + S[:, 1]) * C + S[:, 2], return_index=True)
    F = F[np.sort(uniq)]
    used = np.unique(F)
    remap = np.full(C, -1, np.int64)
    remap[used] = np.arange(len(used))
    return rep[used], remap[F]


SIMPLIFY_PASSES = 6  # grid sizes ``simplify`` tries
SIMPLIFY_AIM = 0.95  # ... each aimed at this share of its target (cells vary a little with h)
# a mesh's cells are taken from its vertices averaged over their edge neighbours this many times:
# a scanner's noise (~1 mm at ~2 mm spacing) scatters a patch of surface over several cells, and
# the triangles between them overlap. A 930k-vertex noisy scan kept at ~240k: 24 % of the edges
# on more than two triangles (the shopper sees a speckled scan), 1.2 % after 5 passes (its own
# share before clustering); 2 passes: 1.8 %
SIMPLIFY_SMOOTHING = 5


def simplify(vertices: np.ndarray, faces: np.ndarray | None,
             max_vertices: int) -> tuple[np.ndarray, np.ndarray | None]:
    """A dense mesh or point cloud (vertices (V, 3), faces (F, 3) or None) down to at most
    ``max_vertices`` by :func:`cluster_vertices`, on the finest of SIMPLIFY_PASSES grids whose
    occupied cells are no more than that (each voxel size from the last by the square root of
    the ratio of its cells to SIMPLIFY_AIM of the target: a surface's cells go with 1 / h^2);
    the grid sits at the points' lower corner (deterministic), a mesh's cells taken from its
    vertices smoothed (SIMPLIFY_SMOOTHING). Returns (indices (C,) of the kept vertices, faces
    (F', 3) into them or None); a cloud or mesh already small enough comes back whole,
    ``(arange(V), faces)``."""
    vertices = np.asarray(vertices, np.float64)
    n = len(vertices)
    if n <= max_vertices:
        return np.arange(n), None if faces is None else np.asarray(faces, np.int64)
    keyed = vertices
    if faces is not None:
        A = neighbour_mean(faces, n)
        on_face = np.asarray(A.sum(axis=1)).ravel() > 0
        for _ in range(SIMPLIFY_SMOOTHING):
            keyed = np.where(on_face[:, None], A @ keyed, keyed)
    lo = keyed.min(0)
    h = float(np.ptp(keyed, axis=0).max()) / np.sqrt(max_vertices)  # max_vertices on a sheet
    best, coarsest = None, h
    for _ in range(SIMPLIFY_PASSES):
        cells = len(np.unique(_cell_keys(keyed, h, lo)))
        if cells <= max_vertices and (best is None or h < best):
            best = h
        coarsest = max(coarsest, h)
        h *= np.sqrt(cells / (SIMPLIFY_AIM * max_vertices))
    while best is None:  # not there yet (a very uneven cloud): coarser until it is
        coarsest *= 1.5
        if len(np.unique(_cell_keys(keyed, coarsest, lo))) <= max_vertices:
            best = coarsest
    return cluster_vertices(vertices, faces, best, lo, keyed=keyed)

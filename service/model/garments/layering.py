"""Garment-garment layering: inner garments pushed back inside the outer ones. Pure numpy/scipy.

Given garments in layer order (inner first) on one body, every vertex of an inner garment that
lies outside (or within ``GAP`` of) an outer garment *where that outer garment covers it* is
moved inward along the outer surface's normal to ``GAP`` below it; the displacement is smoothed
over the inner mesh (a screened Laplacian: argmin_D sum_i c_i |D_i - D0_i|^2 + SMOOTH |grad D|^2
+ EPS |D|^2, factored once per pass), so the inner garment bends instead of creasing, and the
pass is repeated (``PASSES``) for what smoothing left outside.

"Covers": the inner vertex's closest point on the outer garment is inside that surface (not on
its boundary) and nearer than ``COVER_DISTANCE``; the outer surface's normals are oriented away
from the body (each against the body normal at its nearest body vertex), so garments of either
winding work.

Shapes: garment vertices (M, 3), faces (F, 3); body vertices (V, 3) and unit normals (V, 3).
"""
from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.geometry.mesh import (boundary_vertices, closest_points_on_mesh, face_bounds, vertex_faces,
                                         vertex_normals)
from service.model.geometry.solvers import factor_spd
from service.model.garments.skin_weights import dense_weights, top_k, uniform_laplacian

GAP = 0.0025  # metres left between an inner garment and the outer one over it
COVER_DISTANCE = 0.05  # metres: farther than this from the outer garment is not covered by it
MOVES_WITH = 0.1  # the layering figure's skin test: a garment moving with a body vertex shares this much
# of its skin weight (posed, hands and forearms resting on clothes were 91 % of what the figure counted without it)
BOUNDARY_MARGIN = 1e-3  # barycentric weight: closest points this near a boundary edge do not cover
SMOOTH = 2.0  # weight of the displacement's smoothness (uniform Laplacian) against the targets
EPS = 0.1  # pull of free vertices' displacement to 0: the falloff spans ~sqrt(SMOOTH / EPS) ~ 4.5 edges
PASSES = 3
RECHECK_MOVE = 1e-6  # metres: a vertex moved less than this by a pass is not checked again
RIM_SAMPLES = True  # also check the inner garment from the body vertices along the outer garment's rims
RIM_CONE = np.pi / 4  # a rim covers the body vertices it is over within this angle of their normal
RIM_NEAR_ONLY = True  # rim_violations: closest points only for band vertices near the inner garment (same results)


TOPOLOGY_CACHE_SIZE = 64  # garment and base-layer topologies kept per process (Laplacian, rims, vertex faces)
_topologies: OrderedDict[tuple, tuple[sp.csr_matrix, np.ndarray, np.ndarray]] = OrderedDict()
_topologies_lock = threading.Lock()


def topology(faces: np.ndarray, n: int) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """A mesh's (n vertices, faces (F, 3)) uniform Laplacian (n, n), :func:`boundary_vertices`
    (n,) bool and ``geometry.vertex_faces`` (n, valence), once per process per topology (keyed
    by the faces' bytes: a garment basis' faces, or the look's base layer, are the same for every
    customer). Read-only."""
    f = np.ascontiguousarray(faces)
    key = (n, f.shape, f.dtype.str, hashlib.sha1(f.tobytes()).hexdigest())
    with _topologies_lock:
        hit = _topologies.get(key)
        if hit is not None:
            _topologies.move_to_end(key)
            return hit
    L = sp.csr_matrix(uniform_laplacian(f, n))
    b = boundary_vertices(f, n)
    vf = vertex_faces(np.asarray(f, np.int64), n)
    b.setflags(write=False)
    vf.setflags(write=False)
    with _topologies_lock:
        _topologies[key] = (L, b, vf)
        while len(_topologies) > TOPOLOGY_CACHE_SIZE:
            _topologies.popitem(last=False)
    return L, b, vf


def outward_normals(vertices: np.ndarray, faces: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                    body_tree: cKDTree | None = None) -> np.ndarray:
    """Unit vertex normals (M, 3) of a garment flipped, per vertex, to point away from the body."""
    n = vertex_normals(vertices, faces).astype(np.float64)
    _, nn = (body_tree if body_tree is not None else cKDTree(body)).query(vertices)
    flip = np.einsum("ij,ij->i", n, body_normals[nn]) < 0
    n[flip] *= -1
    return n


def violations(inner: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray, outer_normals: np.ndarray,
               outer_boundary: np.ndarray, body: np.ndarray, body_normals: np.ndarray, body_tree: cKDTree,
               gap: float = GAP, outer_index: tuple | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """For each inner vertex (M, 3): the needed inward displacement (M, 3), covered (M,) bool,
    and its closest point on the outer garment as (face (M,), barycentric weights (M, 3)).
    ``outer_index``: (k-d tree over the outer vertices, ``geometry.vertex_faces``,
    ``geometry.face_bounds``) to reuse.

    Where the closest point is inside the outer surface, the vertex is covered within
    ``COVER_DISTANCE`` and must lie ``gap`` below it along the outer normal. Where it is on the
    outer garment's boundary (a hem, cuff, collar or lapel), the vertex is covered when that rim,
    seen from the body vertex under the inner vertex, lies within ``RIM_CONE`` of the body normal
    (the same "over" test as the layering figure, :func:`inner_outside_share`): the inner
    garment's height over that body vertex must stay below the rim's height, so a sleeve or a
    waistband does not bulge out past the edge of the garment over it."""
    F = np.asarray(outer_faces, np.int64)
    X = np.asarray(inner, np.float64)
    M = len(X)
    D = np.zeros_like(X)
    covered = np.zeros(M, bool)
    face, bary = np.zeros(M, np.int64), np.zeros((M, 3))
    # only vertices that can be within COVER_DISTANCE of the outer surface (its closest point is
    # at most one edge from its nearest vertex): the exact closest points are the costly part
    edge = np.linalg.norm(outer[F] - outer[np.roll(F, 1, axis=1)], axis=2).max()
    tree, vf, fb = outer_index if outer_index is not None else \
        (cKDTree(outer), vertex_faces(F, len(outer)), face_bounds(np.asarray(outer, np.float64), F))
    d1, _ = tree.query(X, distance_upper_bound=COVER_DISTANCE + edge)
    near = np.flatnonzero(np.isfinite(d1))
    if len(near) == 0:
        return D, covered, face, bary
    f_n, q, b_n = closest_points_on_mesh(X[near], outer, F, tree=tree, vert_faces=vf, bounds=fb)
    face[near], bary[near] = f_n, b_n
    D_n, cov_n = _violations(X[near], q, f_n, b_n, F, outer_normals, outer_boundary, body, body_normals, body_tree,
                             gap)
    D[near], covered[near] = D_n, cov_n
    return D, covered, face, bary


def _violations(inner, q, face, bary, F, outer_normals, outer_boundary, body, body_normals, body_tree, gap):
    """:func:`violations` on vertices (P, 3) with their closest outer points (P, 3) given."""
    n = np.einsum("mk,mkj->mj", bary, outer_normals[F[face]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    s = np.einsum("ij,ij->i", inner - q, n)  # > 0: outside the outer garment
    # the closest point on a boundary edge (or a boundary vertex's corner) is on the rim
    edge_bound = np.stack([outer_boundary[F[face][:, 1]] & outer_boundary[F[face][:, 2]],
                           outer_boundary[F[face][:, 2]] & outer_boundary[F[face][:, 0]],
                           outer_boundary[F[face][:, 0]] & outer_boundary[F[face][:, 1]]], axis=1)
    at_boundary = ((bary < BOUNDARY_MARGIN) & edge_bound).any(axis=1) | \
        (((bary > 1 - BOUNDARY_MARGIN) & outer_boundary[F[face]]).any(axis=1))
    covered = ~at_boundary & (np.linalg.norm(inner - q, axis=1) < COVER_DISTANCE)
    need = covered & (s > -gap)
    D = np.zeros_like(inner)
    D[need] = -(s[need] + gap)[:, None] * n[need]
    rim = np.flatnonzero(at_boundary)
    if len(rim):
        _, b = body_tree.query(inner[rim])
        nb = body_normals[b]
        u = q[rim] - body[b]
        ho = np.einsum("ij,ij->i", u, nb)  # the rim's height over the body vertex
        du = np.linalg.norm(u, axis=1)
        over = (du < COVER_DISTANCE) & (ho > np.cos(RIM_CONE) * du)
        hi = np.einsum("ij,ij->i", inner[rim] - body[b], nb)
        g = np.minimum(gap, 0.5 * ho)  # a rim closer to the skin than 2 gaps: halfway down
        bad = over & (hi > ho - g)
        covered[rim[over]] = True
        D[rim[bad]] = -(hi[bad] - ho[bad] + g[bad])[:, None] * nb[bad]
    return D, covered


def push_inside(inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray,
                body: np.ndarray, body_normals: np.ndarray, gap: float = GAP, passes: int = PASSES,
                body_tree: cKDTree | None = None) -> np.ndarray:
    """The inner garment (M, 3) with the parts outside the outer garment moved inside it,
    smoothly (see module docstring). Returns (M, 3) float64."""
    return _push_inside(inner, inner_faces, outer, outer_faces, body, body_normals, gap, passes, body_tree)[0]


def prepare_outer(outer: np.ndarray, outer_faces: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                  body_tree: cKDTree, outer_boundary: np.ndarray | None = None,
                  outer_vertex_faces: np.ndarray | None = None) -> tuple:
    """What pushing any inner garment inside an outer garment (M, 3) needs of the outer one on
    this body: (outward normals (M, 3), boundary (M,) bool, (k-d tree, vertex faces, face
    bounds), rim band or None); ``outer_boundary``, ``outer_vertex_faces``: when known. In an
    outfit, made once per outer garment's final shape and shared by every garment under it."""
    O = np.asarray(outer, np.float64)
    on = outward_normals(O, outer_faces, body, body_normals, body_tree)
    ob = outer_boundary if outer_boundary is not None else boundary_vertices(outer_faces, len(O))
    F = np.asarray(outer_faces, np.int64)
    index = (cKDTree(O), outer_vertex_faces if outer_vertex_faces is not None else vertex_faces(F, len(O)),
             face_bounds(O, F))
    band = rim_band(O, outer_faces, ob, body, body_normals, index) if RIM_SAMPLES else None
    return on, ob, index, band


def _push_inside(inner, inner_faces, outer, outer_faces, body, body_normals, gap=GAP, passes=PASSES, body_tree=None,
                 inner_laplacian=None, outer_boundary=None, prepared=None, inner_vertex_faces=None):
    """:func:`push_inside`, also returning the final cover: covered (M,) bool and the closest
    outer points as (face (M,), barycentric (M, 3)). ``inner_laplacian`` (the inner mesh's
    uniform Laplacian), ``outer_boundary`` (:func:`boundary_vertices` of the outer mesh) and
    ``prepared`` (:func:`prepare_outer`), ``inner_vertex_faces``: given when already known."""
    X = np.asarray(inner, np.float64).copy()
    O = np.asarray(outer, np.float64)
    B = np.asarray(body, np.float64)
    tree = body_tree if body_tree is not None else cKDTree(B)
    on, ob, index, band = prepared if prepared is not None else \
        prepare_outer(O, outer_faces, B, body_normals, tree, outer_boundary)
    L = inner_laplacian
    recheck = None  # after the first pass only the vertices that moved can have changed
    for _ in range(passes):
        # the last pass's cover is returned (measured before its move: close enough for skin weights)
        if recheck is None:
            D0, covered, face, bary = violations(X, O, outer_faces, on, ob, B, body_normals, tree, gap, index)
        else:
            D0 = np.zeros_like(X)
            D0[recheck], covered[recheck], face[recheck], bary[recheck] = violations(
                X[recheck], O, outer_faces, on, ob, B, body_normals, tree, gap, index)
        if band is not None:
            Dr = rim_violations(X, inner_faces, band, B, body_normals, gap, inner_vertex_faces)
            deeper = np.einsum("ij,ij->i", Dr, Dr) > np.einsum("ij,ij->i", D0, D0)
            D0[deeper] = Dr[deeper]
        c = (np.einsum("ij,ij->i", D0, D0) > 0).astype(np.float64)
        if not c.any():
            return X, covered, face, bary
        L = uniform_laplacian(inner_faces, len(X)) if L is None else L
        A = sp.diags(c + EPS) + SMOOTH * L
        D = factor_spd(A).solve(c[:, None] * D0)
        # the smoothed field never undershoots the targets: keep whichever goes deeper inward
        move = np.where(c[:, None] > 0, np.where((np.einsum("ij,ij->i", D, D0) >= np.einsum("ij,ij->i", D0, D0))[:, None],
                                                 D, D0), D)
        X += move
        recheck = np.flatnonzero(np.einsum("ij,ij->i", move, move) > RECHECK_MOVE ** 2)
    return X, covered, face, bary


def rim_band(outer: np.ndarray, outer_faces: np.ndarray, outer_boundary: np.ndarray, body: np.ndarray,
             body_normals: np.ndarray, outer_index: tuple | None = None) -> tuple[np.ndarray, np.ndarray] | None:
    """The body vertices near the outer garment's boundary that it covers (the "over" test of
    :func:`inner_outside_share`) and the outer garment's height over each: (body ids (K,),
    heights (K,)), or None. Along a rim the outer surface ends between the inner garment's
    sparse vertices, so the inner garment is also checked from these body vertices.
    ``outer_index``: as in :func:`violations`."""
    if not outer_boundary.any():
        return None
    rim = np.asarray(outer, np.float64)[outer_boundary]
    d, _ = cKDTree(rim).query(body, distance_upper_bound=COVER_DISTANCE)
    k = np.flatnonzero(np.isfinite(d))
    if len(k) == 0:
        return None
    tree, vf, fb = outer_index if outer_index is not None else (None, None, None)
    _, q, _ = closest_points_on_mesh(body[k], outer, np.asarray(outer_faces, np.int64), tree=tree, vert_faces=vf,
                                     bounds=fb)
    u = q - body[k]
    du = np.linalg.norm(u, axis=1)
    ho = np.einsum("ij,ij->i", u, body_normals[k])
    over = (du < COVER_DISTANCE) & (ho > np.cos(RIM_CONE) * du)
    return (k[over], ho[over]) if over.any() else None


def rim_violations(inner: np.ndarray, inner_faces: np.ndarray, band: tuple[np.ndarray, np.ndarray],
                   body: np.ndarray, body_normals: np.ndarray, gap: float = GAP,
                   inner_vertex_faces: np.ndarray | None = None) -> np.ndarray:
    """Inward displacements (M, 3) of the inner garment's vertices from the :func:`rim_band`:
    where the inner surface over a band body vertex (its closest point, within the cone) is above
    the outer garment's height there less the gap, the three vertices of its face move down along
    that body normal by the excess (the largest excess wins). ``inner_vertex_faces``:
    ``geometry.vertex_faces`` of the inner mesh, when known."""
    k, ho = band
    F = np.asarray(inner_faces, np.int64)
    X = np.asarray(inner, np.float64)
    D = np.zeros_like(X)
    # only body vertices within COVER_DISTANCE of the inner surface can be bad: its closest point
    # is at most one edge from its nearest vertex (the same answers, fewer closest points)
    edge = np.linalg.norm(X[F] - X[np.roll(F, 1, axis=1)], axis=2).max()
    tree = cKDTree(X)
    d1, _ = tree.query(body[k], distance_upper_bound=COVER_DISTANCE + edge if RIM_NEAR_ONLY else np.inf)
    near = np.isfinite(d1)
    if not near.any():
        return D
    k, ho = k[near], ho[near]
    f, q, _ = closest_points_on_mesh(body[k], X, F, tree=tree, vert_faces=inner_vertex_faces)
    u = q - body[k]
    du = np.linalg.norm(u, axis=1)
    nb = body_normals[k]
    hi = np.einsum("ij,ij->i", u, nb)
    g = np.minimum(gap, 0.5 * ho)
    bad = (du < COVER_DISTANCE) & (hi > np.cos(RIM_CONE) * du) & (hi > ho - g)
    if not bad.any():
        return D
    ex = (hi - ho + g)[bad]
    order = np.argsort(ex)  # ascending: the largest excess written last
    vid = F[f[bad][order]].ravel()
    D[vid] = -np.repeat(ex[order, None] * nb[bad][order], 3, axis=0)
    return D


def covered_skin(inner_faces: np.ndarray, inner_skin: tuple[np.ndarray, np.ndarray], outer_faces: np.ndarray,
                 outer_skin: tuple[np.ndarray, np.ndarray], covered: np.ndarray, face: np.ndarray,
                 bary: np.ndarray, n_joints: int, inner_laplacian: sp.spmatrix | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights of an inner garment (M vertices) that follow the outer garment where it
    covers them: on ``covered`` vertices, the outer garment's weights at their closest outer
    points (faces (M,), barycentric (M, 3)); elsewhere the inner garment's own weights plus a
    correction that fades out over the inner mesh (the screened Laplacian of the module
    docstring applied to the weight difference, exact on covered vertices). Under linear blend
    skinning an inner vertex and the outer point over it then move with one blended transform,
    so the inner garment stays inside the outer one in any pose. Skins are (indices (n, 4),
    weights (n, 4)); returns the inner garment's (M, 4) int32 and (M, 4) float32."""
    Wi = dense_weights(inner_skin[0], inner_skin[1], n_joints)
    if not covered.any():
        return top_k(Wi)
    Wo = dense_weights(outer_skin[0], outer_skin[1], n_joints)
    F = np.asarray(outer_faces, np.int64)
    Wq = np.einsum("mk,mkj->mj", bary, Wo[F[face]])
    c = covered.astype(np.float64)
    D0 = c[:, None] * (Wq - Wi)
    L = inner_laplacian if inner_laplacian is not None else uniform_laplacian(inner_faces, len(Wi))
    A = sp.diags(c + EPS) + SMOOTH * L
    D = factor_spd(A).solve(D0)
    D[covered] = D0[covered]
    return top_k(Wi + D)


def layer_outfit(garments: list[tuple[np.ndarray, np.ndarray]], body: np.ndarray, body_normals: np.ndarray,
                 gap: float = GAP, skins: list[tuple[np.ndarray, np.ndarray]] | None = None,
                 n_joints: int = 0) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]] | None]:
    """Garments [(vertices (M_i, 3), faces)] in layer order (inner first) on a body: each one
    pushed inside every garment over it (outermost first), from the outermost pair inwards so
    that every garment is pushed inside the final shape of those over it. With ``skins``
    [(indices (M_i, 4), weights (M_i, 4))] (``n_joints`` joints), each inner garment's skin
    also follows the garments over it where they cover it (:func:`covered_skin`; the next
    layer out last, whose own skin already follows the ones over it). Returns (the new
    vertices, the new skins or None)."""
    out = [np.asarray(v, np.float64) for v, _ in garments]
    sk = [(np.asarray(i), np.asarray(w)) for i, w in skins] if skins is not None else None
    B = np.asarray(body, np.float64)
    tree = cKDTree(B)
    # what depends on a garment's faces only, once per process per topology: Laplacians, rims
    topo = [topology(f, len(v)) for v, f in garments]
    lap = [t[0] for t in topo]
    prep: dict[int, tuple] = {}  # per outer garment, once its shape is final (it is never pushed again)
    for i in range(len(garments) - 2, -1, -1):
        for j in range(len(garments) - 1, i, -1):
            if j not in prep:
                prep[j] = prepare_outer(out[j], garments[j][1], B, body_normals, tree, topo[j][1], topo[j][2])
            out[i], covered, face, bary = _push_inside(out[i], garments[i][1], out[j], garments[j][1], B, body_normals,
                                                       gap, PASSES, tree, lap[i], topo[j][1], prep[j], topo[i][2])
            if sk is not None:
                sk[i] = covered_skin(garments[i][1], sk[i], garments[j][1], sk[j], covered, face, bary, n_joints,
                                     lap[i])
    return out, sk


# -- the body a garment hides ----------------------------------------------------------------------
HIDE_GAP = 0.02  # m: a body vertex is hidden only where the garment is at most this far outside its skin
# (on the mean body; 3 cm left holes at the armpits of a 200 cm / 130 kg customer)
HIDE_INSIDE = 0.002  # m: ...or this far inside it (a tight garment the body grazes)
HIDE_CONE_COS = 0.5  # ...and over it: the offset to the garment within 60 degrees of the body normal
HIDE_RIM_MARGIN = 0.05  # m: ...and at least this far from every vertex of the garment's rims (hems, cuffs)


def covered_body(body: np.ndarray, body_normals: np.ndarray, garment: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The body vertices an opaque garment hides, (H,) int64 sorted: the MakeHuman
    ``delete_verts`` idea computed for any garment. Body vertices (V, 3) with unit normals
    (V, 3), garment vertices (M, 3) and faces (F, 3), in the same pose.

    A body vertex is hidden when the garment's closest point lies over it (its offset within
    ``HIDE_CONE_COS`` of the body normal, or within ``HIDE_INSIDE`` of the vertex) at most
    ``HIDE_GAP`` outside or ``HIDE_INSIDE`` inside the skin, and the vertex is at least
    ``HIDE_RIM_MARGIN`` from every rim (boundary) vertex of the garment: near a hem or a cuff
    the skin stays, since a pose can lift the edge off it. Dropping the body's faces there
    (a face goes when all its vertices are hidden) keeps skin that the garment's own
    approximations (skinning, correctives) would let poke through from ever showing."""
    B = np.asarray(body, np.float64)
    n = np.asarray(body_normals, np.float64)
    Gv = np.asarray(garment, np.float64)
    F = np.asarray(faces, np.int64)
    if len(B) == 0 or len(F) == 0:
        return np.zeros(0, np.int64)
    rim = boundary_vertices(F, len(Gv))
    near = np.ones(len(B), bool)
    if rim.any():  # far from every rim vertex
        d_rim, _ = cKDTree(Gv[rim]).query(B, distance_upper_bound=HIDE_RIM_MARGIN)
        near = ~np.isfinite(d_rim)
    cand = np.flatnonzero(near)
    if len(cand) == 0:
        return np.zeros(0, np.int64)
    # only candidates whose nearest garment vertex can be within the gap (plus one edge)
    edge = np.linalg.norm(Gv[F] - Gv[np.roll(F, 1, axis=1)], axis=2).max()
    tree = cKDTree(Gv)
    d1, _ = tree.query(B[cand], distance_upper_bound=HIDE_GAP + edge)
    cand = cand[np.isfinite(d1)]
    if len(cand) == 0:
        return np.zeros(0, np.int64)
    _, q, _ = closest_points_on_mesh(B[cand], Gv, F, tree=tree)
    d = q - B[cand]
    dist = np.linalg.norm(d, axis=1)
    along = np.einsum("ij,ij->i", d, n[cand])
    over = (along >= HIDE_CONE_COS * dist) | (dist <= HIDE_INSIDE)
    hidden = over & (dist <= HIDE_GAP) & (along >= -HIDE_INSIDE)
    return np.sort(cand[hidden]).astype(np.int64)


def inner_outside_share(inner: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray, inner_faces: np.ndarray,
                        body: np.ndarray, body_normals: np.ndarray, body_faces: np.ndarray,
                        tolerance: float = 0.0, skins: tuple | None = None) -> tuple[int, int]:
    """The layering figure: (body vertices covered by both garments, of which the inner garment
    is outside the outer one by more than ``tolerance``). A body vertex is covered by a garment
    when the garment's closest point is within ``COVER_DISTANCE`` and its offset from the body
    vertex is mostly along the body normal (within 45 degrees) -- the garment is over it; the
    inner one is outside when its offset along the body normal is larger than the outer's.
    ``skins`` = (body's, inner's, outer's) skin weights, each ((n, k) indices, (n, k) weights)
    over the same joints: a garment then covers a body vertex only if it also moves with it --
    the skin weights at its closest point share at least ``MOVES_WITH`` with the vertex's
    (sum of the joint-wise minima). A posed hand resting on a hip lies over both garments
    there, seen from outside, but neither covers it: the cloth moves with the hips."""
    B = np.asarray(body, np.float64)
    J = 1 + max(int(np.max(s[0])) for s in skins) if skins is not None else 0
    Wb = dense_weights(*(np.asarray(a)[: len(B)] for a in skins[0]), J) if skins is not None else None

    def over(G, F, skin):
        F = np.asarray(F)
        face, q, bc = closest_points_on_mesh(B, G, F)
        d = q - B
        dist = np.linalg.norm(d, axis=1)
        along = np.einsum("ij,ij->i", d, body_normals)
        ok = (dist < COVER_DISTANCE) & (along > np.cos(np.pi / 4) * dist)
        if skin is not None:  # the garment's weights at its closest point, shared with the vertex's
            Wq = np.einsum("kj,kjb->kb", bc, dense_weights(*skin, J)[F[face]])
            ok &= np.minimum(Wb, Wq).sum(axis=1) >= MOVES_WITH
        return ok, along

    ci, ai = over(np.asarray(inner, np.float64), inner_faces, skins[1] if skins is not None else None)
    co, ao = over(np.asarray(outer, np.float64), outer_faces, skins[2] if skins is not None else None)
    both = ci & co
    return int(both.sum()), int((both & (ai > ao + tolerance)).sum())


def layered_pairs(inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray,
                  body: np.ndarray, body_normals: np.ndarray) -> tuple[np.ndarray, tuple, tuple]:
    """The body vertices covered by both garments (the test of :func:`inner_outside_share`) and,
    over each, the inner and the outer garment's closest points as (face (K,), barycentric
    (K, 3)) -- fixed surface points to follow through a pose. Returns (body vertex ids (K,),
    inner points, outer points)."""
    B = np.asarray(body, np.float64)

    def over(G, F):
        f, q, bc = closest_points_on_mesh(B, np.asarray(G, np.float64), F)
        d = q - B
        dist = np.linalg.norm(d, axis=1)
        return (dist < COVER_DISTANCE) & (np.einsum("ij,ij->i", d, body_normals) > np.cos(np.pi / 4) * dist), f, bc

    ci, fi, bi = over(inner, inner_faces)
    co, fo, bo = over(outer, outer_faces)
    k = np.flatnonzero(ci & co)
    return k, (fi[k], bi[k]), (fo[k], bo[k])


def posed_outside(pairs: tuple[np.ndarray, tuple, tuple], inner: np.ndarray, inner_faces: np.ndarray,
                  outer: np.ndarray, outer_faces: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                  tolerance: float = 0.0) -> int:
    """The posed layering figure: of the rest pose's :func:`layered_pairs`, how many have the
    inner garment's point outside the outer garment's point (higher along the body normal, by
    more than ``tolerance``) once garments (M_i, 3) and body (V, 3) with normals are posed.
    Following fixed points, not re-matching closest points, keeps a hand resting on a hip (over
    both garments, covering neither) out of the figure."""
    k, (fi, bi), (fo, bo) = pairs
    if len(k) == 0:
        return 0
    pi = np.einsum("kj,kji->ki", bi, np.asarray(inner, np.float64)[np.asarray(inner_faces)[fi]])
    po = np.einsum("kj,kji->ki", bo, np.asarray(outer, np.float64)[np.asarray(outer_faces)[fo]])
    n = np.asarray(body_normals, np.float64)[k]
    return int((np.einsum("ij,ij->i", pi - po, n) > tolerance).sum())

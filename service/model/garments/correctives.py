"""Pose-corrective morph targets: per page pose, rest-space POSITION deltas that keep a skinned
garment outside the posed body. Pure numpy/scipy.

Plain linear blend skinning pushes some garment vertices inside the body in the page's poses
(an arm swung back drags the blouse's side into the chest). For each pose (the bone transforms
G (J, 4, 4) the page applies: the presets adapted to the body, ``service.model.body.poses``), the
garment is posed with its own skin weights and:

1. the vertices nearer the posed skin than ``TRIGGER`` (signed distance to the closest point
   of the posed body without the hands, ``geometry.closest_points_on_mesh``) are pushed out to
   ``CLEARANCE`` (plus the layer's gap) along the surface normal there, unless that lands them
   inside another part (the armpit between arm and chest);
2. the pushes are spread to the neighbours by the garment's smoother, as ``garment.push_out``
   does at rest, and pushes that would stretch an edge beyond ``STRETCH_LIMIT`` are dropped;
3. where a body vertex still pokes through a garment triangle between vertices outside the
   body (coarse garments over a bulging chest), that triangle's vertices are pushed the same
   way (``BODY_POKES``), kept only if fewer body vertices poke through afterwards;
4. every edge stretched beyond ``STRAIN_LIMIT`` x its rest length is shortened, the strain
   spread over the neighbouring cloth, the body kept out (:func:`limit_strain`, Provot's strain
   limiting; ``STRAIN_LIMITING``);

and the posed displacement d is taken back to rest space with the inverse of the vertex's
blended LBS matrix: glTF (and three.js) add morph deltas before skinning, and skinning is
linear in the rest position, so skin(v + A^-1 d) = skin(v) + d with A = sum_k w_k
G_{i_k}[:3, :3] (the blended linear part; Kavan et al. 2008, eq. 1).

The target of pose ``p`` is named ``pose:p``; the page sets its influence to 1 in that pose, 0
otherwise. Shapes: garment vertices (M, 3) metres, skin (M, 4) + (M, 4), body (V, 3).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.garments import garment as G
from service.model.body import lbs as L
from service.model.body.model import BONES
from service.model.geometry.mesh import (
    barycentric,
    closest_point_on_triangles,
    closest_points_on_mesh,
    face_bounds,
    vertex_faces,
    vertex_normals,
)

TARGET_PREFIX = "pose:"
# metres: posed garment vertices nearer the posed skin than this are pushed out. Below the try-on's
# CLEARANCE (3 mm) so that cloth merely pressed a little closer by a pose (most of it) keeps a
# zero delta: the targets stay sparse
TRIGGER = 0.001
# metres: where they are pushed to (plus ``garment.LAYER_GAP`` per layer: an outer garment over
# the inner one's correction, as at rest)
CLEARANCE = 0.002
STRETCH_LIMIT = 1.8  # an edge may be stretched by a push up to this ratio (or its stretch without it): the
# avatar's own skin stretches 1.79 at p99.9 in these poses. 1.5 kept 2-4x more vertices inside, 2.2 and no
# limit stretched more (cropped tee, white T-shirt, casual jacket on the 165/105 woman and 200/130 man)
# step 3: the 200/130 man's chest showed through the pinstripe blouse in front of the arm in the
# walking step (page screenshots) with no garment vertex inside it: 66 -> 55 body vertices poking
# through it after steps 1-2, 22 with step 3
BODY_POKES = True
POKE_DISTANCE = 0.02  # metres: body vertices this near the posed garment are tested for poking through it
PREFILTER = 0.02  # metres: closest points only for vertices this near the skin by the push-out's measure
# (0.005 / 0.01 left 1.5x / 1.3x as many vertices inside as exact everywhere; 0.02 within 5 %)
STRETCH_PASSES = 3  # rounds of dropping the pushes that stretch an edge beyond that
MIN_DELTA = 1e-5  # metres: rest deltas shorter than this are left out (0 in the sparse target)
# step 4 (limit_strain): where skinning stretches cloth more than woven cloth gives (an edge between the arm and
# the torso in the arms-down and hands-on-hips poses, bunched cloth pulled open), its edges are
# shortened back to this ratio of their rest length, the strain spread to their neighbours
STRAIN_LIMIT = 1.4
STRAIN_ITERATIONS = 100  # Jacobi rounds of the edge projection
STRAIN_RELAXATION = 1.5  # over-relaxed Jacobi averaging (Macklin et al. 2014, sec. 4.2: 1 < w < 2)
STRAIN_BODY_EVERY = 4  # rounds between the body checks (each a closest-point query)
STRAIN_LIMITING = True
HAND_WEIGHT = 0.5  # body vertices with more skin weight on the hands are no obstacle: a hand on a hip
# rests on the cloth (pushing the skirt out over the hand would hide it)


@dataclass
class PosedBody:
    """One pose of a customer's body: the bone transforms (J, 4, 4), the posed body (Vb, 3)
    and its unit vertex normals (Vb, 3); the obstacle surface (all but the hands: ``ids`` (K,)
    body vertices, ``faces`` (F', 3) into them) with a k-d tree, vertex faces and face bounds
    for ``geometry.closest_points_on_mesh``."""

    transforms: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    ids: np.ndarray
    faces: np.ndarray
    tree: cKDTree
    vert_faces: np.ndarray
    bounds: tuple


@functools.lru_cache(maxsize=4)
def obstacles(model) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body surface garments are kept outside of, all but the hands: its body vertices
    (K,), faces (F', 3) into them and ``geometry.vertex_faces`` (K, valence) (once per model)."""
    nb = model.n_body_vertices
    idx, w = np.asarray(model.lbs_indices[:nb]), np.asarray(model.lbs_weights[:nb], np.float64)
    hands = np.isin(idx, [BONES.index("hand_l"), BONES.index("hand_r")])
    keep = (w * hands).sum(1) <= HAND_WEIGHT
    F = np.asarray(model.body_faces)
    F = F[keep[F].all(axis=1)]
    ids = np.unique(F)
    remap = np.full(nb, -1, np.int64)
    remap[ids] = np.arange(len(ids))
    F = remap[F]
    return ids, F, vertex_faces(F, len(ids))


def posed_body(model, vertices: np.ndarray, pose: np.ndarray) -> PosedBody:
    """The avatar ``vertices`` (V, 3) in ``pose`` ((17, 3) axis-angle, ``BONES`` order)."""
    nb = model.n_body_vertices
    posed = model.forward(pose=pose, vertices=vertices)
    pb = posed.vertices[:nb]
    ids, F, vf = obstacles(model)
    V = pb[ids]
    return PosedBody(posed.transforms, pb, vertex_normals(pb, model.body_faces).astype(np.float64), ids, F,
                     cKDTree(V), vf, face_bounds(V, F))


def skin_offsets(points: np.ndarray, body: PosedBody, below: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(M,) the signed distance of each point (M, 3) to the obstacle surface of ``body`` (< 0
    inside; the sign from the surface's interpolated vertex normal at the closest point) and
    that unit normal (M, 3): the direction to push it out along. With ``below`` (metres): exact
    only for the points whose offset from their nearest obstacle vertex's tangent plane (the
    try-on push-out's distance) is below it; the others keep that offset and vertex normal."""
    p = np.asarray(points, np.float64)
    V, N = body.vertices[body.ids], body.normals[body.ids]
    if below is None:
        todo = np.arange(len(p))
        along, n = np.empty(len(p)), np.empty((len(p), 3))
    else:
        nn = body.tree.query(p)[1]
        n = N[nn]
        along = np.einsum("ij,ij->i", p - V[nn], n)
        todo = np.flatnonzero(along < below)
        if not len(todo):
            return along, n
    face, q, bary = closest_points_on_mesh(p[todo], V, body.faces, tree=body.tree, vert_faces=body.vert_faces,
                                           bounds=body.bounds)
    nq = np.einsum("mk,mkj->mj", bary, N[body.faces[face]])
    nq /= np.maximum(np.linalg.norm(nq, axis=1, keepdims=True), 1e-12)
    d = p[todo] - q
    along[todo] = np.sign(np.einsum("ij,ij->i", d, nq)) * np.linalg.norm(d, axis=1)
    n[todo] = nq
    return along, n


def corrective_deltas(garment: np.ndarray, skin_idx: np.ndarray, skin_w: np.ndarray, body: PosedBody,
                      smoother: sp.csc_matrix | None, layer: int = 0,
                      rest: PosedBody | None = None, faces: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Rest-space deltas (M, 3) float32 that keep the garment (M, 3), skinned with (M, 4) +
    (M, 4), outside the posed ``body`` once added before skinning, and how many vertices were
    pushed: :func:`posed_pushes` taken back to rest space (:func:`to_rest`)."""
    d, count = posed_pushes(garment, skin_idx, skin_w, body, smoother, layer, rest, faces)
    return to_rest(d, body.transforms, skin_idx, skin_w), count


def to_rest(d: np.ndarray, transforms: np.ndarray, skin_idx: np.ndarray, skin_w: np.ndarray) -> np.ndarray:
    """Posed displacements (M, 3) as rest-space morph deltas (M, 3) float32: A_i^-1 d_i with A_i
    the vertex's blended linear part sum_k w_k G_{i_k}[:3, :3] (rows shorter than
    ``MIN_DELTA`` left 0)."""
    out = np.zeros(d.shape, np.float32)
    rows = np.flatnonzero(np.einsum("ij,ij->i", d, d) > MIN_DELTA ** 2)
    A = L.blend_transforms(transforms, np.asarray(skin_idx)[rows], np.asarray(skin_w)[rows])[:, :3, :3]
    out[rows] = np.linalg.solve(A, d[rows][:, :, None])[:, :, 0]
    return out


def posed_pushes(garment: np.ndarray, skin_idx: np.ndarray, skin_w: np.ndarray, body: PosedBody,
                 smoother: sp.csc_matrix | None, layer: int = 0, rest: PosedBody | None = None,
                 faces: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """The posed displacement (M, 3) float64 that keeps the garment (M, 3) skinned into
    ``body``'s pose outside it, and how many vertices were pushed (see the module docstring).
    ``layer``: the garment's rank in its outfit (clearance + layer x LAYER_GAP). ``rest``: the
    body unposed; a vertex nearer the skin than the clearance already at rest (an inner garment
    pushed inside the one over it by ``service.model.garments.layering``) is pushed back no farther out
    than it was at rest, and only once it is ``CLEARANCE - TRIGGER`` deeper: the rest pose gets
    no vertex push (only step 3, the triangles the body pokes through) and the layers keep their order. ``faces``: the garment's; with them, pushes that
    would stretch an edge beyond ``STRETCH_LIMIT`` are dropped."""
    v = np.asarray(garment, np.float64)
    zero = np.zeros(v.shape)
    if np.allclose(body.transforms, np.eye(4), atol=1e-12):
        # the rest pose: no vertex moved into the body, but body vertices can poke through the
        # garment's triangles (the try-on keeps vertices out, not the chords between them: skin
        # showed on the 165/105 woman's jeans in the page's A-pose, 36 body vertices through
        # them); with the faces, step 3 alone
        if faces is None or not BODY_POKES:
            return zero, 0
        edges = _edges(faces, len(v))
        d = _poke_pushes(v, v, faces, edges, body, CLEARANCE + layer * G.LAYER_GAP, smoother)
        if STRAIN_LIMITING and np.any(d):
            d = limit_strain(v, v + d, edges, body, CLEARANCE + layer * G.LAYER_GAP) - v
        return d, int(np.count_nonzero(np.any(d != 0.0, axis=1)))
    clearance, trigger = CLEARANCE + layer * G.LAYER_GAP, TRIGGER + layer * G.LAYER_GAP
    if rest is not None:
        at_rest = skin_offsets(v, rest, CLEARANCE + layer * G.LAYER_GAP + PREFILTER)[0]
        clearance = np.minimum(clearance, np.maximum(at_rest, 0.0))
        trigger = np.minimum(trigger, at_rest - (CLEARANCE - TRIGGER))
    pv = L.skin(v, body.transforms, skin_idx, skin_w)
    along, normal = skin_offsets(pv, body, TRIGGER + layer * G.LAYER_GAP + PREFILTER)
    bad = np.flatnonzero(along < trigger)
    edges = None if faces is None else _edges(faces, len(v))
    d, pushed = zero, 0
    if len(bad):
        n = normal[bad]
        need = (clearance if np.isscalar(clearance) else clearance[bad]) - along[bad]  # > 0
        # pushed out of one part into another (the armpit between arm and chest): left where it is
        keep = skin_offsets(pv[bad] + need[:, None] * n, body)[0] > 0.0
        bad, n, need = bad[keep], n[keep], need[keep]
        d, pushed = _spread_within_stretch(v, pv, bad, need, n, smoother, edges)
    if edges is not None and BODY_POKES:
        # step 3 whether or not a vertex was pushed: with every vertex outside the posed body,
        # body vertices can still poke through the triangles between them (a coarse garment
        # over a convex limb: 25 body vertices up to 2.6 mm through the women's jeans on the
        # 195/80 man in the arms-down and hands-on-hips poses, whose legs are as at rest)
        d = d + _poke_pushes(v, pv + d, faces, edges, body, CLEARANCE + layer * G.LAYER_GAP, smoother)
    if edges is not None and STRAIN_LIMITING:
        d = limit_strain(v, pv + d, edges, body, clearance) - pv
    return d, int(np.count_nonzero(np.any(d != 0.0, axis=1)))


def limit_strain(rest: np.ndarray, posed: np.ndarray, edges: np.ndarray, body: PosedBody,
                 clearance: float | np.ndarray) -> np.ndarray:
    """The posed garment (M, 3) with no edge (E, 2) longer than ``STRAIN_LIMIT`` times its rest
    length (``rest`` (M, 3)), as far as the body lets it: Provot's strain limiting ("Deformation
    constraints in a mass-spring model to describe rigid cloth behavior", 1995, sec. 4: each
    over-stretched edge's ends moved toward each other by half the excess), as Jacobi rounds of
    position-based projections (Mueller et al. 2007, eq. 9 with equal masses) averaged per
    vertex; after each round the moved vertices are kept at least ``clearance`` (scalar or (M,))
    outside the posed body, or as far out as they were (an inner layer's vertex nearer the skin
    stays where it was put). Vertices on no over-stretched edge do not move."""
    x = np.array(posed, np.float64)
    m = len(x)
    limit_all = STRAIN_LIMIT * np.linalg.norm(rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    floor = np.full(m, np.nan)  # how far out each vertex may be kept: the clearance or where it was
    reach = float(np.max(clearance)) + PREFILTER
    start = x.copy()  # where the vertices were at the last body check
    sub = None  # the edges worked on between body checks: those at a vertex that moved or is on an over-stretched edge
    for k in range(STRAIN_ITERATIONS):
        if sub is None:  # a full check of every edge (at the start and after each body check)
            length = np.linalg.norm(x[edges[:, 1]] - x[edges[:, 0]], axis=1)
            hot = np.zeros(m, bool)
            hot[edges[length > limit_all * (1 + 1e-3)].ravel()] = True
            hot |= np.einsum("ij,ij->i", x - posed, x - posed) > 0.0
            ring = hot[edges[:, 0]] | hot[edges[:, 1]]
            hot[edges[ring].ravel()] = True  # and their neighbours: the ends of their edges may move
            sub = np.flatnonzero(hot[edges[:, 0]] | hot[edges[:, 1]])
            a, b, limit = edges[sub, 0], edges[sub, 1], limit_all[sub]
        e = x[b] - x[a]
        length = np.linalg.norm(e, axis=1)
        over = np.flatnonzero(length > limit * (1 + 1e-3))
        if len(over):
            c = (0.5 * (1.0 - limit[over] / length[over]))[:, None] * e[over]
            ends = np.r_[a[over], b[over]]
            dx = np.stack([np.bincount(ends, np.r_[c[:, j], -c[:, j]], minlength=m) for j in range(3)], axis=1)
            cnt = np.bincount(ends, minlength=m)
            moved = np.flatnonzero(cnt)
            x[moved] += STRAIN_RELAXATION * dx[moved] / cnt[moved, None]
        if len(over) and (k + 1) % STRAIN_BODY_EVERY and k + 1 < STRAIN_ITERATIONS:
            continue
        step = x - start
        moved = np.flatnonzero(np.einsum("ij,ij->i", step, step) > 0.0)
        if not len(moved):  # nothing over the limit from the start: no body query at all
            break
        new = moved[np.isnan(floor[moved])]
        if len(new):
            floor[new] = np.minimum(np.broadcast_to(clearance, (m,))[new],
                                    skin_offsets(np.asarray(posed, np.float64)[new], body, reach)[0])
        off, n = skin_offsets(x[moved], body, reach)
        # back out along the surface normal, by no more than the rounds moved it: a closest point
        # that jumped to another part (the vertex between arm and chest) does not throw it across
        push = np.minimum(floor[moved] - off, np.linalg.norm(step[moved], axis=1))
        inside = push > 0
        x[moved[inside]] += push[inside, None] * n[inside]
        start = x.copy()
        sub = None
        if not len(over) and not inside.any():  # no edge over the limit, and none pulled the
            break  # garment into the body since the last check
    return x


def _spread_within_stretch(v: np.ndarray, pv: np.ndarray, bad: np.ndarray, need: np.ndarray, n: np.ndarray,
                           smoother: sp.csc_matrix | None, edges: np.ndarray | None) -> tuple[np.ndarray, int]:
    """The posed displacement (M, 3) of the pushes (``_spread``) of the garment (rest v, posed
    pv (M, 3)), and how many pushes were kept: with ``edges`` (E, 2), an edge the pushes stretch
    beyond STRETCH_LIMIT (and beyond its stretch without them) -- a garment vertex squeezed
    between two parts pushed out of one (the jacket's side between arm and chest) -- has its
    ends' pushes dropped, up to STRETCH_PASSES times."""
    if edges is not None:
        a, b = edges[:, 0], edges[:, 1]
        rest_len = np.linalg.norm(v[a] - v[b], axis=1) + 1e-12
        before = np.linalg.norm(pv[a] - pv[b], axis=1) / rest_len
    for rounds in range(STRETCH_PASSES + 1):
        if not len(bad):
            return np.zeros_like(pv), 0
        d = _spread(len(pv), bad, need, n, smoother)
        if edges is None or rounds == STRETCH_PASSES:
            break
        after = np.linalg.norm(pv[a] + d[a] - pv[b] - d[b], axis=1) / rest_len
        over = after > np.maximum(before, STRETCH_LIMIT)
        if not over.any():
            break
        drop = np.isin(bad, edges[over].ravel())
        bad, n, need = bad[~drop], n[~drop], need[~drop]
    return d, len(bad)


def _poke_pushes(v, pv, faces, edges, body, clearance, smoother):
    """Posed displacement (M, 3) of the garment (posed (M, 3)) where body vertices poke through
    its triangles between vertices outside the body (:func:`body_pokes`), stretch-limited as
    the vertex pushes."""
    bad, need, n = body_pokes(pv, faces, body, clearance)
    pokes = len(bad)  # 3 per body vertex poking through
    if not len(bad):
        return np.zeros_like(pv)
    order = np.lexsort((-need, bad))  # per vertex, its largest push
    bad, need, n = bad[order], need[order], n[order]
    first = np.r_[True, bad[1:] != bad[:-1]]
    bad, need, n = bad[first], need[first], n[first]
    keep = skin_offsets(pv[bad] + need[:, None] * n, body)[0] > 0.0  # not into another part
    bad, need, n = bad[keep], need[keep], n[keep]
    d = _spread_within_stretch(v, pv, bad, need, n, smoother, edges)[0]
    # kept only if fewer body vertices poke through after it: around a foot (a shoe's insole and
    # upper both over the skin) the pushes made more (the leather shoes on the 160/55 woman at
    # rest: 146 -> 226 body vertices, the sneakers on the 185/80 man 18 -> 168)
    if len(body_pokes(pv + d, faces, body, clearance)[0]) >= pokes:
        return np.zeros_like(pv)
    return d


def body_pokes(pv: np.ndarray, faces: np.ndarray, body: PosedBody,
               clearance: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Garment vertices (K,) to push, by how much (K,) and along which unit normal (K, 3), where
    a posed body vertex pokes through a garment triangle (M, 3) / (F, 3): the body vertex's
    closest garment point is over it (within 45 degrees of its normal, not on the garment's
    rim, within ``POKE_DISTANCE``) but nearer than ``TRIGGER`` along the normal or under it;
    the triangle's three vertices are pushed so that the point is ``clearance`` out."""
    X = body.vertices[body.ids]
    N = body.normals[body.ids]
    which, s, face = poking_through(pv, faces, X, N, TRIGGER)
    if not len(which):
        return np.zeros(0, np.int64), np.zeros(0), np.zeros((0, 3))
    F = np.asarray(faces, np.int64)
    return F[face].reshape(-1), np.repeat(clearance - s, 3), np.repeat(N[which], 3, axis=0)


def poking_through(pv: np.ndarray, faces: np.ndarray, X: np.ndarray, N: np.ndarray, trigger: float,
                   index: tuple[cKDTree, cKDTree, float] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body points X (P, 3) with unit normals N (P, 3) that poke through a garment (M, 3) /
    (F, 3): their closest garment point is over them (within 45 degrees of the normal), not
    on the garment's rim, within ``POKE_DISTANCE``, and nearer than ``trigger`` along the
    normal or under it. Returns (indices into X (K,), the garment point's height over the
    point along its normal (K,) (< trigger; negative: the skin is outside the cloth), its
    garment face (K,)). ``index``: :func:`garment_index` of the garment, to reuse."""
    from service.model.garments.layering import topology

    F = np.asarray(faces, np.int64)
    empty = (np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64))
    if not len(X) or not len(F):
        return empty
    tree, sample_tree, reach = index if index is not None else garment_index(pv, F)
    dist0, _ = sample_tree.query(X, distance_upper_bound=reach)
    near = np.flatnonzero(np.isfinite(dist0))
    if not len(near):
        return empty
    _, boundary, vert_faces = topology(F, len(pv))
    face, q, bary = closest_points_on_mesh(X[near], pv, F, tree=tree, vert_faces=vert_faces)
    off = q - X[near]
    dist = np.linalg.norm(off, axis=1)
    s = np.einsum("ij,ij->i", off, N[near])
    fb = boundary[F[face]]
    edge_bound = np.stack([fb[:, 1] & fb[:, 2], fb[:, 2] & fb[:, 0], fb[:, 0] & fb[:, 1]], axis=1)
    rim = ((bary < 1e-3) & edge_bound).any(axis=1) | ((bary > 1 - 1e-3) & fb).any(axis=1)
    poke = ~rim & (dist < POKE_DISTANCE) & (np.abs(s) > np.cos(np.pi / 4) * dist) & (s < trigger)
    return near[poke], s[poke], face[poke]


def skin_under_faces(garment: np.ndarray, faces: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                     trigger: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body vertices (B, 3) with unit normals (B, 3) that poke through a garment (M, 3) /
    (F, 3) between its vertices, or come nearer than ``trigger`` (:func:`poking_through`), for
    ``garment.push_out``'s face pass: (body vertex indices (R,), garment faces (R,), barycentric
    weights (R, 3) of the body vertex's closest point in its face)."""
    X = np.asarray(body, np.float64)
    which, _, face = poking_through(np.asarray(garment, np.float64), faces, X,
                                    np.asarray(body_normals, np.float64), trigger)
    F = np.asarray(faces, np.int64)
    tri = np.asarray(garment, np.float64)[F[face]]
    q = closest_point_on_triangles(X[which], tri[:, 0], tri[:, 1], tri[:, 2])
    return which, face, barycentric(q, tri[:, 0], tri[:, 1], tri[:, 2])


POKE_SAMPLE_SPACING = 0.045  # m: triangles longer than this get extra prefilter samples (see garment_index;
# 0.015 and 0.03 cost more in sampling and a second k-d tree than they saved)


def garment_index(pv: np.ndarray, faces: np.ndarray) -> tuple[cKDTree, cKDTree, float]:
    """What :func:`poking_through` searches a posed garment (M, 3) / (F, 3) with: a k-d tree over
    its vertices (the exact closest points), one over prefilter samples, and the prefilter's
    reach. The samples are the vertices plus, on each triangle whose longest edge L exceeds
    ``POKE_SAMPLE_SPACING``, the points of its barycentric grid of n = ceil(L / spacing)
    subdivisions: every point of the triangle is then within L / n of a sample (the longest edge
    of its sub-triangle), so a body point within POKE_DISTANCE of the garment is within
    POKE_DISTANCE + max(L / n) of a sample. Vertices alone would need POKE_DISTANCE plus the
    longest edge of all (~10 cm on the MakeHuman garments, a third of the body tested; with the
    samples, at most 6.5 cm: the correctives of a shirt under a jacket 7-13 % faster, same
    results)."""
    F = np.asarray(faces, np.int64)
    P = np.asarray(pv, np.float64)
    tri = P[F]
    L = np.sqrt(np.max([((tri[:, k] - tri[:, (k + 1) % 3]) ** 2).sum(1) for k in range(3)], axis=0))
    n = np.maximum(np.ceil(L / POKE_SAMPLE_SPACING), 1).astype(np.int64)
    extra = []
    for m in np.unique(n[n > 1]):
        i, j = np.meshgrid(np.arange(m + 1), np.arange(m + 1), indexing="ij")
        keep = (i + j <= m) & ~(((i == m) | (j == m)) | ((i == 0) & (j == 0)))  # corners are vertices
        W = np.stack([i[keep], j[keep], m - i[keep] - j[keep]], 1) / m  # (k, 3) barycentric
        extra.append(np.einsum("kj,fjd->fkd", W, tri[n == m]).reshape(-1, 3))
    samples = np.concatenate([P, *extra]) if extra else P
    vertex_tree = cKDTree(P)
    return vertex_tree, (cKDTree(samples) if extra else vertex_tree), POKE_DISTANCE + float((L / n).max())


# -- the body's own pose targets: skin still showing through the clothes ---------------------------
TUCK_MARGIN = 0.002  # m: skin showing through a worn garment is pulled this far under it
TUCK_MAX_DEPTH = 0.025  # m: skin farther out than this is left (a limb through the cloth, not flesh on it)
TUCK_PASSES = 5  # rounds of finding what still shows and pulling it in (the smoothing moves neighbours)
BODY_TUCKS = True


@functools.lru_cache(maxsize=4)
def body_smoother(model) -> sp.csc_matrix:
    """The body surface's displacement diffusion operator (``garment.laplacian_smoother`` over
    the body faces, (Vb, Vb)), once per model."""
    return G.laplacian_smoother(np.asarray(model.body_faces), model.n_body_vertices)


def body_tucks(posed: PosedBody, garments: list[tuple[np.ndarray, np.ndarray]], shown: np.ndarray,
               smoother: sp.csc_matrix | None, body_faces: np.ndarray) -> np.ndarray:
    """The posed displacement (Vb, 3) of the body that pulls skin showing through worn garments
    back under them, in one pose: soft flesh pressed on cloth (an upper arm against its sleeve
    and the shirt's side, a hip in the walking step) gives way instead of piercing it, where
    the garments' own corrections (steps 1-4) left it out. ``garments``: the posed garments
    (vertices (M_i, 3), faces (F_i, 3)) as the page shows them (pose targets applied);
    ``shown`` (Vb,) bool: body vertices drawn (not hidden under a garment); ``smoother``: the
    body's diffusion operator (``garment.laplacian_smoother``) spreading each pull to the
    neighbours, as the garments' pushes are spread. A shown vertex (not a hand) poking through
    a garment (:func:`poking_through`, trigger 0: the skin out of the cloth) by less than
    ``TUCK_MAX_DEPTH`` is pulled along its inward normal to ``TUCK_MARGIN`` under the cloth;
    ``TUCK_PASSES`` rounds."""
    nb = len(posed.vertices)
    ids = posed.ids[np.asarray(shown)[posed.ids]]
    garments = [(np.asarray(pv, np.float64), faces) for pv, faces in garments]
    indices = [garment_index(pv, faces) for pv, faces in garments]
    d = np.zeros((nb, 3))
    for _ in range(TUCK_PASSES):
        pb = posed.vertices + d
        N = vertex_normals(pb, body_faces)[ids] if d.any() else posed.normals[ids]
        X = pb[ids]
        depth = np.zeros(len(ids))
        for (pv, faces), index in zip(garments, indices):
            which, s, _ = poking_through(pv, faces, X, N, 0.0, index)
            depth[which] = np.maximum(depth[which], -s)
        pull = np.flatnonzero((depth > 0) & (depth < TUCK_MAX_DEPTH))
        if not len(pull):
            break
        step = _spread(nb, ids[pull], depth[pull] + TUCK_MARGIN, -N[pull], smoother)
        d += step
        # the next pass tests only the skin this one moved (what it pulled and the neighbours the
        # pull spread to, partly pulled): elsewhere nothing changed
        moved = np.zeros(nb, bool)
        moved[np.flatnonzero(np.einsum("ij,ij->i", step, step) > 0)] = True
        ids = ids[moved[ids]]
    return d


def _spread(m: int, bad: np.ndarray, need: np.ndarray, n: np.ndarray, smoother: sp.csc_matrix | None) -> np.ndarray:
    """The posed displacement (m, 3) of pushing vertices ``bad`` (K,) by ``need`` (K,) along
    ``n`` (K, 3): garment.push_out's scheme, each push diffused to the neighbours by the
    garment's smoother, then each pushed vertex's own push made whole."""
    d = np.zeros((m, 3))
    d[bad] = need[:, None] * n
    if smoother is not None:
        d = np.asarray(smoother[:, bad] @ d[bad], np.float64)
        d[bad] += np.maximum(need - np.einsum("ij,ij->i", d[bad], n), 0.0)[:, None] * n
    return d


def _edges(faces: np.ndarray, n: int) -> np.ndarray:
    """(E, 2) the mesh's edges, from ``layering.topology``'s Laplacian (cached per topology)."""
    from service.model.garments.layering import topology

    lap = topology(faces, n)[0].tocoo()
    up = lap.row < lap.col
    return np.stack([lap.row[up], lap.col[up]], axis=1)


def cover_map(inner: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray, body: np.ndarray,
              body_normals: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where an outfit's outer garment (N, 3) covers the inner one (M, 3) on the rest body (V, 3)
    with its normals, as ``layering.violations`` decides it (the closest outer point inside the
    outer surface within ``layering.COVER_DISTANCE``, or a rim over the body vertex under it),
    and those closest points as (face (M,), barycentric (M, 3)). Returns (covered (M,) bool,
    face, bary)."""
    from service.model.garments import layering as LY

    O = np.asarray(outer, np.float64)
    B = np.asarray(body, np.float64)
    Bn = np.asarray(body_normals, np.float64)
    tree = cKDTree(B)
    F = np.asarray(outer_faces, np.int64)
    on, ob, index, _ = LY.prepare_outer(O, F, B, Bn, tree, LY.topology(F, len(O))[1])
    _, covered, face, bary = LY.violations(np.asarray(inner, np.float64), O, F, on, ob, B, Bn, tree,
                                           outer_index=index)
    return covered, face, bary


def follow_outer(d: np.ndarray, cover: tuple[np.ndarray, np.ndarray, np.ndarray], d_outer: np.ndarray,
                 outer_faces: np.ndarray) -> np.ndarray:
    """An inner garment's posed pushes (M, 3) with each covered vertex (:func:`cover_map`) moved
    as the outer garment's point over it (its posed pushes (N, 3) interpolated): the layers
    keep the order they have posed without correctives (the inner one, skinned like the outer
    one where covered, stays under it), and the outer one hides what is under it."""
    covered, face, bary = cover
    out = np.array(d, np.float64)
    F = np.asarray(outer_faces, np.int64)
    out[covered] = np.einsum("mk,mkj->mj", bary[covered], np.asarray(d_outer, np.float64)[F[face[covered]]])
    return out


def target_names(poses) -> list[str]:
    """The morph target names of poses (their names, in order)."""
    return [TARGET_PREFIX + name for name in poses]

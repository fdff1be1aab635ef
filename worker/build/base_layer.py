"""The avatar's base layer (underwear), generated offline from the body template.

There is no CC0 underwear for the hm08 mesh, so it is made here, on the population-mean avatar:

1. *Region*: a smooth scalar field over 3D positions (planes through body landmarks, joined by
   smooth min/max so corners are rounded) is positive where the garment is. It is evaluated on
   the body surface, refined by midpoint subdivision.
2. *Clean edges*: the surface is cut along the field's zero iso-line (marching triangles). A
   vertex whose edge is cut within ``snap`` of it is first moved onto the iso-line, so the cut
   leaves no slivers; the edge is a smooth curve, not a staircase of triangle edges.
3. *Ease*: offset off the skin, then a constrained smoothing (shrink-wrap): umbrella smoothing of
   the surface (boundary vertices along the boundary curve only) alternated with a projection
   that keeps every vertex at least ``ease`` outside the body. Concavities (navel, cleavage,
   gluteal cleft) are bridged like stretched fabric instead of painted on; the elastic edges get
   a slight lift.
4. *Binding*: every vertex is expressed like a MakeHuman ``.mhclo`` vertex: the closest point
   of the body surface (a triangle of hm08 vertices and barycentric weights) plus an offset in
   decimetres, scaled per axis by the suits' reference vertex pairs measured on the mean avatar.
   So the base layer fits any avatar through ``Binding.fit``, exactly as a MakeHuman garment.

Shapes: body vertices (V, 3) metres (the mean avatar), faces (F, 3) int; garment (M, 3).
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from service.model.body.model import BONES
from service.model.geometry.mesh import closest_points_on_mesh, edge_counts, mesh_edges, vertex_faces, vertex_normals
from service.model.formats.mhclo import DM, Binding

B = {b: i for i, b in enumerate(BONES)}
# The suits' reference pairs (x, y, z): hm08 vertices whose distances scale the offsets.
SCALE_PAIRS = ((5399, 11998), (791, 881), (962, 5320))

Field = Callable[[np.ndarray], np.ndarray]  # positions (P, 3) -> (P,) > 0 inside the garment
HIDDEN_NEAR = 0.02  # m: body vertices hidden by a piece lie this close to it


@dataclass(frozen=True)
class BaseLayerParams:
    ease: float = 0.0035  # m of cloth off the skin everywhere
    hem_lift: float = 0.0015  # extra lift of the elastic edges (m)
    hem_width: float = 0.008  # how far in from the edge the lift fades (m)
    wrap_iterations: int = 60  # shrink-wrap: smoothing + projection rounds
    wrap_step: float = 0.5  # umbrella smoothing step per round
    corner: float = 0.012  # radius (m) of the smooth min/max where two cut lines meet
    snap: float = 0.3  # vertices within this fraction of a cut edge snap onto the iso-line
    subdivisions: int = 1  # midpoint subdivisions of the body region before the cut
    hidden_margin: float = 0.015  # body vertices this far inside the edge (field units, m) are hidden
    envelope_smoothing: int = 10  # umbrella rounds that take small bumps (nipples) off the body...
    envelope_radius: float = 0.04  # ...whose height is then spread as smooth tents of this radius (m)


PARAMS = BaseLayerParams()


@dataclass(frozen=True)
class BaseLayerPiece:
    """One generated garment: binding (fits any avatar), faces (F, 3) int32, planar uv (M, 2)
    float32 with face_uv = faces, the body vertices it hides (H,) int32, and its vertices on the
    mean avatar (M, 3) float64."""

    binding: Binding
    faces: np.ndarray
    uv: np.ndarray
    hidden: np.ndarray
    vertices: np.ndarray


# -- fields ---------------------------------------------------------------------------------------
def smin(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Smooth minimum (log-sum-exp) of two fields, softness k (m)."""
    return -k * np.logaddexp(-a / k, -b / k)


def smax(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    return k * np.logaddexp(a / k, b / k)


@dataclass(frozen=True)
class Landmarks:
    """Mean-avatar landmarks the cut lines are placed by (metres)."""

    navel: np.ndarray
    crotch: np.ndarray
    nipple: np.ndarray  # the left one (x > 0)
    shoulder: np.ndarray  # left shoulder joint
    neck: np.ndarray  # neck joint

    @classmethod
    def of(cls, model, X: np.ndarray) -> "Landmarks":
        lm = model.meta["landmarks"]
        J = model.joints(X)
        nip = X[lm["nipples"]]
        return cls(X[lm["navel"]].copy(), X[lm["crotch"]].copy(), nip[np.argmax(nip[:, 0])].copy(),
                   J[B["upper_arm_l"]].copy(), J[B["neck"]].copy())


def briefs_field(L: Landmarks, *, waist_front: float, waist_back_rise: float, leg_inner: float,
                 leg_slope: float, leg_front_rise: float, gusset: float, k: float) -> Field:
    """Briefs / trunks: below a waistband (``waist_front`` m under the navel at the front,
    ``waist_back_rise`` higher at the back) and above two leg openings. A leg line starts
    ``leg_inner`` above the crotch at half-gusset width ``gusset`` and rises ``leg_slope`` m per m
    towards the hip side and ``leg_front_rise`` m per m towards the front (mirrored in x)."""
    zf, zb = L.navel[2], L.navel[2] - 0.30

    def f(P: np.ndarray) -> np.ndarray:
        x, y, z = np.abs(P[:, 0]), P[:, 1], P[:, 2]
        y_waist = L.navel[1] - waist_front + waist_back_rise * (zf - z) / (zf - zb)
        # flat across the gusset (|x| < gusset), rising towards the hip side (a softplus)
        side = k * np.logaddexp(0.0, (x - gusset) / k)
        y_leg = L.crotch[1] + leg_inner + leg_slope * side + leg_front_rise * (z - L.crotch[2])
        return smin(y_waist - y, y - y_leg, k)

    return f


def bra_field(L: Landmarks, *, under: float, top_front: float, top_back: float, strap_x: float,
              strap_width: float, side_x: float, k: float) -> Field:
    """A bralette: a band from ``under`` m below the nipples up to a top edge (``top_front``
    above them at the front, ``top_back`` at the back), within ``side_x`` of the midline (the
    arms hang outside), and two straps of ``strap_width`` centred at |x| = ``strap_x`` over the
    shoulders (below the neck joint)."""
    zf, zb = L.nipple[2], L.nipple[2] - 0.28

    def f(P: np.ndarray) -> np.ndarray:
        x, y, z = np.abs(P[:, 0]), P[:, 1], P[:, 2]
        s = np.clip((z - zb) / (zf - zb), 0.0, 1.0)
        y_top = L.nipple[1] + top_back + (top_front - top_back) * s
        band_top = y_top - y
        strap = smin(strap_width / 2 - np.abs(x - strap_x), L.neck[1] - y, k / 3)
        upper = smax(band_top, strap, k / 2)
        body = smin(y - (L.nipple[1] - under), side_x - x, k)
        return smin(body, upper, k / 2)

    return f


# -- mesh operations ------------------------------------------------------------------------------
def subdivide(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Midpoint subdivision (1 triangle -> 4; new vertices at edge midpoints, on the surface)."""
    E = mesh_edges(F)
    key = {(int(a), int(b)): len(V) + i for i, (a, b) in enumerate(E)}
    mid = lambda a, b: np.array([key[(min(p, q), max(p, q))] for p, q in zip(a, b)], np.int64)  # noqa: E731
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
    V2 = np.concatenate([V, 0.5 * (V[E[:, 0]] + V[E[:, 1]])])
    F2 = np.concatenate([np.stack([a, ab, ca], 1), np.stack([ab, b, bc], 1), np.stack([ca, bc, c], 1),
                         np.stack([ab, bc, ca], 1)])
    return V2, F2


def cut_isoline(V: np.ndarray, F: np.ndarray, f: np.ndarray, snap: float) -> tuple[np.ndarray, np.ndarray]:
    """The part of a triangle mesh where the field ``f`` (V,) > 0, cut exactly along f = 0
    (marching triangles); vertices within ``snap`` (fraction of an edge) of a crossing are first
    moved onto it. Returns (vertices (V', 3), faces (F', 3)) (orientation kept; unused vertices
    not removed)."""
    V = np.array(V, np.float64)
    f = np.where(f == 0, -1e-12, np.asarray(f, np.float64))
    E = mesh_edges(F)
    fa, fb = f[E[:, 0]], f[E[:, 1]]
    cross = (fa > 0) != (fb > 0)
    a, b = E[cross, 0], E[cross, 1]
    t = fa[cross] / (fa[cross] - fb[cross])
    P = V[a] + t[:, None] * (V[b] - V[a])
    near_a, near_b = t < snap, t > 1 - snap
    cand_v = np.concatenate([a[near_a], b[near_b]])
    cand_d = np.concatenate([t[near_a], 1 - t[near_b]])
    cand_p = np.concatenate([P[near_a], P[near_b]])
    order = np.lexsort((cand_d, cand_v))
    first = order[np.r_[True, cand_v[order][1:] != cand_v[order][:-1]]]
    V[cand_v[first]] = cand_p[first]
    f[cand_v[first]] = 0.0
    sign = np.sign(f).astype(np.int64)  # +1 inside, 0 on the line, -1 outside

    new_pts: list[np.ndarray] = []
    edge_vertex: dict[tuple[int, int], int] = {}

    def crossing(p: int, q: int) -> int:
        k = (min(p, q), max(p, q))
        if k not in edge_vertex:
            s = f[p] / (f[p] - f[q])
            new_pts.append(V[p] + s * (V[q] - V[p]))
            edge_vertex[k] = len(V) + len(new_pts) - 1
        return edge_vertex[k]

    s = sign[F]
    keep = F[(s >= 0).all(axis=1)]
    out = [keep]
    mixed = F[(s > 0).any(axis=1) & (s < 0).any(axis=1)]
    extra: list[list[int]] = []
    for tri in mixed:
        sg = sign[tri]
        n_pos, n_neg = int((sg > 0).sum()), int((sg < 0).sum())
        if n_pos == 1 and n_neg == 2:
            r = int(np.argmax(sg > 0))
            v0, v1, v2 = np.roll(tri, -r)
            extra.append([v0, crossing(v0, v1), crossing(v0, v2)])
        elif n_pos == 2 and n_neg == 1:
            r = int(np.argmax(sg < 0))
            v2, v0, v1 = np.roll(tri, -r)  # v2 outside, v0 -> v1 -> v2 in the original order
            x12, x20 = crossing(v1, v2), crossing(v2, v0)
            extra += [[v0, v1, x12], [v0, x12, x20]]
        else:  # one inside, one outside, one on the line
            r = int(np.argmax(sg == 0))
            v0, v1, v2 = np.roll(tri, -r)
            x = crossing(v1, v2)
            extra.append([v0, v1, x] if sign[v1] > 0 else [v0, x, v2])
    if extra:
        out.append(np.array(extra, np.int64))
    V = np.concatenate([V, np.array(new_pts).reshape(-1, 3)])
    return V, np.concatenate(out).astype(np.int64)


def compact(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Drop unreferenced vertices."""
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def component_at(V: np.ndarray, F: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """The faces of the connected component nearest to the point ``anchor`` (3,) (the region
    may also catch a hand or a forearm elsewhere)."""
    n = len(V)
    e = np.concatenate([F[:, [0, 1]], F[:, [1, 2]]])
    _, lab = connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                  directed=False)
    used = np.unique(F)
    seed = used[np.argmin(np.linalg.norm(V[used] - anchor, axis=1))]
    return F[lab[F[:, 0]] == lab[seed]]


def boundary_edges(F: np.ndarray) -> np.ndarray:
    """Edges (B, 2) used by exactly one face."""
    u, c = edge_counts(F)
    return u[c == 1]


def smoothing_operator(F: np.ndarray, n: int) -> sp.csr_matrix:
    """Row-normalised umbrella operator: interior vertices average their neighbours, boundary
    vertices their two boundary neighbours (the edge curve stays smooth and keeps its place)."""
    E = mesh_edges(F)
    Bd = boundary_edges(F)
    on_b = np.zeros(n, bool)
    on_b[Bd.ravel()] = True
    r, c = np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]]
    inner = ~on_b[r]
    rows = np.r_[r[inner], Bd[:, 0], Bd[:, 1]]
    cols = np.r_[c[inner], Bd[:, 1], Bd[:, 0]]
    A = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    deg = np.asarray(A.sum(axis=1)).ravel()
    return sp.diags(1.0 / np.maximum(deg, 1)) @ A


class BodySurface:
    """Closest points and interpolated normals on the body surface (V, 3) with faces (F, 3)."""

    def __init__(self, X: np.ndarray, faces: np.ndarray):
        self.X = np.asarray(X, np.float64)
        self.faces = np.asarray(faces, np.int64)
        self.normals = vertex_normals(self.X, self.faces).astype(np.float64)
        self.tree = cKDTree(self.X)
        self.vf = vertex_faces(self.faces, len(self.X))

    def closest(self, P: np.ndarray):
        """(face ids, closest points (P, 3), barycentric (P, 3), unit normals there (P, 3))."""
        face, Q, bary = closest_points_on_mesh(P, self.X, self.faces, tree=self.tree, vert_faces=self.vf)
        n = np.einsum("pk,pkd->pd", bary, self.normals[self.faces[face]])
        return face, Q, bary, n / np.linalg.norm(n, axis=1, keepdims=True)


def envelope(X: np.ndarray, faces: np.ndarray, params: BaseLayerParams) -> np.ndarray:
    """A smooth surface over the body (V, 3) that bridges its small bumps: the body smoothed
    (bumps and pits flattened), lifted along its normals by the bumps' heights, spread over a
    few rings of neighbours (a dilation), so nipples lie under it, not on it. (V, 3)."""
    n = len(X)
    E = mesh_edges(faces)
    A = sp.csr_matrix((np.ones(2 * len(E)), (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(n, n))
    A = sp.diags(1.0 / np.maximum(np.asarray(A.sum(axis=1)).ravel(), 1)) @ A
    Xs = np.array(X, np.float64)
    for _ in range(params.envelope_smoothing):
        Xs = 0.5 * Xs + 0.5 * (A @ Xs)
    ns = vertex_normals(Xs, faces).astype(np.float64)
    bump = np.maximum(np.einsum("ij,ij->i", X - Xs, ns), 0.0)
    # spread each bump as a smooth tent of radius envelope_radius: e = max_j bump_j w(d_ij / r),
    # w(t) = (1 - t^2)^2 (smooth, 1 at the bump), never below the bump itself
    src = np.flatnonzero(bump > 1e-4)
    e = bump.copy()
    if len(src):
        r = params.envelope_radius
        pairs = cKDTree(X).sparse_distance_matrix(cKDTree(X[src]), r, output_type="coo_matrix")
        w = (1.0 - (pairs.data / r) ** 2) ** 2 * bump[src[pairs.col]]
        np.maximum.at(e, pairs.row, w)
    return Xs + e[:, None] * ns


def wrap(S: np.ndarray, F: np.ndarray, surfaces: list["BodySurface"], params: BaseLayerParams) -> np.ndarray:
    """Shrink-wrap the surface piece S (M, 3) (on the skin) to cloth ``params.ease`` off the
    skin: smoothing alternated with projection out of every surface in ``surfaces`` (the body
    and its envelope; see the module docstring)."""
    P = S + params.ease * vertex_normals(S, F).astype(np.float64)
    A = smoothing_operator(F, len(S))
    for _ in range(params.wrap_iterations):
        P = P + params.wrap_step * (A @ P - P)
        for surf in surfaces:
            _, Q, _, n = surf.closest(P)
            h = np.einsum("ij,ij->i", P - Q, n)
            low = h < params.ease
            P[low] += (params.ease - h[low])[:, None] * n[low]
    # elastic edges: a slight lift that fades within hem_width of the boundary
    bd = np.unique(boundary_edges(F))
    E = mesh_edges(F)
    w = np.linalg.norm(P[E[:, 0]] - P[E[:, 1]], axis=1)
    G = sp.csr_matrix((np.r_[w, w], (np.r_[E[:, 0], E[:, 1]], np.r_[E[:, 1], E[:, 0]])), shape=(len(P),) * 2)
    d = dijkstra(G, indices=bd, min_only=True, limit=4 * params.hem_width)
    lift = params.hem_lift * np.exp(-((np.minimum(d, 1.0) / params.hem_width) ** 2))
    return P + lift[:, None] * vertex_normals(P, F).astype(np.float64)


def bind(P: np.ndarray, body: BodySurface, name: str) -> Binding:
    """Express garment vertices (M, 3) on the mean avatar as an ``.mhclo`` binding: closest
    body triangle, barycentric weights, offset in decimetres; reference distances measured on
    the mean avatar (so ``Binding.fit(mean) == P``)."""
    face, Q, bary, _ = body.closest(P)
    scales = [(a, b, float(abs(body.X[a, ax] - body.X[b, ax]) / DM)) for ax, (a, b) in enumerate(SCALE_PAIRS)]
    return Binding(body.faces[face].astype(np.int64), bary, (P - Q) / DM, scales, name)


def generate(name: str, field: Field, anchor: np.ndarray, X: np.ndarray, body_faces: np.ndarray, n_body: int,
             params: BaseLayerParams = PARAMS) -> BaseLayerPiece:
    """One base-layer garment from its field on the mean avatar X (V, 3) (all hm08 vertices;
    the body surface is ``body_faces`` over the first ``n_body``); the piece is the part of the
    field's region nearest to ``anchor`` (3,)."""
    Xb = np.asarray(X[:n_body], np.float64)
    fb = np.asarray(body_faces, np.int64)
    fv = field(Xb)
    near = fv[fb].max(axis=1) > -0.05
    V, F = compact(Xb, fb[near])
    for _ in range(params.subdivisions):
        V, F = subdivide(V, F)
    V, F = cut_isoline(V, F, field(V), params.snap)
    S, F = compact(V, component_at(V, F, anchor))
    body = BodySurface(Xb, fb)
    P = wrap(S, F, [body, BodySurface(envelope(Xb, fb, params), fb)], params)
    binding = bind(P, body, name)
    lo, hi = P[:, :2].min(axis=0), P[:, :2].max(axis=0)
    uv = ((P[:, :2] - lo) / (hi - lo).max()).astype(np.float32)
    # hidden under the garment: well inside its edge, and under this piece (not a stray region)
    near_piece = cKDTree(P).query(Xb)[0] < HIDDEN_NEAR
    hidden = np.flatnonzero((fv > params.hidden_margin) & near_piece).astype(np.int32)
    return BaseLayerPiece(binding, F.astype(np.int32), uv, hidden, P)


def fields(model, X: np.ndarray, params: BaseLayerParams = PARAMS) -> dict[str, tuple[Field, np.ndarray]]:
    """The base-layer garments on the mean avatar, as (field, anchor point): women's briefs and
    bralette, men's trunks (short legs)."""
    L = Landmarks.of(model, X)
    k = params.corner
    sternum = np.array([0.0, L.nipple[1], L.nipple[2]])
    return {
        # low rise, so trousers' and skirts' waistbands (~6-8 cm under the navel) cover it
        "briefs": (briefs_field(L, waist_front=0.075, waist_back_rise=0.015, leg_inner=-0.006, leg_slope=0.6,
                                leg_front_rise=0.25, gusset=0.03, k=k), L.crotch),
        "bralette": (bra_field(L, under=0.085, top_front=0.055, top_back=0.005, strap_x=0.105, strap_width=0.03,
                               side_x=0.30, k=k), sternum),
        "trunks": (briefs_field(L, waist_front=0.07, waist_back_rise=0.015, leg_inner=-0.06, leg_slope=0.12,
                                leg_front_rise=0.05, gusset=0.0, k=k), L.crotch),
    }

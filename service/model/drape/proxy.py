"""A dense garment draped through a coarser simulation mesh.

Pattern tools export garments at their particle distance (CLO, Marvelous Designer: 5-10 mm,
10,000-100,000 vertices), where one drape takes 18 s and more on 2 cores (the 44k-vertex
T-shirt) and a build drapes each size on some 260 bodies. A garment denser than
``Config.proxy_max_vertices`` is draped as a simulation mesh of about that many vertices
(:func:`collapse_edges`: its shortest edges collapsed, one end into the other, so that the
simulation mesh's vertices are the garment's own, the cloth stays a manifold and its open edges
keep their line). Every garment vertex rides on the simulation triangle nearest to it at rest
(:class:`Embedding`: barycentric weights and its offset in the triangle's frame,
``geometry.face_frames``), searched around the simulation vertex nearest to it along the
garment's own edges, so that a folded collar binds to its own layer and not to the cloth under
it. Folds finer than the simulation mesh's triangles are those of the rest shape, carried along.
:func:`precompute` chooses: the garment as it is (``solver.Draper``) or through its simulation
mesh (:class:`ProxyDraper`), both with ``solve(body, body_faces, start)``.

Shapes: rest (N, 3) m and faces (F, 3) of the garment; the simulation mesh's P kept vertices and
(Q, 3) faces over them."""
from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import dijkstra

from service.model.geometry import mesh as geometry

from .fabrics import Fabric
from .solver import Config, DrapeError, Draper, DrapeResult, _Body, _check_rest, precompute as precompute_as_is

# simplification (`collapse_edges`)
COLLAPSE_MIN_COS = 0.5  # no face around a collapse turns by more than 60 degrees
COLLAPSE_MIN_QUALITY = 0.2  # ... or ends thinner than this (4 sqrt(3) area / sum of squared edges: 1 equilateral)
COLLAPSE_MAX_EDGE = 1.5  # ... or makes an edge longer than this many times the simulation mesh's mean edge length
COLLAPSE_RELAX = 1.25  # where that limit stops the collapses short of max_vertices, it grows by this ...
COLLAPSE_RELAX_ROUNDS = 4  # ... up to this many times
BOUNDARY_MAX_TURN_DEG = 20.0  # an open edge's vertex goes only where the open line turns by less than this
COLLAPSE_MIN_PIECE = 40  # pieces of fewer vertices (buttons, labels) are kept as they are
CARRIED_UNTANGLE_ROUNDS = 3  # the carried garment's untangling: this many times the solver's rounds (the 44k
# T-shirt on the mean avatar: 18 crossing pairs left after 40 rounds, none after 120, 3.3 s)
BIND_NEAR = 12  # simulation vertices whose triangles are searched for each garment vertex's (its nearest, neighbours)


@dataclass
class Embedding:
    """Points carried by a triangle mesh: point i is ``bary[i] @ x[face[i]]`` plus ``offset[i]``
    in the frame of triangle ``face[i]`` (``geometry.face_frames``). face (K, 3) int64 vertex
    ids, bary (K, 3), offset (K, 3) float64."""
    face: np.ndarray
    bary: np.ndarray
    offset: np.ndarray

    @classmethod
    def bind(cls, points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, near: np.ndarray) -> "Embedding":
        """points (K, 3) bound to the mesh (vertices (V, 3), faces (G, 3)): each to its closest
        point among the triangles around its ``near`` (K, k) vertices."""
        fi, q, bary = geometry.closest_points_on_mesh(points, vertices, faces, near=near)
        face = np.asarray(faces, np.int64)[fi]
        offset = np.einsum("kij,kj->ki", geometry.face_frames(vertices, face), points - q)
        return cls(face, bary, offset)

    def place(self, x: np.ndarray) -> np.ndarray:
        """(K, 3) float64: the points on the mesh's vertices x (V, 3)."""
        x = np.asarray(x, np.float64)
        q = np.einsum("kc,kcj->kj", self.bary, x[self.face])
        return q + np.einsum("kij,ki->kj", geometry.face_frames(x, self.face), self.offset)


@dataclass
class SimulationMesh:
    """The coarse cloth a dense garment is draped as: the garment's vertices ``keep`` (P,)
    int64 (its rest, and a start, are the garment's there) with faces (Q, 3) int64 over them;
    ``garment`` carries the garment's N vertices on it."""
    keep: np.ndarray
    faces: np.ndarray
    garment: Embedding


def _cross(u: list[float], v: list[float]) -> tuple[float, float, float]:
    return (u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0])


def _normal(p: list[float], q: list[float], r: list[float]) -> tuple[float, float, float, float]:
    """(unit normal, area) of the triangle p, q, r; area 0 and normal 0 when degenerate."""
    n = _cross([q[0] - p[0], q[1] - p[1], q[2] - p[2]], [r[0] - p[0], r[1] - p[1], r[2] - p[2]])
    a = math.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    return (n[0] / a, n[1] / a, n[2] / a, 0.5 * a) if a > 0 else (0.0, 0.0, 0.0, 0.0)


def collapse_edges(rest: np.ndarray, faces: np.ndarray, max_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh (rest (N, 3), faces (F, 3)) simplified by collapsing its shortest edges, one
    end into the other, until at most ``max_vertices`` remain or no edge may go: the kept
    vertices stay where they are (a subset of the garment: the simulation mesh's rest and
    start are the garment's own). An edge goes only when the mesh stays a manifold cloth: the
    two ends share no neighbour but the corners of the edge's faces (the link condition,
    Dey et al. 1999), no face turns over or becomes a sliver (``COLLAPSE_MIN_COS``,
    ``COLLAPSE_MIN_QUALITY``), an open edge's vertex goes only along its open edge and where
    that edge turns by less than ``BOUNDARY_MAX_TURN_DEG`` (hems and cuffs keep their line and
    corners), no edge grows past ``COLLAPSE_MAX_EDGE`` times the mean edge of ``max_vertices``
    vertices over the garment's area (the simulation mesh stays even; where that stops the
    collapses short, the limit grows by ``COLLAPSE_RELAX``, up to ``COLLAPSE_RELAX_ROUNDS``
    times), and pieces of fewer than ``COLLAPSE_MIN_PIECE`` vertices
    (buttons) stay whole.
    Returns (kept vertex ids (P,) int64 ascending, faces (Q, 3) over them, owner (N,): the kept
    vertex (0..P-1) nearest to each vertex along the garment's edges, itself for a kept one; -1
    for a vertex on no face)."""
    X = np.asarray(rest, np.float64).tolist()
    Fa = np.asarray(faces, np.int64)
    n = len(X)
    tri = [list(f) for f in Fa.tolist()]
    alive = [True] * len(tri)
    fan: list[set[int]] = [set() for _ in range(n)]
    for k, (a, b, c) in enumerate(tri):
        fan[a].add(k), fan[b].add(k), fan[c].add(k)
    parent = list(range(n))
    piece = geometry.vertex_components(Fa, n)
    small = np.bincount(piece)[piece] < COLLAPSE_MIN_PIECE
    frozen = small.tolist()
    cos_turn = math.cos(math.radians(BOUNDARY_MAX_TURN_DEG))
    # the edge length of max_vertices vertices in equilateral triangles over the garment's area
    # (about 2 triangles a vertex): no collapse makes an edge longer than COLLAPSE_MAX_EDGE times it
    tri0 = np.asarray(rest, np.float64)[Fa]
    area = 0.5 * np.linalg.norm(np.cross(tri0[:, 1] - tri0[:, 0], tri0[:, 2] - tri0[:, 0]), axis=1).sum()
    max_edge = COLLAPSE_MAX_EDGE * math.sqrt(2 * area / (math.sqrt(3) * max(max_vertices, 1)))

    def dist(a: int, b: int) -> float:
        p, q = X[a], X[b]
        return math.sqrt((p[0] - q[0]) ** 2 + (p[1] - q[1]) ** 2 + (p[2] - q[2]) ** 2)

    def ring(v: int) -> set[int]:
        out: set[int] = set()
        for k in fan[v]:
            out.update(tri[k])
        out.discard(v)
        return out

    def open_neighbours(v: int) -> list[int]:
        """v's neighbours along open edges (edges on one face)."""
        count: dict[int, int] = {}
        for k in fan[v]:
            for u in tri[k]:
                if u != v:
                    count[u] = count.get(u, 0) + 1
        return [u for u, c in count.items() if c == 1]

    def can_remove(b: int, a: int) -> bool:
        """b collapses into a (a stays where it is)."""
        if frozen[b]:
            return False
        for u in ring(b):
            if u != a and dist(a, u) > max_edge:  # the limit of the current round
                return False
        shared = [k for k in fan[b] if a in tri[k]]
        if not shared or len(shared) > 2:
            return False
        opposite = {u for k in shared for u in tri[k] if u != a and u != b}
        if ring(a) & ring(b) != opposite:
            return False
        ob = open_neighbours(b)
        if ob:  # b on an open edge: only along it, into its open neighbour, where the line runs straight
            if len(shared) != 1 or a not in ob or len(ob) != 2:
                return False
            c = ob[0] if ob[1] == a else ob[1]
            u = [X[b][i] - X[c][i] for i in range(3)]
            w = [X[a][i] - X[b][i] for i in range(3)]
            nu, nw = math.sqrt(sum(t * t for t in u)), math.sqrt(sum(t * t for t in w))
            if nu == 0 or nw == 0 or sum(u[i] * w[i] for i in range(3)) < cos_turn * nu * nw:
                return False
        for k in fan[b]:
            if k in shared:
                continue
            t = tri[k]
            old = _normal(X[t[0]], X[t[1]], X[t[2]])
            moved = [X[a] if u == b else X[u] for u in t]
            new = _normal(*moved)
            if new[3] == 0 or old[0] * new[0] + old[1] * new[1] + old[2] * new[2] < COLLAPSE_MIN_COS:
                return False
            l2 = sum((moved[i][j] - moved[(i + 1) % 3][j]) ** 2 for i in range(3) for j in range(3))
            if 4 * math.sqrt(3) * new[3] < COLLAPSE_MIN_QUALITY * l2:
                return False
        return True

    def collapse(b: int, a: int) -> None:
        for k in list(fan[b]):
            t = tri[k]
            if a in t:
                alive[k] = False
                for u in t:
                    fan[u].discard(k)
            else:
                t[t.index(b)] = a
                fan[a].add(k)
        fan[b].clear()
        parent[b] = a

    count = n - int(np.sum(np.bincount(Fa.reshape(-1), minlength=n) == 0))
    for _ in range(COLLAPSE_RELAX_ROUNDS):
        e = geometry.mesh_edges(np.array([t for t, ok in zip(tri, alive) if ok], np.int64).reshape(-1, 3))
        heap = [(dist(int(i), int(j)), int(i), int(j)) for i, j in e]
        heapq.heapify(heap)
        while heap and count > max_vertices:
            length, a, b = heapq.heappop(heap)
            if not fan[a] or not fan[b] or b not in ring(a) or abs(dist(a, b) - length) > 1e-12:
                continue  # a stale entry: an end gone, or the edge moved
            if can_remove(b, a):
                collapse(b, a)
            elif can_remove(a, b):
                collapse(a, b)
                a = b
            else:
                continue
            count -= 1
            for u in ring(a):
                heapq.heappush(heap, (dist(a, u), a, u))
        if count <= max_vertices:
            break
        max_edge *= COLLAPSE_RELAX  # the length limit stopped it short (an uneven mesh): a little longer edges
    keep = np.array([v for v in range(n) if parent[v] == v and fan[v]], np.int64)
    index = np.full(n, -1, np.int64)
    index[keep] = np.arange(len(keep))
    Q = np.array([t for t, ok in zip(tri, alive) if ok], np.int64).reshape(-1, 3)
    # each vertex's kept vertex: the nearest along the garment's own edges (a chain of collapses
    # may end far away; a layer across a fold is far along the cloth, however near in space)
    _, _, source = dijkstra(geometry.edge_length_graph(np.asarray(rest, np.float64), Fa), directed=False,
                            indices=keep, min_only=True, return_predecessors=True)
    return keep, index[Q], np.where(source >= 0, index[np.maximum(source, 0)], -1)


def _nearest_first(lists: list[np.ndarray], anchor: np.ndarray, points: np.ndarray, vertices: np.ndarray,
                   k: int) -> np.ndarray:
    """(K, k) int64: for each point (K, 3), its ``anchor`` vertex then up to k - 1 of
    ``lists[anchor]`` nearest to the point (vertices (V, 3)), padded with the anchor."""
    out = np.repeat(anchor[:, None], k, axis=1)
    for i, (a, p) in enumerate(zip(anchor.tolist(), points)):
        cand = lists[a]
        if len(cand) > k - 1:
            cand = cand[np.argsort(((vertices[cand] - p) ** 2).sum(1))[: k - 1]]
        out[i, 1: 1 + len(cand)] = cand
    return out


def _neighbours(faces: np.ndarray, n: int) -> list[np.ndarray]:
    """Each vertex's edge neighbours (faces (F, 3) over n vertices)."""
    e = geometry.mesh_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return [A.indices[A.indptr[i]: A.indptr[i + 1]] for i in range(n)]


def simulation_mesh(rest: np.ndarray, faces: np.ndarray, max_vertices: int) -> SimulationMesh | None:
    """The garment (rest (N, 3), faces (F, 3)) as a simulation mesh of at most about
    ``max_vertices`` (:func:`collapse_edges`) and the garment's embedding on it; None when the
    garment has no more than ``max_vertices`` vertices or could not be made smaller."""
    rest = np.asarray(rest, np.float64)
    faces = np.asarray(faces, np.int64)
    if len(rest) <= max_vertices:
        return None
    keep, Q, owner = collapse_edges(rest, faces, max_vertices)
    if len(keep) >= len(rest) or (owner < 0).any():
        return None
    P = rest[keep]
    garment = Embedding.bind(rest, P, Q, _nearest_first(_neighbours(Q, len(P)), owner, rest, P, BIND_NEAR))
    return SimulationMesh(keep=keep, faces=Q, garment=garment)


class ProxyDraper:
    """A dense garment's drape system (``solver.precompute`` gives it for a garment over
    ``Config.proxy_max_vertices``): its simulation mesh's :class:`solver.Draper`, and the
    garment carried on that mesh's drape. ``solve`` as ``Draper.solve``, on the garment's N
    vertices."""

    def __init__(self, rest: np.ndarray, faces: np.ndarray, simulation: SimulationMesh, inner: Draper,
                 precompute_s: float) -> None:
        """``inner``: the simulation mesh's ``Draper``; ``precompute_s``: the time to make it all."""
        self.rest, self.faces, self.n = rest, faces, len(rest)
        self.simulation, self.inner = simulation, inner
        self.fabric, self.config = inner.fabric, inner.config
        self.precompute_s = precompute_s

    def solve(self, body_vertices: np.ndarray | None, body_faces: np.ndarray | None,
              init_vertices: np.ndarray, fallbacks: bool = True) -> DrapeResult:
        """The garment (N, 3) at rest on the body: its simulation mesh draped from the start
        read off ``init_vertices`` (N, 3), the garment carried on it, then every garment vertex
        the simulation triangles' chords leave within the clearance moved out along the body's
        normal (as the solver's last contact pass). Raises ``DrapeError`` as ``Draper.solve``."""
        t0 = time.perf_counter()
        x0 = np.array(init_vertices, np.float64).reshape(-1, 3)
        if x0.shape != (self.n, 3) or not np.all(np.isfinite(x0)):
            raise DrapeError(f"the start shape must be {self.n} finite vertices (N, 3); got {x0.shape}")
        r = self.inner.solve(body_vertices, body_faces, x0[self.simulation.keep], fallbacks)
        y = r.vertices.astype(np.float64)
        stats = dict(r.stats)
        cfg = self.config
        body = _Body(body_vertices, body_faces, cfg) if body_vertices is not None and len(body_vertices) else None

        x = self.simulation.garment.place(y)
        if body is not None:
            x = body.outside(x)
        # where the simulation mesh lies pressed in a fold (an armpit) the garment's offsets off
        # it can cross the layer beside: smoothed out as the solver's untangling does, with more
        # rounds (it ends as soon as nothing crosses)
        pairs = geometry.intersecting_face_pairs(x, self.faces) if cfg.untangle_rounds > 0 else np.zeros((0, 2), int)
        left = 0
        if len(pairs):
            def contact(v: np.ndarray) -> np.ndarray:
                body.refresh_near(v, cfg.contact_near_m, 0.0, cfg.contact_walk_m)
                return body.project(v, None, None)[0]

            x, left = geometry.untangle(x, self.faces, CARRIED_UNTANGLE_ROUNDS * cfg.untangle_rounds,
                                        after=contact if body is not None else None, pairs=pairs)
        stats.update(carried_crossings=int(len(pairs)), self_intersections=int(left))
        if body is not None:
            inside = float(max(0.0, -body.signed_distance(x, exact=True).min()))
            if inside > cfg.max_inside_m:
                raise DrapeError(f"the drape ends with garment vertices {1000 * inside:.1f} mm inside the body "
                                 f"(limit {1000 * cfg.max_inside_m:.1f} mm): the garment cannot be placed on it")
            stats["max_penetration_mm"] = 1000 * inside
        stats.update(simulation_vertices=len(self.simulation.keep), precompute_s=self.precompute_s,
                     seconds=time.perf_counter() - t0)
        return DrapeResult(vertices=x.astype(np.float32), stats=stats)


def precompute(rest_vertices: np.ndarray, faces: np.ndarray, fabric: "str | Fabric" = "woven",
               config: Config | None = None, pinned: np.ndarray | None = None) -> Draper | ProxyDraper:
    """The drape system of one garment (``solver.precompute``'s arguments), factored once: a
    garment of more than ``config.proxy_max_vertices`` vertices (and none pinned) through its
    simulation mesh (:class:`ProxyDraper`, the same ``solve``), any other as it is
    (``solver.Draper``). Raises ``DrapeError`` on a degenerate rest shape."""
    cfg = config or Config()
    rest = np.asarray(rest_vertices, np.float64)
    cap = cfg.proxy_max_vertices
    if cap is None or len(rest) <= cap or (pinned is not None and len(pinned)):
        return precompute_as_is(rest, faces, fabric, cfg, pinned)
    t0 = time.perf_counter()
    F = np.asarray(faces)
    if not np.issubdtype(F.dtype, np.integer):
        raise DrapeError("faces must be integer vertex indices")
    F = F.astype(np.int64)
    _check_rest(rest, F, cfg)  # the garment refused as it would be alone (zero-area faces, non-manifold edges)
    sim = simulation_mesh(rest, F, cap)
    try:
        inner = precompute_as_is(rest[sim.keep], sim.faces, fabric, cfg) if sim is not None else None
    except DrapeError:
        inner = None  # the simplification made a face the solver refuses (or the fabric is unknown: refused below)
    if sim is None or inner is None:
        return precompute_as_is(rest, F, fabric, cfg)
    return ProxyDraper(rest, F, sim, inner, time.perf_counter() - t0)

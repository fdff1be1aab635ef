"""Landmarks on a body scan for the fit's initialisation (issue 12): the extremities (head top,
hands, feet) found as the far ends of geodesics from the torso on a k-nearest-neighbour graph of
the scan's points, and their assignment to the body model's end effectors.

Geodesic (graph) distances work alike for point clouds and meshes with holes: a hole only
lengthens paths around it, a cut head top only moves the head's far end down. The graph's
shortest paths from the point nearest the centroid (the torso) end at the tips of the limbs
and the head; each tip found suppresses the far half of its own branch, so the next farthest
point is another limb's tip.

All positions are in the model frame (metres, Y up) of an up-axis candidate; nothing here
knows the body model beyond the effector positions it is given.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.optimize import linear_sum_assignment
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

# the kNN graph: neighbours per point; edges longer than this are not the same surface
GRAPH_NEIGHBOURS = 8
GRAPH_MAX_EDGE_M = 0.08
# an extremity is at least this far (geodesic) from the torso point
MIN_EXTREMITY_GEODESIC_M = 0.30
# a found tip suppresses the points closer to it than this share of its geodesic distance
SUPPRESS_SHARE = 0.5
MAX_EXTREMITIES = 6
# the tip's position: the mean of the points within this (Euclidean) radius of the far end
TIP_RADIUS_M = 0.04
# a tip is paired with a label whose geodesic distances from the anchors differ by at most this
# (sum over the anchors, metres; see ``assign``)
MAX_ASSIGN_COST_M = 0.8
# the weight of the Euclidean distance to the current fit's effector in a pairing's cost
SIDE_WEIGHT = 0.1
UNREACHED_M = 100.0  # the geodesic distance of a point not connected to an anchor

LABELS = ("head", "hand_l", "hand_r", "foot_l", "foot_r")
SWAPS = (("hand_l", "hand_r"), ("foot_l", "foot_r"))


@dataclass
class Extremities:
    points: np.ndarray  # (n, 3) tip positions, farthest first
    geodesic: np.ndarray  # (n,) graph distance from the torso point (metres)
    centre: np.ndarray  # (3,) the torso point the geodesics start from
    index: np.ndarray = None  # (n,) the far-end point of each tip in the input points
    graph: sp.csr_matrix | None = None  # the kNN graph of the input points

    def anchor_geodesics(self, points: np.ndarray, anchors: np.ndarray) -> np.ndarray:
        """(n, A) graph distances from each tip to the input point nearest each anchor (A, 3)
        (inf where not connected). points: the (P, 3) the tips were found on."""
        if self.graph is None or not len(self.index):
            return np.zeros((len(self.points), len(anchors)))
        src = cKDTree(points).query(anchors)[1]
        return dijkstra(self.graph, directed=False, indices=src)[:, self.index].T


def knn_graph(points: np.ndarray, k: int = GRAPH_NEIGHBOURS,
              max_edge: float = GRAPH_MAX_EDGE_M) -> sp.csr_matrix:
    """Symmetric sparse (P, P) graph of Euclidean edge lengths to the k nearest neighbours,
    edges longer than ``max_edge`` dropped. points: (P, 3)."""
    P = len(points)
    k = min(k, P - 1)
    d, j = cKDTree(points).query(points, k=k + 1)
    d, j = d[:, 1:], j[:, 1:]
    ok = d <= max_edge
    rows = np.repeat(np.arange(P), k)[ok.ravel()]
    G = sp.csr_matrix((np.maximum(d[ok], 1e-9), (rows, j[ok])), shape=(P, P))
    return G.maximum(G.T).tocsr()


def find_extremities(points: np.ndarray, max_count: int = MAX_EXTREMITIES,
                     min_geodesic: float = MIN_EXTREMITY_GEODESIC_M) -> Extremities:
    """The tips of the body's branches (head, hands, feet; fewer when a hand touches the body
    or the scan is cut), farthest first. points: (P, 3) metres, a subsample of ~1-3k points is
    enough. Only the largest connected part of the graph is searched (stray points, a limb
    cut off by a hole are left out)."""
    pts = np.asarray(points, np.float64)
    empty = Extremities(np.zeros((0, 3)), np.zeros(0), pts.mean(0) if len(pts) else np.zeros(3))
    if len(pts) < 50:
        return empty
    G = knn_graph(pts)
    _, comp = connected_components(G, directed=False)
    main = np.bincount(comp).argmax()
    inside = comp == main
    centroid = pts[inside].mean(0)
    cand = np.nonzero(inside)[0]
    c = cand[np.argmin(np.linalg.norm(pts[cand] - centroid, axis=1))]
    dc = dijkstra(G, directed=False, indices=c)
    alive = np.isfinite(dc)
    tips, geo, index = [], [], []
    tree = cKDTree(pts)
    while len(tips) < max_count and alive.any():
        e = int(np.argmax(np.where(alive, dc, -1.0)))
        if dc[e] < min_geodesic:
            break
        de = dijkstra(G, directed=False, indices=e, limit=SUPPRESS_SHARE * dc[e])
        alive &= ~(de <= SUPPRESS_SHARE * dc[e])
        near = tree.query_ball_point(pts[e], TIP_RADIUS_M)
        tips.append(pts[near].mean(0) if near else pts[e])
        geo.append(float(dc[e]))
        index.append(e)
    if not tips:
        return empty
    return Extremities(np.array(tips), np.array(geo), pts[c], np.array(index), G)


def assign(tips: np.ndarray, features: np.ndarray, expected: np.ndarray, effectors: np.ndarray,
           max_cost: float = MAX_ASSIGN_COST_M) -> dict[str, np.ndarray]:
    """{label: tip (3,)}: the tips (n, 3) paired with ``LABELS`` by least total cost
    (Hungarian). The cost of a pair: the difference of the tip's geodesic distances from the
    body's anchors (pelvis, neck; ``features`` (n, A)) to the label's on the template
    (``expected`` (5, A)) -- a foot is far from the neck and near the pelvis, a hand the other
    way, the head nearest the neck -- plus ``SIDE_WEIGHT`` times the tip's distance to the
    label's effector at the current fit (``effectors`` (5, 3)), which only breaks left/right
    ties. Pairs costing more than ``max_cost`` are left out."""
    if not len(tips):
        return {}
    F = np.where(np.isfinite(features), features, UNREACHED_M)
    E = np.where(np.isfinite(expected), expected, UNREACHED_M)
    D = np.abs(F[:, None, :] - E[None, :, :]).sum(2) \
        + SIDE_WEIGHT * np.linalg.norm(tips[:, None, :] - effectors[None, :, :], axis=2)
    r, c = linear_sum_assignment(D)
    return {LABELS[j]: tips[i] for i, j in zip(r, c) if D[i, j] <= max_cost}


def hypotheses(assignment: dict[str, np.ndarray]) -> list[dict[str, np.ndarray]]:
    """The assignment and its left/right swaps (hands, feet, both) where both sides were
    assigned: the side of a crossed or turned limb is what the tips alone do not tell."""
    if not assignment:
        return []
    swaps = [sw for sw in SWAPS if sw[0] in assignment and sw[1] in assignment]
    out = []
    for n in range(len(swaps) + 1):
        for combo in itertools.combinations(swaps, n):
            h = dict(assignment)
            for a, b in combo:
                h[a], h[b] = assignment[b], assignment[a]
            out.append(h)
    return out

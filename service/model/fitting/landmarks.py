"""Landmarks on a body scan for the fit's initialisation (issue 12): the extremities (head top,
hands, feet) found as the far ends of geodesics from the torso on a k-nearest-neighbour graph of
the scan's points, and their assignment to the body model's end effectors.

Geodesic (graph) distances work alike for point clouds and meshes with holes: a hole only
lengthens paths around it, a cut head top only moves the head's far end down. The graph's
shortest paths from the point nearest the centroid (the torso) end at the tips of the limbs
and the head; each tip found suppresses the far half of its own branch, so the next farthest
point is another limb's tip.

The crotch (``find_crotch``) comes from horizontal slices below the hips: the first level
where the legs' cross-sections part, and the surface closing the gap between them from above;
it is None where that is not seen (a skirt's or a coat's hem, thighs pressed together down to
below where a crotch can be), never a hem. The shoulders (``find_shoulder``) are the top-outer
corners of the arm's junction with the torso (the acromia), None for an arm raised along that
direction. Both need a current fit's joints (hips, shoulder joint and the torso's axes).
On synthetic scans (``tests/test_landmarks.py``) both land within a few cm of the true
vertices; the fit does not use them: pulling the template's crotch and acromia to them (even
to the true positions) in the landmark hypotheses' coarse ICP left the fits unchanged.

All positions are in the model frame (metres, Y up) of an up-axis candidate; nothing here
knows the body model beyond the effector positions and joints it is given.
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


# -- the crotch: where the legs' cross-sections join (issue 12) ------------------------------------
# Horizontal slices from above the hips downwards: each slice's points near the pelvis's axis
# are linked into contours (2D single linkage), the contour nearest each hip is its leg, and the
# split is the first level below which the two legs' contours stay apart. The crotch is the
# surface that closes the gap between them from just above (the saddle). Under a skirt or a
# coat the legs part at the hem, farther below the hips than a crotch can be, or with the gap
# open above (nothing is scanned inside the garment): None, never the hem. Thighs pressed
# together part too low as well: None.
CROTCH_STEP_M = 0.01  # slice spacing
CROTCH_HALF_M = 0.015  # half a slice's thickness (thick enough for closed contours at ~1 cm spacing)
CROTCH_LINK_M = 0.025  # points of a slice this close (horizontally) are one contour
# only points this close (horizontally) to the pelvis's axis: wider than any hips, so that a
# garment's contour is not cut into pieces that look like legs
CROTCH_WINDOW_M = 0.35
CROTCH_ABOVE_M = 0.05  # the search starts this far above the hip joints ...
CROTCH_BELOW_M = 0.13  # ... and ends this far below them (the template's crotch: 9 cm)
CROTCH_MIN_LEG_M = 0.08  # a contour this wide (its larger horizontal extent) can be a thigh
CROTCH_MIN_POINTS = 6
CROTCH_SPLIT_SLICES = 3  # the two contours stay apart this many slices down
# the legs' contours lie apart along the hips' axis by at least this share of the hips' distance
# (not a garment's two concentric hems, not crossed legs)
CROTCH_MIN_SPREAD = 0.4
CROTCH_MAX_GAP_M = 0.06  # the legs' closest points at the split are this close ...
CROTCH_BETWEEN = (0.2, 0.8)  # ... their midpoint lies between the hips (share from right to left)
# ... and the crotch is the first surface point straight above it (within CROTCH_RAY_M of the
# vertical through it) less than CROTCH_REACH_M above the split: where the gap closes
CROTCH_RAY_M = 0.012
CROTCH_REACH_M = 0.10


def _slice_contours(xz: np.ndarray, link: float = CROTCH_LINK_M) -> list[np.ndarray]:
    """Indices of the leg-sized contours of a slice's horizontal points (n, 2), largest first."""
    if len(xz) < CROTCH_MIN_POINTS:
        return []
    pairs = cKDTree(xz).query_pairs(link, output_type="ndarray")
    G = sp.csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(xz), len(xz)))
    _, lab = connected_components(G, directed=False)
    out = []
    for c in np.unique(lab):
        idx = np.nonzero(lab == c)[0]
        if len(idx) >= CROTCH_MIN_POINTS and np.ptp(xz[idx], axis=0).max() >= CROTCH_MIN_LEG_M:
            out.append(idx)
    return sorted(out, key=len, reverse=True)


def _legs_apart(P: np.ndarray, idx: np.ndarray, hips: np.ndarray):
    """A slice's legs: (left, right) point indices when the contours nearest each hip are two,
    ``CROTCH_MIN_SPREAD`` apart along the hips' axis; 1 when merged; 0 when no contour."""
    cont = _slice_contours(P[idx][:, [0, 2]])
    if not cont:
        return 0
    cen = np.array([P[idx[c]][:, [0, 2]].mean(0) for c in cont])
    side = [int(np.argmin(np.linalg.norm(cen - h[[0, 2]], axis=1))) for h in hips]
    axis = (hips[0] - hips[1])[[0, 2]]
    if side[0] == side[1] or np.dot(cen[side[0]] - cen[side[1]], axis) < CROTCH_MIN_SPREAD * np.dot(axis, axis):
        return 1
    return idx[cont[side[0]]], idx[cont[side[1]]]


def find_crotch(points: np.ndarray, hips: np.ndarray) -> np.ndarray | None:
    """The crotch (3,) on a scan, or None where the legs' join is not seen (a skirt, a coat,
    legs pressed together). points: (P, 3) model frame, Y up, dense (slices need points ~1 cm
    apart: ~10k points on a body); hips: (2, 3) the hip joints (left, right; a current fit's),
    whose midpoint gives the pelvis's axis and height.

    From ``CROTCH_ABOVE_M`` above the hips down to ``CROTCH_BELOW_M`` below, slices
    ``CROTCH_STEP_M`` apart (``_legs_apart``); the split is the first level whose legs are two
    contours for ``CROTCH_SPLIT_SLICES`` slices under a merged slice. The legs' closest points
    there must be at most ``CROTCH_MAX_GAP_M`` apart, with their midpoint between the hips
    (``CROTCH_BETWEEN``); the crotch is the lowest point straight above that midpoint (within
    ``CROTCH_RAY_M``), less than ``CROTCH_REACH_M`` above: the saddle that closes the gap. Legs
    that part lower down (under a skirt's or a coat's hem, or pressed together) or a gap open
    above (nothing scanned inside a garment) give None."""
    P = np.asarray(points, np.float64)
    hips = np.asarray(hips, np.float64)
    centre = hips.mean(0)
    P = P[np.linalg.norm(P[:, [0, 2]] - centre[[0, 2]], axis=1) < CROTCH_WINDOW_M]
    if len(P) < 50:
        return None
    n_split = int(round((CROTCH_ABOVE_M + CROTCH_BELOW_M) / CROTCH_STEP_M)) + 1
    levels = centre[1] + CROTCH_ABOVE_M - CROTCH_STEP_M * np.arange(n_split + CROTCH_SPLIT_SLICES)
    legs = [_legs_apart(P, np.nonzero(np.abs(P[:, 1] - y) < CROTCH_HALF_M)[0], hips) for y in levels]
    axis = hips[0] - hips[1]
    for k in range(1, n_split):
        if legs[k - 1] != 1 or not all(isinstance(s, tuple) for s in legs[k:k + CROTCH_SPLIT_SLICES]):
            continue  # no merged slice just above, or the split does not hold (a sparse slice)
        a, b = (P[i] for i in legs[k])
        d, j = cKDTree(b[:, [0, 2]]).query(a[:, [0, 2]])
        i = int(np.argmin(d))
        mid = 0.5 * (a[i] + b[j[i]])
        t = float(np.dot(mid - hips[1], axis)) / max(float(np.dot(axis, axis)), 1e-12)
        if d[i] > CROTCH_MAX_GAP_M or not CROTCH_BETWEEN[0] <= t <= CROTCH_BETWEEN[1]:
            return None
        ray = (np.linalg.norm(P[:, [0, 2]] - mid[[0, 2]], axis=1) < CROTCH_RAY_M) \
            & (P[:, 1] > levels[k] - CROTCH_HALF_M) & (P[:, 1] < levels[k] + CROTCH_REACH_M)
        if not ray.any():
            return None  # the gap is open above: the legs part under a garment (a skirt's hem)
        hit = P[ray]
        return hit[int(np.argmin(hit[:, 1]))]
    return None


# -- the shoulders: the bony shoulder tip (acromion) at the top of the arm's junction (issue 12) --
SHOULDER_RADIUS_M = 0.10  # the acromion lies this close to the shoulder joint ...
SHOULDER_BAND_M = 0.02  # ... within this of the joint's frontal plane
SHOULDER_EDGE_SHARE = 0.85  # a farthest point this near the radius is an arm raised past it: None
SHOULDER_MIN_POINTS = 10


def find_shoulder(points: np.ndarray, joint: np.ndarray, lateral: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """The acromion (3,) of one shoulder, or None. points: (P, 3); joint: (3,) the shoulder
    joint (a current fit's); lateral, up: (3,) unit vectors of the torso (out of this side, up).

    Among the points within ``SHOULDER_RADIUS_M`` of the joint and ``SHOULDER_BAND_M`` of its
    frontal plane, the one farthest up and out (along lateral + up): the top-outer corner of
    the shoulder, where the arm's top meets the torso's. An arm raised along that direction
    has its farthest point at the ball's rim, not at a corner: None."""
    P = np.asarray(points, np.float64) - joint
    lateral, up = np.asarray(lateral, np.float64), np.asarray(up, np.float64)
    depth = np.cross(lateral, up)
    r = np.linalg.norm(P, axis=1)
    ok = (r < SHOULDER_RADIUS_M) & (np.abs(P @ depth) < SHOULDER_BAND_M)
    if ok.sum() < SHOULDER_MIN_POINTS:
        return None
    d = (lateral + up) / np.linalg.norm(lateral + up)
    i = np.nonzero(ok)[0][int(np.argmax(P[ok] @ d))]
    if r[i] > SHOULDER_EDGE_SHARE * SHOULDER_RADIUS_M:
        return None
    return P[i] + joint

"""Cleaning real body-scanner output before the body fit (issue 12). Pure numpy/scipy.

A real scan of a person is not the person's outer surface alone: it holds the floor the person
stands on (a dense disc from a turntable scanner, or the room's floor, noisy and slightly
tilted), stray clusters (dust, a cable, reflections), and it misses parts: holes where no
camera saw (armpits, crotch, under the chin, dark or shiny cloth) and the top of the head when
the field of view ends below it. :func:`clean_scan` removes what is not the person:

1. **Floor** (:func:`find_floor`): RANSAC over planes through three points near either end of
   the scan's principal (height) axis, normals within ``FLOOR_MAX_TILT_DEG`` of it; the plane
   with the most inliers (within ``FLOOR_INLIER_M``) that has the scan on one side (at least
   ``FLOOR_ABOVE_SHARE`` of the points above it), holds at least ``FLOOR_MIN_SHARE`` of the
   points and spreads at least ``FLOOR_MIN_EXTENT_M`` across in both directions of the plane
   (the soles of two feet do not) is refitted by least squares to its inliers (Fischler and
   Bolles 1981, RANSAC; the refit is the total-least-squares plane). Points below it or less
   than ``max(FLOOR_BAND_M, FLOOR_BAND_SIGMAS * noise)`` above it are dropped; the feet above
   the band stay. A floor as wide as the person is tall (a short or headless person on a
   scanner's floor) turns the principal axis away from the height; when none is found along
   it, planes through any three points are tried, and one holding ``FLOOR_ANYWHERE_MIN_SHARE``
   of the points with the rest rising ``FLOOR_PERSON_MIN_M`` above it is the floor.
2. **Isolated clusters** (:func:`isolated_clusters`): connected components of the points on a
   voxel grid (``person_check.components``: 26-connected voxels of a few point spacings).
   Components holding less than ``CLUSTER_MIN_SHARE`` of the points and farther than
   ``CLUSTER_NEAR_M`` from every larger one are dropped; a part split off the body by a hole
   (a head above a cut neck, a hand) is large or near, and stays.

A processed scan may have its open head top closed by a flat cap of new points (software
making the mesh watertight); :func:`flat_cap` finds one (a filled plane patch at the top that the
scan lies below, ending in an edge), and the fit, once it knows the up axis, leaves it out so
that the head is open again.

Holes and a cut head top are kept as they are: they are handled in the fit's data term by
:func:`over_hole`, which rejects a correspondence whose nearest scan point lies off to the side
of the template vertex (on the rim of a hole, or of the cut) rather than below or above it, so
the body is not pulled into holes and, where the scan has nothing, the body model (its shape
prior and the rest of the body) carries the surface -- the top of the head included, so the
stature is not lost with it. A template vertex that juts out over a rim (a nose over a hole
that took the face) has its nearest point on the rim straight below it, which that test keeps;
:func:`rim_points` finds the rims on the scan itself (points whose neighbours all lie to one
side), and the fit drops every pair whose scan point is on one.

Shapes: points (P, 3) metres; normals (P, 3); faces (F, 3) int64.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial import cKDTree

# -- the floor ----------------------------------------------------------------------------------
FLOOR_RANSAC_ITERATIONS = 300
FLOOR_END_SHARE = 0.15  # plane hypotheses from points in this share of the height at either end
FLOOR_MAX_TILT_DEG = 30.0  # the floor's normal within this of the scan's height axis
FLOOR_INLIER_M = 0.012  # a point this near a plane lies on it (scanner noise of a few mm)
FLOOR_ABOVE_SHARE = 0.97  # a floor has (nearly) the whole scan on one side
FLOOR_MIN_SHARE = 0.03  # ... holds at least this share of the points
FLOOR_MIN_EXTENT_M = 0.45  # ... and spreads this far in both directions (5th-95th percentile)
FLOOR_BAND_M = 0.015  # points less than this above the floor are floor (the soles' rims go too)
FLOOR_BAND_SIGMAS = 3.5  # ... or this many standard deviations of the floor's noise
FLOOR_SAMPLE = 4000  # points scored per hypothesis (a random subset of larger scans)
# No floor found along the principal axis: a floor as wide as the person is tall (a headless or
# short person on a scanner's 1.4 m floor) turns that axis by 30-40 degrees. Then planes through
# any three points of the scan, kept when the floor holds this share of the points ...
FLOOR_ANYWHERE_MIN_SHARE = 0.1
FLOOR_PERSON_MIN_M = 0.9  # ... and the rest rises this far above it (a person's back is no floor)

# -- isolated clusters --------------------------------------------------------------------------
CLUSTER_MIN_SHARE = 0.005  # smaller components are dropped when isolated ...
CLUSTER_NEAR_M = 0.05  # ... i.e. farther than this from every larger component

# -- a flat cap over the head (a scanner's hole filling) -----------------------------------------
CAP_DEPTH_M = 0.05  # cap planes through points this near the scan's top ...
CAP_RANSAC_ITERATIONS = 200
CAP_MAX_TILT_DEG = 30.0  # ... with normals within this of the up axis
CAP_INLIER_M = 0.004  # a point this near the plane is on the cap
CAP_BELOW_SHARE = 0.999  # the whole scan (but this share: noise) lies below a cap
CAP_MIN_EXTENT_M = 0.08  # and it spreads this far both ways (5th-95th percentile): a crown's 5-8 cm
CAP_MIN_POINTS = 30
CAP_FILLED_SHARE = 0.8  # ... and fills it: cells of its hull holding a point (a cut's rim is a ring)
CAP_CELL_SPACINGS = 3.0  # cells this many of the scan's point spacings wide (at least 1 cm)
CAP_RING_M = 0.015  # the scan within this of the patch (along the plane), outside it ...
CAP_RING_DEPTH_M = 0.06  # ... and at most this far below it, is its edge
CAP_MIN_RING_POINTS = 10
CAP_MIN_SLOPE = 0.95  # ... falling at least this steeply from it (median depth / distance): crowns 0.3-0.9

# -- holes in the data term ----------------------------------------------------------------------
HOLE_MIN_M = 0.015  # a correspondence this far beside the template vertex (tangentially) is
HOLE_SPACINGS = 2.5  # ... or this many scan point spacings: the nearest point is a hole's rim
SPACING_SAMPLE = 500  # points sampled to measure the scan's point spacing


@dataclass
class Cleaning:
    """What :func:`clean_scan` did: kept (P,) bool over the input points, the floor plane
    (normal (3,), offset: n . p + d = 0, normal pointing to the person) or None, counts."""

    kept: np.ndarray
    floor: tuple[np.ndarray, float] | None
    stats: dict = field(default_factory=dict)


def _principal_axis(points: np.ndarray) -> np.ndarray:
    c = points - points.mean(0)
    _, _, Vt = np.linalg.svd(c[:: max(1, len(c) // 5000)], full_matrices=False)
    return Vt[0]


def _plane_through(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (H, 3) and offsets (H,) of the planes through point triples (H, 3) each;
    degenerate triples get a zero normal."""
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(ln > 1e-12, n / np.maximum(ln, 1e-12), 0.0)
    return n, -np.einsum("ij,ij->i", n, a)


def _tls_plane(points: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Total-least-squares plane of points (N, 3): (unit normal, offset, rms distance)."""
    c = points.mean(0)
    _, s, Vt = np.linalg.svd(points - c, full_matrices=False)
    n = Vt[2]
    return n, -float(n @ c), float(s[2] / np.sqrt(max(len(points), 1)))


def find_floor(points: np.ndarray, rng: np.random.Generator | None = None,
               axis: np.ndarray | None = None) -> tuple[np.ndarray, float, float] | None:
    """The floor under a scanned person (module docstring, step 1): (unit normal (3,) towards
    the person, offset d with n . p + d = 0, noise rms in metres), or None when the scan has no
    floor. points (P, 3) metres; ``axis`` (3,): the scan's height axis if known (default: its
    principal axis, which a person standing on a floor narrower than their height has; when no
    floor is found along it, a floor across the scan: :func:`_planes_anywhere`)."""
    P = np.asarray(points, np.float64)
    if len(P) < 50:
        return None
    rng = rng or np.random.default_rng(0)
    S = P[rng.choice(len(P), FLOOR_SAMPLE, replace=False)] if len(P) > FLOOR_SAMPLE else P
    if axis is None:
        floor = _best_floor(P, S, _planes_along(P, rng, _principal_axis(P)))
        if floor is None:  # a floor as wide as the person is tall turns the principal axis
            floor = _best_floor(P, S, _planes_anywhere(P, rng), FLOOR_ANYWHERE_MIN_SHARE, FLOOR_PERSON_MIN_M)
        return floor
    return _best_floor(P, S, _planes_along(P, rng, np.asarray(axis, np.float64) / np.linalg.norm(axis)))


def _planes_along(P: np.ndarray, rng: np.random.Generator, axis: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plane hypotheses (normals (H, 3), offsets (H,)) through point triples near either end of
    the height ``axis`` (3,) unit, normals within ``FLOOR_MAX_TILT_DEG`` of it; one batch per end."""
    h = P @ axis
    lo, hi = h.min(), h.max()
    span = hi - lo
    cos_tilt = np.cos(np.radians(FLOOR_MAX_TILT_DEG))
    out = []
    for end in (h <= lo + FLOOR_END_SHARE * span, h >= hi - FLOOR_END_SHARE * span):
        cand = np.flatnonzero(end)
        if len(cand) < 3:
            continue
        tri = P[cand[rng.integers(0, len(cand), size=(FLOOR_RANSAC_ITERATIONS, 3))]]
        n, d = _plane_through(tri[:, 0], tri[:, 1], tri[:, 2])
        ok = np.abs(n @ axis) >= cos_tilt
        if ok.any():
            out.append((n[ok], d[ok]))
    return out


def _planes_anywhere(P: np.ndarray, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """Plane hypotheses through point triples drawn from the whole scan, any orientation: a
    floor holding a large share of the points (``FLOOR_ANYWHERE_MIN_SHARE``) is hit often."""
    tri = P[rng.integers(0, len(P), size=(FLOOR_RANSAC_ITERATIONS, 3))]
    n, d = _plane_through(tri[:, 0], tri[:, 1], tri[:, 2])
    ok = np.linalg.norm(n, axis=1) > 0
    return [(n[ok], d[ok])] if ok.any() else []


def _best_floor(P: np.ndarray, S: np.ndarray, batches: list[tuple[np.ndarray, np.ndarray]],
                min_share: float = FLOOR_MIN_SHARE,
                min_height: float = 0.0) -> tuple[np.ndarray, float, float] | None:
    """The floor among plane hypotheses (batches of (normals (H, 3), offsets (H,))): the plane
    with the most inliers in the sample S (N, 3) that has (nearly) the whole scan on one side,
    refitted to its inliers in P (P, 3), holding ``min_share`` of the sample, spreading
    ``FLOOR_MIN_EXTENT_M`` both ways, and with the rest of the scan rising ``min_height`` metres
    above it (see :func:`find_floor`)."""
    best = None
    for n, d in batches:
        # orient every normal towards the bulk of the scan (the person above the floor)
        flip = P.mean(0) @ n.T + d < 0
        n[flip], d[flip] = -n[flip], -d[flip]
        dist = S @ n.T + d  # (N, H) signed
        inl = np.abs(dist) <= FLOOR_INLIER_M
        above = (dist >= -FLOOR_INLIER_M).mean(0)
        score = np.where(above >= FLOOR_ABOVE_SHARE, inl.sum(0), -1)
        k = int(np.argmax(score))
        if score[k] > 0 and (best is None or score[k] > best[0]):
            best = (int(score[k]), n[k], d[k])
    if best is None or best[0] < min_share * len(S):
        return None
    _, n, d = best
    for _ in range(2):  # refit to the inliers (total least squares), keep the orientation
        inl = P[np.abs(P @ n + d) <= FLOOR_INLIER_M]
        if len(inl) < 3:
            return None
        n2, d2, rms = _tls_plane(inl)
        if n2 @ n < 0:
            n2, d2 = -n2, -d2
        n, d = n2, d2
    # a floor spreads beyond the feet in both directions of the plane
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    q = inl @ np.stack([u, v], 1)
    cov = np.cov(q.T)
    ev = np.linalg.eigh(cov)[1]  # the inliers' own in-plane axes
    ext = np.ptp(np.percentile(q @ ev, [5, 95], axis=0), axis=0)
    if ext.min() < FLOOR_MIN_EXTENT_M:
        return None
    if min_height > 0 and np.percentile(P @ n + d, 99.5) < min_height:  # nobody stands on it
        return None
    return n, float(d), rms


def isolated_clusters(points: np.ndarray) -> np.ndarray:
    """(P,) bool: points in small components far from every larger one (module docstring,
    step 2). points (P, 3) metres."""
    from service.model.fitting.person_check import components

    P = np.asarray(points, np.float64)
    labels, _ = components(P)
    counts = np.bincount(labels)
    small = counts < CLUSTER_MIN_SHARE * len(P)
    if not small.any() or small.all():
        return np.zeros(len(P), bool)
    big_pts = ~small[labels]
    d, _ = cKDTree(P[big_pts]).query(P[~big_pts], distance_upper_bound=CLUSTER_NEAR_M)
    out = np.zeros(len(P), bool)
    far = np.isinf(d)
    # a small component goes when all of its points are far from the larger ones
    lab_small = labels[~big_pts]
    near_any = np.zeros(len(counts), bool)
    near_any[np.unique(lab_small[~far])] = True
    out[~big_pts] = ~near_any[lab_small]
    return out


def clean_scan(points: np.ndarray, normals: np.ndarray | None = None, faces: np.ndarray | None = None,
               rng: np.random.Generator | None = None, axis: np.ndarray | None = None):
    """Drop the floor and isolated clusters from a scan (module docstring). points (P, 3)
    metres, normals (P, 3) or None, faces (F, 3) or None, ``axis`` the height axis for
    :func:`find_floor` (default: the principal axis). Returns (points (P', 3), normals or
    None, faces (F', 3) re-indexed, the faces whose three vertices stay, or None,
    :class:`Cleaning`)."""
    P = np.asarray(points, np.float64)
    keep = np.ones(len(P), bool)
    floor = find_floor(P, rng, axis)
    stats: dict = {"points_in": int(len(P))}
    if floor is not None:
        n, d, rms = floor
        band = max(FLOOR_BAND_M, FLOOR_BAND_SIGMAS * rms)
        on_floor = P @ n + d < band
        keep &= ~on_floor
        stats.update(floor_points=int(on_floor.sum()), floor_band_mm=round(1000 * band, 1),
                     floor_rms_mm=round(1000 * rms, 1))
        floor = (n, d)
    if keep.sum() >= 100:
        idx = np.flatnonzero(keep)
        stray = isolated_clusters(P[idx])
        keep[idx[stray]] = False
        stats["stray_points"] = int(stray.sum())
    if keep.sum() < 100:  # cleaning would leave nothing to fit: leave the scan as it is
        keep[:] = True
        stats["undone"] = True
    stats["points_out"] = int(keep.sum())
    nrm = None if normals is None else np.asarray(normals)[keep]
    return P[keep], nrm, kept_faces(faces, keep), Cleaning(keep, floor, stats)


def kept_faces(faces: np.ndarray | None, keep: np.ndarray) -> np.ndarray | None:
    """The faces (F, 3) whose three vertices are kept (keep: (P,) bool), re-indexed into the kept
    vertices: (F', 3) int64, or None without faces."""
    if faces is None:
        return None
    faces = np.asarray(faces, np.int64)
    remap = np.cumsum(keep) - 1
    return remap[faces[keep[faces].all(1)]] if len(faces) else faces


def clean_wide_scan(points: np.ndarray, normals: np.ndarray | None = None, faces: np.ndarray | None = None):
    """A scan wider than a person because of its floor (a room's floor scanned around the
    person, more than ``frames.PERSON_MAX_M`` across), in unknown units: for each unit
    (``frames.UNITS``, metres first) and each height-axis hypothesis -- the principal axis (a
    floor narrower than the person is tall) and the least principal axis (the normal of a floor
    wider than that: it dominates the spread) -- the scan is cleaned in metres
    (:func:`clean_scan`); the first whose floor is found and whose rest is a person's size
    (``frames.detect_unit`` in metres) wins; only units at which the scan is too wide for a
    person are tried (a person's back is flat enough to pass for a floor: the floor must be what
    made the scan too wide). points (P, 3) file units. Returns (unit, metres per
    unit, points (P', 3) metres, normals, faces, :class:`Cleaning`) or None."""
    from service.model.formats.frames import PERSON_MAX_M, UNITS, UnitError, detect_unit

    pts = np.asarray(points, np.float64)
    for name, scale in UNITS.items():
        Pm = pts * scale
        if np.ptp(Pm, axis=0).max() <= PERSON_MAX_M:  # not too wide at this unit: not a wide floor
            continue
        c = Pm[:: max(1, len(Pm) // 5000)] - Pm.mean(0)
        _, _, Vt = np.linalg.svd(c, full_matrices=False)
        for axis in (Vt[0], Vt[2]):
            kept, nrm, F, cleaning = clean_scan(Pm, normals, faces, axis=axis)
            if cleaning.floor is None or cleaning.stats.get("undone"):
                continue
            try:
                detect_unit(kept)  # the rest must be a person's size in metres
            except UnitError:
                continue
            cleaning.stats["wide_floor"] = True
            return name, scale, kept, nrm, F, cleaning
    return None


def flat_cap(points: np.ndarray, up: np.ndarray | None = None, rng: np.random.Generator | None = None) -> np.ndarray:
    """(P,) bool: the points of a flat cap closing the top of the scan, or none. A scanner whose
    field of view ends below the crown leaves the head open; software that makes the mesh
    watertight may close it with a plane of new points, which would pull the fitted head down
    to it (a flat cap 4 cm below the crown: rest-pose stature 0.9 cm short). A cap is a plane
    (RANSAC over triples of points within ``CAP_DEPTH_M`` of the top, normals within
    ``CAP_MAX_TILT_DEG`` of ``up``; refitted by total least squares) that the whole scan lies
    below (but ``1 - CAP_BELOW_SHARE``), holding at least ``CAP_MIN_POINTS`` points within
    ``CAP_INLIER_M`` that spread at least ``CAP_MIN_EXTENT_M`` both ways (5th-95th percentile
    along their own axes), fill their hull as densely as the scan (``CAP_FILLED_SHARE`` of the
    cells ``CAP_CELL_SPACINGS`` of the scan's point spacings wide hold a point; a cut's rim is a
    ring) and end in an edge: the scan just outside the patch (within ``CAP_RING_M`` of it, seen
    along the plane's normal) falls away from it at a median slope of ``CAP_MIN_SLOPE`` or more
    (depth below the band over distance from the patch), where a crown (or hair) touching a
    plane curves away gradually (0.3-0.9 on the bench's heads, a cut's walls 1.0-2.6). The
    cap's points are then no data: dropped, the head is open and its top the body model's (as a
    cut head). points (P, 3) metres; ``up`` (3,) the scan's up direction (default +Y, the model
    frame)."""
    on, figures = cap_candidate(points, up, rng)
    ok = (on is not None and figures["extent_m"] >= CAP_MIN_EXTENT_M and figures["filled"] >= CAP_FILLED_SHARE
          and figures["ring_points"] >= CAP_MIN_RING_POINTS and figures["slope"] >= CAP_MIN_SLOPE)
    out = np.zeros(len(points), bool)
    if ok:
        out[on] = True
    return out


def cap_candidate(points: np.ndarray, up: np.ndarray | None = None,
                  rng: np.random.Generator | None = None) -> tuple[np.ndarray | None, dict]:
    """The plane patch :func:`flat_cap` judges: (indices of its points or None, figures:
    ``extent_m`` (the smaller 5th-95th percentile extent), ``filled`` (share of its hull's cells
    holding a point), ``ring_points``, ``drop_m`` and ``slope`` (how many points lie just outside
    it, their median depth below it and the median of depth over distance)). points (P, 3)
    metres, ``up`` (3,)."""
    P = np.asarray(points, np.float64)
    up = np.array([0.0, 1.0, 0.0]) if up is None else np.asarray(up, np.float64) / np.linalg.norm(up)
    rng = rng or np.random.default_rng(0)
    h = P @ up
    cand = np.flatnonzero(h >= h.max() - CAP_DEPTH_M)
    if len(cand) < CAP_MIN_POINTS:
        return None, {}
    tri = P[cand[rng.integers(0, len(cand), size=(CAP_RANSAC_ITERATIONS, 3))]]
    n, d = _plane_through(tri[:, 0], tri[:, 1], tri[:, 2])
    flip = n @ up < 0
    n[flip], d[flip] = -n[flip], -d[flip]
    ok = n @ up >= np.cos(np.radians(CAP_MAX_TILT_DEG))
    if not ok.any():
        return None, {}
    n, d = n[ok], d[ok]
    top = P[cand]
    S = P[rng.choice(len(P), FLOOR_SAMPLE, replace=False)] if len(P) > FLOOR_SAMPLE else P
    below = (S @ n.T + d <= CAP_INLIER_M).mean(0)
    score = np.where(below >= CAP_BELOW_SHARE, (np.abs(top @ n.T + d) <= CAP_INLIER_M).sum(0), 0)
    k = int(np.argmax(score))
    if score[k] < CAP_MIN_POINTS:
        return None, {}
    n, d = n[k], d[k]
    on = cand[np.abs(top @ n + d) <= CAP_INLIER_M]
    n2, d2, _ = _tls_plane(P[on])
    if n2 @ n < 0:
        n2, d2 = -n2, -d2
    on = cand[np.abs(top @ n2 + d2) <= CAP_INLIER_M]
    depth = -(P @ n2 + d2)
    if len(on) < CAP_MIN_POINTS or (depth >= -CAP_INLIER_M).mean() < CAP_BELOW_SHARE:
        return None, {}
    centre = P[on].mean(0)
    _, _, Vt = np.linalg.svd(P[on] - centre, full_matrices=False)  # the patch's own in-plane axes
    xy = (P[on] - centre) @ Vt[:2].T
    ext = np.ptp(np.percentile(xy, [5, 95], axis=0), axis=0)
    cell = max(0.01, CAP_CELL_SPACINGS * point_spacing(cKDTree(P), P, rng))
    # the scan just outside the patch, below it: a cap's edge drops, a crown curves away
    near = np.flatnonzero((depth > CAP_INLIER_M) & (depth < CAP_RING_DEPTH_M))
    rxy = (P[near] - centre) @ Vt[:2].T
    dist, _ = cKDTree(xy).query(rxy, distance_upper_bound=CAP_RING_M)
    out = np.isfinite(dist) & ~_inside_hull(xy, rxy)
    ring = near[out]
    slope = (depth[ring] - CAP_INLIER_M) / np.maximum(dist[out], 1e-3)
    figures = {"points": int(len(on)), "extent_m": float(ext.min()), "filled": _filled_share(xy, cell),
               "ring_points": int(len(ring)), "drop_m": float(np.median(depth[ring])) if len(ring) else 0.0,
               "slope": float(np.median(slope)) if len(ring) else 0.0}
    return on, figures


def _inside_hull(xy: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(Q,) bool: the 2D points q (Q, 2) inside the convex hull of xy (N, 2) (none when xy
    spans no area)."""
    from scipy.spatial import ConvexHull, Delaunay, QhullError

    try:
        return Delaunay(xy[ConvexHull(xy).vertices]).find_simplex(q) >= 0
    except QhullError:  # collinear or too few points: no area
        return np.zeros(len(q), bool)


def _filled_share(xy: np.ndarray, cell: float) -> float:
    """The share of the square cells ``cell`` wide (metres) whose centre is inside the convex
    hull of the 2D points xy (N, 2) that hold a point: ~1 for a patch as dense as the scan, low
    for a ring of points around a hole or a sparse slice through hair."""
    ij = np.floor((xy - xy.min(0)) / cell).astype(np.int64)
    shape = ij.max(0) + 1
    gi, gj = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    centres = (np.stack([gi.ravel(), gj.ravel()], 1) + 0.5) * cell + xy.min(0)
    inside = _inside_hull(xy, centres)
    if not inside.any():
        return 0.0
    held = np.zeros(shape, bool)
    held[ij[:, 0], ij[:, 1]] = True
    return float(held.ravel()[inside].mean())


def point_spacing(tree: cKDTree, points: np.ndarray, rng: np.random.Generator | None = None) -> float:
    """Median distance (metres) from a scan point to its nearest neighbour (a sample of
    ``SPACING_SAMPLE`` points of ``points``, the tree's data)."""
    rng = rng or np.random.default_rng(0)
    s = points[rng.choice(len(points), min(SPACING_SAMPLE, len(points)), replace=False)]
    d, _ = tree.query(s, k=2)
    return float(np.median(d[:, 1]))


LOCAL_SPACING_K = 4  # the local spacing at a scan point: distance to its (k-1)-th neighbour


def over_hole(T: np.ndarray, c: np.ndarray, nc: np.ndarray, spacing: float,
              tree: cKDTree | None = None) -> np.ndarray:
    """(V,) bool: template vertices T (V, 3) whose nearest scan point c (V, 3) (normal nc) lies
    off to the side rather than below or above them: the tangential offset
    |(T - c) - ((T - c) . nc) nc| exceeds ``max(HOLE_MIN_M, HOLE_SPACINGS * s)``, s the scan's
    ``spacing`` or, given the scan's ``tree``, the larger local spacing around c (meshes with
    large triangles: their vertices are far apart where the surface is flat). On a surface
    sampled s apart the nearest point is at most about s aside; over a hole (or a cut head top)
    it is on the rim, farther. Such correspondences are rejected."""
    r = T - c
    tang = r - np.einsum("ij,ij->i", r, nc)[:, None] * nc
    s = np.full(len(T), float(spacing))
    if tree is not None:
        d, _ = tree.query(c, k=LOCAL_SPACING_K)
        s = np.maximum(s, d[:, -1])
    return np.linalg.norm(tang, axis=1) > np.maximum(HOLE_MIN_M, HOLE_SPACINGS * s)


# -- holes' rims ---------------------------------------------------------------------------------
RIM_NEIGHBOURS = 24  # neighbours whose directions around a point tell a rim from the inside
RIM_GAP_DEG = 120.0  # ... a rim point has none over this wide an angle (a half-plane: 180)
RIM_BLOCK = 20_000  # points per block of rim_points (~12 MB of neighbour offsets)


def rim_points(points: np.ndarray, normals: np.ndarray, tree: cKDTree | None = None,
               k: int = RIM_NEIGHBOURS, gap_deg: float = RIM_GAP_DEG) -> np.ndarray:
    """(P,) bool: points on a boundary of the scanned surface -- a hole's rim, a cut head top,
    the edge of a partial scan -- by the angle criterion (Bendels, Schnabel and Klein 2006,
    "Detecting holes in point set surfaces"): the k nearest neighbours' offsets projected onto
    the point's tangent plane (normal (P, 3)) leave an angular gap wider than ``gap_deg``. Inside
    a surface the neighbours surround the point (the widest gap ~30-60 degrees with noise); on a
    rim they lie on one side (~180). Points (P, 3) metres; works on point clouds and meshes alike."""
    P = np.asarray(points, np.float64)
    n = np.asarray(normals, np.float64)
    if len(P) <= k:
        return np.zeros(len(P), bool)
    tree = tree if tree is not None else cKDTree(P)
    out = np.zeros(len(P), bool)
    for a0 in range(0, len(P), RIM_BLOCK):  # (block, k, 3) offsets at a time: bounded memory
        p, nb = P[a0:a0 + RIM_BLOCK], n[a0:a0 + RIM_BLOCK]
        _, nn = tree.query(p, k=k + 1)
        d = P[nn[:, 1:]] - p[:, None, :]  # (B, k, 3)
        # an orthonormal tangent basis (u, v) per point
        a = np.where(np.abs(nb[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
        u = np.cross(nb, a)
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        v = np.cross(nb, u)
        ang = np.sort(np.arctan2(np.einsum("pki,pi->pk", d, v), np.einsum("pki,pi->pk", d, u)), axis=1)
        gaps = np.diff(np.concatenate([ang, ang[:, :1] + 2 * np.pi], axis=1), axis=1)
        out[a0:a0 + RIM_BLOCK] = gaps.max(axis=1) > np.radians(gap_deg)
    return out


def rim_distance(points: np.ndarray, rim: np.ndarray) -> np.ndarray:
    """(P,) metres from each of ``points`` (P, 3) to the nearest rim point (``rim`` (P,) bool
    from :func:`rim_points`); inf where the scan has no rim."""
    P = np.asarray(points, np.float64)
    if not rim.any():
        return np.full(len(P), np.inf)
    d, _ = cKDTree(P[rim]).query(P)
    return d

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
   the band stay.
2. **Isolated clusters** (:func:`isolated_clusters`): connected components of the points on a
   voxel grid (``person_check.components``: 26-connected voxels of a few point spacings).
   Components holding less than ``CLUSTER_MIN_SHARE`` of the points and farther than
   ``CLUSTER_NEAR_M`` from every larger one are dropped; a part split off the body by a hole
   (a head above a cut neck, a hand) is large or near, and stays.

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

# -- isolated clusters --------------------------------------------------------------------------
CLUSTER_MIN_SHARE = 0.005  # smaller components are dropped when isolated ...
CLUSTER_NEAR_M = 0.05  # ... i.e. farther than this from every larger component

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
    principal axis, which a person standing on a floor narrower than their height has)."""
    P = np.asarray(points, np.float64)
    if len(P) < 50:
        return None
    rng = rng or np.random.default_rng(0)
    axis = _principal_axis(P) if axis is None else np.asarray(axis, np.float64) / np.linalg.norm(axis)
    h = P @ axis
    lo, hi = h.min(), h.max()
    span = hi - lo
    S = P[rng.choice(len(P), FLOOR_SAMPLE, replace=False)] if len(P) > FLOOR_SAMPLE else P
    cos_tilt = np.cos(np.radians(FLOOR_MAX_TILT_DEG))
    best = None
    for end in (h <= lo + FLOOR_END_SHARE * span, h >= hi - FLOOR_END_SHARE * span):
        cand = np.flatnonzero(end)
        if len(cand) < 3:
            continue
        tri = P[cand[rng.integers(0, len(cand), size=(FLOOR_RANSAC_ITERATIONS, 3))]]
        n, d = _plane_through(tri[:, 0], tri[:, 1], tri[:, 2])
        ok = np.abs(n @ axis) >= cos_tilt
        if not ok.any():
            continue
        n, d = n[ok], d[ok]
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
    if best is None or best[0] < FLOOR_MIN_SHARE * len(S):
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
    return n, float(d), rms


def isolated_clusters(points: np.ndarray) -> np.ndarray:
    """(P,) bool: points in small components far from every larger one (module docstring,
    step 2). points (P, 3) metres."""
    from service.model.person_check import components

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
    from service.model.frames import PERSON_MAX_M, UNITS, UnitError, detect_unit

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

"""Preparing a scan for the fit: its unit, its points and normals in metres in the body's frame
(:class:`_Scan`), hole rims, what of the template the scan sees, and the correspondences
between the posed template and the scan.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.model.fitting import scan_cleanup as SC
from service.model.formats.frames import UnitError, detect_unit
from service.model.geometry.mesh import vertex_normals
from service.model.geometry.solvers import nearest_correspondences
from service.model.fitting.checks import FitError
from service.model.fitting.params import FitParams, TUNING
from service.model.fitting.regions import _hair
from service.model.fitting.rig import _bone_ids, _pose_model, _Posed, _Rig, _State, _subset

MAX_HEIGHT_M, MIN_HEIGHT_M = 2.6, 0.9  # a standing, sitting or crouching adult




def seen_vertices(rig: "_Rig", s: "_State", P: np.ndarray, rims: tuple | None) -> np.ndarray:
    """(n,) bool: the template vertices, posed by the state ``s``, with a scan point of P (P, 3;
    model frame) near them (TUNING.seen_m, TUNING.seen_spacings) that is not on a hole's rim (``rims``: (rim
    distance (P,), point spacing) or None)."""
    V = _pose_model(rig, s, _subset(rig, np.arange(len(rig.mean)))).v
    tree = cKDTree(P)
    radius = max(TUNING.seen_m, TUNING.seen_spacings * SC.point_spacing(tree, P))
    d, j = tree.query(V, distance_upper_bound=radius)
    seen = np.isfinite(d)
    if rims is not None:
        seen &= ~(rims[0][np.minimum(j, len(P) - 1)] <= TUNING.rim_spacings * rims[1])
    return seen


def seen_shares(rig: "_Rig", s: "_State", P: np.ndarray, rims: tuple | None,
                seen: np.ndarray | None = None) -> np.ndarray:
    """(17,) per bone (BONES order): the share of the template vertices it moves most that are
    seen (``seen_vertices``, or ``seen`` (n,) bool when given)."""
    bone = np.argmax(rig.W, axis=1)
    seen = seen_vertices(rig, s, P, rims) if seen is None else seen
    count = np.bincount(bone, minlength=len(rig.parents))
    return np.bincount(bone, weights=seen, minlength=len(rig.parents)) / np.maximum(count, 1) + (count == 0)


# -- scan preparation and initialisation ------------------------------------------------------
def detect_scan_unit(points: np.ndarray) -> tuple[str, float]:
    """(unit, metres per unit) of a scan (``frames.detect_unit``); :class:`FitError` if none fits."""
    try:
        return detect_unit(points)
    except UnitError as exc:
        raise FitError(str(exc)) from exc


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])




@dataclass
class _Scan:
    points: np.ndarray  # (P, 3) model frame, metres
    normals: np.ndarray  # (P, 3)
    sub: np.ndarray  # indices of a subsample for the coarse stage
    sub_tree: cKDTree
    # (P,) bool: points at a hole's rim (within a point spacing of one); None: not checked
    rim: np.ndarray | None = None
    # (len(sub),) bool: subsample points within the subsample's spacing of a rim; None: not checked
    sub_rim: np.ndarray | None = None

    @functools.cached_property
    def tree(self) -> cKDTree:
        """All points (built only for the candidate that goes on to Alg. 1)."""
        return cKDTree(self.points)


def _make_scan(points: np.ndarray, normals: np.ndarray, R: np.ndarray, t: np.ndarray,
               n_sub: int, rng: np.random.Generator, rims: tuple[np.ndarray, float] | None = None) -> _Scan:
    """The scan (P, 3) moved by R, t, with a random subsample of ``n_sub`` points. With
    ``rims`` (rim distance (P,): metres from each point to the nearest rim point,
    ``scan_cleanup.rim_distance``; the scan's point spacing, metres), the points near a hole's
    rim are marked: the full scan's within ``TUNING.rim_spacings`` spacings, the subsample's within as
    many of the subsample's spacings (the nearest subsample point to a spot inside a hole lies
    about that close to the rim)."""
    P = points @ R.T + t
    N = normals @ R.T
    sub = rng.choice(len(P), size=min(n_sub, len(P)), replace=False)
    sub_tree = cKDTree(P[sub])
    if rims is None:
        return _Scan(P, N, sub, sub_tree)
    rim_distance, spacing = rims
    sub_spacing = SC.point_spacing(sub_tree, P[sub])
    return _Scan(P, N, sub, sub_tree, rim=rim_distance <= TUNING.rim_spacings * spacing,
                 sub_rim=rim_distance[sub] <= TUNING.rim_spacings * sub_spacing)


def _posed_normals(rest_normals: np.ndarray, p: _Posed) -> np.ndarray:
    """Normals of posed vertices from rest normals rotated by the blended bone rotations."""
    n = (p.M @ rest_normals[:, :, None])[:, :, 0]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _rims(pts_m: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, float]:
    """The scan's holes' rims for ``FitParams.rim_reject``: (distance (P,) metres from each point
    to the nearest rim point, the scan's point spacing). pts_m, nrm (P, 3)."""
    tree = cKDTree(pts_m)
    return SC.rim_distance(pts_m, SC.rim_points(pts_m, nrm, tree)), SC.point_spacing(tree, pts_m)


# -- Alg. 1 -----------------------------------------------------------------------------------
def _correspondences(T: np.ndarray, rig: _Rig, tree: cKDTree, points: np.ndarray, normals: np.ndarray,
                     clothed: bool, params: FitParams, rim: np.ndarray | None = None):
    """Nearest scan point of each template vertex, rejected when normals differ by more than
    the threshold or it is too far (Alg. 1, line 4). Returns (c, nc, weight (0 = rejected))."""
    nT = vertex_normals(T, rig.faces, rig.incidence)
    j, _, ok = nearest_correspondences(T, nT, tree, normals, max_dist=params.max_corr_dist,
                                       normal_reject_deg=params.normal_reject_deg)
    c, nc = points[j], normals[j]
    signed = np.einsum("ij,ij->i", T - c, nc)
    if clothed:  # Alg. 1's alternation would carry T, then the body, out to loose clothes
        ok &= signed >= -params.alg1_inside_tol
    elif params.hair_region:  # ... and on a bare scan the scalp out to the hair
        ok &= ~_hair(rig, params) | (signed >= -params.alg1_inside_tol)
    if params.scan_cleanup:  # holes, a cut head top (issue 12)
        ok &= ~SC.over_hole(T, c, nc, SC.point_spacing(tree, points), tree)
    if rim is not None:  # (P,) bool: a hole's rim (FitParams.rim_reject)
        ok &= ~rim[j]
    if params.exclusive_hops is not None:  # the scan point is another body part's (FitParams)
        region = _subset(rig, np.arange(len(T))).region
        owner = cKDTree(T).query(c[ok])[1]
        ok[ok] = rig.hops[region[ok], region[owner]] <= params.exclusive_hops
    if params.absent_bones:
        ok &= ~np.isin(_subset(rig, np.arange(len(T))).region, _bone_ids(params.absent_bones))
    return c, nc, ok.astype(np.float64)

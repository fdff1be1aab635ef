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

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.geometry import closest_points_on_mesh, vertex_normals
from service.model.nonrigid import factor_spd
from service.model.skin_weights import uniform_laplacian

GAP = 0.0025  # metres left between an inner garment and the outer one over it
COVER_DISTANCE = 0.05  # metres: farther than this from the outer garment is not covered by it
BOUNDARY_MARGIN = 1e-3  # barycentric weight: closest points this near a boundary edge do not cover
SMOOTH = 2.0  # weight of the displacement's smoothness (uniform Laplacian) against the targets
EPS = 0.1  # pull of free vertices' displacement to 0: the falloff spans ~sqrt(SMOOTH / EPS) ~ 4.5 edges
PASSES = 3


def boundary_vertices(faces: np.ndarray, n: int) -> np.ndarray:
    """(n,) bool: vertices on an edge used by exactly one face."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    u, c = np.unique(e, axis=0, return_counts=True)
    out = np.zeros(n, bool)
    out[u[c == 1].ravel()] = True
    return out


def outward_normals(vertices: np.ndarray, faces: np.ndarray, body: np.ndarray, body_normals: np.ndarray) -> np.ndarray:
    """Unit vertex normals (M, 3) of a garment flipped, per vertex, to point away from the body."""
    n = vertex_normals(vertices, faces).astype(np.float64)
    _, nn = cKDTree(body).query(vertices)
    flip = np.einsum("ij,ij->i", n, body_normals[nn]) < 0
    n[flip] *= -1
    return n


def violations(inner: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray, outer_normals: np.ndarray,
               outer_boundary: np.ndarray, gap: float = GAP) -> tuple[np.ndarray, np.ndarray]:
    """For each inner vertex: (needed inward displacement (M, 3), covered (M,) bool). The
    displacement is nonzero where the vertex is covered and above -gap along the outer normal."""
    F = np.asarray(outer_faces, np.int64)
    face, q, bary = closest_points_on_mesh(inner, outer, F)
    n = np.einsum("mk,mkj->mj", bary, outer_normals[F[face]])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    s = np.einsum("ij,ij->i", inner - q, n)  # > 0: outside the outer garment
    # the closest point on a boundary edge (or a boundary vertex's corner) is not covering
    edge_bound = np.stack([outer_boundary[F[face][:, 1]] & outer_boundary[F[face][:, 2]],
                           outer_boundary[F[face][:, 2]] & outer_boundary[F[face][:, 0]],
                           outer_boundary[F[face][:, 0]] & outer_boundary[F[face][:, 1]]], axis=1)
    at_boundary = ((bary < BOUNDARY_MARGIN) & edge_bound).any(axis=1) | \
        (((bary > 1 - BOUNDARY_MARGIN) & outer_boundary[F[face]]).any(axis=1))
    covered = ~at_boundary & (np.linalg.norm(inner - q, axis=1) < COVER_DISTANCE)
    need = covered & (s > -gap)
    D = np.zeros_like(inner)
    D[need] = -(s[need] + gap)[:, None] * n[need]
    return D, covered


def push_inside(inner: np.ndarray, inner_faces: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray,
                body: np.ndarray, body_normals: np.ndarray, gap: float = GAP,
                passes: int = PASSES) -> np.ndarray:
    """The inner garment (M, 3) with the parts outside the outer garment moved inside it,
    smoothly (see module docstring). Returns (M, 3) float64."""
    X = np.asarray(inner, np.float64).copy()
    O = np.asarray(outer, np.float64)
    on = outward_normals(O, outer_faces, body, body_normals)
    ob = boundary_vertices(outer_faces, len(O))
    L = uniform_laplacian(inner_faces, len(X))
    for _ in range(passes):
        D0, _ = violations(X, O, outer_faces, on, ob, gap)
        c = (np.einsum("ij,ij->i", D0, D0) > 0).astype(np.float64)
        if not c.any():
            break
        A = sp.diags(c + EPS) + SMOOTH * L
        D = factor_spd(A).solve(c[:, None] * D0)
        # the smoothed field never undershoots the targets: keep whichever goes deeper inward
        X += np.where(c[:, None] > 0, np.where((np.einsum("ij,ij->i", D, D0) >= np.einsum("ij,ij->i", D0, D0))[:, None],
                                                D, D0), D)
    return X


def layer_outfit(garments: list[tuple[np.ndarray, np.ndarray]], body: np.ndarray, body_normals: np.ndarray,
                 gap: float = GAP) -> list[np.ndarray]:
    """Garments [(vertices (M_i, 3), faces)] in layer order (inner first) on a body: each one
    pushed inside every garment over it (outermost first). Returns the new vertices."""
    out = [np.asarray(v, np.float64) for v, _ in garments]
    for i in range(len(garments)):
        for j in range(len(garments) - 1, i, -1):
            out[i] = push_inside(out[i], garments[i][1], out[j], garments[j][1], body, body_normals, gap)
    return out


def inner_outside_share(inner: np.ndarray, outer: np.ndarray, outer_faces: np.ndarray, inner_faces: np.ndarray,
                        body: np.ndarray, body_normals: np.ndarray, body_faces: np.ndarray,
                        tolerance: float = 0.0) -> tuple[int, int]:
    """The layering figure: (body vertices covered by both garments, of which the inner garment
    is outside the outer one by more than ``tolerance``). A body vertex is covered by a garment
    when the garment's closest point is within ``COVER_DISTANCE`` and its offset from the body
    vertex is mostly along the body normal (within 45 degrees) -- the garment is over it; the
    inner one is outside when its offset along the body normal is larger than the outer's."""
    B = np.asarray(body, np.float64)

    def over(G, F):
        _, q, _ = closest_points_on_mesh(B, G, F)
        d = q - B
        dist = np.linalg.norm(d, axis=1)
        along = np.einsum("ij,ij->i", d, body_normals)
        return (dist < COVER_DISTANCE) & (along > np.cos(np.pi / 4) * dist), along

    ci, ai = over(np.asarray(inner, np.float64), inner_faces)
    co, ao = over(np.asarray(outer, np.float64), outer_faces)
    both = ci & co
    return int(both.sum()), int((both & (ai > ao + tolerance)).sum())

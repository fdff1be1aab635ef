"""Mesh helpers shared by the body model, garments, the GLB writer and the offline build.

vertices: (V, 3) float, faces: (F, 3) int (counter-clockwise seen from outside).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp


def mesh_edges(faces: np.ndarray) -> np.ndarray:
    """Unique undirected edges (E, 2), each as (low, high)."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    return np.unique(np.sort(e, axis=1), axis=0)


def face_incidence(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, F) sparse vertex-face incidence: ``incidence @ face_values`` sums around vertices.
    Cache it per mesh: normals then cost one sparse product."""
    f = np.asarray(faces, np.int64)
    return sp.csr_matrix((np.ones(f.size, np.float32), (f.reshape(-1), np.repeat(np.arange(len(f)), 3))),
                         shape=(n_vertices, len(f)))


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix | None = None) -> np.ndarray:
    """Smooth, area-weighted unit vertex normals (V, 3) float32 (|n| = 1 within float32 eps).

    The un-normalised face cross product has length 2 x area: area weighting for free.
    Vertices on no face, or whose faces are degenerate, get +Y."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    inc = incidence if incidence is not None else face_incidence(f, len(v))
    acc = np.asarray(inc @ fn, np.float64)
    length = np.sqrt(np.einsum("ij,ij->i", acc, acc))
    ok = length > 1e-20
    if not ok.all():
        acc[~ok] = (0.0, 1.0, 0.0)
        length[~ok] = 1.0
    n32 = (acc / length[:, None]).astype(np.float32)
    # re-normalise after rounding so |n| == 1 within float32 eps (the glTF validator checks)
    n64 = n32.astype(np.float64)
    return (n64 / np.sqrt(np.einsum("ij,ij->i", n64, n64))[:, None]).astype(np.float32)


def winding_numbers(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray, chunk: int = 64) -> np.ndarray:
    """Generalised winding numbers (P,) of points (P, 3) with respect to a closed triangle
    mesh: ~1 inside, ~0 outside (Jacobson et al. 2013; solid angles by Van Oosterom and
    Strackee). Exact and robust, O(P F): use it to confirm a few candidate points."""
    V = np.asarray(vertices, np.float64)
    F = np.asarray(faces)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = np.asarray(points[s:s + chunk], np.float64)[:, None, :]
        a, b, c = V[F[:, 0]] - p, V[F[:, 1]] - p, V[F[:, 2]] - p
        la, lb, lc = (np.sqrt(np.einsum("pfi,pfi->pf", x, x)) for x in (a, b, c))
        num = np.einsum("pfi,pfi->pf", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pfi,pfi->pf", a, b) * lc + np.einsum("pfi,pfi->pf", b, c) * la
               + np.einsum("pfi,pfi->pf", c, a) * lb)
        out[s:s + chunk] = np.arctan2(num, den).sum(axis=1) / (2 * np.pi)
    return out


def closest_point_on_triangles(p, a, b, c):
    """Closest points on triangles (..., 3) to points p (Ericson, Real-Time Collision
    Detection 5.1.5), vectorised."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = (ab * ap).sum(-1), (ac * ap).sum(-1)
    bp = p - b
    d3, d4 = (ab * bp).sum(-1), (ac * bp).sum(-1)
    cp = p - c
    d5, d6 = (ab * cp).sum(-1), (ac * cp).sum(-1)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        res = a + ab * v[..., None] + ac * w[..., None]  # interior
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    cases = [
        ((d1 <= 0) & (d2 <= 0), a),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + ab * t_ab[..., None]),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + ac * t_ac[..., None]),
        ((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + (c - b) * t_bc[..., None]),
    ]
    for cond, val in reversed(cases):
        res = np.where(cond[..., None], val, res)
    return res


def vertex_faces(faces: np.ndarray, n: int) -> np.ndarray:
    """(n, max valence) face ids around each vertex, -1 padded."""
    order = np.argsort(faces.reshape(-1), kind="stable")
    vid = faces.reshape(-1)[order]
    fid = order // 3
    counts = np.bincount(vid, minlength=n)
    out = np.full((n, counts.max()), -1, np.int64)
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    pos = np.arange(len(vid)) - start[vid]
    out[vid, pos] = fid
    return out

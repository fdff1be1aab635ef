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

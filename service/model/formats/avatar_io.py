"""Avatars uploaded in the template topology -> PCA weights (the clothes paper's projection).

Accepts the published template's vertex count (the body surface, ``n_body_vertices``) or the
full hm08 vertex set. Units are detected from the height (m, cm or mm); axis conventions (Y or
Z up, facing any axis) are undone by the axis-aligned rotation nearest to a Kabsch alignment
with the mean avatar (small tilts are posture, which the shape space owns). Then
w = argmin |U_b w + t - (x_b - m_b)| over the uploaded rows and a translation t (exactly the
paper's dot products U (x - m) when all vertices are given, since U is orthonormal).

Shapes: vertices (n, 3); weights (K,).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from service.model.formats.frames import UnitError, detect_unit, kabsch, nearest_axis_rotation

MAX_RESIDUAL_M = 0.05  # mean distance to the reconstruction above which an upload is refused


class AvatarMeshError(ValueError):
    """An uploaded avatar that cannot be projected (wrong topology, units, not a body)."""


@dataclass
class Projection:
    weights: np.ndarray  # (K,)
    unit: str
    residual_mm: float  # mean per-vertex distance between the aligned upload and its projection


@functools.lru_cache(maxsize=4)
def _solver(model, n_rows: int):
    """Least-squares operator (K + 3, 3 n_rows) over the first n_rows vertices for the weights
    and a translation (where the upload stands is not part of its shape). A tiny ridge keeps
    the system regular where a component is itself nearly a translation."""
    U = model.components.reshape(model.n_components, -1, 3)[:, :n_rows].reshape(model.n_components, -1)
    T = np.zeros((3, n_rows, 3))
    for ax in range(3):
        T[ax, :, ax] = 1.0
    A = np.vstack([U.astype(np.float64), T.reshape(3, -1)])
    return np.linalg.solve(A @ A.T + 1e-9 * np.eye(len(A)), A)


def project_mesh(model, vertices: np.ndarray) -> Projection:
    """Weights of an uploaded avatar mesh in template topology (see module docstring)."""
    X = np.asarray(vertices, np.float64)
    n_full, n_body = model.mean.shape[0], model.n_body_vertices
    if X.ndim != 2 or X.shape[1] != 3:
        raise AvatarMeshError("vertices must be (n, 3)")
    if len(X) not in (n_full, n_body):
        raise AvatarMeshError(f"the mesh has {len(X)} vertices; the template topology has {n_body} "
                              f"(body surface, /v1/body-model/template.obj) or {n_full} (with helpers)")
    if not np.all(np.isfinite(X)):
        raise AvatarMeshError("the mesh has non-finite vertex coordinates")
    try:
        unit, scale = detect_unit(X[:n_body], what="the mesh")
    except UnitError as exc:
        raise AvatarMeshError(str(exc)) from exc
    X = X * scale
    K = model.n_components
    mean = model.mean[: len(X)].astype(np.float64)
    R, _ = kabsch(X, mean)
    Y = X @ nearest_axis_rotation(R).T
    sol = _solver(model, len(X)) @ (Y - mean).reshape(-1)
    w, shift = sol[:K], sol[K:]
    Y = Y - shift
    target = model.vertices(w)[: len(X)].astype(np.float64)
    res = float(np.linalg.norm(Y - target, axis=1).mean())
    if res > MAX_RESIDUAL_M:
        raise AvatarMeshError(f"the mesh is not an avatar in the template topology: mean distance to "
                              f"the closest body of the model is {1000 * res:.0f} mm")
    return Projection(weights=w, unit=unit, residual_mm=1000 * res)

"""The non-rigid toolkit shared by body fitting (editing paper, Sec. 4.2) and the body-aware
warping graph (Sec. 5.1): factored sparse systems, correspondences and Gauss-Newton steps.
Pure numpy/scipy (CHOLMOD through scikit-sparse when installed; the point-to-plane rows by a compiled
kernel where numba is there, ``service.model.geometry.kernels``).

Factor once, solve many: a sparse SPD matrix that is solved for many right-hand sides gets a
:class:`Factor` (:func:`factor_spd`); Eq. 2's edge system is :class:`EdgeSystem`.

Shapes: vertices / points (n, 3) float64; normals (n, 3) unit; faces (F, 3) int.
"""
from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.linalg import splu
from scipy.spatial import cKDTree

from service.model.geometry import kernels
from service.model.geometry.mesh import mesh_edges


# -- factored sparse systems ---------------------------------------------------------------------
@functools.lru_cache(maxsize=1)
def solver_backend() -> str:
    """'cholmod' when scikit-sparse is importable (the ``fast`` extra), else 'superlu'."""
    try:
        import sksparse.cholmod  # noqa: F401  # type: ignore[import-not-found]

        return "cholmod"
    except ImportError:
        return "superlu"


@dataclass
class Factor:
    """A factored sparse symmetric positive definite matrix A (n, n): ``solve(b)`` returns
    A^-1 b for b (n,) or (n, k). ``backend``: 'cholmod' or 'superlu'."""

    backend: str
    n: int
    _solve: Callable[[np.ndarray], np.ndarray]

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._solve(np.asarray(rhs, np.float64))


def factor_spd(A: sp.spmatrix, backend: str | None = None, *, mode: str = "auto") -> Factor:
    """Factor a sparse SPD matrix once (CHOLMOD's Cholesky when available, else SciPy's
    SuperLU with COLAMD ordering; ``backend`` forces one). ``mode`` is CHOLMOD's: 'auto',
    'supernodal' or 'simplicial' (a simplicial factor back-substitutes a few right-hand sides
    several times faster when the factor is small: the warping graph uses it)."""
    A = sp.csc_matrix(A, dtype=np.float64)
    backend = backend or solver_backend()
    if backend == "cholmod":
        from sksparse.cholmod import cholesky  # type: ignore[import-not-found]  # optional: the `fast` extra

        f = cholesky(A, mode=mode)
        return Factor("cholmod", A.shape[0], f)
    if backend != "superlu":
        raise ValueError(f"unknown sparse solver backend {backend!r}")
    lu = splu(A, permc_spec="COLAMD")
    return Factor("superlu", A.shape[0], lu.solve)


# -- Eq. 2 of the editing paper: the template update -----------------------------------------------
def edge_incidence(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, sp.csr_matrix]:
    """Unique edges (E, 2) of a triangle mesh and their signed incidence matrix D (E, n):
    (D v)_e = v_a - v_b."""
    edges = mesh_edges(faces)
    E = len(edges)
    D = sp.csr_matrix((np.r_[np.ones(E), -np.ones(E)], (np.r_[np.arange(E), np.arange(E)],
                                                         np.r_[edges[:, 0], edges[:, 1]])), shape=(E, n_vertices))
    return edges, D


def edge_laplacian(faces: np.ndarray, n_vertices: int) -> sp.csc_matrix:
    """The graph Laplacian L = D^T D (n, n) of the mesh edges (Eq. 2's edge term)."""
    _, D = edge_incidence(faces, n_vertices)
    return (D.T @ D).tocsc()


class EdgeSystem:
    """argmin_v' sum_edges ||(v'_a - v'_b) - e_ab||^2 + sum_i w_i (a_pt ||v'_i - c_i||^2
    + a_pl ||v'_i - pi_i||^2) (Eq. 2 of the editing paper, with its point-to-plane term
    n^T (v' - c) written as the distance to pi_i, the current v'_i projected onto c_i's tangent
    plane, and iterated in the inner loop). The matrix L + diag(w (a_pt + a_pl)) is the same
    for x, y and z and changes only with the correspondences: ``precompute`` factors it once
    (CHOLMOD when scikit-sparse is installed, else SuperLU) and ``solve`` back-substitutes."""

    def __init__(self, laplacian: sp.csc_matrix, diag: np.ndarray, eps: float = 1e-8,
                 backend: str | None = None):
        self.eps = eps
        self.diag = diag
        self.factor = factor_spd(laplacian + sp.diags(diag + eps), backend)
        self.backend = self.factor.backend

    @classmethod
    def precompute(cls, laplacian: sp.csc_matrix, diag: np.ndarray, backend: str | None = None) -> "EdgeSystem":
        return cls(laplacian, diag, backend=backend)

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """rhs: (n, 3) -> v' (n, 3)."""
        return self.factor.solve(rhs)


# -- correspondences ------------------------------------------------------------------------------
def nearest_correspondences(points: np.ndarray, point_normals: np.ndarray, tree: cKDTree,
                            target_normals: np.ndarray, *, max_dist: float,
                            normal_reject_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each point, its nearest target point (``tree`` over the targets), rejected when the
    normals differ by more than ``normal_reject_deg`` or it is farther than ``max_dist``
    (editing paper, Alg. 1 line 4). Returns (target index (n,), distance (n,), accepted (n,) bool)."""
    d, j = tree.query(points)
    cos_rej = np.cos(np.radians(normal_reject_deg))
    ok = (np.einsum("ij,ij->i", point_normals, target_normals[j]) >= cos_rej) & (d <= max_dist)
    return j, d, ok


def trimmed_mean(d: np.ndarray, keep: float = 0.9, weights: np.ndarray | None = None) -> float:
    """Mean of the smallest ``keep`` fraction of ``d`` (n,) (robust to outliers); with
    ``weights`` (n,) >= 0 the weighted mean of the smallest values holding ``keep`` of the
    total weight (e.g. the surface area each template vertex stands for)."""
    d = np.asarray(d, np.float64)
    if weights is None:
        d = np.sort(d)
        return float(d[: max(1, int(keep * len(d)))].mean())
    order = np.argsort(d)
    d, w = d[order], np.asarray(weights, np.float64)[order]
    n = max(1, int(np.searchsorted(np.cumsum(w), keep * w.sum(), side="right")))
    return float(np.average(d[:n], weights=w[:n]) if w[:n].sum() > 0 else d[:n].mean())


# -- Gauss-Newton ---------------------------------------------------------------------------------
def point_to_plane_normal_equations(jacobian: np.ndarray, vi: np.ndarray, nn: np.ndarray, w: np.ndarray,
                                    r: np.ndarray, region: np.ndarray | None = None,
                                    n_regions: int = 0, compiled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Newton normal equations of point-to-plane residuals r_k = n_k . (v_{vi_k} - c_k)
    with weights w_k: rows_k = n_k^T J_{vi_k}, H = rows^T W rows, g = rows^T W r.
    jacobian: (m, 3, P) of the m vertices; vi (k,), nn (k, 3), w (k,), r (k,) -> (H (P, P), g (P,)).
    With ``region`` (k,) int in [0, n_regions): one more unknown per region, the residuals
    r_k + o_{region_k} (the target moved in by o along its normal: the clothes' stand-off of
    ``fitting``), a one-hot column per region in the rows; H (P + R, P + R), g (P + R,), the
    region unknowns last. ``compiled`` (and numba there): the rows by ``kernels.pair_rows``,
    without the gathered copy of the Jacobian (k, 3, P)."""
    if compiled and kernels.AVAILABLE:
        rows = kernels.pair_rows(np.ascontiguousarray(jacobian, np.float64), np.asarray(vi, np.int64),
                                 np.ascontiguousarray(nn, np.float64))
    else:
        rows = np.matmul(nn[:, None, :], jacobian[vi])[:, 0]  # (k, P), one batched product
    wr = rows * w[:, None]
    H, g = rows.T @ wr, wr.T @ r
    if region is None:
        return H, g
    # the one-hot columns summed per region, never formed: H_po = sum_k w_k rows_k e_region_k^T,
    # H_oo = diag(sum of w per region), g_o = sum of w_k r_k per region
    n_par = len(g)
    per_region = sp.csr_matrix((np.ones(len(r)), (region, np.arange(len(r)))), shape=(n_regions, len(r)))
    Hf = np.zeros((n_par + n_regions, n_par + n_regions))
    Hf[:n_par, :n_par] = H
    Hf[n_par:, :n_par] = per_region @ wr
    Hf[:n_par, n_par:] = Hf[n_par:, :n_par].T
    Hf[n_par:, n_par:] = np.diag(np.bincount(region, weights=w, minlength=n_regions))
    return Hf, np.r_[g, np.bincount(region, weights=w * r, minlength=n_regions)]


def damped_step(H: np.ndarray, g: np.ndarray, *, damping: float = 1e-6, levenberg: float = 0.0) -> np.ndarray:
    """The Levenberg-Marquardt step -(H + (damping + levenberg mean(diag H)) I)^-1 g."""
    lam = damping + levenberg * float(np.trace(H)) / max(len(H), 1)
    return -np.linalg.solve(H + lam * np.eye(len(H)), g)


def prior_gauss_newton_step(w: np.ndarray, w0: np.ndarray, r: np.ndarray, J: np.ndarray, C: np.ndarray,
                            prior_weight: float) -> np.ndarray:
    """The Gauss-Newton update of  |r(w)|^2 + prior_weight |L^-1 (w - w0)|^2,  L L^T = C  (a
    Gaussian prior of mean w0 and covariance C):

        w - (J^T J + prior_weight C^-1)^-1 (J^T r + prior_weight C^-1 (w - w0))
          = w0 - C J^T (prior_weight I + J C J^T)^-1 (r - J (w - w0))      (Woodbury)

    w, w0: (K,); r: (m,) residuals at w; J: (m, K) their Jacobian; C: (K, K) SPD. Returns the
    new w (K,). With few residuals (m << K) this solves an m x m system, never inverts C."""
    CJ = C @ J.T  # (K, m)
    S = prior_weight * np.eye(len(r)) + J @ CJ
    return w0 - CJ @ np.linalg.solve(S, r - J @ (w - w0))

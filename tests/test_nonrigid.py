"""The non-rigid toolkit (service/model/geometry/solvers.py): the prefactored Eq. 2 solve and factored
systems against dense references on both sparse back ends, Gauss-Newton normal equations
against explicit rows, correspondences against a brute-force search."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.model.geometry import solvers as N

BACKENDS = ["cholmod", "superlu"]


def _need(backend):
    if backend == "cholmod":
        pytest.importorskip("sksparse.cholmod", reason="scikit-sparse (the `fast` extra) not installed")


def test_normal_equations_match_explicit_rows():
    rng = np.random.default_rng(3)
    Jac = rng.normal(size=(40, 3, 7))
    vi = rng.integers(0, 40, 90)
    nn = rng.normal(size=(90, 3))
    w, r = rng.uniform(0.1, 1, 90), rng.normal(size=90)
    H, g = N.point_to_plane_normal_equations(Jac, vi, nn, w, r)
    rows = np.stack([nn[k] @ Jac[vi[k]] for k in range(90)])
    np.testing.assert_allclose(H, rows.T @ np.diag(w) @ rows, atol=1e-10)
    np.testing.assert_allclose(g, rows.T @ (w * r), atol=1e-10)


def test_damped_step_is_levenberg_marquardt():
    rng = np.random.default_rng(5)
    A = rng.normal(size=(6, 6))
    H, g = A @ A.T, rng.normal(size=6)
    step = N.damped_step(H, g, damping=1e-3, levenberg=0.1)
    lam = 1e-3 + 0.1 * np.trace(H) / 6
    np.testing.assert_allclose((H + lam * np.eye(6)) @ step, -g, atol=1e-10)


def test_prior_gauss_newton_step_is_the_normal_equations():
    rng = np.random.default_rng(7)
    K, m = 9, 4
    A = rng.normal(size=(K, K))
    C = A @ A.T + 1e-3 * np.eye(K)  # SPD, ill-conditioned directions included
    J, r, w, w0 = rng.normal(size=(m, K)), rng.normal(size=m), rng.normal(size=K), rng.normal(size=K)
    P = 0.02 * np.linalg.inv(C)
    ref = w - np.linalg.solve(J.T @ J + P, J.T @ r + P @ (w - w0))
    np.testing.assert_allclose(N.prior_gauss_newton_step(w, w0, r, J, C, 0.02), ref, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("backend", BACKENDS)
def test_factor_spd_solves(backend):
    _need(backend)
    rng = np.random.default_rng(6)
    A = rng.normal(size=(12, 12))
    A = A @ A.T + 12 * np.eye(12)
    A[np.abs(A) < 1.0] = 0.0  # sparse-ish, still SPD (diagonally dominant)
    A = (A + A.T) / 2 + 40 * np.eye(12)
    f = N.factor_spd(__import__("scipy.sparse", fromlist=["csc_matrix"]).csc_matrix(A), backend)
    assert f.backend == backend
    b = rng.normal(size=(12, 3))
    np.testing.assert_allclose(f.solve(b), np.linalg.solve(A, b), atol=1e-9)


@pytest.mark.parametrize("backend", BACKENDS)
def test_edge_system_solves_eq2(backend):
    """The factored Eq. 2 matrix gives the dense least-squares solution of the energy."""
    _need(backend)
    faces = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    n = 6
    edges, B = N.edge_incidence(faces, n)
    L = N.edge_laplacian(faces, n)
    np.testing.assert_allclose(L.toarray(), (B.T @ B).toarray())
    rng = np.random.default_rng(4)
    w = np.array([1.0, 0.0, 1.0, 1.0, 0.0, 1.0]) * 1.1
    system = N.EdgeSystem.precompute(L, w, backend=backend)
    assert system.backend == backend
    target_edges = rng.normal(size=(len(edges), 3))
    c = rng.normal(size=(n, 3))
    rhs = B.T @ target_edges + w[:, None] * c
    x = system.solve(rhs)
    A = np.vstack([B.toarray(), np.diag(np.sqrt(w + system.eps))])
    b = np.vstack([target_edges, np.sqrt(w)[:, None] * c])
    ref = np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose(x, ref, atol=1e-6)


def test_nearest_correspondences_match_brute_force():
    rng = np.random.default_rng(7)
    P = rng.normal(size=(50, 3))
    Pn = rng.normal(size=(50, 3))
    Pn /= np.linalg.norm(Pn, axis=1, keepdims=True)
    T = rng.normal(size=(80, 3))
    Tn = rng.normal(size=(80, 3))
    Tn /= np.linalg.norm(Tn, axis=1, keepdims=True)
    j, d, ok = N.nearest_correspondences(P, Pn, cKDTree(T), Tn, max_dist=1.0, normal_reject_deg=60.0)
    for i in range(50):
        dist = np.linalg.norm(T - P[i], axis=1)
        assert j[i] == int(np.argmin(dist)) and np.isclose(d[i], dist.min())
        cos = float(Pn[i] @ Tn[j[i]])
        assert ok[i] == (cos >= np.cos(np.radians(60.0)) and dist.min() <= 1.0)


def test_trimmed_mean_ignores_the_largest():
    assert N.trimmed_mean(np.r_[np.ones(9), 1000.0], keep=0.9) == 1.0

"""The body-aware warping graph (service/model/nonrigid/warping.py; editing paper Sec. 5.1, Eqs. 5-7):
the factored, R-eliminated solve against a dense least-squares reference of the energy on tiny
graphs (both sparse back ends), exact reproduction of the identity, rigid motions and uniform
scaling, connectivity, node counts and the Poisson-disk property of the samples."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from service.model.nonrigid import warping as W

BACKENDS = ["cholmod", "superlu"]


def _need(backend):
    if backend == "cholmod":
        pytest.importorskip("sksparse.cholmod", reason="scikit-sparse (the `fast` extra) not installed")


def _body():
    s = trimesh.creation.icosphere(subdivisions=1, radius=0.3)
    V = np.asarray(s.vertices) * np.array([1.0, 1.6, 0.8])  # not a sphere: curvature differs
    return V, np.asarray(s.faces)


def _garment():
    s = trimesh.creation.icosphere(subdivisions=1, radius=0.36)
    V = np.asarray(s.vertices) * np.array([1.0, 1.5, 0.85])
    keep = V[:, 1] < 0.2  # an open garment: the lower part of a shell around the body
    F = np.asarray(s.faces)
    F = F[keep[F].all(axis=1)]
    used = np.unique(F)
    remap = np.full(len(V), -1)
    remap[used] = np.arange(len(used))
    return V[used], remap[F]


def _bend(V):
    """A smooth non-rigid deformation of the body."""
    x, y, z = V[:, 0], V[:, 1], V[:, 2]
    return np.stack([x * (1 + 0.2 * y) + 0.05 * np.sin(3 * y), y + 0.1 * x * x, z * (1 - 0.15 * y)], axis=1)


def dense_reference(graph: W.WarpGraph, body_new: np.ndarray, with_reg: bool = True):
    """argmin over (R_j, t_j) of Ec + wp Ep (+ Er), written out residual by residual (Eqs. 6-7),
    solved as one dense least-squares problem with 12 unknowns per node."""
    m, mb = graph.n_nodes, graph.n_body_nodes
    g = graph.nodes
    sub = graph.body_subset(body_new)
    targets = graph.body_targets(sub)
    F = graph.gradients(sub)
    rows, rhs = [], []

    def R(j):  # column offsets of R_j (row-major) and t_j
        return 12 * j

    for a, b in graph.edges:
        for j, k in ((a, b), (b, a)):  # Eq. 6: both directions
            d = g[k] - g[j]
            for r in range(3):
                row = np.zeros(12 * m)
                row[R(j) + 3 * r: R(j) + 3 * r + 3] = d
                row[R(j) + 9 + r] = 1.0
                row[R(k) + 9 + r] = -1.0
                rows.append(row)
                rhs.append(g[k, r] - g[j, r])  # R_j d + g_j + t_j - g_k - t_k = 0
    sw = np.sqrt(graph.params.wp)
    for j in range(mb):  # Eq. 7: g_j + t_j = v'_j
        for r in range(3):
            row = np.zeros(12 * m)
            row[R(j) + 9 + r] = sw
            rows.append(row)
            rhs.append(sw * (targets[j, r] - g[j, r]))
    if with_reg:
        sr = np.sqrt(graph.reg)
        for j in range(m):  # Er: R_j = F_j
            for r in range(3):
                for c in range(3):
                    row = np.zeros(12 * m)
                    row[R(j) + 3 * r + c] = sr
                    rows.append(row)
                    rhs.append(sr * F[j, r, c])
    x = np.linalg.lstsq(np.array(rows), np.array(rhs), rcond=None)[0].reshape(m, 12)
    Rm, t = x[:, :9].reshape(m, 3, 3), x[:, 9:]
    return Rm, t


def blend_reference(graph: W.WarpGraph, A: np.ndarray, Rm: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Sumner et al.'s blend of the node affines: v' = sum_j w_j (R_j (v - g_j) + g_j + t_j)."""
    out = np.zeros_like(A)
    for i, v in enumerate(A):
        for j, w in zip(graph.blend_idx[i], graph.blend_w[i]):
            out[i] += w * (Rm[j] @ (v - graph.nodes[j]) + graph.nodes[j] + t[j])
    return out


@pytest.mark.parametrize("backend", BACKENDS)
def test_solve_matches_dense_least_squares(backend):
    _need(backend)
    BV, BF = _body()
    AV, AF = _garment()
    graph = W.WarpGraph.precompute(BV, BF, AV, AF, W.WarpParams(max_nodes=40, seed=3), backend=backend)
    assert graph.factor.backend == backend
    new = _bend(BV)
    Rm, t = dense_reference(graph, new)
    R_fast, t_fast = graph.affines(new)
    np.testing.assert_allclose(R_fast, Rm, atol=1e-8)
    np.testing.assert_allclose(t_fast, t, atol=1e-10)
    np.testing.assert_allclose(graph.warp(new), blend_reference(graph, AV, Rm, t), atol=1e-10)
    # a batch of bodies is the same as one at a time
    batch = graph.warp(np.stack([new, BV, 1.1 * new]))
    np.testing.assert_allclose(batch[0], graph.warp(new), atol=1e-12)
    np.testing.assert_allclose(batch[2], graph.warp(1.1 * new), atol=1e-12)


@pytest.mark.parametrize("backend", BACKENDS)
def test_paper_energy_without_regulariser(backend):
    """Where every node's edges span 3D (a point cloud A filling a shell), Ec + wp Ep alone is
    positive definite: with gradient_weight = 0 the solve is exactly the paper's Eq. 5."""
    _need(backend)
    BV, BF = _body()
    rng = np.random.default_rng(0)
    d = rng.normal(size=(60, 3))
    AV = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(0.2, 0.5, size=(60, 1))
    graph = W.WarpGraph.precompute(BV, BF, AV, None, W.WarpParams(max_nodes=70, gradient_weight=0.0, seed=1,
                                                                  min_normal_cos=None), backend=backend)
    new = _bend(BV)
    Rm, t = dense_reference(graph, new, with_reg=False)
    R_fast, t_fast = graph.affines(new)
    np.testing.assert_allclose(R_fast, Rm, atol=1e-7)
    np.testing.assert_allclose(graph.warp(new), blend_reference(graph, AV, Rm, t), atol=1e-9)


def test_identity_rigid_motion_and_scaling_are_reproduced():
    BV, BF = _body()
    AV, AF = _garment()
    graph = W.WarpGraph.precompute(BV, BF, AV, AF, W.WarpParams(max_nodes=80))
    np.testing.assert_allclose(graph.warp(BV), AV, atol=1e-12)
    Q = Rotation.from_rotvec([0.4, -1.3, 0.7]).as_matrix()
    c = np.array([0.3, -0.1, 2.0])
    np.testing.assert_allclose(graph.warp(BV @ Q.T + c), AV @ Q.T + c, atol=1e-10)
    F = graph.gradients(graph.body_subset(BV @ Q.T + c))  # Er's targets: the motion itself
    np.testing.assert_allclose(F, np.broadcast_to(Q, F.shape), atol=1e-12)
    np.testing.assert_allclose(graph.warp(1.7 * BV + c), 1.7 * AV + c, atol=1e-10)
    # and a non-rigid deformation moves the garment (the test can fail)
    assert np.abs(graph.warp(_bend(BV)) - AV).max() > 0.01


def test_graph_is_connected_sized_and_deterministic():
    BV, BF = _body()
    AV, AF = _garment()
    far = AV + np.array([3.0, 0.0, 0.0])  # a garment nowhere near the body: bridged anyway
    p = W.WarpParams(max_nodes=50, seed=7)
    graph = W.WarpGraph.precompute(BV, BF, far, AF, p)
    m = graph.n_nodes
    assert m == min(50, len(BV) + len(AV))
    assert graph.n_body_nodes == round(50 * len(BV) / (len(BV) + len(AV)))
    A = np.zeros((m, m))
    A[graph.edges[:, 0], graph.edges[:, 1]] = 1
    assert connected_components(A, directed=False)[0] == 1
    deg = np.bincount(graph.edges.ravel(), minlength=m)
    assert deg.min() >= 1
    again = W.WarpGraph.precompute(BV, BF, far, AF, p)
    np.testing.assert_array_equal(again.nodes, graph.nodes)
    np.testing.assert_array_equal(again.edges, graph.edges)
    # body nodes lie on the body and are evaluated through (face, barycentric)
    np.testing.assert_allclose(graph.body_targets(graph.body_subset(BV)), graph.nodes[:graph.n_body_nodes],
                               atol=1e-12)
    assert np.all(np.isfinite(graph.warp(_bend(BV))))


def test_knn_edges_join_six_nearest_and_skip_facing_surfaces():
    rng = np.random.default_rng(2)
    P = rng.normal(size=(40, 3))
    N = np.tile([0.0, 1.0, 0.0], (40, 1))
    e = W.knn_edges(P, N, 6, None)
    nn = cKDTree(P).query(P, k=7)[1][:, 1:]
    expect = {tuple(sorted((i, int(j)))) for i in range(40) for j in nn[i]}
    assert {tuple(x) for x in e.tolist()} == expect
    N[20:] *= -1  # half the points face the other way: no edge between the halves
    e = W.knn_edges(P, N, 6, 0.0)
    assert np.all((e[:, 0] < 20) == (e[:, 1] < 20))


def test_farthest_point_sampling_is_a_maximal_poisson_disk_set():
    rng = np.random.default_rng(4)
    P = rng.uniform(size=(3000, 3)) * np.array([1.0, 1.0, 0.01])
    idx = W.farthest_point_sampling(P, 200, np.random.default_rng(0))
    assert len(np.unique(idx)) == 200
    S = P[idx]
    dmin = cKDTree(S).query(S, k=2)[0][:, 1].min()
    cover = cKDTree(S).query(P)[0].max()
    assert dmin >= cover - 1e-12  # every pair at least r apart, every point within r


def test_blend_weights_sum_to_one_and_vanish_at_dmax():
    rng = np.random.default_rng(5)
    nodes = rng.normal(size=(30, 3))
    v = rng.normal(size=(10, 3))
    n = np.tile([0.0, 0.0, 1.0], (30, 1))
    idx, w = W.blend_weights(v, n[:10], nodes, n, 4, None)
    np.testing.assert_allclose(w.sum(axis=1), 1.0)
    d, nn = cKDTree(nodes).query(v, k=5)
    np.testing.assert_array_equal(idx, nn[:, :4])
    raw = (1 - d[:, :4] / d[:, 4:5]) ** 2
    np.testing.assert_allclose(w, raw / raw.sum(axis=1, keepdims=True))

"""The outfit layering's fast path (issue 11, outfit.glb latency) gives the reference's results:
closest points on a mesh with candidate faces pruned by a distance bound
(``geometry.PRUNE_CANDIDATES``) and in compiled code (``geometry.COMPILED``: the numba kernels
of ``service.model.geometry.kernels``, also the winding numbers), and ``layering.layer_outfit`` with its per-outer and
per-topology reuse and near-only rim checks against the plain per-pair passes. Tolerance:
1e-9 m on vertices, 1e-6 on skin weights (measured: bitwise equal)."""
from __future__ import annotations

import numpy as np
import pytest
import trimesh

from service.model.geometry import mesh as Gm
from service.model.garments import layering as LY
from service.model.garments.skin_weights import uniform_laplacian
from tests.test_skinning import cylinder

POSITION_TOLERANCE = 1e-9  # metres
WEIGHT_TOLERANCE = 1e-6


def test_pruned_closest_points_equal_the_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(3)
    m = trimesh.creation.icosphere(subdivisions=3)
    V = np.asarray(m.vertices) * 0.3 + rng.normal(0, 0.004, m.vertices.shape)
    V = np.vstack([V, [[0.31, 0.0, 0.0]]])  # an isolated vertex (no face): nearest to some points
    F = np.asarray(m.faces)
    P = np.vstack([V[rng.integers(0, len(V) - 1, 800)] * (1 + rng.normal(0, 0.05, (800, 1))),
                   V[:200],  # on vertices: several faces tie
                   rng.normal(0, 0.5, (300, 3)),  # far away
                   [[0.315, 0.0, 0.0]]])
    compiled = Gm.closest_points_on_mesh(P, V, F)
    monkeypatch.setattr(Gm, "COMPILED", False)
    fast = Gm.closest_points_on_mesh(P, V, F)
    monkeypatch.setattr(Gm, "PRUNE_CANDIDATES", False)
    ref = Gm.closest_points_on_mesh(P, V, F)
    ties = 0
    for i in range(len(P)):  # the reference's own tie rule, checked: of equally near faces, the first around
        t = V[F]  # the k nearest vertices wins (a point on a vertex ties all the faces around it)
        d = Gm.squared_norms(Gm.closest_point_on_triangles(P[i], t[:, 0], t[:, 1], t[:, 2]) - P[i])
        ties += int((d == d[ref[0][i]]).sum() > 1)
    assert ties >= 200
    for a, b, c in zip(compiled, fast, ref):
        assert np.array_equal(a, c) and np.array_equal(b, c)
    empty = Gm.closest_points_on_mesh(np.zeros((0, 3)), V, F)  # no points: empty answers, both paths
    assert [x.shape for x in empty] == [(0,), (0, 3), (0, 3)]


@pytest.mark.skipif(not Gm.kernels.AVAILABLE, reason="the compiled kernels are off (numba missing, or TRYON_NO_KERNELS)")
def test_compiled_closest_points_equal_numpy_on_the_body(monkeypatch: pytest.MonkeyPatch) -> None:
    """On the body mesh (25k faces), points near and on the skin and far from it: the compiled
    kernel picks the same faces, ties included, and the same closest points, bit for bit."""
    from service.model.body.model import load_body_model

    model = load_body_model()
    nb = model.n_body_vertices
    X = model.vertices(np.zeros(model.n_components))[:nb].astype(np.float64)
    rng = np.random.default_rng(5)
    P = np.vstack([X[rng.integers(0, nb, 3000)] + rng.normal(0, 0.01, (3000, 3)), X[::40],
                   rng.normal(0, 1.0, (200, 3))])
    compiled = Gm.closest_points_on_mesh(P, X, model.body_faces)
    monkeypatch.setattr(Gm, "COMPILED", False)
    ref = Gm.closest_points_on_mesh(P, X, model.body_faces)
    for a, b in zip(compiled, ref):
        assert np.array_equal(a, b)


@pytest.mark.skipif(not Gm.kernels.AVAILABLE, reason="the compiled kernels are off (numba missing, or TRYON_NO_KERNELS)")
def test_compiled_winding_numbers_equal_numpy(monkeypatch: pytest.MonkeyPatch) -> None:
    m = trimesh.creation.icosphere(subdivisions=3)
    rng = np.random.default_rng(4)
    far = rng.normal(0, 0.6, (400, 3))
    far = far[np.abs(np.linalg.norm(far, axis=1) - 1) > 0.05][:300]  # clear of the faceted surface
    P = np.vstack([far, m.vertices[:50] * 0.999, m.vertices[:50] * 1.001])
    compiled = Gm.winding_numbers(P, m.vertices, m.faces)
    monkeypatch.setattr(Gm, "COMPILED", False)
    ref = Gm.winding_numbers(P, m.vertices, m.faces)
    assert np.abs(compiled - ref).max() <= 1e-12
    inside = np.linalg.norm(P, axis=1) < 1
    assert np.array_equal(compiled > 0.5, ref > 0.5) and (compiled > 0.5).sum() == inside.sum() > 100


def reference_layer_outfit(garments, body, body_normals, skins, n_joints):
    """``layer_outfit`` as before the fast path: every pair from scratch."""
    from scipy.spatial import cKDTree

    out = [np.asarray(v, np.float64) for v, _ in garments]
    sk = list(skins)
    tree = cKDTree(body)
    for i in range(len(garments) - 2, -1, -1):
        for j in range(len(garments) - 1, i, -1):
            lap = uniform_laplacian(garments[i][1], len(out[i]))
            out[i], covered, face, bary = LY._push_inside(out[i], garments[i][1], out[j], garments[j][1], body,
                                                          body_normals, LY.GAP, LY.PASSES, tree, lap)
            sk[i] = LY.covered_skin(garments[i][1], sk[i], garments[j][1], sk[j], covered, face, bary, n_joints, lap)
    return out, sk


def test_layer_outfit_fast_path_equals_the_reference(monkeypatch: pytest.MonkeyPatch) -> None:
    """Three layers on a cylinder "body": a bulging base layer, a shirt with a waistband bulge
    and a short outer layer with rims (hem and top) over both."""
    body, _ = cylinder(0.10, -0.5, 0.5, 60, 40)
    bn = body * np.array([1, 0, 1])
    bn /= np.linalg.norm(bn, axis=1, keepdims=True)
    base, BF = cylinder(lambda y: 0.105 + 0.03 * np.exp(-((y - 0.1) / 0.04) ** 2), -0.3, 0.3, 50, 61)
    shirt, SF = cylinder(lambda y: 0.12 + 0.03 * np.exp(-((y - 0.05) / 0.05) ** 2), -0.4, 0.2, 40, 61)
    outer, OF = cylinder(0.13, 0.0, 0.4)
    rng = np.random.default_rng(0)
    n_joints = 6

    def skin(n):
        j = np.stack([rng.permutation(n_joints)[:4] for _ in range(n)]).astype(np.int32)
        w = rng.random((n, 4)).astype(np.float32)
        return j, w / w.sum(axis=1, keepdims=True)

    layers = [(base, BF), (shirt, SF), (outer, OF)]
    skins = [skin(len(v)) for v, _ in layers]
    fast_v, fast_s = LY.layer_outfit(layers, body, bn, skins=skins, n_joints=n_joints)
    monkeypatch.setattr(Gm, "PRUNE_CANDIDATES", False)
    monkeypatch.setattr(LY, "RIM_NEAR_ONLY", False)
    ref_v, ref_s = reference_layer_outfit(layers, body, bn, skins, n_joints)
    assert np.abs(ref_v[0] - base).max() > 1e-3 and np.abs(ref_v[1] - shirt).max() > 1e-3  # both pushed
    for a, b in zip(fast_v, ref_v):
        assert np.abs(a - b).max() <= POSITION_TOLERANCE
    for (ja, wa), (jb, wb) in zip(fast_s, ref_s):
        assert np.array_equal(ja, jb)
        assert np.abs(wa - wb).max() <= WEIGHT_TOLERANCE


def test_topology_is_cached_per_faces() -> None:
    V, F = cylinder(0.1, 0.0, 0.4)
    a = LY.topology(F, len(V))
    b = LY.topology(F.copy(), len(V))  # the same faces in another array: one entry
    assert a is b
    assert (a[0] != uniform_laplacian(F, len(V))).nnz == 0
    assert np.array_equal(a[1], LY.boundary_vertices(F, len(V)))
    assert np.array_equal(a[2], Gm.vertex_faces(F, len(V)))

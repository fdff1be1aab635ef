"""Parametric body fitting (service/model/fitting.py): Jacobians against finite differences,
the prefactored Eq. 2 solve against a dense reference on both sparse back ends, and whole fits
of synthetic scans with a known body (service/model/synthetic_scans.py)."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from service.model import fitting as F
from service.model import synthetic_scans as SS
from service.model.skinning import axis_angle_to_matrix


@pytest.fixture(scope="module")
def rig(model):
    return F._rig(model)


def _random_state(model, rig, seed=1):
    rng = np.random.default_rng(seed)
    return F._State(rng.normal(size=len(rig.U)) * np.sqrt(model.variances) * 0.5,
                    axis_angle_to_matrix(rng.normal(size=(17, 3)) * 0.3), rng.normal(size=3) * 0.1)


def test_pose_model_matches_skinning(model, rig):
    s = _random_state(model, rig)
    sub = F._subset(rig, np.arange(0, model.n_body_vertices, 53))
    ref = F._full_posed(model, s)[: model.n_body_vertices][sub.idx]
    assert np.abs(F._pose_model(rig, s, sub).v - ref).max() < 1e-6


def test_jacobians_match_finite_differences(model, rig):
    s = _random_state(model, rig, 2)
    sub = F._subset(rig, np.arange(0, model.n_body_vertices, 97))
    p = F._pose_model(rig, s, sub)
    J = F._pose_jacobian(rig, p, F.ALL_BONES)
    eps = 1e-6
    for k in range(J.shape[2]):  # translation and every bone's rotation
        d = np.zeros(J.shape[2])
        d[k] = eps
        s2 = s.copy()
        F._apply_pose(rig, s2, p, F.ALL_BONES, d)
        fd = (F._pose_model(rig, s2, sub).v - p.v) / eps
        assert np.abs(fd - J[:, :, k]).max() < 1e-4 * max(1.0, np.abs(J[:, :, k]).max()), k
    comps = np.array([0, 3, 17, 75])
    Jb = F._shape_jacobian(rig, p, comps)
    for c, k in enumerate(comps):
        s2 = s.copy()
        s2.beta[k] += eps
        fd = (F._pose_model(rig, s2, sub).v - p.v) / eps
        assert np.abs(fd - Jb[:, :, c]).max() < 1e-6


def test_normal_equations_match_explicit_rows(rig):
    rng = np.random.default_rng(3)
    Jac = rng.normal(size=(40, 3, 7))
    vi = rng.integers(0, 40, 90)
    nn = rng.normal(size=(90, 3))
    w, r = rng.uniform(0.1, 1, 90), rng.normal(size=90)
    H, g = F._normal_equations(Jac, vi, nn, w, r)
    rows = np.stack([nn[k] @ Jac[vi[k]] for k in range(90)])
    np.testing.assert_allclose(H, rows.T @ np.diag(w) @ rows, atol=1e-10)
    np.testing.assert_allclose(g, rows.T @ (w * r), atol=1e-10)


@pytest.mark.parametrize("backend", ["cholmod", "superlu"])
def test_edge_system_solves_eq2(rig, backend):
    """The factored Eq. 2 matrix gives the dense least-squares solution of the energy."""
    if backend == "cholmod":
        pytest.importorskip("sksparse.cholmod", reason="scikit-sparse (the `fast` extra) not installed")
    faces = np.array([[0, 1, 2], [1, 3, 2], [2, 3, 4], [3, 5, 4]])
    n = 6
    edges = F.mesh_edges(faces)
    B = sp.csr_matrix((np.r_[np.ones(len(edges)), -np.ones(len(edges))],
                       (np.r_[np.arange(len(edges)), np.arange(len(edges))], np.r_[edges[:, 0], edges[:, 1]])),
                      shape=(len(edges), n))
    L = (B.T @ B).tocsc()
    rng = np.random.default_rng(4)
    w = np.array([1.0, 0.0, 1.0, 1.0, 0.0, 1.0]) * 1.1
    system = F.EdgeSystem(L, w, backend=backend)
    assert system.backend == backend
    target_edges = rng.normal(size=(len(edges), 3))
    c = rng.normal(size=(n, 3))
    rhs = B.T @ target_edges + w[:, None] * c + system.eps * 0
    x = system.solve(rhs)
    A = np.vstack([B.toarray(), np.diag(np.sqrt(w + system.eps))])
    b = np.vstack([target_edges, np.sqrt(w)[:, None] * c])
    ref = np.linalg.lstsq(A, b, rcond=None)[0]
    np.testing.assert_allclose(x, ref, atol=1e-6)


def test_unit_and_up_detection():
    pts = np.random.default_rng(0).normal(size=(500, 3)) * [0.2, 0.5, 0.1]
    pts[:, 1] = np.linspace(0, 1.75, 500)
    assert F.detect_scan_unit(pts)[0] == "m"
    assert F.detect_scan_unit(pts * 100)[0] == "cm"
    assert F.detect_scan_unit(pts * 1000)[0] == "mm"
    with pytest.raises(F.FitError, match="units"):
        F.detect_scan_unit(pts * 10)
    labels = [label for label, _ in F._up_rotations(pts[:, [0, 2, 1]])]
    assert labels == ["+z", "-z"]
    for label, R in F._up_rotations(pts[:, [0, 2, 1]]):
        assert np.allclose(R @ np.eye(3)[2] * (1 if label == "+z" else -1), [0, 1, 0])


def _evaluate(model, scan, fit):
    """Mean distance (mm) between the fitted and the true body, vertex to vertex."""
    C = scan.to_model @ np.linalg.inv(fit.to_model)
    V = fit.posed_vertices[: model.n_body_vertices] @ C[:3, :3].T + C[:3, 3]
    return 1000 * float(np.linalg.norm(V - scan.true_posed[: model.n_body_vertices], axis=1).mean())


def _person(model):
    from service.bench_fitting import heldout_people

    return heldout_people(model, 1)[0]


def test_fit_unclothed_scan(model):
    """A posed, noisy, re-meshed body in cm with Z up: the fit recovers units, the up axis,
    the body (vertex-to-vertex) and the measurements."""
    person = _person(model)
    scan = SS.make_scan(model, np.random.default_rng(11), person["weights"], person["gender"], clothed=False,
                        point_cloud=False, n_points=8000, max_pose_deg=20, unit="cm", up="+z")
    progress = []
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                     progress=lambda f, m: progress.append(f))
    assert (fit.unit, fit.up) == ("cm", "+z")
    assert progress[-1] == 1.0 and progress == sorted(progress)
    err = _evaluate(model, scan, fit)
    assert err < 8.0, err
    height = model.measure(model.vertices(fit.weights), person["gender"])["height_cm"]
    assert abs(height - scan.measurements["height_cm"]) < 4.0
    assert fit.outer_iterations >= 1 and fit.inner_iterations >= 1
    assert fit.residual_mm < 10


def test_fit_clothed_point_cloud_stays_inside_clothes(model):
    """A clothed point cloud without normals (estimated) in mm: the body is recovered and sits
    inside the clothes, not inflated to them."""
    from service.model.geometry import winding_numbers

    person = _person(model)
    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    scan = SS.make_scan(model, np.random.default_rng(12), person["weights"], person["gender"], clothed=True,
                        point_cloud=True, n_points=8000, max_pose_deg=20, unit="mm", up="+y")
    fit = F.fit_body(model, scan.points, None, None, clothed=True)
    assert fit.unit == "mm"
    err = _evaluate(model, scan, fit)
    assert err < 20.0, err
    body = fit.posed_vertices[: model.n_body_vertices]
    P = scan.points @ fit.to_model[:3, :3].T + fit.to_model[:3, 3]
    covered = ~scan.point_is_body
    inside = winding_numbers(P[covered][::10], body, model.body_faces) > 0.5
    assert inside.mean() < 0.2  # cloth points inside the fitted body: the body pokes through


def test_fit_rejects_non_person(model):
    with pytest.raises(F.FitError):
        F.fit_body(model, np.random.default_rng(0).normal(size=(50, 3)))
    with pytest.raises(F.FitError, match="units"):
        F.fit_body(model, np.random.default_rng(0).uniform(0, 5, size=(2000, 3)))

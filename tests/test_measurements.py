"""Measurements against a slow reference (trimesh plane slicing), Jacobians against finite
differences, and the invariances a tape measure has."""
from __future__ import annotations

import numpy as np
import pytest

from service.model.body import measurements as M





def avatars(model, n=6, seed=0):
    rng = np.random.default_rng(seed)
    pop = model.population["weights"]
    picks = rng.choice(len(pop), size=n, replace=False)
    return [model.vertices(np.zeros(model.n_components))] + [model.vertices(pop[i]) for i in picks]


def test_fast_measurements_match_plane_slicing_reference(model):
    for X in avatars(model):
        fast = M.measure(model.measurement_spec, X, "female")
        ref = M.reference_measure(model.measurement_spec, X, "female")
        for i, name in enumerate(M.RAW_NAMES[:11]):
            tol = 1e-4 if name != "weight_kg" else 1e-6
            assert abs(fast[i] - ref[i]) <= tol, (name, fast[i], ref[i])


def test_girths_are_plausible_for_the_mean_avatar(model):
    a = model.measure(model.vertices(np.zeros(model.n_components)), "male")
    assert 150 < a["height_cm"] < 190
    assert 50 < a["weight_kg"] < 100
    assert a["hip_cm"] > a["thigh_cm"] > a["calf_cm"] > 25
    assert a["height_cm"] > a["waist_height_cm"] > a["inseam_cm"]


def test_jacobian_matches_finite_differences(model):
    spec = model.measurement_spec
    rng = np.random.default_rng(3)
    for X in avatars(model, n=3, seed=5):
        X = X.astype(np.float64)
        m, J = M.measure(spec, X, "male", jacobian=True)
        d = rng.normal(size=X.shape) * 1e-6
        d[spec.soles] = 0  # the floor is a min over a flat sole: only a subgradient there
        fd = M.measure(spec, X + d, "male") - m
        lin = J @ d.reshape(-1)
        for i, name in enumerate(M.RAW_NAMES[:11]):
            if name == "calf_cm":
                continue  # max over levels: piecewise
            assert abs(fd[i] - lin[i]) <= 0.05 * abs(fd[i]) + 2e-8, (name, fd[i], lin[i])


def test_tape_measure_invariances(model):
    spec = model.measurement_spec
    X = model.vertices(model.population["weights"][7]).astype(np.float64)
    base = M.measure(spec, X, "male")
    moved = M.measure(spec, X + np.array([0.3, 0.2, -0.5]), "male")
    np.testing.assert_allclose(moved, base, atol=1e-9)
    s = 1.05
    scaled = M.measure(spec, X * s, "male")
    wi = M.RAW_NAMES.index("weight_kg")
    for i in range(len(M.RAW_NAMES)):
        expect = base[i] * (s**3 if i == wi else s)
        assert abs(scaled[i] - expect) <= 1e-6 * max(1, abs(expect)), M.RAW_NAMES[i]


def test_hull_perimeter_of_known_shapes():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]], float)  # interior point ignored
    per, hv, g = M.hull_perimeter(sq)
    assert per == pytest.approx(4.0)
    assert len(hv) == 4
    circle = np.stack([np.cos(np.linspace(0, 2 * np.pi, 2000, endpoint=False)),
                       np.sin(np.linspace(0, 2 * np.pi, 2000, endpoint=False))], 1) * 0.5
    assert M.hull_perimeter(circle)[0] == pytest.approx(np.pi, rel=1e-5)
    # a tape bridges concavities: a C shape measures like its hull
    c_shape = np.array([[0, 0], [2, 0], [2, 0.2], [0.2, 0.2], [0.2, 1.8], [2, 1.8], [2, 2], [0, 2]], float)
    assert M.hull_perimeter(c_shape)[0] == pytest.approx(8.0)


def test_volume_of_a_unit_cube_and_its_gradient():
    import trimesh

    box = trimesh.creation.box(extents=(1, 2, 3))
    v, g = M.volume(np.asarray(box.vertices, float), np.asarray(box.faces), grad=True)
    assert v == pytest.approx(6.0)
    # moving every vertex outward along x by e grows the volume by (area of x faces) * e
    d = np.zeros_like(box.vertices)
    d[:, 0] = np.sign(box.vertices[:, 0]) * 1e-6
    assert (g * d).sum() == pytest.approx(2 * 6 * 1e-6, rel=1e-6)


# -- the pieces the measurements -> avatar fast path is built from --------------------------
def test_restricted_spec_measures_the_same_on_its_vertices(model):
    spec = model.measurement_spec
    small, ids = spec.restrict()
    assert len(ids) < 0.3 * model.n_body_vertices
    K = model.n_components
    basis = model.components_T  # (3V, K)
    basis_small = np.ascontiguousarray(model.components[:, ids].reshape(K, -1).T, dtype=np.float64)
    wi = M.RAW_NAMES.index("weight_kg")
    for X in avatars(model, n=3, seed=1):
        full, Jw = M.measure(spec, X, "male", jacobian=True, basis=basis)
        part, Jw_small = M.measure(small, X[ids], "male", jacobian=True, basis=basis_small)
        assert part[wi] == 0 and not Jw_small[wi].any()  # weight needs the whole surface
        keep = np.arange(len(M.RAW_NAMES)) != wi
        np.testing.assert_allclose(part[keep], full[keep], rtol=0, atol=1e-12)
        np.testing.assert_allclose(Jw_small[keep], Jw[keep], rtol=0, atol=1e-9 * np.abs(Jw).max())


def test_jacobian_in_a_basis_is_the_vertex_jacobian_times_the_basis(model):
    spec = model.measurement_spec
    X = model.vertices(model.population["weights"][11])
    _, JX = M.measure(spec, X, "female", jacobian=True)
    _, Jw = M.measure(spec, X, "female", jacobian=True, basis=model.components_T)
    np.testing.assert_allclose(Jw, np.asarray(JX @ model.components_T), rtol=1e-10, atol=1e-12)


def test_only_the_named_measurements_are_taken(model):
    spec = model.measurement_spec
    X = model.vertices(model.population["weights"][4])
    full, J = M.measure(spec, X, "male", jacobian=True)
    for names in (["height_cm", "weight_kg"], ["calf_cm"], ["thigh_cm", "hip_breadth", "arm_length_cm"]):
        part, Jp = M.measure(spec, X, "male", jacobian=True, names=names)
        rows = [M.RAW_NAMES.index(n) for n in names]
        np.testing.assert_allclose(part[rows], full[rows], rtol=0, atol=1e-12)
        np.testing.assert_allclose(Jp[rows].toarray(), J[rows].toarray(), rtol=0, atol=1e-12)
        others = np.setdiff1d(np.arange(len(M.RAW_NAMES)), rows)
        assert not part[others].any()
    no_extras = M.measure(spec, X, "male", extras=False)
    n = len(M.ATTRIBUTES) - 1
    np.testing.assert_allclose(no_extras[:n], full[:n], rtol=1e-13, atol=0)
    assert not no_extras[n:].any()


def test_horizontal_plane_basis_is_the_generic_one():
    generic = M._plane_basis(M.Y.copy())  # a copy takes the generic path
    for a, b in zip(generic, M._plane_basis(M.Y)):
        np.testing.assert_array_equal(a, b)


def test_calf_level_ranking_matches_brute_force(model):
    spec = model.measurement_spec
    for X in avatars(model, n=3, seed=2):
        X = X.astype(np.float64)
        J = np.asarray(spec.joint_regressor @ X)
        knee, ankle = J[spec.joint_ids["knee"]], J[spec.joint_ids["ankle"]]
        levels = knee[1] + M.CALF_FRACTIONS * (ankle[1] - knee[1])
        est = []
        for lv in levels:  # support function of each section's points over the directions
            pts = M.plane_section(X, spec.calf_edges, M.Y, float(lv))[0]
            est.append((pts[:, [0, 2]] @ M._DIRS.T).max(axis=0).sum())
        np.testing.assert_array_equal(M._rank_levels(X, spec.calf_edges, levels), np.argsort(-np.array(est)))


def test_volume_polynomial_is_the_volume_of_the_shape_space():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=1)
    mean, faces = np.asarray(sphere.vertices, float), np.asarray(sphere.faces)
    rng = np.random.default_rng(4)
    comps = rng.normal(size=(5,) + mean.shape) * 0.2  # (K, V, 3)
    exact = M.VolumePolynomial.fit(mean, comps, faces, n_cubic=5)
    truncated = M.VolumePolynomial.fit(mean, comps, faces, n_cubic=2)
    for _ in range(5):
        w = rng.normal(size=5)
        X = mean + np.einsum("k,kvc->vc", w, comps)
        vol, grad = exact(w)
        assert vol == pytest.approx(M.volume(X, faces), rel=1e-12, abs=1e-12)
        _, gv = M.volume(X, faces, grad=True)
        np.testing.assert_allclose(grad, np.einsum("vc,kvc->k", gv, comps), rtol=1e-10, atol=1e-12)
        w[2:] = 0  # with only the first two components, dropping the others' cubes changes nothing
        X = mean + np.einsum("k,kvc->vc", w, comps)
        assert truncated(w)[0] == pytest.approx(M.volume(X, faces), rel=1e-12, abs=1e-12)


def test_volume_polynomial_of_the_body_model_is_within_grams(model):
    nb = model.n_body_vertices
    poly = M.VolumePolynomial.fit(model.mean[:nb], model.components[:, :nb], model.body_faces, n_cubic=20)
    for w in model.population["weights"][::500]:  # ANSUR subjects and heavy civilians
        vol = M.volume(model.vertices(w).astype(np.float64), model.body_faces)
        assert abs(poly(w)[0] - vol) * M.DENSITY["female"] <= 0.06  # kg

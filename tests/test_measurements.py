"""Measurements against a slow reference (trimesh plane slicing), Jacobians against finite
differences, and the invariances a tape measure has."""
from __future__ import annotations

import numpy as np
import pytest

from service.model import measurements as M





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

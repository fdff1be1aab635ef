"""The compiled body model artifact: topology, frame, PCA round trips, rig data."""
from __future__ import annotations

import numpy as np

from service.model.body.model import BONES, DEFAULT_MODEL_PATH




def test_artifact_is_compact_and_loads_with_numpy_only(model):
    assert DEFAULT_MODEL_PATH.stat().st_size <= 25 * 1024 * 1024
    assert model.mean.shape == (19158, 3)
    assert model.n_body_vertices == 13380
    assert model.components.shape == (model.n_components, 19158, 3)
    assert model.variances.shape == (model.n_components,)
    assert np.all(np.diff(model.variances) <= 0)  # sorted


def test_body_surface_is_watertight_and_outward(model):
    f = model.body_faces
    assert f.max() < model.n_body_vertices
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    assert np.all(counts == 2), "every edge is shared by exactly two triangles"
    from service.model.body.measurements import volume

    assert volume(model.mean.astype(np.float64), f) > 0.03  # outward normals, ~ 70 L


def test_frame_metres_y_up_facing_plus_z_feet_on_floor(model):
    body = model.body_vertices(model.mean)
    assert abs(body[:, 1].min()) < 0.01  # feet on y = 0
    assert 1.5 < body[:, 1].max() < 1.95  # an adult's height in metres
    spec = model.measurement_spec
    nipples = model.mean[spec.nipples]
    assert np.all(nipples[:, 2] > body[:, 2].mean())  # chest faces +Z
    assert model.mean[spec.acromion[0], 0] > 0 > model.mean[spec.acromion[1], 0]  # left is +X


def test_pca_round_trip(model):
    U = model.components.reshape(model.n_components, -1).astype(np.float64)
    np.testing.assert_allclose(U @ U.T, np.eye(model.n_components), atol=1e-4)
    rng = np.random.default_rng(1)
    w = rng.normal(size=(5, model.n_components)) * np.sqrt(model.variances)
    X = model.vertices(w)
    np.testing.assert_allclose(model.project(X), w, atol=1e-3 * np.sqrt(model.variances[0]))
    # population weights are centred, so the mean avatar is w = 0
    assert np.abs(model.population["weights"].mean(0)).max() < 1e-2 * np.sqrt(model.variances[0])


def test_rig_data(model):
    assert len(BONES) == 17
    np.testing.assert_allclose(model.lbs_weights.sum(1), 1.0, atol=1e-5)
    assert model.lbs_indices.max() < 17
    jr = model.joint_regressor
    np.testing.assert_allclose(np.asarray(jr.sum(1)).ravel(), 1.0, atol=1e-4)
    J = model.joints(model.mean)
    names = {n: i for i, n in enumerate(BONES)}
    assert J[names["head"], 1] > J[names["neck"], 1] > J[names["chest"], 1] > J[names["pelvis"], 1]
    assert J[names["pelvis"], 1] > J[names["shin_l"], 1] > J[names["foot_l"], 1]
    # joints follow the shape: stretching the avatar vertically stretches the skeleton
    X = model.mean.astype(np.float64) * np.array([1.0, 1.1, 1.0])
    np.testing.assert_allclose(model.joints(X)[:, 1], J[:, 1] * 1.1, atol=1e-4)
    # parents precede children
    assert all(p < j for j, p in enumerate(model.bone_parents))


def test_population_reaches_heavy_civilians(model):
    a = model.population["attributes"]
    bmi = a[:, 2] / (a[:, 1] / 100) ** 2
    assert bmi.max() > 40
    ranges = {s.name: (s.min, s.max) for s in model.attributes}
    assert ranges["height_cm"][0] < 150 and ranges["height_cm"][1] > 195
    assert ranges["weight_kg"][1] > 130

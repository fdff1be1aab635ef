"""Editing a fitted clothed avatar (service/model/nonrigid/editing.py, issue 13): no edit is no change,
measurement edits reach their targets and hold the others, pose edits go through the graph and
carry a clothing layer with the body, dual-quaternion skinning against closed forms, and the
editor's partial forward pass against the body model's."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from service.model.nonrigid import editing as E
from service.model.body import lbs
from service.model.body.model import BONES
from service.model.geometry.mesh import vertex_normals
from service.model.body.shape import MeasurementError

OFFSET = 0.006  # a skin-tight suit 6 mm off the skin


def _suit(model, X):
    nb = model.n_body_vertices
    n = vertex_normals(X[:nb], model.body_faces).astype(np.float64)
    return X[:nb] + OFFSET * n


@pytest.fixture(scope="module")
def editor(model):
    rng = np.random.default_rng(3)
    w = rng.normal(size=model.n_components) * np.sqrt(model.variances) * 0.5
    pose = np.zeros((len(BONES), 3))
    pose[BONES.index("upper_arm_l")] = [0.0, 0.0, -0.4]
    pose[BONES.index("thigh_r")] = [0.3, 0.0, 0.0]
    t = np.array([0.1, 0.0, -0.2])
    posed = model.forward(w, pose, t).vertices
    A = _suit(model, posed)
    # M* posed by the body model's own LBS: the suit must then follow model.forward exactly
    ed = E.ClothedAvatarEditor(model, w, pose, t, A, model.body_faces, "female", E.EditParams(skinning="lbs"))
    return ed, A


def test_no_edit_is_no_change(model, editor):
    ed, A = editor
    # (to float32 rounding: the body model's shape is float32, the editor's subset float64)
    np.testing.assert_allclose(ed.edit(), A, atol=1e-6)
    np.testing.assert_allclose(ed.edit(measurements=dict(ed.measurements)), A, atol=1e-6)
    # the editor's forward pass on the graph's vertices is the body model's
    full = model.forward(ed.weights, ed.pose, ed.translation).vertices
    np.testing.assert_allclose(ed.body_subset(ed.weights, ed.pose), full[ed.graph.body_vertex_ids], atol=1e-6)


def test_measurement_edit_reaches_target_and_holds_the_others(model, editor):
    ed, A = editor
    target = ed.measurements["waist_cm"] + 4.0
    w = ed.weights_for({"waist_cm": target})
    got = model.measure(model.vertices(w), "female")
    assert abs(got["waist_cm"] - target) < 0.5
    for name in ("height_cm", "inseam_cm", "shoulder_width_cm"):
        assert abs(got[name] - ed.measurements[name]) < 0.5, name
    # the suit follows the body: it stays about 6 mm off the edited body's skin
    nb = model.n_body_vertices
    body = model.forward(w, ed.pose, ed.translation).vertices[:nb]
    suit = ed.edit({"waist_cm": target})
    err = np.linalg.norm(suit - _suit(model, body), axis=1)
    assert np.abs(suit - A).max() > 0.005  # it moved (4 cm of girth: about 6 mm of radius)
    assert err.mean() < 0.001 and np.percentile(err, 99) < 0.004


def test_pose_edit_carries_the_suit(model, editor):
    ed, A = editor
    new = {"forearm_l": [0.0, 0.0, -1.2], "head": [0.3, 0.2, 0.0]}
    suit = ed.edit(pose=new)
    body = model.forward(ed.weights, ed.pose_for(new), ed.translation).vertices[: model.n_body_vertices]
    err = np.linalg.norm(suit - _suit(model, body), axis=1)
    assert np.abs(suit - A).max() > 0.1
    assert np.median(err) < 0.001 and np.percentile(err, 95) < 0.005


def test_bad_edits_are_refused(editor):
    ed, _ = editor
    with pytest.raises(ValueError, match="unknown bone"):
        ed.edit(pose={"tail": [0, 0, 0]})
    with pytest.raises(ValueError, match="finite"):
        ed.edit(pose={"head": [0, np.nan, 0]})
    with pytest.raises(MeasurementError, match="gender"):
        ed.edit({"gender": "male"})
    with pytest.raises(MeasurementError, match="outside the allowed range"):
        ed.edit({"height_cm": 400})


def test_dqs_reproduces_rigid_motions_and_blends_rotations():
    rng = np.random.default_rng(0)
    P = rng.normal(size=(30, 3))
    G = np.tile(np.eye(4), (2, 1, 1))
    G[0, :3, :3] = Rotation.from_rotvec([0.3, -0.8, 0.5]).as_matrix()
    G[0, :3, 3] = [0.2, -0.1, 0.4]
    G[1, :3, 3] = [-0.3, 0.5, 0.1]
    idx = np.tile([0, 1], (30, 1))
    one = np.tile([1.0, 0.0], (30, 1))
    np.testing.assert_allclose(E.dqs_skin(P, G, idx, one), P @ G[0, :3, :3].T + G[0, :3, 3], atol=1e-12)
    # pure translations blend linearly, like LBS
    T = np.tile(np.eye(4), (2, 1, 1))
    T[:, :3, 3] = [[0.1, 0.2, 0.3], [-0.5, 0.0, 0.2]]
    w = rng.uniform(size=(30, 1))
    ww = np.hstack([w, 1 - w])
    np.testing.assert_allclose(E.dqs_skin(P, T, idx, ww), lbs.skin(P, T, idx, ww), atol=1e-12)
    # half-way between the identity and a 90-degree twist about z is a rigid 45-degree twist
    # (LBS shrinks the point towards the axis by cos 45)
    Q = np.tile(np.eye(4), (2, 1, 1))
    Q[1, :3, :3] = Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix()
    p = np.array([[1.0, 0.0, 0.0]])
    half = np.array([[0.5, 0.5]])
    np.testing.assert_allclose(E.dqs_skin(p, Q, idx[:1], half), [[np.sqrt(0.5), np.sqrt(0.5), 0.0]], atol=1e-12)
    np.testing.assert_allclose(lbs.skin(p, Q, idx[:1], half), [[0.5, 0.5, 0.0]], atol=1e-12)


def test_reskin_scan_round_trip(model):
    w = np.zeros(model.n_components)
    pose = np.zeros((len(BONES), 3))
    pose[BONES.index("forearm_r")] = [0.0, 0.5, 0.0]
    a = model.forward(w, pose)
    b = model.forward(w, None)
    nb = model.n_body_vertices
    idx, ww = E.transfer_skin_weights(a.vertices[:nb], a.vertices[:nb], model.body_faces,
                                      model.lbs_indices[:nb], model.lbs_weights[:nb])
    back = E.reskin_scan(a.vertices[:nb], idx, ww, a.transforms, b.transforms, "lbs")
    # LBS with the body's own weights undoes the pose up to the blend (exact for rigid parts)
    err = np.linalg.norm(back - b.vertices[:nb], axis=1)
    assert np.median(err) < 1e-6 and err.max() < 0.02


@pytest.mark.slow
def test_twisted_elbow_keeps_more_volume_than_skinning_the_suit(model):
    """Paper Fig. 8: a 90-degree forearm twist of a closed suit, through the graph (default: M*
    by dual quaternions) against LBS of the suit with weights transferred from the body."""
    from service.model.body.measurements import volume

    nb = model.n_body_vertices
    w = np.zeros(model.n_components)
    posed = model.forward(w, None)
    body = posed.vertices[:nb]
    suit = _suit(model, body)
    faces = model.body_faces
    fa, hand = BONES.index("forearm_l"), BONES.index("hand_l")
    axis = posed.rest_joints[hand] - posed.rest_joints[fa]
    twist = axis / np.linalg.norm(axis) * np.pi / 2
    v0 = volume(suit, faces)
    ed = E.ClothedAvatarEditor(model, w, None, None, suit, faces, "female")
    graph_loss = v0 - volume(ed.edit(pose={"forearm_l": twist}), faces)
    pose = np.zeros((len(BONES), 3))
    pose[fa] = twist
    idx, ww = E.transfer_skin_weights(suit, body, faces, model.lbs_indices[:nb], model.lbs_weights[:nb])
    lbs_loss = v0 - volume(E.reskin_scan(suit, idx, ww, posed.transforms, model.forward(w, pose).transforms), faces)
    assert lbs_loss > 1e-4  # LBS collapses the twisted elbow (> 100 cm3)
    assert graph_loss < 0.5 * lbs_loss


def test_no_edit_is_no_change_with_the_default_dual_quaternion_body(model):
    """The default editor poses M* by dual quaternions for every edit: the graph is built on that
    same M*, so an empty edit gives the scan back (a graph built on the LBS body would not)."""
    rng = np.random.default_rng(4)
    w = rng.normal(size=model.n_components) * np.sqrt(model.variances) * 0.5
    pose = np.zeros((len(BONES), 3))
    pose[BONES.index("forearm_l")] = [0.0, 0.0, 0.9]
    pose[BONES.index("thigh_l")] = [0.5, 0.0, 0.0]
    A = _suit(model, model.forward(w, pose).vertices)
    ed = E.ClothedAvatarEditor(model, w, pose, None, A, model.body_faces, "female")
    assert E.DEFAULT_PARAMS.skinning == "dqs"
    np.testing.assert_allclose(ed.edit(), A, atol=1e-6)

"""Linear blend skinning over the 17 bones (service/model/body/lbs.py) against a slow per-vertex
reference, and the body model's one forward pass (``BodyModel.forward``)."""
from __future__ import annotations

import numpy as np
import pytest

from service.model.body import lbs as sk
from service.model.body.model import BONES


def slow_pose(vertices, joints, parents, rotvecs, idx, w):
    """Per vertex, per influence: walk the chain root -> bone, rotating about each joint."""
    def apply_chain(j, p):
        chain = []
        while j >= 0:
            chain.append(j)
            j = parents[j]
        for b in chain:  # innermost bone first, then its ancestors
            R = sk.axis_angle_to_matrix(rotvecs[b])
            p = R @ (p - joints[b]) + joints[b]
        return p

    out = np.zeros_like(vertices)
    for v in range(len(vertices)):
        for k in range(idx.shape[1]):
            out[v] += w[v, k] * apply_chain(idx[v, k], vertices[v])
    return out


def test_fast_lbs_matches_slow_reference_on_tiny_rig():
    rng = np.random.default_rng(0)
    parents = np.array([-1, 0, 1, 0])
    joints = rng.normal(size=(4, 3))
    V = rng.normal(size=(30, 3))
    idx = rng.integers(0, 4, size=(30, 2))
    w = rng.random((30, 2))
    w /= w.sum(1, keepdims=True)
    rot = rng.normal(size=(4, 3)) * 0.5
    np.testing.assert_allclose(sk.pose(V, joints, parents, rot, idx, w), slow_pose(V, joints, parents, rot, idx, w),
                               atol=1e-12)


def test_rodrigues_is_a_rotation():
    R = sk.axis_angle_to_matrix(np.array([[0.3, -1.2, 0.7], [0, 0, 0]]))
    np.testing.assert_allclose(R @ R.transpose(0, 2, 1), np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(R[1], np.eye(3))
    assert np.linalg.det(R[0]) == pytest.approx(1.0)


def test_avatar_pose(model):
    X = model.mean.astype(np.float64)
    J = model.joints(X)
    zero = np.zeros((17, 3))
    np.testing.assert_allclose(sk.pose(X, J, model.bone_parents, zero, model.lbs_indices, model.lbs_weights), X,
                               atol=1e-6)
    # a root rotation moves the whole body rigidly about the pelvis joint
    rot = zero.copy()
    rot[0] = [0, np.pi / 2, 0]
    P = sk.pose(X, J, model.bone_parents, rot, model.lbs_indices, model.lbs_weights)
    R = sk.axis_angle_to_matrix(rot[0])
    np.testing.assert_allclose(P, (X - J[0]) @ R.T + J[0], atol=1e-5)
    # bending the left elbow moves the left hand, not the head or the right hand
    b = {n: i for i, n in enumerate(BONES)}
    rot = zero.copy()
    rot[b["forearm_l"]] = [0, 0, 1.0]
    P = sk.pose(X, J, model.bone_parents, rot, model.lbs_indices, model.lbs_weights)
    moved = np.linalg.norm(P - X, axis=1)
    dominant = model.lbs_indices[np.arange(len(X)), np.argmax(model.lbs_weights, axis=1)]
    assert moved[dominant == b["hand_l"]].min() > 0.05
    assert moved[dominant == b["head"]].max() < 1e-6  # float32 weights sum to 1 +- 1e-7
    assert moved[dominant == b["hand_r"]].max() < 1e-6
    # the elbow stays where it was (rotation about the forearm joint)
    assert np.linalg.norm(model.joints(X)[b["forearm_l"]] - J[b["forearm_l"]]) < 1e-9


def test_forward_pass(model):
    """``BodyModel.forward``: shape, pose (axis-angle or matrices), translation -> vertices,
    joints and transforms, the same as composing the pieces by hand."""
    rng = np.random.default_rng(3)
    w = rng.normal(size=model.n_components) * np.sqrt(model.variances) * 0.5
    rot = rng.normal(size=(17, 3)) * 0.3
    t = np.array([0.1, -0.2, 0.3])
    out = model.forward(w, rot, t)
    X = model.vertices(w).astype(np.float64)
    J = model.joints(X)
    ref = sk.pose(X, J, model.bone_parents, rot, model.lbs_indices, model.lbs_weights, t)
    np.testing.assert_allclose(out.vertices, ref, atol=1e-9)
    np.testing.assert_allclose(out.rest_joints, J)
    G = sk.global_transforms(J, model.bone_parents, sk.axis_angle_to_matrix(rot), t)
    np.testing.assert_allclose(out.transforms, G)
    np.testing.assert_allclose(out.joints, np.einsum("jab,jb->ja", G[:, :3, :3], J) + G[:, :3, 3])
    mats = model.forward(w, sk.axis_angle_to_matrix(rot), t)
    np.testing.assert_allclose(mats.vertices, out.vertices, atol=1e-12)
    rest = model.forward(w)
    np.testing.assert_allclose(rest.vertices, X, atol=1e-6)
    np.testing.assert_allclose(sk.matrix_to_axis_angle(sk.axis_angle_to_matrix(rot[:3])), rot[:3], atol=1e-9)
    with pytest.raises(ValueError, match="pose"):
        model.forward(w, np.zeros((16, 3)))

"""Linear blend skinning over the 17-bone skeleton: the body model's one forward pass
(editing paper, Sec. 4.1: pose deformation Q(theta) = sum_j w_j theta_j applied to the rest
shape). Pure numpy, modelled on smplx's ``lbs.py``.

Shapes: rest vertices (V, 3); joints (J, 3) rest positions; parents (J,) with -1 for the root
(parents precede children); rotations (J, 3, 3) local rotations about each joint (the rest
joint frames are axis-aligned, so a bone's local frame is the world frame at rest);
lbs_indices / lbs_weights (V, 4); transforms (J, 4, 4) world transforms of the bones.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotvec (..., 3) radians -> rotation matrices (..., 3, 3) float64."""
    rv = np.asarray(rotvec, np.float64)
    theta = np.linalg.norm(rv, axis=-1, keepdims=True)
    k = rv / np.maximum(theta, 1e-12)
    kx, ky, kz = k[..., 0], k[..., 1], k[..., 2]
    zero = np.zeros_like(kx)
    Kmat = np.stack([zero, -kz, ky, kz, zero, -kx, -ky, kx, zero], axis=-1).reshape(rv.shape[:-1] + (3, 3))
    s = np.sin(theta)[..., None]
    c = np.cos(theta)[..., None]
    eye = np.broadcast_to(np.eye(3), Kmat.shape)
    return eye + s * Kmat + (1 - c) * (Kmat @ Kmat)


def matrix_to_axis_angle(R: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) -> axis-angle (..., 3) radians."""
    R = np.asarray(R, np.float64)
    return Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-2] + (3,))


def as_rotations(pose: np.ndarray | None, n_joints: int) -> np.ndarray:
    """A pose as local rotation matrices (J, 3, 3): None (the rest pose), axis-angle (J, 3) or
    matrices (J, 3, 3)."""
    if pose is None:
        return np.tile(np.eye(3), (n_joints, 1, 1))
    p = np.asarray(pose, np.float64)
    if p.shape == (n_joints, 3):
        return axis_angle_to_matrix(p)
    if p.shape == (n_joints, 3, 3):
        return p
    raise ValueError(f"pose must be ({n_joints}, 3) axis-angle or ({n_joints}, 3, 3) matrices, got {p.shape}")


def global_transforms(joints: np.ndarray, parents: np.ndarray, rotations: np.ndarray,
                      translation: np.ndarray | None = None) -> np.ndarray:
    """World transforms (J, 4, 4) that map rest-pose points to posed points for each bone.

    A bone j rotates its subtree by rotations[j] about its rest joint: the chain
    G_j = G_parent(j) @ T(c_j) R_j T(-c_j) (forward kinematics on relative transforms), then the
    whole body moves by ``translation`` (3,)."""
    J = len(parents)
    G = np.zeros((J, 4, 4))
    for j in range(J):  # parents precede children
        L = np.eye(4)
        L[:3, :3] = rotations[j]
        L[:3, 3] = joints[j] - rotations[j] @ joints[j]
        G[j] = L if parents[j] < 0 else G[parents[j]] @ L
    if translation is not None:
        G[:, :3, 3] += translation
    return G


def blend_transforms(transforms: np.ndarray, lbs_indices: np.ndarray, lbs_weights: np.ndarray) -> np.ndarray:
    """Per-vertex blended transforms (V, 4, 4) = sum_k w_k G_{i_k}."""
    return np.einsum("vk,vkij->vij", np.asarray(lbs_weights, np.float64), transforms[lbs_indices])


def skin(vertices: np.ndarray, transforms: np.ndarray, lbs_indices: np.ndarray,
         lbs_weights: np.ndarray) -> np.ndarray:
    """LBS: posed (V, 3) = sum_k w_k G_{i_k} [v; 1]."""
    A = blend_transforms(transforms, lbs_indices, lbs_weights)
    return np.einsum("vij,vj->vi", A[:, :3, :3], np.asarray(vertices, np.float64)) + A[:, :3, 3]


def bone_hops(parents: np.ndarray) -> np.ndarray:
    """(J, J) int: the number of bones between two bones along the skeleton tree (0 on the
    diagonal, 1 for a parent and its child)."""
    J = len(parents)
    hops = np.full((J, J), J, np.int64)
    for a in range(J):
        hops[a, a] = 0
        frontier, d = [a], 0
        while frontier:
            d += 1
            nxt = []
            for b in frontier:
                for c in [int(parents[b])] + [int(x) for x in np.flatnonzero(np.asarray(parents) == b)]:
                    if c >= 0 and hops[a, c] > d:
                        hops[a, c] = d
                        nxt.append(c)
            frontier = nxt
    return hops


def main_bone(lbs_indices: np.ndarray, lbs_weights: np.ndarray) -> np.ndarray:
    """(V,) the bone of largest skinning weight of each vertex."""
    return np.take_along_axis(np.asarray(lbs_indices), np.argmax(lbs_weights, axis=1)[:, None], 1)[:, 0]


@dataclass
class Posed:
    """The output of :func:`lbs`: posed vertices (V, 3), rest joints (J, 3), posed joints
    (J, 3) and the bones' world transforms (J, 4, 4), all float64."""

    vertices: np.ndarray
    rest_joints: np.ndarray
    joints: np.ndarray
    transforms: np.ndarray


def lbs(rest_vertices: np.ndarray, joints: np.ndarray, parents: np.ndarray, pose: np.ndarray | None,
        lbs_indices: np.ndarray, lbs_weights: np.ndarray, translation: np.ndarray | None = None) -> Posed:
    """Pose a rest-shape body: ``pose`` None, (J, 3) axis-angle or (J, 3, 3) local rotations;
    ``translation`` (3,) metres. Returns :class:`Posed`."""
    joints = np.asarray(joints, np.float64)
    R = as_rotations(pose, len(parents))
    t = None if translation is None else np.asarray(translation, np.float64)
    G = global_transforms(joints, parents, R, t)
    V = skin(rest_vertices, G, lbs_indices, lbs_weights)
    posed_joints = np.einsum("jab,jb->ja", G[:, :3, :3], joints) + G[:, :3, 3]
    return Posed(vertices=V, rest_joints=joints, joints=posed_joints, transforms=G)


def pose(vertices: np.ndarray, joints: np.ndarray, parents: np.ndarray, rotvecs: np.ndarray,
         lbs_indices: np.ndarray, lbs_weights: np.ndarray,
         translation: np.ndarray | None = None) -> np.ndarray:
    """Posed vertices (V, 3) from per-bone axis-angle rotations rotvecs (J, 3)."""
    return lbs(vertices, joints, parents, rotvecs, lbs_indices, lbs_weights, translation).vertices

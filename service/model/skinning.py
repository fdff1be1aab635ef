"""Linear blend skinning over the 17-bone skeleton (editing paper, Sec. 4.1: pose deformation
Q(theta) = sum_j w_j theta_j applied to the rest shape). Pure numpy, modelled on smplx's lbs.py.

Shapes: vertices (V, 3); joints (J, 3) rest positions; parents (J,) with -1 for the root;
rotations (J, 3, 3) local rotations about each joint (parent frame == world frame at rest,
since rest joint frames are axis-aligned); lbs_indices / lbs_weights (V, 4).
"""
from __future__ import annotations

import numpy as np


def axis_angle_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: rotvec (..., 3) radians -> rotation matrices (..., 3, 3)."""
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


def global_transforms(joints: np.ndarray, parents: np.ndarray, rotations: np.ndarray,
                      translation: np.ndarray | None = None) -> np.ndarray:
    """World transforms (J, 4, 4) that map rest-pose points to posed points for each bone.

    A bone j rotates its subtree by rotations[j] about its rest joint: the chain
    G_j = G_parent(j) @ T(c_j) R_j T(-c_j) (forward kinematics on relative transforms)."""
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


def skin(vertices: np.ndarray, transforms: np.ndarray, lbs_indices: np.ndarray,
         lbs_weights: np.ndarray) -> np.ndarray:
    """LBS: posed (V, 3) = sum_k w_k G_{i_k} [v; 1]."""
    A = np.einsum("vk,vkij->vij", lbs_weights, transforms[lbs_indices])  # (V, 4, 4)
    return np.einsum("vij,vj->vi", A[:, :3, :3], vertices) + A[:, :3, 3]


def pose(vertices: np.ndarray, joints: np.ndarray, parents: np.ndarray, rotvecs: np.ndarray,
         lbs_indices: np.ndarray, lbs_weights: np.ndarray,
         translation: np.ndarray | None = None) -> np.ndarray:
    """Posed vertices (V, 3) from per-bone axis-angle rotations rotvecs (J, 3)."""
    G = global_transforms(joints, parents, axis_angle_to_matrix(rotvecs), translation)
    return skin(np.asarray(vertices, np.float64), G, lbs_indices, lbs_weights)

"""Regions of the template the fit weights differently: hair (scalp, back of the head), face,
fingers and loose clothing. Pure numpy.
"""
from __future__ import annotations

from typing import Protocol

import numpy as np

from service.model.geometry.mesh import vertex_normals
from service.model.fitting.params import FitParams, TUNING


class _HairMasks(Protocol):
    """What :func:`_hair` reads of a rig (``rig._Rig``, which imports this module)."""

    scalp: np.ndarray
    hair_back: np.ndarray


def scalp_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) bool: where a scan of a bare person may show hair, not skin, on a rest body
    (vertices (n, 3), faces (F, 3), dense skinning weights W (n, 17)): the head but the face,
    and the neck."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    head = bone == BONES.index("head")
    if not head.any():
        return head
    y = vertices[:, 1]
    top = float(y[head].max())
    nz = vertex_normals(vertices, faces)[:, 2]
    face = head & (nz > TUNING.scalp_face_normal_z) & (y < top - TUNING.scalp_hairline_m)
    return np.isin(bone, [BONES.index(b) for b in TUNING.hair_bones]) & ~face


def face_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) bool: the face on a rest body (vertices (n, 3), faces (F, 3), dense skinning weights
    W (n, 17)): the vertices of TUNING.hair_bones outside ``scalp_region``."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    return np.isin(bone, [BONES.index(b) for b in TUNING.hair_bones]) & ~scalp_region(vertices, faces, W)




def hair_back_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(n,) bool: where long hair may cover the back of a bare person on a rest body (vertices
    (n, 3), faces (F, 3), dense skinning weights W (n, 17), joints (17, 3))."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    nz = vertex_normals(vertices, faces)[:, 2]
    head = joints[BONES.index("head")]
    half = 0.5 * abs(joints[BONES.index("upper_arm_l"), 0] - joints[BONES.index("upper_arm_r"), 0])
    return (np.isin(bone, [BONES.index(b) for b in TUNING.hair_back_bones]) & (nz < TUNING.hair_back_normal_z)
            & (vertices[:, 1] > head[1] - TUNING.hair_back_below_m) & (np.abs(vertices[:, 0] - head[0]) < half))




def finger_region(vertices: np.ndarray, W: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(n,) bool: the fingers of a rest body (vertices (n, 3), dense skinning weights W (n, 17),
    joints (17, 3)), which the 17 bones cannot bend (``FitParams.finger_scale``)."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    out = np.zeros(len(vertices), bool)
    for name in ("hand_l", "hand_r"):
        b = BONES.index(name)
        at = np.flatnonzero(bone == b)
        if not len(at):
            continue
        P = vertices[at] - joints[b]
        reach = np.linalg.norm(P, axis=1)
        axis = P[reach >= np.percentile(reach, 95)].mean(0)  # towards the fingertips
        axis /= np.linalg.norm(axis)
        along = P @ axis
        out[at] = along > TUNING.finger_knuckle_share * along.max()
    return out


def finger_weights(residuals: np.ndarray, fingers: np.ndarray, scale: float) -> np.ndarray:
    """(n,) multipliers of n pairs' weights: 1 / (1 + (r / scale)^2) where ``fingers`` (n,) bool
    (residuals r (n,) metres), else 1 (``FitParams.finger_scale``)."""
    return np.where(fingers, 1.0 / (1.0 + (np.asarray(residuals, np.float64) / scale) ** 2), 1.0)


def _hair(rig: _HairMasks, params: FitParams) -> np.ndarray:
    """(n,) bool: the template vertices a bare scan may show hair over (``FitParams.hair_region``,
    ``hair_back``)."""
    return rig.scalp | rig.hair_back if params.hair_back else rig.scalp


def _clothing_weight(signed: np.ndarray, clothed: bool, params: FitParams,
                     contact: float | None = None, hair: np.ndarray | None = None) -> np.ndarray:
    """Weight (n,) of correspondences by the side of the scan the body is on: ``signed`` (n,)
    metres > 0 is a body point outside the scan (through the clothes: full weight), < 0 inside:
    ``inside_weight``, or with ``contact`` (metres) the asymmetric Cauchy weight
    1 / (1 + (depth / contact)^2) (see ``FitParams.clothing_contact``)."""
    if not clothed:  # a bare scan: as clothed on the scalp (``hair`` (n,) bool per pair), else 1
        if hair is None or not hair.any():
            return np.ones_like(signed)
        return np.where(hair, _clothing_weight(signed, True, params, contact), 1.0)
    if contact is None:
        return np.where(signed >= 0, 1.0, params.inside_weight)
    return np.where(signed >= 0, 1.0, 1.0 / (1.0 + (signed / contact) ** 2))


def loose_region_weight(signed: np.ndarray, region: np.ndarray, depth: float) -> np.ndarray:
    """(n,) multipliers of the clothing weights of n body-scan pairs (``FitParams.loose_region_depth``):
    ``signed`` (n,) metres, < 0 a body point inside the clothes; ``region`` (n,) int, the pair's
    body region. A pair inside in region R gets 1 / (1 + (m_R / depth)^2), with m_R the
    median over R's pairs of max(-signed, 0); pairs outside get 1."""
    inside = np.maximum(-np.asarray(signed, np.float64), 0.0)
    out = np.ones(len(inside))
    for b in np.unique(region):
        at = region == b
        out[at & (inside > 0)] = 1.0 / (1.0 + (float(np.median(inside[at])) / depth) ** 2)
    return out

"""Pose-corrective morph targets: per page pose, rest-space POSITION deltas that keep a skinned
garment outside the posed body. Pure numpy/scipy.

Plain linear blend skinning pushes some garment vertices inside the body in the page's poses
(an arm swung back drags the blouse's side into the chest). For each pose (the bone transforms
G (J, 4, 4) the page applies: ``service.model.poses``), the garment is posed with its own skin
weights, the vertices nearer the posed skin than ``TRIGGER`` are pushed out to ``CLEARANCE``
(plus the layer's gap) along the body normal of their nearest posed body vertex, the push spread
to the neighbours by the garment's smoother (``garment.push_out``, the try-on's own push-out,
run on the posed shapes), and the posed displacement d taken back to rest space with the
inverse of the vertex's blended LBS matrix: glTF (and three.js) add morph deltas before
skinning, and skinning is linear in the rest position, so skin(v + A^-1 d) = skin(v) + d with
A = sum_k w_k G_{i_k}[:3, :3] (the blended linear part; Kavan et al. 2008, eq. 1).

The target of pose ``p`` is named ``pose:p``; the page sets its influence to 1 in that pose, 0
otherwise. Shapes: garment vertices (M, 3) metres, skin (M, 4) + (M, 4), body (V, 3).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model import garment as G
from service.model import lbs as L
from service.model.body import BONES
from service.model.geometry import vertex_normals

TARGET_PREFIX = "pose:"
# metres: posed garment vertices nearer the posed skin than this (along the nearest body vertex's
# normal) are pushed out. Below the try-on's CLEARANCE (3 mm) so that cloth merely pressed a
# little closer by a pose (most of it) keeps a zero delta: the targets stay sparse
TRIGGER = 0.001
# metres: where they are pushed to (plus ``garment.LAYER_GAP`` per layer: an outer garment over
# the inner one's correction, as at rest)
CLEARANCE = 0.002
MIN_DELTA = 1e-5  # metres: rest deltas shorter than this are left out (0 in the sparse target)
HAND_WEIGHT = 0.5  # body vertices with more skin weight on the hands are no obstacle: a hand on a hip
# rests on the cloth (pushing the skirt out over the hand would hide it)


@dataclass
class PosedBody:
    """One pose of a customer's body: the bone transforms (J, 4, 4), the posed body (Vb, 3)
    and its unit normals (Vb, 3), and a k-d tree of the posed vertices that are obstacles
    (``ids`` (K,) into the body: all but the hands)."""

    transforms: np.ndarray
    vertices: np.ndarray
    normals: np.ndarray
    ids: np.ndarray
    tree: cKDTree


def obstacle_vertices(model) -> np.ndarray:
    """(K,) the body vertices garments are kept outside of: all but the hands'."""
    nb = model.n_body_vertices
    idx, w = np.asarray(model.lbs_indices[:nb]), np.asarray(model.lbs_weights[:nb], np.float64)
    hands = np.isin(idx, [BONES.index("hand_l"), BONES.index("hand_r")])
    return np.flatnonzero((w * hands).sum(1) <= HAND_WEIGHT)


def posed_body(model, vertices: np.ndarray, pose: np.ndarray, ids: np.ndarray | None = None) -> PosedBody:
    """The avatar ``vertices`` (V, 3) in ``pose`` ((17, 3) axis-angle, ``BONES`` order)."""
    nb = model.n_body_vertices
    posed = model.forward(pose=pose, vertices=vertices)
    pb = posed.vertices[:nb]
    ids = obstacle_vertices(model) if ids is None else ids
    return PosedBody(posed.transforms, pb, vertex_normals(pb, model.body_faces).astype(np.float64), ids,
                     cKDTree(pb[ids]))


def skin_offsets(points: np.ndarray, body: PosedBody) -> tuple[np.ndarray, np.ndarray]:
    """(M,) each point's (M, 3) offset along the normal of its nearest obstacle vertex of
    ``body`` (the push-out's distance to the skin), and that vertex (M,) int32."""
    nn = body.ids[body.tree.query(points)[1]].astype(np.int32)
    return np.einsum("ij,ij->i", points - body.vertices[nn], body.normals[nn]), nn


def corrective_deltas(garment: np.ndarray, skin_idx: np.ndarray, skin_w: np.ndarray, body: PosedBody,
                      smoother: sp.csc_matrix | None, layer: int = 0,
                      rest: PosedBody | None = None) -> tuple[np.ndarray, int]:
    """Rest-space deltas (M, 3) float32 that keep the garment (M, 3), skinned with (M, 4) +
    (M, 4), outside the posed ``body`` once added before skinning, and how many vertices were
    pushed. ``layer``: the garment's rank in its outfit (clearance + layer x LAYER_GAP).
    ``rest``: the body unposed; a vertex nearer the skin than the clearance already at rest (an
    inner garment pushed inside the one over it by ``service.model.layering``) is pushed back
    no farther out than it was at rest, and only once it is ``CLEARANCE - TRIGGER`` deeper:
    the rest pose gets no delta and the layers keep their order."""
    v = np.asarray(garment, np.float64)
    clearance, trigger = CLEARANCE + layer * G.LAYER_GAP, TRIGGER + layer * G.LAYER_GAP
    if rest is not None:
        at_rest = skin_offsets(v, rest)[0]
        clearance = np.minimum(clearance, np.maximum(at_rest, 0.0))
        trigger = np.minimum(trigger, at_rest - (CLEARANCE - TRIGGER))
    pv = L.skin(v, body.transforms, skin_idx, skin_w)
    nn = skin_offsets(pv, body)[1][:, None]
    moved, count = G.push_out(pv, body.vertices, body.normals, nn, smoother, clearance, trigger=trigger)
    out = np.zeros(v.shape, np.float32)
    if not count:
        return out, 0
    d = moved.astype(np.float64) - pv
    rows = np.flatnonzero(np.einsum("ij,ij->i", d, d) > MIN_DELTA ** 2)
    A = L.blend_transforms(body.transforms, np.asarray(skin_idx)[rows], np.asarray(skin_w)[rows])[:, :3, :3]
    out[rows] = np.linalg.solve(A, d[rows][:, :, None])[:, :, 0]
    return out, count


def target_names(poses) -> list[str]:
    """The morph target names of poses (their names, in order)."""
    return [TARGET_PREFIX + name for name in poses]

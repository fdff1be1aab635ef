"""The avatar's look: eyes, eyebrows, hair and a base layer (underwear) from the compiled
catalogue (``service.model.garments.catalogue``), fitted to a customer's avatar. Pure numpy/scipy.

Once per process and catalogue item (:func:`prepare_item`): the item's render layout (one
vertex per (vertex, uv) corner, glTF's UV convention), the k nearest body vertices of each item
vertex on the mean avatar (push-out candidates: the nearest of them on the customer's body is
used), the displacement smoother of the push-out and the item's skin weights. Per customer
(:meth:`PreparedItem.fit`): the item's MakeHuman binding (3 base-mesh vertices, weights and a
scaled offset per item vertex, ``Binding.fit``: a fancy-index and an einsum, O(M)), then, for
hair and the base layer, the try-on's push-out out of the body (``garment.push_out``); eyes sit
in their sockets and eyebrows on the skin as bound (``Fit.push_out`` false).

Skinning: items marked ``skinning='head'`` (eyes, eyebrows, hair) are rigid to the head bone;
the others take the body's weights at the closest body vertex (:func:`transfer_skin_weights`,
the one function to swap for a smoother transfer).

Shapes: avatar vertices (V, 3) metres, all hm08 base-mesh vertices (helpers included: items bind
to them); body vertices (Vb, 3) = the first ``n_body_vertices``; item vertices (M, 3); render
vertices (R, 3).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.garments import garment as G
from service.model.body.model import BONES
from service.model.garments.catalogue import CatalogueItem, RenderLayout
from service.model.geometry.mesh import face_incidence, vertex_normals

HEAD_BONE = BONES.index("head")
NEAR_K = 4  # push-out candidates per item vertex (nearest body vertices on the mean avatar)
SKIN_K = 4  # joints per vertex in a GLB skin


def transfer_skin_weights(points: np.ndarray, body_vertices: np.ndarray, lbs_indices: np.ndarray,
                          lbs_weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights of points (M, 3) near a body (Vb, 3): those of each point's nearest body
    vertex. lbs_indices (Vb, 4) int, lbs_weights (Vb, 4) -> ((M, 4) int32, (M, 4) float32).
    Computed once per item on the mean avatar (a vertex of a thin base layer has the body's
    weights under it; a smoother transfer can replace this function)."""
    _, near = cKDTree(np.asarray(body_vertices, np.float64)).query(np.asarray(points, np.float64))
    return np.asarray(lbs_indices)[near].astype(np.int32), np.asarray(lbs_weights)[near].astype(np.float32)


def rigid_skin_weights(n: int, bone: int = HEAD_BONE) -> tuple[np.ndarray, np.ndarray]:
    """n vertices bound to one bone with weight 1: ((n, 4) int32, (n, 4) float32)."""
    idx = np.zeros((n, SKIN_K), np.int32)
    idx[:, 0] = bone
    w = np.zeros((n, SKIN_K), np.float32)
    w[:, 0] = 1.0
    return idx, w


@dataclass(frozen=True, eq=False)
class PreparedItem:
    """A catalogue item ready to be fitted to any avatar (see the module docstring).
    near: (M, NEAR_K) int32 body vertices; smoother: (M, M) push-out displacement diffusion, or
    None (items that are not pushed out); skin_idx/skin_w: (M, 4) per item vertex; incidence:
    (M, F) vertex-face incidence (normals)."""

    item: CatalogueItem
    layout: RenderLayout
    near: np.ndarray
    smoother: sp.csc_matrix | None
    clearance: float
    skin_idx: np.ndarray
    skin_w: np.ndarray
    incidence: sp.csr_matrix
    prone: np.ndarray | None = None  # (P,) int64 item vertices near a crease of the mean avatar

    def fit_vertices(self, vertices: np.ndarray, body_normals: np.ndarray, body=None) -> np.ndarray:
        """The item on an avatar (V, 3), body normals (Vb, 3) -> (M, 3) float32 item vertices:
        bound (``Binding.fit``), then pushed out of the body when the item is (``Fit.push_out``).
        ``body``: the avatar as a ``tryon.CustomerBody`` with its triangles
        (``tryon.surface_body``): the push-out then binds the item's vertices near a crease of
        the mean avatar (``prone``) to their nearest vertex of this avatar (its k-d tree), not
        to the nearest of ``near``, with the crease anchors (``garment.crease_anchors``)."""
        P = self.item.fit_to(vertices)
        if self.smoother is None:
            return P.astype(np.float32)
        nb = len(body_normals)
        X = np.asarray(vertices[:nb])
        near, anchors = self.near, None
        if body is not None and body.faces is not None and self.prone is not None and len(self.prone):
            # near a crease, this avatar's own nearest vertices (the facing skin is rarely among
            # the candidates found on the mean avatar) and the crease anchors
            nn = body.nearest(P[self.prone], G.CREASE_K)
            a, q, qn, most = body.crease_anchors(P[self.prone], nn)
            anchors = (self.prone[a], q, qn, most)
            near = near.copy()
            near[self.prone] = nn[:, :1]
        P, _ = G.push_out(P, X, body_normals, near, self.smoother, self.clearance, anchors)
        return np.asarray(P, np.float32)

    def fit(self, vertices: np.ndarray, body_normals: np.ndarray, body=None) -> dict[str, np.ndarray]:
        """The item on an avatar as a render mesh: {vertices (R, 3) float32, normals (R, 3)
        float32 (smooth across UV seams), faces (F, 3) int64, uv (R, 2) float32 (glTF
        convention), vertex_joints (R, 4), vertex_weights (R, 4)}; ``body`` as in
        :meth:`fit_vertices`."""
        P = self.fit_vertices(vertices, body_normals, body)
        n = vertex_normals(P, self.item.faces, self.incidence)
        v = self.layout.vertex
        return {"vertices": P[v], "normals": n[v].astype(np.float32), "faces": self.layout.faces,
                "uv": self.layout.uv, "vertex_joints": self.skin_idx[v], "vertex_weights": self.skin_w[v]}


def prepare_item(item: CatalogueItem, mean_vertices: np.ndarray, n_body_vertices: int, lbs_indices: np.ndarray,
                 lbs_weights: np.ndarray, body_faces: np.ndarray | None = None) -> PreparedItem:
    """Precompute what fitting ``item`` to any avatar needs, on the mean avatar (V, 3); with
    ``body_faces`` (F, 3) also the item vertices prone to a crease (:func:`crease_prone`)."""
    X = np.asarray(mean_vertices, np.float64)
    body = X[:n_body_vertices]
    P = item.fit_to(X)
    near = G.bind_to_body(P, body, k=NEAR_K)
    smoother = G.laplacian_smoother(item.faces, len(P)) if item.fit.push_out else None
    prone = crease_prone(P, body, body_faces) if smoother is not None and body_faces is not None else None
    clearance = item.fit.clearance if item.fit.clearance is not None else G.CLEARANCE + (item.layer or 0) * G.LAYER_GAP
    if item.fit.skinning == "head":
        skin_idx, skin_w = rigid_skin_weights(len(P))
    else:
        skin_idx, skin_w = transfer_skin_weights(P, body, lbs_indices[:n_body_vertices], lbs_weights[:n_body_vertices])
    layout = item.render_layout()
    for a in (near, skin_idx, skin_w, layout.vertex, layout.uv, layout.faces):
        a.setflags(write=False)
    return PreparedItem(item, layout, near, smoother, float(clearance), skin_idx, skin_w,
                        face_incidence(item.faces, len(P)), prone)


CREASE_PRONE_K = 16  # mean-avatar body vertices looked at for a crease near an item vertex


def crease_prone(points: np.ndarray, body: np.ndarray, body_faces: np.ndarray) -> np.ndarray:
    """Item vertices (M, 3) on the mean avatar's body (Vb, 3) whose ``CREASE_PRONE_K`` nearest
    body vertices include skin facing the nearest one (``garment.in_crease``'s test over more
    neighbours: a heavier body's crease is deeper and wider than the mean's) -> (P,) int64."""
    _, nn = cKDTree(body).query(points, k=CREASE_PRONE_K)
    return G.in_crease(nn, vertex_normals(body, body_faces), CREASE_PRONE_K)


def merge_meshes(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Several render meshes (the dicts of :meth:`PreparedItem.fit`) as one: arrays stacked,
    faces offset."""
    if len(parts) == 1:
        return dict(parts[0])
    offsets = np.cumsum([0] + [len(p["vertices"]) for p in parts[:-1]])
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k != "faces"}
    out["faces"] = np.concatenate([p["faces"] + o for p, o in zip(parts, offsets)])
    return out


def visible_body_faces(body_faces: np.ndarray, hidden: np.ndarray, n_body_vertices: int) -> np.ndarray:
    """The body faces (F, 3) to draw under items hiding body vertices ``hidden`` (H,): a face
    is dropped when all three of its vertices are hidden (the skin there cannot show through)."""
    mask = np.zeros(n_body_vertices, bool)
    mask[np.asarray(hidden, np.int64)] = True
    return np.asarray(body_faces)[~mask[body_faces].all(axis=1)]

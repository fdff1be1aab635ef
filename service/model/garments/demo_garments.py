"""The project's own demo garments, built from the body template, and the offline method that
fits them to any avatar (used on the example avatars to build their clothing bases, and on
held-out avatars as the ground truth of the garment-accuracy benchmark).

* ``tshirt`` and ``trousers``: a region of the body surface (chosen by skinning weights and
  landmarks on the mean avatar), offset along the avatar's normals by an ease.
* ``skirt``: an A-line surface of revolution-like rings from the waist to above the knee; each
  ring is the convex hull of that level's body section plus an ease, never narrower than the
  ring above it below the hip (cloth hangs, it does not follow the thighs in).

Shapes: avatar vertices (V, 3) metres, garment (M, 3), faces (F, 3) int32.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from service.model.body import measurements as M
from service.model.body.model import BONES
from service.model.garments.garment import bind_to_body, laplacian_smoother, push_out
from service.model.geometry.mesh import vertex_components, vertex_normals

B = {b: i for i, b in enumerate(BONES)}
EASE = {"tshirt": 0.012, "trousers": 0.010}
FIT_CLEARANCE = 0.006  # skin-to-cloth clearance the offline fit guarantees on each example
SKIRT = {"rings": 24, "angles": 72, "waist_below_navel": 0.03, "hem_above_knee": 0.06,
         "ease_top": 0.012, "ease_hem": 0.03, "flare": 0.12,
         "thigh_above_crotch": 0.02}
COLORS = {"tshirt": (0.16, 0.35, 0.75, 1.0), "trousers": (0.12, 0.13, 0.18, 1.0),
          "skirt": (0.62, 0.12, 0.22, 1.0)}
LAYER = {"trousers": 1, "skirt": 1, "tshirt": 2}


@dataclass
class DemoGarment:
    """A demo garment's template: how to fit it to any avatar."""

    name: str
    faces: np.ndarray
    vids: np.ndarray | None = None  # body-region garments: body vertex of each garment vertex
    ease: float = 0.0

    def fit(self, model, vertices: np.ndarray) -> np.ndarray:
        """The garment on an avatar (V, 3) -> (M, 3) float64 (the offline method): construct
        it, then resolve collisions with that avatar (push-out, as a cloth fit would)."""
        X = np.asarray(vertices, np.float64)
        nb = model.n_body_vertices
        n = vertex_normals(X[:nb], model.body_faces)
        if self.name == "skirt":
            P = skirt_rings(model, X)
        else:
            P = X[self.vids] + self.ease * n[self.vids]
        binding = bind_to_body(P, X[:nb])
        P, _ = push_out(P, X[:nb], n, binding, laplacian_smoother(self.faces, len(P)), FIT_CLEARANCE)
        return P.astype(np.float64)


def _largest_component(faces: np.ndarray) -> np.ndarray:
    lab = vertex_components(faces, faces.max() + 1)
    keep = lab[faces[:, 0]] == np.bincount(lab[faces[:, 0]]).argmax()
    return faces[keep]


def _region(model, mask: np.ndarray, name: str) -> DemoGarment:
    f = model.body_faces
    faces = _largest_component(f[mask[f].all(axis=1)])
    vids = np.unique(faces)
    remap = np.full(model.n_body_vertices, -1, np.int64)
    remap[vids] = np.arange(len(vids))
    return DemoGarment(name, remap[faces].astype(np.int32), vids, EASE[name])


def make_demo_garments(model) -> dict[str, DemoGarment]:
    """The three demo garments, defined on the mean avatar."""
    X = model.mean.astype(np.float64)
    nb = model.n_body_vertices
    J = model.joints(X)
    dom = model.lbs_indices[:nb][np.arange(nb), np.argmax(model.lbs_weights[:nb], axis=1)]
    y = X[:nb, 1]
    spec = model.measurement_spec
    navel_y = X[spec.navel, 1]
    crotch_y = X[spec.crotch, 1]
    hipline = crotch_y + 0.5 * (navel_y - crotch_y)
    # T-shirt: torso above the hipline, short sleeves, neck opening
    torso = np.isin(dom, [B["spine"], B["chest"]]) | ((dom == B["pelvis"]) & (y > hipline))
    sleeve = np.zeros(nb, bool)
    for side in ("l", "r"):
        sh, el = J[B[f"upper_arm_{side}"]], J[B[f"forearm_{side}"]]
        axis = el - sh
        s = (X[:nb] - sh) @ axis / (axis @ axis)
        sleeve |= (dom == B[f"upper_arm_{side}"]) & (s < 0.45)
    tshirt = (torso | sleeve) & (y < J[B["neck"], 1] - 0.015) & (y > hipline - 0.02)
    # trousers: below the waist to above the ankle, legs and pelvis
    legs = np.isin(dom, [B["thigh_l"], B["thigh_r"], B["shin_l"], B["shin_r"], B["pelvis"], B["spine"]])
    trousers = legs & (y < navel_y - 0.02) & (y > J[B["foot_l"], 1] + 0.04)
    out = {"tshirt": _region(model, tshirt, "tshirt"), "trousers": _region(model, trousers, "trousers")}
    out["skirt"] = DemoGarment("skirt", skirt_faces(SKIRT["rings"], SKIRT["angles"]))
    return out


def skirt_faces(rings: int, angles: int) -> np.ndarray:
    """Triangles (F, 3) between consecutive rings of ``angles`` vertices (outward facing)."""
    r, a = np.meshgrid(np.arange(rings - 1), np.arange(angles), indexing="ij")
    i0 = (r * angles + a).reshape(-1)
    i1 = (r * angles + (a + 1) % angles).reshape(-1)
    return np.concatenate([np.stack([i0, i1 + angles, i1], 1), np.stack([i0, i0 + angles, i1 + angles], 1)]).astype(np.int32)


def _ray_hull(hull: np.ndarray, center: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance from ``center`` to a convex polygon's boundary along unit ``dirs`` (A, 2)."""
    p = hull - center
    q = np.roll(p, -1, axis=0)
    e = q - p  # edges (H, 2)
    # solve center + t d = p + s e for each direction and edge
    det = dirs[:, None, 0] * (-e[None, :, 1]) - dirs[:, None, 1] * (-e[None, :, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (p[None, :, 0] * (-e[None, :, 1]) - p[None, :, 1] * (-e[None, :, 0])) / det
        s = (dirs[:, None, 0] * p[None, :, 1] - dirs[:, None, 1] * p[None, :, 0]) / det
    ok = (s >= -1e-9) & (s <= 1 + 1e-9) & (t > 0) & np.isfinite(t)
    return np.where(ok, t, np.inf).min(axis=1)


def skirt_rings(model, X: np.ndarray, rings: int | None = None, angles: int | None = None) -> np.ndarray:
    """The skirt on an avatar (V, 3): (rings x angles, 3).

    Rings run from the waist (below the navel) to the hem (above the knee) around a vertical
    axis between the hip joints. Between waist and hip a ring's radius blends the
    waist and hip sections' convex hulls; below the hip it is the hip hull flared linearly (an
    A-line hangs from the hip; it does not follow the thighs in)."""
    spec = model.measurement_spec
    J = model.joints(X)
    waist_y = X[spec.navel, 1] - SKIRT["waist_below_navel"]
    hem_y = J[B["shin_l"], 1] + SKIRT["hem_above_knee"]
    f = M.HIP_LEVEL_FRACTION
    hip_y = (1 - f) * X[spec.crotch, 1] + f * X[spec.navel, 1]
    R, A = rings or SKIRT["rings"], angles or SKIRT["angles"]
    ang = np.linspace(0, 2 * np.pi, A, endpoint=False)
    dirs = np.stack([np.sin(ang), np.cos(ang)], axis=1)  # (x, z); angle 0 = front

    def hull_at(level):
        pts, *_ = M.plane_section(X, spec.torso_edges, M.Y, float(level))
        p2 = pts[:, [0, 2]]
        return p2[ConvexHull(p2).vertices]

    hip_hull = hull_at(hip_y)
    # axis through the midpoint of the hip joints: linear in the vertices, so the skirt moves
    # smoothly with the body (a mean of hull vertices jumps when the hull changes)
    center = 0.5 * (J[B["thigh_l"], [0, 2]] + J[B["thigh_r"], [0, 2]])
    r_hip = _ray_hull(hip_hull, center, dirs)
    r_waist = _ray_hull(hull_at(waist_y), center, dirs)
    # below the hip it hangs from the wider of the hip and upper-thigh sections
    r_hang = np.maximum(r_hip, _ray_hull(hull_at(X[spec.crotch, 1] + SKIRT["thigh_above_crotch"]), center, dirs))
    levels = np.linspace(waist_y, hem_y, R)
    out = np.zeros((R, A, 3))
    for k, lv in enumerate(levels):
        if lv >= hip_y:
            t = (waist_y - lv) / (waist_y - hip_y)
            r = (1 - t) * r_waist + t * r_hip + SKIRT["ease_top"]
        else:
            u = (hip_y - lv) / (hip_y - hem_y)
            r = (1 - u) * r_hip + u * r_hang * (1 + SKIRT["flare"]) + SKIRT["ease_top"] \
                + u * (SKIRT["ease_hem"] - SKIRT["ease_top"])
        out[k, :, 0] = center[0] + r * dirs[:, 0]
        out[k, :, 2] = center[1] + r * dirs[:, 1]
        out[k, :, 1] = lv
    return out.reshape(-1, 3)

"""MakeHuman ``.mhclo`` garments: parse the binding and fit the garment to any avatar.

Each garment vertex is bound to three hm08 base-mesh vertices (helper geometry included):
``i1 i2 i3 w1 w2 w3 dx dy dz``, position = sum_k w_k B[i_k] + (dx sx, dy sy, dz sz), where the
per-axis scales s = (current distance / reference distance) of the ``x_scale``/``y_scale``/
``z_scale`` vertex pairs. Files are in decimetres, Y up, facing +Z: the same axes as our frame,
so only the unit differs (offsets x 0.1 m; distances measured on the avatar in metres).

Shapes: avatar vertices (V, 3) metres (all 19,158 hm08 vertices); garment (M, 3).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.model.formats.obj_io import ObjError, read_obj

DM = 0.1  # metres per decimetre
# The hm08 ``helper-tights`` vertices [start, stop): MakeHuman's surface of skin-tight clothing,
# which suits and shoes bind to (kept in the body model; the garment auto-fit follows it too).
HELPER_TIGHTS = (15328, 17976)
MAX_BYTES = 8 * 1024 * 1024


class MhcloError(ValueError):
    """A malformed or unusable ``.mhclo``/``.obj`` pair."""


@dataclass
class Binding:
    """indices (M, 3) int, weights (M, 3), offsets (M, 3) decimetres, scale pairs per axis
    ((a, b, reference distance dm) x 3), name."""

    indices: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray
    scales: list[tuple[int, int, float]]
    name: str

    def axis_scales(self, vertices: np.ndarray) -> np.ndarray:
        """(3,) per-axis offset scales on an avatar (V, 3) metres: current / reference distance."""
        X = np.asarray(vertices, np.float64)
        return np.array([abs(X[a, ax] - X[b, ax]) / (ref * DM) for ax, (a, b, ref) in enumerate(self.scales)])

    def fit(self, vertices: np.ndarray) -> np.ndarray:
        """The garment on an avatar: (M, 3) float64 metres."""
        X = np.asarray(vertices, np.float64)
        return np.einsum("mk,mkd->md", self.weights, X[self.indices]) + self.offsets * DM * self.axis_scales(X)


def parse_mhclo(text: str, n_base_vertices: int) -> Binding:
    """Parse an ``.mhclo`` file. Keyword lines may follow ``verts 0`` (MakeHuman's shoes02)."""
    scales: dict[str, tuple[int, int, float]] = {}
    rows: list[list[float]] = []
    name = "garment"
    in_verts = False
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        key = parts[0]
        if key in ("x_scale", "y_scale", "z_scale") and len(parts) == 4:
            try:
                scales[key] = (int(parts[1]), int(parts[2]), float(parts[3]))
            except ValueError as e:
                raise MhcloError(f"bad {key} line: {line!r}") from e
            continue
        if key == "name" and len(parts) > 1:
            name = " ".join(parts[1:])
            continue
        if key == "verts":
            in_verts = True
            continue
        if key in ("delete_verts", "faces", "weights"):
            in_verts = False
            continue
        if in_verts:
            try:
                nums = [float(p) for p in parts]
            except ValueError:
                continue  # keyword lines among the bindings (shoes02.mhclo)
            if len(nums) == 9:
                rows.append(nums)
            elif len(nums) == 1:
                rows.append([nums[0], nums[0], nums[0], 1, 0, 0, 0, 0, 0])
            else:
                raise MhcloError(f"binding line has {len(nums)} numbers, expected 9: {line!r}")
    if not rows:
        raise MhcloError("no vertex bindings found (expected a 'verts 0' section)")
    missing = {"x_scale", "y_scale", "z_scale"} - set(scales)
    if missing:
        raise MhcloError(f"missing {', '.join(sorted(missing))}")
    A = np.array(rows)
    idx = A[:, :3].astype(np.int64)
    if not np.all(np.isfinite(A)):
        raise MhcloError("non-finite numbers in the binding")
    if idx.min() < 0 or idx.max() >= n_base_vertices:
        raise MhcloError(f"binding refers to vertex {int(idx.max())}; the base mesh has {n_base_vertices}")
    for key, (a, b, ref) in scales.items():
        if not (0 <= a < n_base_vertices and 0 <= b < n_base_vertices) or ref <= 0:
            raise MhcloError(f"bad {key} reference")
    return Binding(idx, A[:, 3:6], A[:, 6:9], [scales["x_scale"], scales["y_scale"], scales["z_scale"]], name)


@dataclass
class ObjMesh:
    """An OBJ's topology: n_vertices, faces (F, 3) int64 (polygons fanned from their first
    corner), and, when every face corner names a texture vertex, face_uv (F, 3) int64 (the
    corners' ``vt`` indices, same fan) into uv (T, 2) float64 (OBJ convention: origin bottom-left;
    glTF's is top-left, v' = 1 - v); else both None."""

    n_vertices: int
    faces: np.ndarray
    face_uv: np.ndarray | None = None
    uv: np.ndarray | None = None


def parse_obj(text: str) -> ObjMesh:
    """Vertex count, triangulated faces and per-corner texture coordinates of an OBJ (the
    project's OBJ reader, :func:`service.model.formats.obj_io.read_obj`)."""
    try:
        mesh = read_obj(text.encode("utf-8", errors="surrogateescape"), uv=True)
    except ObjError as e:
        raise MhcloError(str(e)) from e
    if len(mesh.vertices) == 0 or len(mesh.faces) == 0:
        raise MhcloError("the OBJ has no vertices or no faces")
    if mesh.uv is not None and not np.all(np.isfinite(mesh.uv)):
        raise MhcloError("the OBJ has a non-finite texture coordinate")
    return ObjMesh(len(mesh.vertices), mesh.faces, mesh.face_uv, mesh.uv)


def parse_obj_faces(text: str) -> tuple[int, np.ndarray]:
    """Vertex count and triangulated faces (F, 3) of an OBJ (quads and polygons fanned)."""
    mesh = parse_obj(text)
    return mesh.n_vertices, mesh.faces

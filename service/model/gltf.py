"""Binary glTF 2.0 (GLB) writer and a minimal reader: pure functions over numpy arrays.

No web or 3D-library imports: numpy, json and struct only. The writer produces a single-mesh,
single-primitive GLB (POSITION, NORMAL, optional JOINTS_0/WEIGHTS_0 + skin) that the Khronos
glTF validator accepts without errors or warnings.
"""
from __future__ import annotations

import json
import struct
from typing import Any, TypedDict

import numpy as np

from service.model.geometry import vertex_normals

GLB_MAGIC = 0x46546C67  # b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

# glTF component types and buffer-view targets.
BYTE, UNSIGNED_BYTE, SHORT, UNSIGNED_SHORT, UNSIGNED_INT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
TRIANGLES = 4

_DTYPES: dict[int, np.dtype[Any]] = {
    BYTE: np.dtype("<i1"),
    UNSIGNED_BYTE: np.dtype("<u1"),
    SHORT: np.dtype("<i2"),
    UNSIGNED_SHORT: np.dtype("<u2"),
    UNSIGNED_INT: np.dtype("<u4"),
    FLOAT: np.dtype("<f4"),
}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class Skin(TypedDict):
    """Skinning data for :func:`mesh_to_glb`.

    joints: (J, 3) rest joint world positions; parents: (J,) int, -1 for a root;
    joint_names: J names; vertex_joints: (N, 4) int joint indices;
    vertex_weights: (N, 4) float weights (normalised by the writer).
    """

    joints: np.ndarray
    parents: np.ndarray
    joint_names: list[str] | tuple[str, ...]
    vertex_joints: np.ndarray
    vertex_weights: np.ndarray


def _unit_float32(n: np.ndarray) -> np.ndarray:
    """Unit vectors (N, 3) rounded to float32 and re-normalised so |n| == 1 within float32 eps."""
    n32 = n.astype(np.float32)
    norm = np.linalg.norm(n32.astype(np.float64), axis=1, keepdims=True)
    return (n32 / norm).astype(np.float32)


def _clean_skin_weights(
    joints: np.ndarray, weights: np.ndarray, n_joints: int
) -> tuple[np.ndarray, np.ndarray]:
    """Validator-clean JOINTS_0/WEIGHTS_0.

    joints: (N, 4) int, weights: (N, 4) float -> ((N, 4) int64, (N, 4) float32): negative
    weights clipped, duplicate joints merged, rows normalised to sum 1 (the rounding residue is
    put on each row's largest weight), and joint index 0 wherever the weight is 0.
    """
    j = np.asarray(joints, dtype=np.int64).copy()
    w = np.clip(np.asarray(weights, dtype=np.float64), 0.0, None).copy()
    if j.shape != w.shape or j.ndim != 2 or j.shape[1] != 4:
        raise ValueError(f"vertex_joints/vertex_weights must both be (N, 4), got {j.shape}, {w.shape}")
    if j.size and (j.min() < 0 or j.max() >= n_joints):
        raise ValueError(f"vertex_joints out of range [0, {n_joints})")
    for a in range(4):  # merge duplicate joint indices into the first occurrence
        for b in range(a + 1, 4):
            dup = (j[:, a] == j[:, b]) & (w[:, b] > 0)
            w[dup, a] += w[dup, b]
            w[dup, b] = 0.0
    total = w.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("every skinned vertex needs a positive weight")
    w = (w / total).astype(np.float32)
    # Make the float32 row sums as close to 1 as float32 allows.
    top = np.argmax(w, axis=1)
    rows = np.arange(w.shape[0])
    w[rows, top] = 0.0
    w[rows, top] = np.float32(1.0) - w.sum(axis=1, dtype=np.float32)
    j[w == 0] = 0
    return j, w


class _Builder:
    """Accumulates the binary buffer, buffer views and accessors of one GLB."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.buffer_views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(
        self,
        data: np.ndarray,
        component_type: int,
        type_: str,
        *,
        target: int | None = None,
        minmax: bool = False,
    ) -> int:
        """Append ``data`` ((count, ncomp) or (count,)) as a tightly packed, 4-byte aligned view
        plus one accessor; returns the accessor index."""
        arr = np.ascontiguousarray(data, dtype=_DTYPES[component_type])
        count = arr.shape[0]
        while len(self.blob) % 4:
            self.blob.append(0)
        view: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": arr.nbytes}
        if target is not None:
            view["target"] = target
        self.blob += arr.tobytes()
        self.buffer_views.append(view)
        acc: dict[str, Any] = {
            "bufferView": len(self.buffer_views) - 1,
            "componentType": component_type,
            "count": int(count),
            "type": type_,
        }
        if minmax:
            flat = arr.reshape(count, -1)
            cast = float if component_type == FLOAT else int
            acc["min"] = [cast(x) for x in flat.min(axis=0)]
            acc["max"] = [cast(x) for x in flat.max(axis=0)]
        self.accessors.append(acc)
        return len(self.accessors) - 1


def mesh_to_glb(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    color: tuple[float, float, float, float] = (0.8, 0.7, 0.62, 1.0),
    name: str = "avatar",
    skin: Skin | dict[str, Any] | None = None,
) -> bytes:
    """A triangle mesh as GLB 2.0 bytes.

    vertices: (N, 3) float (metres, Y up), faces: (F, 3) int (counter-clockwise = outside),
    normals: (N, 3) or None (smooth area-weighted normals are computed),
    color: linear RGBA base colour of the PBR material, name: mesh/node name,
    skin: optional :class:`Skin`; adds a joint node hierarchy (translations relative to the
    parent, identity rotations), inverse bind matrices (translation by -joint) and
    JOINTS_0/WEIGHTS_0 attributes.
    """
    v = np.asarray(vertices, dtype=np.float32)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must be (N, 3) with N > 0, got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must be (F, 3) with F > 0, got {f.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("vertices must be finite")
    n = v.shape[0]
    if f.min() < 0 or f.max() >= n:
        raise ValueError(f"face indices out of range [0, {n})")
    nrm = vertex_normals(v, f) if normals is None else _unit_float32(np.asarray(normals, np.float64))
    if nrm.shape != v.shape:
        raise ValueError(f"normals must be {v.shape}, got {nrm.shape}")

    b = _Builder()
    attributes: dict[str, int] = {
        "POSITION": b.add(v, FLOAT, "VEC3", target=ARRAY_BUFFER, minmax=True),
        "NORMAL": b.add(nrm, FLOAT, "VEC3", target=ARRAY_BUFFER),
    }
    nodes: list[dict[str, Any]] = []
    gltf_skins: list[dict[str, Any]] = []
    scene_nodes = [0]
    nodes.append({"name": name, "mesh": 0})

    if skin is not None:
        jpos = np.asarray(skin["joints"], dtype=np.float64)
        parents = np.asarray(skin["parents"], dtype=np.int64)
        names = list(skin["joint_names"])
        n_j = jpos.shape[0]
        if jpos.shape != (n_j, 3) or parents.shape != (n_j,) or len(names) != n_j or n_j == 0:
            raise ValueError("skin joints (J, 3), parents (J,) and joint_names (J) must agree")
        for i, p in enumerate(parents):
            if not (p == -1 or 0 <= p < i):
                raise ValueError("skin parents must precede their children (-1 for roots)")
        vj, vw = _clean_skin_weights(skin["vertex_joints"], skin["vertex_weights"], n_j)
        if vj.shape[0] != n:
            raise ValueError(f"skin vertex arrays must have {n} rows, got {vj.shape[0]}")
        jtype = UNSIGNED_BYTE if n_j <= 256 else UNSIGNED_SHORT
        attributes["JOINTS_0"] = b.add(vj, jtype, "VEC4", target=ARRAY_BUFFER)
        attributes["WEIGHTS_0"] = b.add(vw, FLOAT, "VEC4", target=ARRAY_BUFFER)
        ibm = np.tile(np.eye(4, dtype=np.float32), (n_j, 1, 1))
        ibm[:, 3, :3] = -jpos  # column-major storage: translation is the 4th column
        ibm_acc = b.add(ibm.reshape(n_j, 16), FLOAT, "MAT4")
        first = len(nodes)
        for i in range(n_j):
            rel = jpos[i] - (jpos[parents[i]] if parents[i] >= 0 else 0.0)
            node: dict[str, Any] = {"name": str(names[i]), "translation": [float(x) for x in rel]}
            children = [first + c for c in range(n_j) if parents[c] == i]
            if children:
                node["children"] = children
            nodes.append(node)
        roots = [first + i for i in range(n_j) if parents[i] == -1]
        scene_nodes += roots
        gltf_skins.append(
            {
                "name": f"{name}_skeleton",
                "inverseBindMatrices": ibm_acc,
                "joints": list(range(first, first + n_j)),
                "skeleton": roots[0],
            }
        )
        nodes[0]["skin"] = 0

    itype = UNSIGNED_SHORT if n < 65535 else UNSIGNED_INT
    indices = b.add(f.reshape(-1), itype, "SCALAR", target=ELEMENT_ARRAY_BUFFER)

    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "tryon service.model.gltf"},
        "scene": 0,
        "scenes": [{"name": "scene", "nodes": scene_nodes}],
        "nodes": nodes,
        "meshes": [
            {
                "name": name,
                "primitives": [
                    {"attributes": attributes, "indices": indices, "material": 0, "mode": TRIANGLES}
                ],
            }
        ],
        "materials": [
            {
                "name": f"{name}_material",
                "pbrMetallicRoughness": {
                    "baseColorFactor": [float(c) for c in color],
                    "metallicFactor": 0.0,
                    "roughnessFactor": 0.8,
                },
            }
        ],
        "accessors": b.accessors,
        "bufferViews": b.buffer_views,
        "buffers": [{"byteLength": 0}],
    }
    if gltf_skins:
        doc["skins"] = gltf_skins
    while len(b.blob) % 4:
        b.blob.append(0)
    doc["buffers"][0]["byteLength"] = len(b.blob)

    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + len(b.blob)
    out = bytearray(struct.pack("<III", GLB_MAGIC, GLB_VERSION, total))
    out += struct.pack("<II", len(js), CHUNK_JSON) + js
    out += struct.pack("<II", len(b.blob), CHUNK_BIN) + bytes(b.blob)
    return bytes(out)


def _read_accessor(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    """Accessor ``index`` as an array (count,) or (count, ncomp) of its component dtype."""
    acc = doc["accessors"][index]
    dtype = _DTYPES[acc["componentType"]]
    ncomp = _NCOMP[acc["type"]]
    count = int(acc["count"])
    view = doc["bufferViews"][acc["bufferView"]]
    start = int(view.get("byteOffset", 0)) + int(acc.get("byteOffset", 0))
    elem = dtype.itemsize * ncomp
    stride = int(view.get("byteStride", elem))
    if count == 0:
        return np.zeros((0, ncomp) if ncomp > 1 else (0,), dtype)
    raw = np.frombuffer(blob, np.uint8, count=(count - 1) * stride + elem, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, elem), strides=(stride, 1))
    arr = np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)
    return arr[:, 0] if ncomp == 1 else arr


def read_glb(data: bytes) -> dict[str, Any]:
    """Minimal GLB reader (first mesh, first primitive), for round-trip tests.

    Returns ``{"json": dict, "positions": (N, 3) float32, "indices": (F, 3) int64,
    "normals": (N, 3) float32 | None, "joints": (N, 4) | None, "weights": (N, 4) | None}``.
    """
    if len(data) < 20:
        raise ValueError("not a GLB: too short")
    magic, version, length = struct.unpack_from("<III", data, 0)
    if magic != GLB_MAGIC or version != 2 or length != len(data):
        raise ValueError("not a GLB 2.0 file (bad header)")
    doc: dict[str, Any] | None = None
    blob = b""
    pos = 12
    while pos + 8 <= length:
        clen, ctype = struct.unpack_from("<II", data, pos)
        chunk = data[pos + 8 : pos + 8 + clen]
        if ctype == CHUNK_JSON:
            doc = json.loads(chunk.decode("utf-8"))
        elif ctype == CHUNK_BIN:
            blob = bytes(chunk)
        pos += 8 + clen
    if doc is None:
        raise ValueError("GLB has no JSON chunk")
    prim = doc["meshes"][0]["primitives"][0]
    attrs = prim["attributes"]

    def opt(key: str) -> np.ndarray | None:
        return _read_accessor(doc, blob, attrs[key]) if key in attrs else None

    positions = _read_accessor(doc, blob, attrs["POSITION"])
    if "indices" in prim:
        indices = _read_accessor(doc, blob, prim["indices"]).astype(np.int64).reshape(-1, 3)
    else:
        indices = np.arange(positions.shape[0], dtype=np.int64).reshape(-1, 3)
    return {
        "json": doc,
        "positions": positions,
        "indices": indices,
        "normals": opt("NORMAL"),
        "joints": opt("JOINTS_0"),
        "weights": opt("WEIGHTS_0"),
    }

"""A minimal binary glTF 2.0 (GLB) reader: the meshes of a GLB (positions, faces, normals, texture
coordinates, skins) in world coordinates, quantised and normalised accessors decoded. numpy,
json and struct only.
"""
from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from service.model.formats.gltf_buffers import (
    _DTYPES,
    _mo,
    _NCOMP,
    BYTE,
    CHUNK_BIN,
    CHUNK_JSON,
    FLOAT,
    GLB_MAGIC,
    SHORT,
    UNSIGNED_BYTE,
    UNSIGNED_SHORT,
)


# ----------------------------------------------------------------------------------- reading


def _parse_glb(data: bytes) -> tuple[dict[str, Any], bytes]:
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
    return doc, blob


def _view_bytes(doc: dict[str, Any], blob: bytes, index: int) -> bytes:
    """Bytes of bufferView ``index`` (GLB buffer 0), decoding EXT_meshopt_compression."""
    view = doc["bufferViews"][index]
    ext = view.get("extensions", {}).get("EXT_meshopt_compression")
    if ext is not None:
        if int(ext.get("buffer", 0)) != 0:
            raise ValueError("only GLB-stored (buffer 0) meshopt data can be read")
        off = int(ext.get("byteOffset", 0))
        src = blob[off : off + int(ext["byteLength"])]
        count, size = int(ext["count"]), int(ext["byteStride"])
        filt = ext.get("filter", "NONE")
        raw = _mo().decode_gltf_buffer(src, count, size, ext.get("mode", "ATTRIBUTES"), filt)
        return np.ascontiguousarray(raw).tobytes()
    if int(view.get("buffer", 0)) != 0:
        raise ValueError("only GLB-stored (buffer 0) data can be read")
    off = int(view.get("byteOffset", 0))
    return blob[off : off + int(view["byteLength"])]


def _read_accessor(doc: dict[str, Any], blob: bytes, index: int, plain: bool = False) -> np.ndarray:
    """Accessor ``index`` as an array (count,) or (count, ncomp) of its component dtype
    (raw stored values; meshopt-encoded views are decoded; sparse values substituted, over
    zeros when the accessor has no view)."""
    acc = doc["accessors"][index]
    dtype = _DTYPES[acc["componentType"]]
    ncomp = _NCOMP[acc["type"]]
    count = int(acc["count"])
    if not plain and ("bufferView" not in acc or "sparse" in acc):
        dense = np.zeros((count, ncomp), dtype)
        if "bufferView" in acc:
            dense[:] = _read_accessor(doc, blob, index, plain=True).reshape(count, ncomp)
        sp_ = acc.get("sparse")
        if sp_ is not None:
            k = int(sp_["count"])
            itype = _DTYPES[sp_["indices"]["componentType"]]
            ib = _view_bytes(doc, blob, sp_["indices"]["bufferView"])
            vb = _view_bytes(doc, blob, sp_["values"]["bufferView"])
            idx = np.frombuffer(ib, itype, count=k, offset=int(sp_["indices"].get("byteOffset", 0)))
            vals = np.frombuffer(vb, dtype, count=k * ncomp, offset=int(sp_["values"].get("byteOffset", 0)))
            dense[idx.astype(np.int64)] = vals.reshape(k, ncomp)
        return dense[:, 0] if ncomp == 1 else dense
    view = doc["bufferViews"][acc["bufferView"]]
    data = _view_bytes(doc, blob, acc["bufferView"])
    start = int(acc.get("byteOffset", 0))
    elem = dtype.itemsize * ncomp
    stride = int(view.get("byteStride", elem))
    if count == 0:
        return np.zeros((0, ncomp) if ncomp > 1 else (0,), dtype)
    raw = np.frombuffer(data, np.uint8, count=(count - 1) * stride + elem, offset=start)
    rows = np.lib.stride_tricks.as_strided(raw, shape=(count, elem), strides=(stride, 1))
    arr = np.ascontiguousarray(rows).view(dtype).reshape(count, ncomp)
    return arr[:, 0] if ncomp == 1 else arr


_NORM_DIV = {BYTE: 127.0, UNSIGNED_BYTE: 255.0, SHORT: 32767.0, UNSIGNED_SHORT: 65535.0}


def _read_float(doc: dict[str, Any], blob: bytes, index: int) -> np.ndarray:
    """Accessor ``index`` as float64, normalized integers mapped to [-1, 1] / [0, 1]."""
    acc = doc["accessors"][index]
    arr = _read_accessor(doc, blob, index).astype(np.float64)
    if acc.get("normalized"):
        arr = np.maximum(arr / _NORM_DIV[acc["componentType"]], -1.0)
    return arr


def _quat_matrix(q: list[float]) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _world_matrices(doc: dict[str, Any]) -> list[np.ndarray]:
    """Each node's rest world matrix (4, 4)."""
    nodes = doc.get("nodes", [])
    local = []
    for nd in nodes:
        if "matrix" in nd:
            mat = np.array(nd["matrix"], np.float64).reshape(4, 4).T
        else:
            mat = np.eye(4)
            mat[:3, :3] = _quat_matrix(nd.get("rotation", [0, 0, 0, 1])) * np.array(nd.get("scale", [1, 1, 1]))
            mat[:3, 3] = nd.get("translation", [0, 0, 0])
        local.append(mat)
    parent = [-1] * len(nodes)
    for i, nd in enumerate(nodes):
        for c in nd.get("children", []):
            parent[c] = i
    world: list[np.ndarray | None] = [None] * len(nodes)

    def get(i: int) -> np.ndarray:
        if world[i] is None:
            world[i] = local[i] if parent[i] < 0 else get(parent[i]) @ local[i]
        return world[i]  # type: ignore[return-value]

    return [get(i) for i in range(len(nodes))]


def _read_mesh(doc: dict[str, Any], blob: bytes, mi: int, world: list[np.ndarray]) -> dict[str, Any]:
    gm = doc["meshes"][mi]
    prim = gm["primitives"][0]
    attrs = prim["attributes"]
    pos_acc = doc["accessors"][attrs["POSITION"]]
    positions = _read_float(doc, blob, attrs["POSITION"])
    # Quantized positions are dequantized by the mesh node's transform or, when skinned, by the
    # skin's bind (world(joint) @ IBM is that transform for a skeleton at rest).
    deq = np.eye(4)
    quantized = pos_acc["componentType"] != FLOAT
    if quantized:
        ni = next((i for i, nd in enumerate(doc.get("nodes", [])) if nd.get("mesh") == mi), None)
        if ni is not None:
            nd = doc["nodes"][ni]
            if "skin" in nd:
                sk = doc["skins"][nd["skin"]]
                ibm = _read_float(doc, blob, sk["inverseBindMatrices"])[0].reshape(4, 4).T
                deq = world[sk["joints"][0]] @ ibm
            else:
                deq = world[ni]
        positions = positions @ deq[:3, :3].T + deq[:3, 3]

    def opt(key: str) -> np.ndarray | None:
        return _read_accessor(doc, blob, attrs[key]) if key in attrs else None

    normals = None
    if "NORMAL" in attrs:
        normals = _read_float(doc, blob, attrs["NORMAL"])
        if doc["accessors"][attrs["NORMAL"]]["componentType"] != FLOAT:
            normals = normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
        normals = normals.astype(np.float32)
    uv = None
    if "TEXCOORD_0" in attrs:
        uv = _read_float(doc, blob, attrs["TEXCOORD_0"]).astype(np.float32)
    tangents = None
    if "TANGENT" in attrs:
        tangents = _read_float(doc, blob, attrs["TANGENT"]).astype(np.float32)
    weights = None
    if "WEIGHTS_0" in attrs:
        weights = _read_float(doc, blob, attrs["WEIGHTS_0"]).astype(np.float32)
    targets = []
    for tg in prim.get("targets", []):
        d = _read_float(doc, blob, tg["POSITION"])
        if quantized:
            d = d @ deq[:3, :3].T
        targets.append(d.astype(np.float32))
    if "indices" in prim:
        indices = _read_accessor(doc, blob, prim["indices"]).astype(np.int64).reshape(-1, 3)
    else:
        indices = np.arange(positions.shape[0], dtype=np.int64).reshape(-1, 3)
    return {
        "name": gm.get("name"),
        "positions": positions.astype(np.float32),
        "indices": indices,
        "normals": normals,
        "uv": uv,
        "tangents": tangents,
        "joints": opt("JOINTS_0"),
        "weights": weights,
        "targets": np.stack(targets) if targets else None,
        "target_names": gm.get("extras", {}).get("targetNames"),
        "morph_weights": gm.get("weights"),
        "material": prim.get("material"),
    }


def read_glb(data: bytes) -> dict[str, Any]:
    """Minimal GLB reader (first primitive of each mesh), for round-trip tests.

    Returns the first mesh's ``{"positions": (N, 3) float32, "indices": (F, 3) int64,
    "normals": (N, 3) float32 | None, "uv": (N, 2) float32 TEXCOORD_0 | None, "tangents": (N, 4)
    float32 | None, "joints": (N, 4) | None, "weights": (N, 4) float32 | None,
    "targets": (K, N, 3) float32 morph POSITION deltas | None, "target_names", "morph_weights",
    "name", "material"}`` plus ``"json"`` (the glTF document) and ``"meshes"`` (that dict for
    every mesh) and ``"images"`` (``{"name", "mime", "data"}`` of each embedded image, in
    ``images`` order). KHR_mesh_quantization data is dequantized (positions and deltas back in the
    writer's units, normalized normals/weights as floats); EXT_meshopt_compression views are
    decoded with the ``meshopt`` package.
    """
    doc, blob = _parse_glb(data)
    world = _world_matrices(doc)
    meshes = [_read_mesh(doc, blob, i, world) for i in range(len(doc.get("meshes", [])))]
    if not meshes:
        raise ValueError("GLB has no mesh")
    images = [{"name": im.get("name"), "mime": im.get("mimeType"), "data": _view_bytes(doc, blob, im["bufferView"])}
              for im in doc.get("images", []) if "bufferView" in im]
    return {"json": doc, **meshes[0], "meshes": meshes, "images": images}

"""glTF 2.0 building blocks shared by the GLB writer (``gltf``) and reader (``gltf_read``): the
format's constants, vertex attributes as glTF stores them (tangents, quantised normals and skin
weights), buffer views (optionally meshopt-compressed) and the GLB container builder.
numpy, json and struct only.
"""
from __future__ import annotations

from typing import Any, TypedDict

import numpy as np

from service.model.geometry.mesh import row_dot

GLB_MAGIC = 0x46546C67  # b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942

# glTF component types and buffer-view targets.
BYTE, UNSIGNED_BYTE, SHORT, UNSIGNED_SHORT, UNSIGNED_INT, FLOAT = 5120, 5121, 5122, 5123, 5125, 5126
ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963
TRIANGLES = 4
LINEAR, LINEAR_MIPMAP_LINEAR, REPEAT = 9729, 9987, 10497
IMAGE_MIMES = ("image/png", "image/jpeg")

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
    n64 = np.asarray(n, np.float32).astype(np.float64)  # the float32 rounding first
    return (n64 / np.sqrt(row_dot(n64, n64))[:, None]).astype(np.float32)


def vertex_tangents(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """glTF TANGENT (N, 4) float32 of a UV-mapped mesh: xyz unit and orthogonal to the normal,
    w = +/-1 the handedness (bitangent = w * cross(normal, tangent)).

    vertices (N, 3), faces (F, 3), uv (N, 2) in glTF convention (origin top-left), normals (N, 3)
    unit. Per face, the tangent dP/du and bitangent dP/dv' (v' = 1 - v: the normal map's +Y is
    image up, MikkTSpace's and Blender's convention) from the UV edge system (Lengyel, "Computing
    Tangent Space Basis Vectors for an Arbitrary Mesh", 2001), summed per vertex, Gram-Schmidt
    orthogonalised against the normal. Vertices whose faces have no usable UV area get an
    arbitrary tangent perpendicular to the normal."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    t = np.asarray(uv, np.float64)
    n = np.asarray(normals, np.float64)
    e1 = v[f[:, 1]] - v[f[:, 0]]
    e2 = v[f[:, 2]] - v[f[:, 0]]
    d1 = t[f[:, 1]] - t[f[:, 0]]
    d2 = t[f[:, 2]] - t[f[:, 0]]
    d1[:, 1] *= -1.0  # v' = 1 - v
    d2[:, 1] *= -1.0
    r = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(r) > 1e-20
    inv = np.where(ok, 1.0 / np.where(ok, r, 1.0), 0.0)[:, None]
    ft = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) * inv
    fb = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) * inv
    N = v.shape[0]
    idx = f.reshape(-1)
    tan = np.stack([np.bincount(idx, np.repeat(ft[:, k], 3), N) for k in range(3)], axis=1)
    bit = np.stack([np.bincount(idx, np.repeat(fb[:, k], 3), N) for k in range(3)], axis=1)
    tan -= n * np.einsum("ij,ij->i", n, tan)[:, None]
    norm = np.linalg.norm(tan, axis=1)
    bad = norm < 1e-12
    if np.any(bad):  # any unit vector perpendicular to the normal
        nb = n[bad]
        axis = np.where(np.abs(nb[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
        alt = axis - nb * np.einsum("ij,ij->i", nb, axis)[:, None]
        tan[bad] = alt
        norm[bad] = np.linalg.norm(alt, axis=1)
    tan /= norm[:, None]
    w = np.where(np.einsum("ij,ij->i", np.cross(n, tan), bit) < 0.0, -1.0, 1.0)
    out = np.empty((N, 4), np.float32)
    out[:, :3] = _unit_float32(tan)
    out[:, 3] = w
    return out


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


def _quantize_weights(w: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Float weights (N, 4) summing to 1 -> (N, 4) uint8 summing to exactly 255 (largest
    remainder rounding), with joint index 0 wherever a quantized weight is 0."""
    scaled = np.asarray(w, np.float64) * 255.0
    q = np.floor(scaled).astype(np.int64)
    short = 255 - q.sum(axis=1)
    order = np.argsort(-(scaled - q), axis=1, kind="stable")
    for k in range(4):  # hand out the missing units to the largest remainders
        give = short > k
        rows = np.nonzero(give)[0]
        q[rows, order[rows, k]] += 1
    j = np.asarray(j, np.int64).copy()
    j[q == 0] = 0
    return q.astype(np.uint8), j


def _quantize_normals(n: np.ndarray) -> np.ndarray:
    """Unit normals (N, 3) -> (N, 3) int8 (normalized BYTE, value / 127)."""
    return np.clip(np.round(np.asarray(n, np.float64) * 127.0), -127, 127).astype(np.int8)


def _bounds(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column minima and maxima ((ncomp,), (ncomp,)) of rows (count, ncomp), NaN propagating.
    Through a transposed copy: numpy's axis-0 reduction over 3-wide rows is ~40x slower."""
    t = np.ascontiguousarray(a.T)
    return t.min(axis=1), t.max(axis=1)


def _pad_rows(arr: np.ndarray) -> np.ndarray:
    """(count, ncomp) -> (count, k) with zero columns appended so each row is a multiple of 4
    bytes (glTF's vertex attribute alignment rule; KHR_mesh_quantization's SHORT/BYTE VEC3)."""
    per = arr.dtype.itemsize * arr.shape[1]
    if per % 4 == 0:
        return arr
    extra = (-per % 4) // arr.dtype.itemsize
    return np.concatenate([arr, np.zeros((arr.shape[0], extra), arr.dtype)], axis=1)


# One bufferView before layout: (raw bytes, element count, target, meshopt mode, byteStride).
View = tuple[bytes, int, "int | None", "str | None", "int | None"]


def _make_view(
    data: np.ndarray,
    component_type: int,
    type_: str,
    *,
    target: int | None = None,
    minmax: bool = False,
    normalized: bool = False,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[View, dict[str, Any]]:
    """``data`` ((count, ncomp) or (count,)) as a tightly packed view and its accessor (without
    ``bufferView``). Vertex attribute rows that are not a multiple of 4 bytes are zero padded
    (the view then gets a byteStride). ``minmax``: the accessor gets min/max, ``bounds`` when
    given (the caller knows them: (ncomp,) each), else computed."""
    arr = np.ascontiguousarray(data, dtype=_DTYPES[component_type])
    count = arr.shape[0]
    flat = arr.reshape(count, -1)
    stride: int | None = None
    stored = arr
    if target == ARRAY_BUFFER and (flat.shape[1] * arr.dtype.itemsize) % 4:
        stored = _pad_rows(flat)
        stride = stored.shape[1] * arr.dtype.itemsize
    mode = None
    if target == ARRAY_BUFFER:
        mode = "ATTRIBUTES"
    elif target == ELEMENT_ARRAY_BUFFER and count % 3 == 0:
        mode = "TRIANGLES"
    acc: dict[str, Any] = {"componentType": component_type, "count": int(count), "type": type_}
    if normalized:
        acc["normalized"] = True
    if minmax:
        cast = float if component_type == FLOAT else int
        lo, hi = bounds if bounds is not None else _bounds(flat)
        acc["min"] = [cast(x) for x in lo]
        acc["max"] = [cast(x) for x in hi]
    return (np.ascontiguousarray(stored).tobytes(), count, target, mode, stride), acc


def _meshopt_encode(view: View) -> bytes:
    """The EXT_meshopt_compression bytes of a vertex-attribute or triangle-index view."""
    raw, count, _target, mode, _stride = view
    elem = len(raw) // count
    if mode == "ATTRIBUTES":
        return bytes(_mo().encode_gltf_buffer(np.frombuffer(raw, np.uint8).reshape(count, elem), mode))
    idx = np.frombuffer(raw, np.uint16 if elem == 2 else np.uint32)
    return bytes(_mo().encode_gltf_buffer(idx.astype(np.uint32), mode))


class _Builder:
    """Accumulates the buffer views and accessors of one GLB; :meth:`finish` lays out the binary
    buffer, plain or with meshoptimizer-encoded views (EXT_meshopt_compression)."""

    def __init__(self) -> None:
        self.views: list[View] = []
        self.encoded: list[bytes | None] = []  # meshopt bytes known in advance (static views)
        self.buffer_views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def add(self, data: np.ndarray, component_type: int, type_: str, **options: Any) -> int:
        """Append ``data`` as one view plus one accessor (:func:`_make_view`, whose keyword
        options ``target``, ``minmax``, ``normalized``, ``bounds`` it takes); returns the
        accessor index."""
        return self.add_view(*_make_view(data, component_type, type_, **options))

    def add_view(self, view: View, acc: dict[str, Any], encoded: bytes | None = None) -> int:
        """Append a view made by :func:`_make_view` (and, optionally, its meshopt bytes) plus
        a copy of its accessor; returns the accessor index."""
        self.views.append(view)
        self.encoded.append(encoded)
        self.accessors.append({"bufferView": len(self.views) - 1, **acc})
        return len(self.accessors) - 1

    def add_sparse(self, data: np.ndarray, component_type: int, type_: str) -> int:
        """Append ``data`` (count, ncomp) as a sparse accessor over zeros: only its non-zero rows
        are stored (UNSIGNED_SHORT/INT indices and their values, two views with no target), min
        and max over all rows; no rows at all: an accessor without a view (all zeros). For
        morph deltas that move a few vertices. Returns the accessor index."""
        arr = np.ascontiguousarray(data, dtype=_DTYPES[component_type])
        count, flat = arr.shape[0], arr.reshape(arr.shape[0], -1)
        rows = np.flatnonzero(np.any(flat != 0, axis=1))
        cast = float if component_type == FLOAT else int
        lo, hi = _bounds(flat[rows]) if len(rows) else (np.zeros(flat.shape[1]), np.zeros(flat.shape[1]))
        if len(rows) < count:  # the rows left out are zeros
            lo, hi = np.minimum(lo, 0), np.maximum(hi, 0)
        acc: dict[str, Any] = {"componentType": component_type, "count": int(count), "type": type_,
                               "min": [cast(x) for x in lo], "max": [cast(x) for x in hi]}
        if len(rows):
            itype = UNSIGNED_SHORT if count <= 65535 else UNSIGNED_INT
            views = []
            for a in (rows.astype(_DTYPES[itype]), flat[rows]):
                raw = np.ascontiguousarray(a).tobytes()
                self.views.append((raw, len(rows), None, None, None))
                self.encoded.append(None)
                views.append(len(self.views) - 1)
            acc["sparse"] = {"count": int(len(rows)), "indices": {"bufferView": views[0], "componentType": itype},
                             "values": {"bufferView": views[1]}}
        self.accessors.append(acc)
        return len(self.accessors) - 1

    def add_bytes(self, raw: bytes) -> int:
        """Append opaque bytes (an encoded image) as a bufferView with no target, never
        meshopt-encoded; returns the bufferView index."""
        self.views.append((raw, len(raw), None, None, None))
        self.encoded.append(None)
        return len(self.views) - 1

    def finish(self, meshopt: bool) -> tuple[list[bytes], int, list[dict[str, Any]]]:
        """(the BIN chunk's pieces, their total length, the ``buffers`` array); fills
        :attr:`buffer_views`. Pieces, not one buffer: the GLB is joined once (one copy)."""
        parts: list[bytes] = []
        size = 0
        fallback_len = 0
        self.buffer_views = []
        for (raw, count, target, mode, stride), known in zip(self.views, self.encoded):
            if size % 4:
                parts.append(b"\0" * (-size % 4))
                size += -size % 4
            view: dict[str, Any] = {"buffer": 0, "byteOffset": size, "byteLength": len(raw)}
            if meshopt and mode is not None:
                elem = len(raw) // count
                enc = known if known is not None else _meshopt_encode((raw, count, target, mode, stride))
                # The bufferView itself points into the (data-less) fallback buffer 1.
                view = {"buffer": 1, "byteOffset": fallback_len, "byteLength": len(raw)}
                fallback_len += len(raw) + (-len(raw) % 4)
                view["extensions"] = {
                    "EXT_meshopt_compression": {
                        "buffer": 0,
                        "byteOffset": size,
                        "byteLength": len(enc),
                        "byteStride": elem,
                        "count": int(count),
                        "mode": mode,
                    }
                }
                parts.append(enc)
                size += len(enc)
            else:
                parts.append(raw)
                size += len(raw)
            if stride is not None:
                view["byteStride"] = stride
            if target is not None:
                view["target"] = target
            self.buffer_views.append(view)
        if size % 4:
            parts.append(b"\0" * (-size % 4))
            size += -size % 4
        buffers: list[dict[str, Any]] = [{"byteLength": size}]
        if meshopt:
            buffers.append(
                {"byteLength": max(fallback_len, 4), "extensions": {"EXT_meshopt_compression": {"fallback": True}}}
            )
        return parts, size, buffers


def _mo() -> Any:
    """The ``meshopt`` module (meshoptimizer's codecs), imported on first use."""
    try:
        import meshopt
    except ImportError as e:  # pragma: no cover - it is a declared dependency
        raise RuntimeError("compression='meshopt' needs the `meshopt` Python package") from e
    return meshopt

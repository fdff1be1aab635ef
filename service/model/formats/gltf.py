"""Binary glTF 2.0 (GLB) writer: pure functions over numpy arrays (the reader: ``gltf_read``).

No web or 3D-library imports: numpy, json and struct only. The writer produces a single-mesh,
single-primitive GLB (POSITION, NORMAL, optional TEXCOORD_0/TANGENT, JOINTS_0/WEIGHTS_0 + skin,
PBR materials with embedded base-colour/normal textures) that the Khronos glTF validator accepts
without errors or warnings.
"""

from __future__ import annotations

import json
import struct
from typing import Any

import numpy as np

from service.model.geometry.mesh import vertex_normals
from service.model.formats.gltf_buffers import (
    _bounds,
    _Builder,
    _clean_skin_weights,
    _make_view,
    _meshopt_encode,
    _quantize_normals,
    _quantize_weights,
    _unit_float32,
    ARRAY_BUFFER,
    BYTE,
    CHUNK_BIN,
    CHUNK_JSON,
    ELEMENT_ARRAY_BUFFER,
    FLOAT,
    GLB_MAGIC,
    GLB_VERSION,
    IMAGE_MIMES,
    LINEAR,
    LINEAR_MIPMAP_LINEAR,
    REPEAT,
    SHORT,
    Skin,
    TRIANGLES,
    UNSIGNED_BYTE,
    UNSIGNED_INT,
    UNSIGNED_SHORT,
    vertex_tangents,
    View,
)


COMPRESSIONS = (None, "quantize", "meshopt")
DEFAULT_COLOR = (0.8, 0.7, 0.62, 1.0)


def _check_compression(compression: str | None) -> None:
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")


def _check_skeleton(skin: dict[str, Any]) -> tuple[np.ndarray, np.ndarray, list[str]]:
    jpos = np.asarray(skin["joints"], dtype=np.float64)
    parents = np.asarray(skin["parents"], dtype=np.int64)
    names = [str(x) for x in skin["joint_names"]]
    n_j = jpos.shape[0] if jpos.ndim == 2 else 0
    if jpos.shape != (n_j, 3) or parents.shape != (n_j,) or len(names) != n_j or n_j == 0:
        raise ValueError("skin joints (J, 3), parents (J,) and joint_names (J) must agree")
    if not np.all(np.isfinite(jpos)):
        raise ValueError("skin joints must be finite")
    for i, p in enumerate(parents):
        if not (p == -1 or 0 <= p < i):
            raise ValueError("skin parents must precede their children (-1 for roots)")
    return jpos, parents, names


def _check_material(mat: Any) -> None:
    """A :class:`service.model.garments.catalogue.Material` (or any object with its fields)."""
    if len(tuple(mat.base_color_factor)) != 4:
        raise ValueError(f"base_color_factor must be RGBA, got {mat.base_color_factor}")
    if mat.alpha_mode not in ("OPAQUE", "MASK", "BLEND"):
        raise ValueError(f"alpha_mode must be OPAQUE, MASK or BLEND, got {mat.alpha_mode!r}")
    for tex in (mat.base_color_texture, mat.normal_texture):
        if tex is not None and tex.mime not in IMAGE_MIMES:
            raise ValueError(f"texture {tex.name!r}: mime type must be one of {IMAGE_MIMES}, got {tex.mime!r}")


def _check_faces(faces: Any, n: int) -> np.ndarray:
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0:
        raise ValueError(f"faces must be (F, 3) with F > 0, got {f.shape}")
    if f.min() < 0 or f.max() >= n:
        raise ValueError(f"face indices out of range [0, {n})")
    return f


def _check_uv(uv: Any, n: int) -> np.ndarray:
    t = np.asarray(uv, dtype=np.float32)
    if t.shape != (n, 2) or not np.all(np.isfinite(t)):
        raise ValueError(f"uv must be finite ({n}, 2), got {t.shape}")
    return t


class MeshTemplate:
    """The static part of one scene mesh, checked and encoded once: its faces, TEXCOORD_0 and
    cleaned JOINTS_0/WEIGHTS_0, and per compression mode their bufferViews, accessors and
    meshoptimizer bytes. A garment's try-on changes only POSITION, NORMAL and TANGENT (and the
    customer's skeleton): give the template as a mesh dict's ``template`` (see
    :func:`scene_to_glb`) and the GLB is the same bytes without redoing the static work.

    faces (F, 3) int into n_vertices vertices; uv (N, 2) or None; vertex_joints (N, 4) int and
    vertex_weights (N, 4) float (cleaned like :func:`scene_to_glb` does) for a skin of
    ``n_joints`` joints, or None. Immutable once built; the per-mode cache is filled on first
    use (a race only computes the same entry twice)."""

    def __init__(self, faces: np.ndarray, n_vertices: int, *, uv: np.ndarray | None = None,
                 vertex_joints: np.ndarray | None = None, vertex_weights: np.ndarray | None = None,
                 n_joints: int | None = None) -> None:
        self.n = int(n_vertices)
        if self.n <= 0:
            raise ValueError("a mesh template needs vertices")
        self.f = _check_faces(faces, self.n)
        self.uv = None if uv is None else _check_uv(uv, self.n)
        self.n_joints = n_joints
        self.joints: np.ndarray | None = None
        self.weights: np.ndarray | None = None
        if vertex_joints is not None or vertex_weights is not None:
            if vertex_joints is None or vertex_weights is None or n_joints is None:
                raise ValueError("vertex_joints, vertex_weights and n_joints go together")
            self.joints, self.weights = _clean_skin_weights(vertex_joints, vertex_weights, n_joints)
            if self.joints.shape[0] != self.n:
                raise ValueError(f"skin vertex arrays must have {self.n} rows, got {self.joints.shape[0]}")
        self._views: dict[str | None, dict[str, tuple[View, dict[str, Any], bytes | None]]] = {}
        self._parent: MeshTemplate | None = None

    def with_faces(self, faces: np.ndarray) -> "MeshTemplate":
        """The same vertices, UVs and skin with other ``faces`` (F', 3) (the avatar with the faces
        under its clothes left out): shares this template's arrays and its encoded attribute
        views, only the indices are checked and encoded anew (the same bytes as a template built
        from scratch; for the body with its plain and meshopt views 0.46 MB instead of 2.2)."""
        t = object.__new__(MeshTemplate)
        t.n, t.uv, t.n_joints, t.joints, t.weights = self.n, self.uv, self.n_joints, self.joints, self.weights
        f = _check_faces(faces, self.n)  # checked (as int64); kept as given when int32, not copied
        src = np.asarray(faces)
        t.f = src if src.dtype == np.int32 else f
        t._views = {}
        t._parent = self._parent if self._parent is not None else self
        return t

    def views(self, compression: str | None) -> dict[str, tuple[View, dict[str, Any], bytes | None]]:
        """{"TEXCOORD_0"?, "JOINTS_0"?, "WEIGHTS_0"?, "indices": (view, accessor, meshopt bytes
        or None)} for ``compression`` (computed once per mode)."""
        hit = self._views.get(compression)
        if hit is None:
            _check_compression(compression)
            if self._parent is not None:  # the attributes' views are the parent's
                view, acc = _index_view(self.f, self.n)
                hit = {k: v for k, v in self._parent.views(compression).items() if k != "indices"}
                hit["indices"] = (view, acc, _meshopt_encode(view) if compression == "meshopt" else None)
            else:
                made = _static_views(self.f, self.n, self.uv, self.joints, self.weights, self.n_joints,
                                     compression in ("quantize", "meshopt"))
                hit = {k: (view, acc, _meshopt_encode(view) if compression == "meshopt" else None)
                       for k, (view, acc) in made.items()}
            self._views[compression] = hit
        return hit


def _static_views(f: np.ndarray, n: int, uv: np.ndarray | None, joints: np.ndarray | None,
                  weights: np.ndarray | None, n_joints: int | None,
                  quant: bool) -> dict[str, tuple[View, dict[str, Any]]]:
    """The views and accessors of a mesh's static attributes (TEXCOORD_0, JOINTS_0, WEIGHTS_0,
    in that order) and indices: faces (F, 3) into n vertices, uv (n, 2), joints (n, 4) and
    weights (n, 4) as cleaned by :func:`_clean_skin_weights`, for a skin of n_joints."""
    out: dict[str, tuple[View, dict[str, Any]]] = {}
    if uv is not None:
        if quant and uv.min() >= 0.0 and uv.max() <= 1.0:  # normalized UNSIGNED_SHORT, step 1/65535
            uq = np.round(uv.astype(np.float64) * 65535.0).astype(np.uint16)
            out["TEXCOORD_0"] = _make_view(uq, UNSIGNED_SHORT, "VEC2", target=ARRAY_BUFFER, normalized=True)
        else:  # FLOAT is valid in every mode (tiling UVs outside [0, 1] stay exact)
            out["TEXCOORD_0"] = _make_view(uv, FLOAT, "VEC2", target=ARRAY_BUFFER)
    if joints is not None:
        jtype = UNSIGNED_BYTE if n_joints is not None and n_joints <= 256 else UNSIGNED_SHORT
        if quant:
            w8, j = _quantize_weights(weights, joints)  # type: ignore[arg-type]
            out["JOINTS_0"] = _make_view(j, jtype, "VEC4", target=ARRAY_BUFFER)
            out["WEIGHTS_0"] = _make_view(w8, UNSIGNED_BYTE, "VEC4", target=ARRAY_BUFFER, normalized=True)
        else:
            out["JOINTS_0"] = _make_view(joints, jtype, "VEC4", target=ARRAY_BUFFER)
            out["WEIGHTS_0"] = _make_view(weights, FLOAT, "VEC4", target=ARRAY_BUFFER)  # type: ignore[arg-type]
    out["indices"] = _index_view(f, n)
    return out


def _index_view(f: np.ndarray, n: int) -> tuple[View, dict[str, Any]]:
    """The indices' view and accessor of faces (F, 3) into n vertices."""
    itype = UNSIGNED_SHORT if n < 65535 else UNSIGNED_INT
    return _make_view(f.reshape(-1), itype, "SCALAR", target=ELEMENT_ARRAY_BUFFER)


def _prepare_mesh(m: dict[str, Any], index: int, n_joints: int | None) -> dict[str, Any]:
    """Validated float32/int arrays of one mesh dict (see :func:`scene_to_glb`); with a
    ``template`` (:class:`MeshTemplate`), only the per-request arrays are checked."""
    v = np.asarray(m["vertices"], dtype=np.float32)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices must be (N, 3) with N > 0, got {v.shape}")
    n = v.shape[0]
    # min/max propagate NaN and keep +/-inf: finite bounds <=> finite vertices (and the bounds
    # are POSITION's accessor min/max and the quantization grid's extent)
    vmin, vmax = _bounds(v)
    if not (np.all(np.isfinite(vmin)) and np.all(np.isfinite(vmax))):
        raise ValueError("vertices must be finite")
    tpl: MeshTemplate | None = m.get("template")
    if tpl is not None:
        if tpl.n != n:
            raise ValueError(f"the mesh template has {tpl.n} vertices, got {n}")
        if tpl.joints is not None and tpl.n_joints != n_joints:
            raise ValueError(f"the mesh template is skinned for {tpl.n_joints} joints, the skin has {n_joints}")
        f = tpl.f
    else:
        f = _check_faces(m["faces"], n)
    normals = m.get("normals")
    nrm = vertex_normals(v, f) if normals is None else _unit_float32(np.asarray(normals))
    if nrm.shape != v.shape:
        raise ValueError(f"normals must be {v.shape}, got {nrm.shape}")
    color = tuple(float(c) for c in m.get("color", DEFAULT_COLOR))
    if len(color) == 3:
        color = (*color, 1.0)
    if len(color) != 4:
        raise ValueError(f"color must be RGBA, got {color}")
    out: dict[str, Any] = {
        "v": v,
        "vmin": vmin,
        "vmax": vmax,
        "f": f,
        "n": nrm,
        "color": color,
        "name": str(m.get("name", f"mesh{index}")),
        "double_sided": bool(m.get("double_sided", False)),
        "targets": None,
        "target_names": None,
        "sparse_targets": bool(m.get("sparse_targets", False)),
        "joints": None,
        "weights": None,
        "uv": None,
        "tangents": None,
        "material": None,
        "template": tpl,
    }
    if tpl is not None:
        out["uv"] = tpl.uv
    elif m.get("uv") is not None:
        out["uv"] = _check_uv(m["uv"], n)
    mat = m.get("material")
    if mat is not None:
        _check_material(mat)
        out["material"] = mat
        out["color"] = tuple(float(c) for c in mat.base_color_factor)
        out["double_sided"] = bool(mat.double_sided)
        if (mat.base_color_texture is not None or mat.normal_texture is not None) and out["uv"] is None:
            raise ValueError(f"mesh {out['name']!r}: a textured material needs uv")
        if mat.normal_texture is not None:
            if m.get("tangents") is not None:
                tg = np.asarray(m["tangents"])
                # one pass: the float64 sum of (unit-sized) entries is finite <=> all of them are
                if tg.shape != (n, 4) or not np.isfinite(np.sum(tg, dtype=np.float64)):
                    raise ValueError(f"tangents must be finite ({n}, 4), got {tg.shape}")
                tan = np.empty((n, 4), np.float32)
                tan[:, :3] = _unit_float32(tg[:, :3])
                tan[:, 3] = np.where(tg[:, 3] < 0, -1.0, 1.0)
                out["tangents"] = tan
            else:
                out["tangents"] = vertex_tangents(v, f, out["uv"], nrm)
    if m.get("targets") is not None:
        t = np.asarray(m["targets"], dtype=np.float32)
        if t.ndim != 3 or t.shape[1:] != v.shape:
            raise ValueError(f"targets must be (K, {n}, 3), got {t.shape}")
        if not np.all(np.isfinite(t)):
            raise ValueError("targets must be finite")
        names = m.get("target_names")
        names = [f"basis_{i}" for i in range(t.shape[0])] if names is None else [str(x) for x in names]
        if len(names) != t.shape[0]:
            raise ValueError(f"target_names must have {t.shape[0]} entries, got {len(names)}")
        if t.shape[0] > 0:
            out["targets"], out["target_names"] = t, names
    if tpl is not None:
        out["joints"], out["weights"] = tpl.joints, tpl.weights
        return out
    has_j = m.get("vertex_joints") is not None or m.get("vertex_weights") is not None
    if has_j:
        if n_joints is None:
            raise ValueError(f"mesh {out['name']!r} has vertex_joints/vertex_weights but no skin was given")
        if m.get("vertex_joints") is None or m.get("vertex_weights") is None:
            raise ValueError("vertex_joints and vertex_weights go together")
        vj, vw = _clean_skin_weights(m["vertex_joints"], m["vertex_weights"], n_joints)
        if vj.shape[0] != n:
            raise ValueError(f"skin vertex arrays must have {n} rows, got {vj.shape[0]}")
        out["joints"], out["weights"] = vj, vw
    return out


def _quant_grid(meshes: list[dict[str, Any]]) -> tuple[float, np.ndarray]:
    """One uniform step ``s`` and centre ``t`` so that (v - t) / s and every morph delta / s fit
    in [-32767, 32767] for all ``meshes``. Uniform, so normals stay correct under the node scale."""
    lo = np.min([m["vmin"] for m in meshes], axis=0).astype(np.float64)
    hi = np.max([m["vmax"] for m in meshes], axis=0).astype(np.float64)
    t = (lo + hi) / 2.0
    s = float(np.max(hi - lo)) / (2 * 32767)
    for m in meshes:
        if m["targets"] is not None:
            s = max(s, float(np.abs(m["targets"]).max()) / 32767)
    s = s * (1 + 1e-9) if s > 0 else 1.0  # keep rounding inside the range
    return s, t


def _build_glb(
    meshes: list[dict[str, Any]],
    skin: dict[str, Any] | None,
    compression: str | None,
    skin_name: str = "skeleton",
) -> bytes:
    _check_compression(compression)
    if not meshes:
        raise ValueError("at least one mesh is needed")
    skel = _check_skeleton(skin) if skin is not None else None
    n_j = skel[0].shape[0] if skel is not None else None
    ms = [_prepare_mesh(m, i, n_j) for i, m in enumerate(meshes)]
    quant = compression in ("quantize", "meshopt")
    skinned = [m for m in ms if m["joints"] is not None]
    skin_grid = _quant_grid(skinned) if quant and skinned else None

    b = _Builder()
    nodes: list[dict[str, Any]] = []
    gltf_meshes: list[dict[str, Any]] = []
    materials: list[dict[str, Any]] = []
    images: list[dict[str, Any]] = []
    image_of: dict[tuple[str, bytes], int] = {}

    def texture_index(tex: Any) -> int:
        """One image (and texture) per distinct encoded image in this GLB, however many
        materials use it (bytes objects cache their hash, so repeats are cheap)."""
        key = (tex.mime, tex.data)
        if key not in image_of:
            image_of[key] = len(images)
            images.append({"name": str(tex.name), "mimeType": tex.mime, "bufferView": -1, "_data": tex.data})
        return image_of[key]

    for mi, m in enumerate(ms):
        node: dict[str, Any] = {"name": m["name"], "mesh": mi}
        if quant:
            s, t = skin_grid if m["joints"] is not None else _quant_grid([m])  # type: ignore[misc]
            def grid(x: np.ndarray) -> np.ndarray:
                return np.clip(np.round((x.astype(np.float64) - t) / s), -32767, 32767).astype(np.int16)

            # monotone per axis: the grid's bounds are those of the vertices' bounds
            pos = b.add(grid(m["v"]), SHORT, "VEC3", target=ARRAY_BUFFER, minmax=True,
                        bounds=(grid(m["vmin"]), grid(m["vmax"])))
            nrm = b.add(_quantize_normals(m["n"]), BYTE, "VEC3", target=ARRAY_BUFFER, normalized=True)
            if m["joints"] is None:  # a skinned node's transform is ignored: the skin dequantizes
                node["translation"] = [float(x) for x in t]
                node["scale"] = [s, s, s]
        else:
            pos = b.add(m["v"], FLOAT, "VEC3", target=ARRAY_BUFFER, minmax=True, bounds=(m["vmin"], m["vmax"]))
            nrm = b.add(m["n"], FLOAT, "VEC3", target=ARRAY_BUFFER)
        attributes: dict[str, int] = {"POSITION": pos, "NORMAL": nrm}
        if m["tangents"] is not None:
            if quant:  # KHR_mesh_quantization: TANGENT as normalized BYTE VEC4 (w = +/-127)
                tq = np.concatenate([_quantize_normals(m["tangents"][:, :3]),
                                     np.where(m["tangents"][:, 3:] < 0, -127, 127).astype(np.int8)], axis=1)
                attributes["TANGENT"] = b.add(tq, BYTE, "VEC4", target=ARRAY_BUFFER, normalized=True)
            else:
                attributes["TANGENT"] = b.add(m["tangents"], FLOAT, "VEC4", target=ARRAY_BUFFER)
        # the static attributes and indices: once per template and mode, or made here
        if m["template"] is not None:
            static = m["template"].views(compression)
        else:
            static = {k: (view, acc, None) for k, (view, acc) in _static_views(
                m["f"], m["v"].shape[0], m["uv"], m["joints"], m["weights"], n_j, quant).items()}
        for key in ("TEXCOORD_0", "JOINTS_0", "WEIGHTS_0"):
            if key in static:
                attributes[key] = b.add_view(*static[key])
        if m["joints"] is not None:
            node["skin"] = 0
        prim: dict[str, Any] = {"attributes": attributes}
        gmesh: dict[str, Any] = {"name": m["name"], "primitives": [prim]}
        if m["targets"] is not None:
            targets = []
            for d in m["targets"]:
                if quant:
                    s = node["scale"][0] if "scale" in node else skin_grid[0]  # type: ignore[index]
                    dq = np.clip(np.round(d.astype(np.float64) / s), -32767, 32767).astype(np.int16)
                    targets.append({"POSITION": b.add_sparse(dq, SHORT, "VEC3") if m["sparse_targets"] else
                                    b.add(dq, SHORT, "VEC3", target=ARRAY_BUFFER, minmax=True)})
                else:
                    targets.append({"POSITION": b.add_sparse(d, FLOAT, "VEC3") if m["sparse_targets"] else
                                    b.add(d, FLOAT, "VEC3", target=ARRAY_BUFFER, minmax=True)})
            prim["targets"] = targets
            gmesh["weights"] = [0.0] * len(targets)
            gmesh["extras"] = {"targetNames": list(m["target_names"])}
        prim["indices"] = b.add_view(*static["indices"])
        prim["material"] = mi
        prim["mode"] = TRIANGLES
        mat: dict[str, Any] = {
            "name": f"{m['name']}_material",
            "pbrMetallicRoughness": {
                "baseColorFactor": list(m["color"]),
                "metallicFactor": 0.0,
                "roughnessFactor": 0.8,
            },
        }
        src = m["material"]
        if src is None:
            if m["color"][3] < 1.0:
                mat["alphaMode"] = "BLEND"
        else:
            pbr = mat["pbrMetallicRoughness"]
            pbr["metallicFactor"] = float(np.clip(src.metallic, 0.0, 1.0))
            pbr["roughnessFactor"] = float(np.clip(src.roughness, 0.0, 1.0))
            if src.base_color_texture is not None:
                pbr["baseColorTexture"] = {"index": texture_index(src.base_color_texture)}
            if src.normal_texture is not None:
                mat["normalTexture"] = {"index": texture_index(src.normal_texture)}
            if src.alpha_mode != "OPAQUE":
                mat["alphaMode"] = src.alpha_mode
            if src.alpha_mode == "MASK" and src.alpha_cutoff is not None:
                mat["alphaCutoff"] = float(src.alpha_cutoff)
        if m["double_sided"]:
            mat["doubleSided"] = True
        materials.append(mat)
        gltf_meshes.append(gmesh)
        nodes.append(node)
    scene_nodes = list(range(len(nodes)))

    gltf_skins: list[dict[str, Any]] = []
    if skel is not None:
        jpos, parents, names = skel
        first = len(nodes)
        for i in range(len(names)):
            rel = jpos[i] - (jpos[parents[i]] if parents[i] >= 0 else 0.0)
            jn: dict[str, Any] = {"name": names[i], "translation": [float(x) for x in rel]}
            children = [first + c for c in range(len(names)) if parents[c] == i]
            if children:
                jn["children"] = children
            nodes.append(jn)
        roots = [first + i for i in range(len(names)) if parents[i] == -1]
        scene_nodes += roots
        if skinned:
            ibm = np.tile(np.eye(4), (len(names), 1, 1))
            ibm[:, :3, 3] = -jpos
            if skin_grid is not None:  # bake the dequantization into the bind: IBM @ D
                s, t = skin_grid
                dq = np.eye(4)
                dq[:3, :3] *= s
                dq[:3, 3] = t
                ibm = ibm @ dq
            ibm_col = np.transpose(ibm, (0, 2, 1)).reshape(len(names), 16)  # column-major
            gltf_skins.append(
                {
                    "name": skin_name,
                    "inverseBindMatrices": b.add(ibm_col, FLOAT, "MAT4"),
                    "joints": list(range(first, first + len(names))),
                    "skeleton": roots[0],
                }
            )

    for img in images:  # after every accessor's view: images are never meshopt-encoded
        img["bufferView"] = b.add_bytes(img.pop("_data"))

    parts, blob_len, buffers = b.finish(meshopt=compression == "meshopt")
    doc: dict[str, Any] = {"asset": {"version": "2.0", "generator": "tryon service.model.formats.gltf"}}
    ext = {"quantize": ["KHR_mesh_quantization"], "meshopt": ["KHR_mesh_quantization", "EXT_meshopt_compression"]}
    if compression is not None:
        doc["extensionsUsed"] = ext[compression]
        doc["extensionsRequired"] = ext[compression]
    doc.update(
        {
            "scene": 0,
            "scenes": [{"name": "scene", "nodes": scene_nodes}],
            "nodes": nodes,
            "meshes": gltf_meshes,
            "materials": materials,
            "accessors": b.accessors,
            "bufferViews": b.buffer_views,
            "buffers": buffers,
        }
    )
    if gltf_skins:
        doc["skins"] = gltf_skins
    if images:
        doc["images"] = images
        doc["samplers"] = [{"magFilter": LINEAR, "minFilter": LINEAR_MIPMAP_LINEAR, "wrapS": REPEAT, "wrapT": REPEAT}]
        doc["textures"] = [{"sampler": 0, "source": i} for i in range(len(images))]

    js = json.dumps(doc, separators=(",", ":")).encode("utf-8")
    js += b" " * (-len(js) % 4)
    total = 12 + 8 + len(js) + 8 + blob_len
    return b"".join([struct.pack("<IIIII", GLB_MAGIC, GLB_VERSION, total, len(js), CHUNK_JSON), js,
                     struct.pack("<II", blob_len, CHUNK_BIN), *parts])


def mesh_to_glb(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray | None = None,
    color: tuple[float, float, float, float] = DEFAULT_COLOR,
    name: str = "avatar",
    skin: Skin | dict[str, Any] | None = None,
    compression: str | None = None,
    uv: np.ndarray | None = None,
    material: Any = None,
) -> bytes:
    """A triangle mesh as GLB 2.0 bytes.

    vertices: (N, 3) float (metres, Y up), faces: (F, 3) int (counter-clockwise = outside),
    normals: (N, 3) or None (smooth area-weighted normals are computed),
    color: linear RGBA base colour of the PBR material, name: mesh/node name,
    skin: optional :class:`Skin`; adds a joint node hierarchy (translations relative to the
    parent, identity rotations), inverse bind matrices (translation by -joint) and
    JOINTS_0/WEIGHTS_0 attributes,
    compression: None (float32), "quantize" or "meshopt" (see :func:`scene_to_glb`),
    uv (N, 2) and material: as in :func:`scene_to_glb`.
    """
    mesh: dict[str, Any] = {"vertices": vertices, "faces": faces, "normals": normals, "color": color, "name": name,
                            "uv": uv, "material": material}
    skeleton = None
    if skin is not None:
        mesh["vertex_joints"], mesh["vertex_weights"] = skin["vertex_joints"], skin["vertex_weights"]
        skeleton = {k: skin[k] for k in ("joints", "parents", "joint_names")}  # type: ignore[literal-required]
    return _build_glb([mesh], skeleton, compression, skin_name=f"{name}_skeleton")


def scene_to_glb(
    meshes: list[dict[str, Any]],
    *,
    skin: dict[str, Any] | None = None,
    compression: str | None = None,
) -> bytes:
    """Several triangle meshes in one scene (e.g. an avatar and the garments it wears) as GLB.

    Each mesh dict: ``vertices`` (N, 3) float, ``faces`` (F, 3) int, optional ``normals``
    (N, 3), ``color`` RGBA (linear, PBR base colour; alpha < 1 gives alphaMode BLEND),
    ``name``, ``double_sided`` (bool, e.g. for garments), ``uv`` (N, 2) float TEXCOORD_0 (glTF
    convention, origin top-left), ``material`` (a :class:`service.model.garments.catalogue.Material`:
    base colour factor, base-colour / normal textures (PNG or JPEG bytes, each embedded once per
    GLB however many meshes share it), alpha mode and cutoff, double sided, metallic, roughness;
    it overrides ``color`` and ``double_sided``; textures need ``uv``), ``tangents`` (N, 4)
    (only used with a normal texture; computed by :func:`vertex_tangents` when absent),
    ``vertex_joints`` (N, 4) int +
    ``vertex_weights`` (N, 4) float (skinned meshes; need ``skin``), and ``targets`` (K, N, 3)
    morph POSITION deltas with ``target_names`` (K) (see :func:`basis_to_glb`), stored as
    sparse accessors (only the moved vertices) with ``sparse_targets`` True (also with a
    ``template``: the targets are per-request arrays). Mesh i is node i and mesh i, with material i.

    skin: {joints (J, 3) rest world positions, parents (J,) (-1 for roots, parents first),
    joint_names (J)}: ONE joint node hierarchy and ONE glTF skin (skins[0]) shared by every
    mesh that has vertex_joints, so posing the skeleton poses the body and its clothes together.

    compression:
      None: float32 positions/normals/weights/morph deltas (default).
      "quantize": KHR_mesh_quantization. Positions and morph POSITION deltas as SHORT
        (non-normalized) on a uniform grid of step s: the original is q * s + t; the
        dequantization is the node's scale/translation, or for skinned meshes it is baked into
        the shared skin's inverse bind matrices (a skinned node's own transform is ignored by
        glTF), using one grid for all skinned meshes. Normals as normalized BYTE, weights as
        normalized UNSIGNED_BYTE (rows sum to 255, joint 0 where the weight is 0), tangents as
        normalized BYTE, texture coordinates as normalized UNSIGNED_SHORT when they lie in
        [0, 1] (step 1/65535), FLOAT otherwise (both allowed by the extension).
      "meshopt": "quantize" plus EXT_meshopt_compression: every vertex attribute and index
        bufferView is encoded with meshoptimizer's vertex / index codecs (Python package
        ``meshopt``); the bufferViews point into a data-less fallback buffer (buffers[1],
        ``fallback: true``) and the extension is required.
    Raises ValueError on bad input or an unknown compression.
    """
    return _build_glb(list(meshes), skin, compression)


def basis_to_glb(
    g: np.ndarray,
    B: np.ndarray,
    faces: np.ndarray,
    *,
    color: tuple[float, float, float, float] = (0.25, 0.35, 0.6, 1.0),
    name: str = "garment",
    target_names: list[str] | tuple[str, ...] | None = None,
    normals: np.ndarray | None = None,
    compression: str | None = None,
    skin: Skin | dict[str, Any] | None = None,
    uv: np.ndarray | None = None,
    material: Any = None,
) -> bytes:
    """A garment's clothing basis as one GLB mesh with morph targets.

    g: (M, 3) mean garment (the base POSITION), B: (N, M, 3) basis, stored as N morph targets
    whose POSITION deltas are B[i]; faces: (F, 3). The morph weights default to 0 and
    ``mesh.extras.targetNames`` holds ``target_names`` (default "basis_0".."basis_{N-1}").
    glTF's morph formula, POSITION = g + sum_i weight_i * B[i], is exactly the basis
    synthesis g + sum_i w_i B_i: a client holding a customer's PCA weights w sets the mesh's
    morph weights to w[:N] to render that customer's fit (with compression the targets are
    quantized to the position grid, see :func:`scene_to_glb`). Normals are those of g.
    The material is double sided. skin: optional :class:`Skin` (as for :func:`mesh_to_glb`).
    uv (M, 2) and material: as in :func:`scene_to_glb` (the tangents of a normal texture are
    those of g).
    """
    Bf = np.asarray(B)
    mesh: dict[str, Any] = {
        "vertices": g,
        "faces": faces,
        "normals": normals,
        "color": color,
        "name": name,
        "double_sided": True,
        "targets": Bf,
        "target_names": target_names,
        "uv": uv,
        "material": material,
    }
    if Bf.ndim != 3:
        raise ValueError(f"B must be (N, M, 3), got {Bf.shape}")
    skeleton = None
    if skin is not None:
        mesh["vertex_joints"], mesh["vertex_weights"] = skin["vertex_joints"], skin["vertex_weights"]
        skeleton = {k: skin[k] for k in ("joints", "parents", "joint_names")}  # type: ignore[literal-required]
    return _build_glb([mesh], skeleton, compression, skin_name=f"{name}_skeleton")

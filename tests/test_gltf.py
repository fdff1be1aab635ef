"""GLB writer: Khronos validator reports no errors/warnings; positions/indices round-trip."""
from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import trimesh

from service.model.formats.gltf import MeshTemplate, basis_to_glb, mesh_to_glb, scene_to_glb, vertex_normals
from service.model.formats.gltf_read import read_glb
from tests.conftest import format_issues


def _sphere() -> trimesh.Trimesh:
    return trimesh.creation.icosphere(subdivisions=3, radius=0.5)


def _chain_skin(vertices: np.ndarray) -> dict[str, Any]:
    """A 3-joint vertical chain; each vertex weighted between its two nearest joints by height.

    Slots 2-3 are deliberately messy (duplicates, zero weights) to exercise the cleaning."""
    joints = np.array([[0.0, -0.5, 0.0], [0.0, 0.0, 0.0], [0.0, 0.5, 0.0]])
    y = vertices[:, 1]
    t = np.clip((y + 0.5) / 1.0, 0.0, 1.0) * 2.0  # 0..2 along the chain
    lo = np.minimum(np.floor(t).astype(int), 1)
    frac = t - lo
    n = len(vertices)
    vj = np.stack([lo, lo + 1, lo, np.full(n, 2)], axis=1)  # slot 2 duplicates slot 0
    vw = np.stack([1 - frac, frac, np.full(n, 0.1), np.zeros(n)], axis=1).astype(np.float32)
    return {
        "joints": joints,
        "parents": np.array([-1, 0, 1]),
        "joint_names": ["root", "mid", "top"],
        "vertex_joints": vj,
        "vertex_weights": vw,
    }


def _assert_clean(report: dict[str, Any]) -> None:
    issues = report["issues"]
    assert issues["numErrors"] == 0, format_issues(report)
    assert issues["numWarnings"] == 0, format_issues(report)


def test_glb_header_and_alignment() -> None:
    m = _sphere()
    glb = mesh_to_glb(m.vertices.astype(np.float32), m.faces)
    magic, version, length = struct.unpack_from("<III", glb, 0)
    assert glb[:4] == b"glTF" and version == 2 and length == len(glb)
    json_len, json_type = struct.unpack_from("<II", glb, 12)
    assert json_type == 0x4E4F534A and json_len % 4 == 0
    bin_len, bin_type = struct.unpack_from("<II", glb, 20 + json_len)
    assert bin_type == 0x004E4942 and bin_len % 4 == 0
    assert 20 + json_len + 8 + bin_len == len(glb)


def test_static_mesh_validates(validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    m = _sphere()
    _assert_clean(validate_glb(mesh_to_glb(m.vertices.astype(np.float32), m.faces)))


def test_skinned_mesh_validates(validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    m = _sphere()
    v = m.vertices.astype(np.float32)
    glb = mesh_to_glb(v, m.faces, skin=_chain_skin(v), color=(0.2, 0.4, 0.6, 1.0), name="ball")
    report = validate_glb(glb)
    _assert_clean(report)
    assert report["info"]["hasSkins"] is True


def test_round_trip_positions_indices() -> None:
    m = _sphere()
    v = m.vertices.astype(np.float32)
    out = read_glb(mesh_to_glb(v, m.faces, skin=_chain_skin(v)))
    np.testing.assert_array_equal(out["positions"], v)
    np.testing.assert_array_equal(out["indices"], m.faces)
    doc = out["json"]
    pos_acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert pos_acc["min"] == [float(x) for x in v.min(axis=0)]
    assert pos_acc["max"] == [float(x) for x in v.max(axis=0)]
    # Skin attributes: rows sum to 1, zero weights point at joint 0, no duplicate live joints.
    w, j = out["weights"].astype(np.float64), out["joints"]
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
    assert np.all(j[w == 0] == 0)
    for row_j, row_w in zip(j, w):
        live = row_j[row_w > 0]
        assert len(set(live.tolist())) == len(live)
    # Joint nodes: translations relative to the parent reproduce the world positions.
    nodes = doc["nodes"]
    skin = doc["skins"][0]
    assert [nodes[i]["name"] for i in skin["joints"]] == ["root", "mid", "top"]
    assert nodes[skin["joints"][1]]["translation"] == [0.0, 0.5, 0.0]


def test_large_mesh_uses_uint32_indices() -> None:
    grid = 260  # 67,600 vertices > 65,535
    xs, zs = np.meshgrid(np.arange(grid, dtype=np.float32), np.arange(grid, dtype=np.float32))
    v = np.stack([xs.ravel(), np.zeros(grid * grid, np.float32), zs.ravel()], axis=1)
    idx = np.arange(grid * grid).reshape(grid, grid)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    out = read_glb(mesh_to_glb(v, faces))
    prim = out["json"]["meshes"][0]["primitives"][0]
    assert out["json"]["accessors"][prim["indices"]]["componentType"] == 5125
    np.testing.assert_array_equal(out["indices"], faces)


def test_vertex_normals_sphere_point_outwards() -> None:
    m = _sphere()
    n = vertex_normals(m.vertices, m.faces)
    assert n.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-6)
    radial = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    assert np.min(np.sum(n * radial, axis=1)) > 0.99


@pytest.mark.parametrize(
    "vertices, faces",
    [
        (np.zeros((0, 3)), np.zeros((1, 3), int)),
        (np.zeros((3, 2)), np.array([[0, 1, 2]])),
        (np.zeros((3, 3)), np.array([[0, 1, 3]])),
        (np.full((3, 3), np.nan), np.array([[0, 1, 2]])),
    ],
)
def test_bad_input_raises(vertices: np.ndarray, faces: np.ndarray) -> None:
    with pytest.raises(ValueError):
        mesh_to_glb(vertices, faces)


# --------------------------------------------------------------------------------------------
# Scenes, clothing bases as morph targets, and compression (KHR_mesh_quantization, meshopt).

COMPRESSIONS = [None, "quantize", "meshopt"]


def _garment(around: int = 100, high: int = 100, n_basis: int = 16) -> tuple[np.ndarray, ...]:
    """A tube-shaped 'garment' (around * high vertices, open ends) and a smooth basis (K, M, 3):
    radial bulges of increasing frequency, a few cm each, like a clothing PCA basis."""
    th = np.linspace(0, 2 * np.pi, around, endpoint=False)
    ys = np.linspace(0.6, 1.4, high)
    T, Y = np.meshgrid(th, ys)
    g = np.stack([0.18 * np.cos(T), Y, 0.15 * np.sin(T)], axis=-1).reshape(-1, 3).astype(np.float32)
    idx = np.arange(around * high).reshape(high, around)
    nxt = np.roll(idx, -1, axis=1)
    a, b, c, d = idx[:-1].ravel(), nxt[:-1].ravel(), idx[1:].ravel(), nxt[1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([b, c, d], 1)])
    radial = np.stack([np.cos(T), np.zeros_like(T), np.sin(T)], axis=-1).reshape(-1, 3)
    B = []
    for k in range(n_basis):
        amp = 0.03 / (1 + k) * np.cos((k % 4 + 1) * T.ravel()) * np.sin((k // 4 + 1) * np.pi * (Y.ravel() - 0.6) / 0.8)
        B.append(radial * amp[:, None] + np.array([0.0, 0.002 * k, 0.0]))
    return g, faces, np.stack(B).astype(np.float32)


def _skin_step(glb: bytes) -> float:
    from service.model.formats.gltf_read import _parse_glb, _read_float  # noqa: PLC0415

    doc, blob = _parse_glb(glb)
    ibm = _read_float(doc, blob, doc["skins"][0]["inverseBindMatrices"])
    return float(ibm[0, 0])  # column-major: element (0, 0) is the uniform scale s


def _canon(faces: np.ndarray) -> np.ndarray:
    """Each triangle rotated to start at its smallest index (winding kept): meshopt's index
    codec may rotate triangles."""
    f = np.asarray(faces, np.int64)
    k = np.argmin(f, axis=1)
    rows = np.arange(len(f))[:, None]
    return f[rows, (k[:, None] + np.arange(3)) % 3]


def _mesh_step(glb: bytes, doc: dict[str, Any], mesh_index: int) -> float:
    node = next(n for n in doc["nodes"] if n.get("mesh") == mesh_index)
    return _skin_step(glb) if "skin" in node else float(node["scale"][0])


def _assert_no_warnings(report: dict[str, Any]) -> None:
    """0 errors, 0 warnings (infos allowed: the validator does not know EXT_meshopt_compression
    and says so as an info)."""
    issues = report["issues"]
    assert issues["numErrors"] == 0, format_issues(report)
    assert issues["numWarnings"] == 0, format_issues(report)
    for m in issues["messages"]:
        assert m["code"] in ("UNSUPPORTED_EXTENSION", "UNUSED_OBJECT"), format_issues(report)


def _check_compression_json(doc: dict[str, Any], compression: str | None) -> None:
    if compression is None:
        assert "extensionsUsed" not in doc and len(doc["buffers"]) == 1
        return
    assert "KHR_mesh_quantization" in doc["extensionsRequired"]
    assert set(doc["extensionsRequired"]) == set(doc["extensionsUsed"])
    for mesh in doc["meshes"]:
        attrs = mesh["primitives"][0]["attributes"]
        assert doc["accessors"][attrs["POSITION"]]["componentType"] == 5122  # SHORT
        nrm = doc["accessors"][attrs["NORMAL"]]
        assert nrm["componentType"] == 5120 and nrm["normalized"] is True  # normalized BYTE
        for tg in mesh["primitives"][0].get("targets", []):
            assert doc["accessors"][tg["POSITION"]]["componentType"] == 5122
    if compression == "meshopt":
        assert "EXT_meshopt_compression" in doc["extensionsRequired"]
        fallback = doc["buffers"][1]
        assert "uri" not in fallback and fallback["extensions"]["EXT_meshopt_compression"]["fallback"] is True
        encoded = [v for v in doc["bufferViews"] if "EXT_meshopt_compression" in v.get("extensions", {})]
        assert encoded and all(v["buffer"] == 1 for v in encoded)
        for v in encoded:
            ext = v["extensions"]["EXT_meshopt_compression"]
            assert ext["buffer"] == 0 and ext["byteOffset"] % 4 == 0
            assert ext["mode"] in ("ATTRIBUTES", "TRIANGLES") and ext["count"] * ext["byteStride"] == v["byteLength"]
    else:
        assert len(doc["buffers"]) == 1


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_mesh_compression_validates_and_round_trips(
    compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]
) -> None:
    m = _sphere()
    v = m.vertices.astype(np.float32)
    for skin in (None, _chain_skin(v)):
        glb = mesh_to_glb(v, m.faces, skin=skin, compression=compression)
        report = validate_glb(glb)
        _assert_no_warnings(report)
        out = read_glb(glb)
        _check_compression_json(out["json"], compression)
        np.testing.assert_array_equal(_canon(out["indices"]), _canon(m.faces))
        if compression is None:
            np.testing.assert_array_equal(out["positions"], v)
        else:
            s = _mesh_step(glb, out["json"], 0)
            assert 0 < s <= 1.0 / 65534 * (1 + 1e-6)  # 1 m extent over 16 bits
            assert np.abs(out["positions"] - v).max() <= s / 2 * 1.001 + 1e-6
            ref = vertex_normals(v, m.faces)
            assert np.min(np.sum(out["normals"] * ref, axis=1)) > 0.999  # 8-bit normals, < 2.6 deg
        if skin is not None:
            w, j = out["weights"].astype(np.float64), out["joints"]
            np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
            assert np.all(j[w == 0] == 0)
            assert report["info"]["hasSkins"] is True


def test_meshopt_decodes_to_the_quantized_data() -> None:
    g, faces, B = _garment(40, 30, 4)
    q = read_glb(basis_to_glb(g, B, faces, compression="quantize"))
    mo = read_glb(basis_to_glb(g, B, faces, compression="meshopt"))
    for key in ("positions", "normals", "targets"):
        np.testing.assert_array_equal(mo[key], q[key])
    np.testing.assert_array_equal(_canon(mo["indices"]), _canon(q["indices"]))


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_basis_morph_targets(compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    g, faces, B = _garment(40, 30, 6)
    names = [f"pc{i}" for i in range(6)]
    glb = basis_to_glb(g, B, faces, target_names=names, compression=compression)
    report = validate_glb(glb)
    _assert_no_warnings(report)
    out = read_glb(glb)
    doc = out["json"]
    _check_compression_json(doc, compression)
    mesh = doc["meshes"][0]
    assert mesh["extras"]["targetNames"] == names and out["target_names"] == names
    assert mesh["weights"] == [0.0] * 6
    assert doc["materials"][0]["doubleSided"] is True
    for tg in mesh["primitives"][0]["targets"]:
        acc = doc["accessors"][tg["POSITION"]]
        assert "min" in acc and "max" in acc
    assert out["targets"].shape == B.shape
    if compression is None:
        np.testing.assert_array_equal(out["positions"], g)
        np.testing.assert_array_equal(out["targets"], B)  # deltas are B exactly
    else:
        s = _mesh_step(glb, doc, 0)
        assert np.abs(out["positions"] - g).max() <= s / 2 * 1.001 + 1e-6
        assert np.abs(out["targets"] - B).max() <= s / 2 * 1.001 + 1e-6
    # The morph formula is the basis synthesis: g + sum w_i B_i.
    w = np.array([0.5, -1.0, 2.0, 0.0, 0.3, -0.7])
    morphed = out["positions"].astype(np.float64) + np.tensordot(w, out["targets"].astype(np.float64), 1)
    tol = 1e-6 if compression is None else (1 + np.abs(w).sum()) * _mesh_step(glb, doc, 0)
    assert np.abs(morphed - (g + np.tensordot(w, B.astype(np.float64), 1))).max() <= tol


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_skinned_basis_validates(compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    g, faces, B = _garment(30, 20, 3)
    glb = basis_to_glb(g - [0.0, 1.0, 0.0], B, faces, skin=_chain_skin(g - [0.0, 1.0, 0.0]), compression=compression)
    report = validate_glb(glb)
    _assert_no_warnings(report)
    assert report["info"]["hasSkins"] is True and report["info"]["hasMorphTargets"] is True
    out = read_glb(glb)
    np.testing.assert_allclose(out["targets"], B, atol=1e-6 if compression is None else 1e-4)


def _scene(compression: str | None) -> tuple[list[dict[str, Any]], dict[str, Any], bytes]:
    body = _sphere()
    bv = body.vertices.astype(np.float32)
    bskin = _chain_skin(bv)
    shirt = trimesh.creation.icosphere(subdivisions=2, radius=0.55)
    sv = shirt.vertices.astype(np.float32)
    sv[:, 1] = np.clip(sv[:, 1], -0.1, 0.55)
    sskin = _chain_skin(sv)
    hat = trimesh.creation.box(extents=(0.3, 0.1, 0.3))
    skeleton = {k: bskin[k] for k in ("joints", "parents", "joint_names")}
    meshes = [
        {"vertices": bv, "faces": body.faces, "name": "avatar",
         "vertex_joints": bskin["vertex_joints"], "vertex_weights": bskin["vertex_weights"]},
        {"vertices": sv, "faces": shirt.faces, "name": "shirt", "color": (0.1, 0.3, 0.8, 1.0),
         "double_sided": True, "vertex_joints": sskin["vertex_joints"], "vertex_weights": sskin["vertex_weights"]},
        {"vertices": hat.vertices + [0.0, 0.6, 0.0], "faces": hat.faces, "name": "hat", "color": (0.9, 0.1, 0.1, 0.5)},
    ]
    return meshes, skeleton, scene_to_glb(meshes, skin=skeleton, compression=compression)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_scene_shared_skin(compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    meshes, skeleton, glb = _scene(compression)
    report = validate_glb(glb)
    _assert_no_warnings(report)
    out = read_glb(glb)
    doc = out["json"]
    _check_compression_json(doc, compression)
    assert len(doc["skins"]) == 1 and len(doc["meshes"]) == 3 and len(doc["materials"]) == 3
    skin = doc["skins"][0]
    assert [doc["nodes"][j]["name"] for j in skin["joints"]] == skeleton["joint_names"]
    mesh_nodes = {doc["nodes"][i]["name"]: doc["nodes"][i] for i in doc["scenes"][0]["nodes"] if "mesh" in doc["nodes"][i]}
    assert mesh_nodes["avatar"].get("skin") == 0 and mesh_nodes["shirt"].get("skin") == 0
    assert "skin" not in mesh_nodes["hat"]
    assert doc["materials"][1]["doubleSided"] is True and doc["materials"][2]["alphaMode"] == "BLEND"
    for i, (m, got) in enumerate(zip(meshes, out["meshes"])):
        assert got["name"] == m["name"]
        np.testing.assert_array_equal(_canon(got["indices"]), _canon(m["faces"]))
        v = np.asarray(m["vertices"], np.float32)
        if compression is None:
            np.testing.assert_array_equal(got["positions"], v)
        else:
            s = _mesh_step(glb, doc, i)
            assert np.abs(got["positions"] - v).max() <= s / 2 * 1.001 + 1e-6
        if "vertex_joints" in m:
            w = got["weights"].astype(np.float64)
            np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-6)
            assert np.all(got["joints"][w == 0] == 0)
    if compression is not None:  # the skinned meshes share one grid, baked into the skin
        assert "scale" not in mesh_nodes["avatar"] and "scale" in mesh_nodes["hat"]


def test_scene_without_skin_and_bad_inputs() -> None:
    meshes, _, _ = _scene(None)
    with pytest.raises(ValueError):
        scene_to_glb(meshes)  # vertex_joints but no skin
    static = [{k: v for k, v in m.items() if not k.startswith("vertex_")} for m in meshes]
    out = read_glb(scene_to_glb(static))
    assert "skins" not in out["json"] and len(out["meshes"]) == 3
    with pytest.raises(ValueError):
        scene_to_glb([])
    g, faces, B = _garment(10, 5, 2)
    with pytest.raises(ValueError):
        basis_to_glb(g, B[:, :-1], faces)
    with pytest.raises(ValueError):
        basis_to_glb(g, B, faces, target_names=["only one"])


@pytest.mark.parametrize("mode", ["draco", "Quantize", ""])
def test_unknown_compression_raises(mode: str) -> None:
    m = _sphere()
    v = m.vertices.astype(np.float32)
    g, faces, B = _garment(10, 5, 2)
    with pytest.raises(ValueError):
        mesh_to_glb(v, m.faces, compression=mode)
    with pytest.raises(ValueError):
        scene_to_glb([{"vertices": v, "faces": m.faces}], compression=mode)
    with pytest.raises(ValueError):
        basis_to_glb(g, B, faces, compression=mode)


def test_compressed_sizes_10k_vertices_16_targets(validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    g, faces, B = _garment(100, 100, 16)  # 10,000 vertices, 16 morph targets
    sizes = {}
    for comp in COMPRESSIONS:
        glb = basis_to_glb(g, B, faces, compression=comp)
        _assert_no_warnings(validate_glb(glb))
        sizes[comp] = len(glb)
    print(f"10k-vertex garment, 16 morph targets, GLB bytes: {sizes}")
    # plain: 12 B a position/normal/delta; quantized: 8 B (SHORT VEC3 padded), 4 B a normal.
    assert sizes["quantize"] < 0.7 * sizes[None]
    assert sizes["meshopt"] < 0.7 * sizes["quantize"]


# Texture coordinates, tangents and materials with embedded textures.

def _textures() -> tuple[Any, Any]:
    """Two real encoded images from the compiled catalogue: a JPEG colour map and a JPEG normal map."""
    from service.model.garments.catalogue import DEFAULT_CATALOGUE_DIR, Texture

    root = DEFAULT_CATALOGUE_DIR / "textures"
    return (Texture("cloth.jpg", "image/jpeg", (root / "white-tshirt.jpg").read_bytes()),
            Texture("cloth-normal.jpg", "image/jpeg", (root / "sports-trousers-normal.jpg").read_bytes()))


def _material(color: Any, normal: Any, alpha_mode: str = "OPAQUE", cutoff: float | None = None) -> Any:
    from service.model.garments.catalogue import Material

    return Material((0.9, 0.8, 0.7, 1.0), color, normal, alpha_mode, cutoff, True, 0.1, 0.7)


def _tube_uv(around: int = 100, high: int = 100) -> np.ndarray:
    """glTF-convention uv of :func:`_garment`'s tube: u around, v from the top (0) down."""
    u, v = np.meshgrid(np.arange(around) / around, 1.0 - (np.arange(high) / (high - 1)))
    return np.stack([u, v], axis=-1).reshape(-1, 2).astype(np.float32)


def _assert_clean_textured(report: dict[str, Any]) -> None:
    """0 errors, 0 warnings; infos only about meshopt and non-power-of-two images."""
    _assert_clean(report)
    for m in report["issues"]["messages"]:
        assert m["code"] in ("UNSUPPORTED_EXTENSION", "IMAGE_NPOT_DIMENSIONS"), format_issues(report)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_textured_scene_round_trip(compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    """uv, material fields and textures survive every compression mode; an image shared by two
    meshes is embedded once; a normal-mapped mesh gets TANGENT; the validator is clean."""
    color, normal = _textures()
    g, faces, _ = _garment(40, 30, 1)
    uv = _tube_uv(40, 30)
    skin = _chain_skin(g - [0.0, 1.0, 0.0])
    skeleton = {k: skin[k] for k in ("joints", "parents", "joint_names")}
    meshes = [
        {"vertices": g - [0.0, 1.0, 0.0], "faces": faces, "uv": uv, "material": _material(color, normal),
         "name": "shirt", "vertex_joints": skin["vertex_joints"], "vertex_weights": skin["vertex_weights"]},
        {"vertices": g * 1.1, "faces": faces, "uv": uv * 3.0, "name": "tiled",  # uv outside [0, 1]
         "material": _material(color, None, "MASK", 0.4)},
        {"vertices": g * 0.9, "faces": faces, "name": "plain", "color": (0.2, 0.3, 0.4, 1.0)},
    ]
    glb = scene_to_glb(meshes, skin=skeleton, compression=compression)
    _assert_clean_textured(validate_glb(glb))
    out = read_glb(glb)
    doc = out["json"]
    assert len(doc["images"]) == 2 and len(doc["textures"]) == 2 and len(out["images"]) == 2
    assert [im["data"] for im in out["images"]] == [color.data, normal.data]
    assert all(im["mime"] == "image/jpeg" for im in out["images"])
    m0, m1, m2 = doc["materials"]
    assert m0["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0} and m0["normalTexture"] == {"index": 1}
    assert m0["pbrMetallicRoughness"]["baseColorFactor"] == [0.9, 0.8, 0.7, 1.0] and m0["doubleSided"] is True
    assert m0["pbrMetallicRoughness"]["metallicFactor"] == pytest.approx(0.1)
    assert m0["pbrMetallicRoughness"]["roughnessFactor"] == pytest.approx(0.7)
    assert "alphaMode" not in m0 and m1["alphaMode"] == "MASK" and m1["alphaCutoff"] == pytest.approx(0.4)
    assert m1["pbrMetallicRoughness"]["baseColorTexture"] == {"index": 0} and "normalTexture" not in m1
    assert "baseColorTexture" not in m2["pbrMetallicRoughness"]
    shirt, tiled, plain = out["meshes"]
    tol = 0.0 if compression is None else 0.5 / 65535 + 1e-7
    assert np.abs(shirt["uv"] - uv).max() <= tol
    np.testing.assert_array_equal(tiled["uv"], uv * 3.0)  # FLOAT in every mode
    assert plain["uv"] is None and plain["tangents"] is None and tiled["tangents"] is None
    t = shirt["tangents"]
    assert t.shape == (len(g), 4) and set(np.unique(t[:, 3])) <= {-1.0, 1.0}
    if compression is not None:
        acc = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["TEXCOORD_0"]]
        assert acc["componentType"] == 5123 and acc["normalized"] is True


def test_tangents_follow_uv_directions() -> None:
    """On a flat grid (normal +Z) with u along +x and image-up (v' = 1 - v) along +y the tangent
    is +x with w = +1; mirroring u flips the tangent to -x and the handedness to -1."""
    from service.model.formats.gltf_buffers import vertex_tangents

    x, y = np.meshgrid(np.linspace(0, 1, 5), np.linspace(0, 1, 4))
    v = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    idx = np.arange(20).reshape(4, 5)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    n = np.tile([0.0, 0.0, 1.0], (20, 1))
    uv = np.stack([x.ravel(), 1.0 - y.ravel()], axis=1)
    t = vertex_tangents(v, faces, uv, n)
    np.testing.assert_allclose(t, np.tile([1.0, 0.0, 0.0, 1.0], (20, 1)), atol=1e-6)
    t = vertex_tangents(v, faces, np.stack([1.0 - x.ravel(), 1.0 - y.ravel()], axis=1), n)
    np.testing.assert_allclose(t, np.tile([-1.0, 0.0, 0.0, -1.0], (20, 1)), atol=1e-6)
    t = vertex_tangents(v, faces, np.zeros((20, 2)), n)  # no UV area: any unit tangent in the plane
    np.testing.assert_allclose(np.linalg.norm(t[:, :3], axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(t[:, 2], 0.0, atol=1e-6)


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_textured_basis_and_mesh(compression: str | None, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    color, normal = _textures()
    g, faces, B = _garment(30, 20, 3)
    uv = _tube_uv(30, 20)
    glb = basis_to_glb(g, B, faces, uv=uv, material=_material(color, normal), compression=compression)
    _assert_clean_textured(validate_glb(glb))
    out = read_glb(glb)
    assert out["uv"].shape == uv.shape and len(out["images"]) == 2 and out["targets"].shape == B.shape
    glb = mesh_to_glb(g, faces, uv=uv, material=_material(color, None), compression=compression)
    _assert_clean_textured(validate_glb(glb))
    assert read_glb(glb)["images"][0]["data"] == color.data


def test_textured_bad_inputs() -> None:
    from service.model.garments.catalogue import Texture

    color, _ = _textures()
    g, faces, _ = _garment(10, 5, 1)
    uv = _tube_uv(10, 5)
    with pytest.raises(ValueError, match="needs uv"):
        scene_to_glb([{"vertices": g, "faces": faces, "material": _material(color, None)}])
    with pytest.raises(ValueError, match="uv"):
        scene_to_glb([{"vertices": g, "faces": faces, "uv": uv[:-1]}])
    with pytest.raises(ValueError, match="uv"):
        scene_to_glb([{"vertices": g, "faces": faces, "uv": np.full_like(uv, np.nan)}])
    gif = Texture("x.gif", "image/gif", b"GIF89a")
    with pytest.raises(ValueError, match="mime"):
        scene_to_glb([{"vertices": g, "faces": faces, "uv": uv, "material": _material(gif, None)}])
    with pytest.raises(ValueError, match="alpha_mode"):
        scene_to_glb([{"vertices": g, "faces": faces, "uv": uv, "material": _material(color, None, "CLIP")}])


# --------------------------------------------------------------------------------------------
# Mesh templates: the static part of a mesh (faces, UVs, skinning) checked and encoded once.

def _template_scene(scale: float) -> tuple[list[dict[str, Any]], list[dict[str, Any]], dict[str, Any]]:
    """(the reference meshes, the same meshes with their static arrays as templates, the
    skeleton): a skinned normal-mapped mesh, a skinned untextured one, an unskinned tiled one."""
    color, normal = _textures()
    g, faces, _ = _garment(40, 30, 1)
    uv = _tube_uv(40, 30)
    skin = _chain_skin(g - [0.0, 1.0, 0.0])
    skeleton = {k: skin[k] for k in ("joints", "parents", "joint_names")}
    vj, vw = skin["vertex_joints"], skin["vertex_weights"]
    v = (g - [0.0, 1.0, 0.0]) * scale
    per = [  # per-request arrays and fields
        {"vertices": v, "material": _material(color, normal), "name": "shirt"},
        {"vertices": v * 1.05, "normals": vertex_normals(v * 1.05, faces), "name": "plain", "color": (0.2, 0.3, 0.4, 1.0)},
        {"vertices": g * 1.1, "material": _material(color, None, "MASK", 0.4), "name": "tiled"},
    ]
    static = [{"faces": faces, "uv": uv, "vertex_joints": vj, "vertex_weights": vw},
              {"faces": faces, "vertex_joints": vj, "vertex_weights": vw},
              {"faces": faces, "uv": uv * 3.0}]
    ref = [{**p, **s} for p, s in zip(per, static)]
    templates = [MeshTemplate(s["faces"], len(g), uv=s.get("uv"), vertex_joints=s.get("vertex_joints"),
                              vertex_weights=s.get("vertex_weights"),
                              n_joints=3 if "vertex_joints" in s else None) for s in static]
    fast = [{**p, "template": t} for p, t in zip(per, templates)]
    return ref, fast, skeleton


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_mesh_template_gives_the_same_bytes(compression: str | None,
                                            validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    """Templated meshes give byte for byte the GLB of the plain mesh dicts, in every mode, for
    other vertices too (the template's views are cached per mode); the validator is clean."""
    ref, fast, skeleton = _template_scene(1.0)
    glb = scene_to_glb(fast, skin=skeleton, compression=compression)
    assert glb == scene_to_glb(ref, skin=skeleton, compression=compression)
    _assert_clean_textured(validate_glb(glb))
    views = fast[0]["template"].views(compression)
    assert fast[0]["template"].views(compression) is views  # once per mode
    for m in fast + ref:  # another request: the same templates, other vertices
        m["vertices"] = np.asarray(m["vertices"]) * 0.97 + 0.01
    ref[1]["normals"] = fast[1]["normals"] = vertex_normals(ref[1]["vertices"], ref[1]["faces"])
    again = scene_to_glb(fast, skin=skeleton, compression=compression)
    assert again == scene_to_glb(ref, skin=skeleton, compression=compression) and again != glb
    out = read_glb(again)
    np.testing.assert_array_equal(_canon(out["indices"]), _canon(ref[0]["faces"]))


def test_mesh_template_bad_inputs() -> None:
    ref, fast, skeleton = _template_scene(1.0)
    g, faces = ref[0]["vertices"], ref[0]["faces"]
    with pytest.raises(ValueError, match="template has"):
        scene_to_glb([{**fast[0], "vertices": g[:-1]}], skin=skeleton)
    with pytest.raises(ValueError, match="joints"):
        scene_to_glb([fast[0]], skin={"joints": np.zeros((1, 3)), "parents": np.array([-1]), "joint_names": ["r"]})
    # morph targets are per-request arrays: a templated mesh takes them (pose correctives), the
    # same bytes as the reference path, dense or sparse
    t = np.zeros((2, len(g), 3))
    t[0, 3] = 0.01
    for sparse in (False, True):
        assert scene_to_glb([{**fast[2], "targets": t, "sparse_targets": sparse}]) == \
            scene_to_glb([{**ref[2], "targets": t, "sparse_targets": sparse}])
    with pytest.raises(ValueError, match="targets"):
        scene_to_glb([{**fast[2], "targets": np.zeros((1, len(g) - 1, 3))}])
    with pytest.raises(ValueError, match="finite"):
        scene_to_glb([{**fast[2], "vertices": np.where(np.arange(len(g))[:, None] == 5, np.inf, g)}])
    with pytest.raises(ValueError, match="range"):
        MeshTemplate(faces, len(g) - 5)
    with pytest.raises(ValueError, match="uv"):
        MeshTemplate(faces, len(g), uv=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="go together"):
        MeshTemplate(faces, len(g), vertex_joints=ref[0]["vertex_joints"], vertex_weights=ref[0]["vertex_weights"])
    with pytest.raises(ValueError, match="compression"):
        fast[0]["template"].views("draco")

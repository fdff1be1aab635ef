"""service.model.formats.mesh_io: scans of any topology (OBJ, PLY, STL, GLB, glTF, XYZ) -> arrays.

Real files are written with trimesh's exporters (and by hand for XYZ and PLY point clouds) and
read back; every failure must be a ScanError with a reason.
"""
from __future__ import annotations

import functools
import json
import struct
import time

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from service.model.geometry.mesh import cluster_vertices, closest_points_on_mesh, neighbour_mean, simplify
from service.model.formats.mesh_io import (
    KEPT_SCAN_POINTS,
    MAX_SCAN_POINTS,
    MIN_SCAN_POINTS,
    SCAN_TYPES,
    Scan,
    ScanError,
    estimate_normals,
    read_scan,
    scan_from_npz_bytes,
    scan_to_npz_bytes,
    scan_type,
    simplified,
)

RADII = np.array([0.25, 0.85, 0.15])  # a 1.7 m tall ellipsoid
CENTER = np.array([0.1, 0.9, -0.05])


@functools.lru_cache(maxsize=1)
def _body() -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=3)  # 642 vertices, outward winding
    return trimesh.Trimesh(m.vertices * RADII + CENTER, m.faces, process=False)


def body() -> trimesh.Trimesh:
    return _body().copy()


def true_normals(points: np.ndarray, radii=RADII, center=CENTER) -> np.ndarray:
    g = (points - center) / np.asarray(radii) ** 2
    return g / np.linalg.norm(g, axis=1, keepdims=True)


def ellipsoid_points(n: int, seed: int = 0, radii=RADII, center=CENTER) -> np.ndarray:
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True) * radii + center


def assert_outward_unit(scan: Scan, min_fraction: float = 0.95) -> None:
    n = scan.normals
    assert n is not None and n.shape == scan.points.shape and n.dtype == np.float64
    assert np.all(np.isfinite(n))
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-9)
    out = np.einsum("ij,ij->i", n, scan.points - scan.points.mean(axis=0))
    assert (out > 0).mean() >= min_fraction


def assert_same_points(a: np.ndarray, b: np.ndarray, tol: float = 1e-5) -> None:
    """Same point sets up to order (nearest distances both ways)."""
    assert len(a) == len(b)
    assert cKDTree(a).query(b)[0].max() < tol
    assert cKDTree(b).query(a)[0].max() < tol


def write(tmp_path, name: str, data: bytes | str) -> tuple[bytes, str]:
    path = tmp_path / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path.read_bytes(), path.name


def obj_text(vertices, faces=None, extra: str = "") -> str:
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in np.asarray(vertices, np.float64)]
    if faces is not None:
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces)]
    return "\n".join(lines) + "\n" + extra


def ply_points_binary(points: np.ndarray, normals: np.ndarray | None) -> bytes:
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    header = ("ply\nformat binary_little_endian 1.0\n"
              f"element vertex {len(points)}\n" + "".join(f"property float {c}\n" for c in names) + "end_header\n")
    cols = points if normals is None else np.hstack([points, normals])
    return header.encode() + np.ascontiguousarray(cols, "<f4").tobytes()


# -- meshes through every format ---------------------------------------------------------------
def _export(fmt: str) -> tuple[str, bytes]:
    m = body()
    if fmt == "obj":
        return "body.obj", m.export(file_type="obj").encode()
    if fmt in ("ply_ascii", "ply_binary"):
        return "body.ply", m.export(file_type="ply", encoding=fmt.split("_")[1])
    if fmt == "stl_binary":
        return "body.stl", m.export(file_type="stl")
    if fmt == "stl_ascii":
        return "body.stl", m.export(file_type="stl_ascii").encode()
    if fmt == "glb":
        return "body.glb", m.export(file_type="glb")
    if fmt == "gltf":
        files = m.export(file_type="gltf", embed_buffers=True)
        assert list(files) == ["model.gltf"]
        doc = json.loads(files["model.gltf"])
        assert all(b["uri"].startswith("data:") for b in doc["buffers"])
        return "body.gltf", files["model.gltf"]
    raise AssertionError(fmt)


@pytest.mark.parametrize("fmt,kind", [("obj", "obj"), ("ply_ascii", "ply"), ("ply_binary", "ply"),
                                      ("glb", "glb"), ("gltf", "gltf")])
def test_mesh_round_trip(tmp_path, fmt, kind):
    m = body()
    data, name = write(tmp_path, *_export(fmt))
    scan = read_scan(data, name)
    assert scan.kind == kind and not scan.is_point_cloud
    assert scan.points.dtype == np.float64 and scan.points.shape == (642, 3)
    assert scan.faces is not None and scan.faces.dtype == np.int64 and scan.faces.shape == (1280, 3)
    assert np.abs(scan.points - m.vertices).max() < 1e-6  # same order; float32 in binary files
    # same triangles (as vertex sets, any rotation of a face)
    assert np.array_equal(np.sort(np.sort(scan.faces, axis=1), axis=0), np.sort(np.sort(m.faces, axis=1), axis=0))
    assert_outward_unit(scan, 1.0)
    # area-weighted vertex normals of an ellipsoid are close to the analytic ones
    cos = np.einsum("ij,ij->i", scan.normals, true_normals(scan.points))
    assert np.quantile(cos, 0.05) > np.cos(np.radians(10))


@pytest.mark.parametrize("fmt", ["stl_binary", "stl_ascii"])
def test_stl_merges_the_triangle_soup(tmp_path, fmt):
    m = body()
    data, name = write(tmp_path, *_export(fmt))
    scan = read_scan(data, name)
    assert scan.kind == "stl" and scan.faces is not None
    assert scan.points.shape == (642, 3) and scan.faces.shape == (1280, 3)
    assert_same_points(scan.points, m.vertices)
    # the faces are the original triangles
    tri = np.sort(scan.points[scan.faces].reshape(-1, 9), axis=0)
    assert np.abs(tri - np.sort(m.vertices[m.faces].reshape(-1, 9), axis=0)).max() < 1e-5
    assert_outward_unit(scan, 1.0)


def test_stl_detected_by_content_not_name(tmp_path):
    _, stl = _export("stl_binary")
    assert read_scan(stl, "upload.bin").kind == "stl"
    assert read_scan(stl, None).kind == "stl"


def test_glb_scene_nodes_are_merged_with_their_transforms(tmp_path):
    m = body()
    scene = trimesh.Scene()
    scene.add_geometry(m, node_name="a", transform=trimesh.transformations.translation_matrix([2.0, 0, 0]))
    mirror = np.diag([-1.0, 1.0, 1.0, 1.0])  # a mirroring node: faces must stay outward
    mirror[:3, 3] = [-2.0, 0.0, 0.0]
    scene.add_geometry(m, node_name="b", transform=mirror)
    data, name = write(tmp_path, "scene.glb", scene.export(file_type="glb"))
    scan = read_scan(data, name)
    assert scan.points.shape == (1284, 3) and scan.faces.shape == (2560, 3)
    a = m.vertices + [2.0, 0.0, 0.0]
    b = m.vertices * [-1.0, 1.0, 1.0] + [-2.0, 0.0, 0.0]
    assert_same_points(scan.points, np.vstack([a, b]))
    for part in (scan.points[:, 0] > 0, scan.points[:, 0] < 0):
        p, n = scan.points[part], scan.normals[part]
        assert (np.einsum("ij,ij->i", n, p - p.mean(axis=0)) > 0).all()


def test_glb_points_primitive_is_a_point_cloud(tmp_path):
    pts = ellipsoid_points(800)
    data, name = write(tmp_path, "cloud.glb", trimesh.Scene(trimesh.PointCloud(pts)).export(file_type="glb"))
    scan = read_scan(data, name)
    assert scan.kind == "glb" and scan.is_point_cloud and scan.faces is None and scan.normals is None
    assert_same_points(scan.points, pts)


def test_unused_vertices_are_dropped_and_faces_remapped(tmp_path):
    m = body()
    v = np.vstack([[[9.0, 9.0, 9.0]], m.vertices, [[-9.0, 0.0, 0.0]]])
    data, name = write(tmp_path, "extra.obj", obj_text(v, m.faces + 1))
    scan = read_scan(data, name)
    assert scan.points.shape == (642, 3)
    assert np.array_equal(scan.points[scan.faces], m.vertices[m.faces])
    assert_outward_unit(scan, 1.0)


# -- point clouds --------------------------------------------------------------------------------
def test_obj_with_only_vertices_is_a_point_cloud(tmp_path):
    pts = ellipsoid_points(700)
    data, name = write(tmp_path, "cloud.obj", obj_text(pts))
    scan = read_scan(data, name)
    assert scan.kind == "obj" and scan.is_point_cloud and scan.normals is None
    assert np.abs(scan.points - pts).max() < 1e-9


@pytest.mark.parametrize("encoding", ["ascii", "binary"])
def test_ply_point_cloud_with_and_without_normals(tmp_path, encoding):
    pts = ellipsoid_points(700)
    nrm = true_normals(pts)
    if encoding == "binary":
        with_n = ply_points_binary(pts, nrm)
        without = ply_points_binary(pts, None)
    else:
        header = ("ply\nformat ascii 1.0\nelement vertex 700\nproperty float x\nproperty float y\n"
                  "property float z\nproperty float nx\nproperty float ny\nproperty float nz\n"
                  "property uchar red\nend_header\n")
        with_n = header + "".join(f"{a:.7f} {b:.7f} {c:.7f} {d:.7f} {e:.7f} {f:.7f} 200\n"
                                  for (a, b, c), (d, e, f) in zip(pts, nrm))
        without = trimesh.PointCloud(pts).export(file_type="ply", encoding="ascii")
    scan = read_scan(*write(tmp_path, "n.ply", with_n))
    assert scan.kind == "ply" and scan.is_point_cloud
    assert np.abs(scan.points - pts).max() < 1e-6
    assert scan.normals is not None and np.abs(scan.normals - nrm).max() < 1e-5
    assert np.allclose(np.linalg.norm(scan.normals, axis=1), 1.0)
    scan = read_scan(*write(tmp_path, "p.ply", without))
    assert scan.is_point_cloud and scan.normals is None and len(scan.points) == 700


def test_ply_point_cloud_with_unusable_normals_drops_them(tmp_path):
    pts = ellipsoid_points(700)
    nrm = true_normals(pts)
    nrm[5] = 0.0
    scan = read_scan(*write(tmp_path, "z.ply", ply_points_binary(pts, nrm)))
    assert scan.normals is None and len(scan.points) == 700
    nrm[5] = np.nan
    assert read_scan(*write(tmp_path, "nan.ply", ply_points_binary(pts, nrm))).normals is None


def test_xyz_with_normals_commas_and_comments(tmp_path):
    pts = ellipsoid_points(650)
    nrm = true_normals(pts)
    text = "# exported scan\n# x, y, z, nx, ny, nz\n" + "".join(
        f"{a:.9f}, {b:.9f}, {c:.9f}, {d:.9f}, {e:.9f}, {f:.9f}  # point {i}\n\n"
        for i, ((a, b, c), (d, e, f)) in enumerate(zip(pts, nrm)))
    scan = read_scan(*write(tmp_path, "scan.xyz", text))
    assert scan.kind == "xyz" and scan.is_point_cloud
    assert np.abs(scan.points - pts).max() < 1e-8
    assert np.abs(scan.normals - nrm).max() < 1e-8


def test_xyz_without_normals_and_with_colours(tmp_path):
    pts = ellipsoid_points(650)
    scan = read_scan(*write(tmp_path, "plain.xyz", "".join(f"{a}\t{b} {c}\n" for a, b, c in pts)))
    assert scan.normals is None and np.abs(scan.points - pts).max() < 1e-12
    # x y z r g b: the last three are colours, not normals
    text = "".join(f"{a} {b} {c} 255 128 {i % 256}\n" for i, (a, b, c) in enumerate(pts))
    scan = read_scan(*write(tmp_path, "rgb.xyz", text))
    assert scan.normals is None and len(scan.points) == 650


def test_the_services_own_glbs(tmp_path):
    """Avatars/try-ons written by service.model.formats.gltf: float32 (skinned or not) and quantized
    unskinned read back; compression trimesh cannot undo is refused with a reason."""
    from service.model.formats import gltf

    m = body()
    skin = {"joints": np.array([[0.1, 0.5, 0.0], [0.1, 1.2, 0.0]]), "parents": np.array([-1, 0]),
            "joint_names": ["root", "spine"], "vertex_joints": np.tile([0, 1, 0, 0], (642, 1)),
            "vertex_weights": np.tile([0.5, 0.5, 0.0, 0.0], (642, 1))}
    for sk in (None, skin):
        scan = read_scan(*write(tmp_path, "avatar.glb", gltf.mesh_to_glb(m.vertices, m.faces, skin=sk)))
        assert np.abs(scan.points - m.vertices).max() < 1e-6
    scan = read_scan(gltf.mesh_to_glb(m.vertices, m.faces, compression="quantize"), "q.glb")
    assert np.abs(scan.points - m.vertices).max() < 1e-4
    with pytest.raises(ScanError, match="quantized skinned"):
        read_scan(gltf.mesh_to_glb(m.vertices, m.faces, skin=skin, compression="quantize"), "qs.glb")
    with pytest.raises(ScanError, match="EXT_meshopt_compression"):
        read_scan(gltf.mesh_to_glb(m.vertices, m.faces, compression="meshopt"), "mo.glb")


def test_gltf_scene_size_is_checked_before_loading():
    doc = json.loads(_export("gltf")[1])
    doc["nodes"] = [{"mesh": 0, "translation": [float(i), 0.0, 0.0]} for i in range(10_001)]
    doc["scenes"] = [{"nodes": list(range(10_001))}]
    with pytest.raises(ScanError, match="nodes"):
        read_scan(json.dumps(doc).encode(), "many.gltf")
    doc["nodes"], doc["scenes"] = doc["nodes"][:10_000], [{"nodes": list(range(10_000))}]  # 6.4M instanced points
    t0 = time.perf_counter()
    with pytest.raises(ScanError, match="at most 2000000"):
        read_scan(json.dumps(doc).encode(), "instances.gltf")
    assert time.perf_counter() - t0 < 1.0


# -- glTF external buffers -------------------------------------------------------------------
@pytest.mark.parametrize("uri", ["model.bin", "https://example.com/model.bin", "/etc/passwd",
                                 "file:///etc/passwd", "../secret.bin"])
def test_gltf_external_buffer_uri_is_refused_and_never_opened(tmp_path, monkeypatch, uri):
    _, text = _export("gltf")
    doc = json.loads(text)
    import base64

    blob = base64.b64decode(doc["buffers"][0]["uri"].split("base64,", 1)[1])
    (tmp_path / "model.bin").write_bytes(blob)  # a real file it could have read
    monkeypatch.chdir(tmp_path)
    doc["buffers"][0]["uri"] = uri
    opened = []
    real_open = open

    def spy_open(file, *args, **kwargs):
        opened.append(str(file))
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr("builtins.open", spy_open)
    with pytest.raises(ScanError, match="external"):
        read_scan(json.dumps(doc).encode(), "body.gltf")
    assert not any("model.bin" in f or "passwd" in f or "secret" in f for f in opened)


def test_glb_with_external_buffer_is_refused():
    data = _export("glb")[1]
    jlen = struct.unpack_from("<I", data, 12)[0]
    doc = json.loads(data[20:20 + jlen])
    doc["buffers"].append({"uri": "extra.bin", "byteLength": 4})
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    rest = data[20 + jlen:]
    glb = struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(js) + len(rest)) + struct.pack("<II", len(js), 0x4E4F534A)
    with pytest.raises(ScanError, match="external"):
        read_scan(glb + js + rest, "x.glb")


# -- errors ------------------------------------------------------------------------------------
def test_scan_type():
    assert scan_type(b"glTF\x02\x00\x00\x00", "a.obj") == "glb"
    assert scan_type(b"ply\nformat ascii 1.0\n", None) == "ply"
    assert scan_type(b"solid body\nfacet normal 0 0 1\n", "a.txt") == "stl"
    assert scan_type(b"\xef\xbb\xbf  {\"asset\": {}}", None) == "gltf"
    assert scan_type(b"v 1 2 3\n", "Scan.OBJ") == "obj"
    assert scan_type(b"1 2 3\n", "dir.v2/scan.xyz") == "xyz"
    assert scan_type(b"\x00" * 80 + struct.pack("<I", 1) + b"\x00" * 50, None) == "stl"
    for name in (None, "scan", "scan.fbx", "dir.obj/scan"):
        with pytest.raises(ScanError) as err:
            scan_type(b"1 2 3\n", name)
        assert all(f".{t}" in str(err.value) for t in SCAN_TYPES)


@pytest.mark.parametrize("data,name,match", [
    (b"", "a.obj", "empty"),
    (b"\x00\x01\x02garbage\xff" * 50, "scan.bin", "unknown"),
    (b"\x00\x01\x02garbage\xff" * 50, "scan.glb", "GLB"),
    (b"\x00\x01\x02garbage\xff" * 50, "scan.ply", "PLY"),
    (b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4, "scan.xyz", "XYZ"),
    (b"ply\nformat ascii 1.0\nelement vertex 10\nproperty float x\nend_header\n1\n2\n", None, "PLY"),
    (b"glTF\x02\x00\x00\x00\x10\x00\x00\x00garbage!", "a.glb", "GLB"),
    (b'{"asset": {"version": "2.0"}, "meshes": [}', "a.gltf", "GLTF"),
    (b'{"asset": {"version": "2.0"}}', "a.gltf", "no points"),
    (b"# only a comment\n", "a.obj", "no points|cannot read"),
    (b"# nothing\n\n", "a.xyz", "no points"),
    (b"1 2\n3 4\n", "a.xyz", "expected"),
    (b"1 2 3\n4 5\n", "a.xyz", "XYZ"),
    (b"solid x\nfacet normal 0 0 1\n", "a.stl", "STL|no points"),
])
def test_garbage_is_a_scan_error(data, name, match):
    with pytest.raises(ScanError, match=match):
        read_scan(data, name)


def test_non_finite_coordinates(tmp_path):
    m = body()
    v = m.vertices.copy()
    v[10, 1] = np.nan
    with pytest.raises(ScanError, match="non-finite"):
        read_scan(*write(tmp_path, "nan.obj", obj_text(v, m.faces)))
    pts = ellipsoid_points(600)
    text = "".join(f"{a} {b} {c}\n" for a, b, c in pts) + "inf 0 0\n"
    with pytest.raises(ScanError, match="non-finite"):
        read_scan(*write(tmp_path, "inf.xyz", text))


def test_point_count_limits(tmp_path):
    data, name = write(tmp_path, *_export("ply_binary"))
    with pytest.raises(ScanError, match="at most 600"):
        read_scan(data, name, max_points=600)
    assert len(read_scan(data, name, max_points=642).points) == 642
    small = trimesh.creation.icosphere(subdivisions=2)  # 162 vertices
    with pytest.raises(ScanError, match=f"at least {MIN_SCAN_POINTS}"):
        read_scan(*write(tmp_path, "small.obj", obj_text(small.vertices, small.faces)))
    with pytest.raises(ScanError, match="at most 500"):
        read_scan(*write(tmp_path, "c.xyz", "".join(f"{a} {b} {c}\n" for a, b, c in ellipsoid_points(700))),
                  max_points=500)
    assert MAX_SCAN_POINTS == 2_000_000 and KEPT_SCAN_POINTS == 250_000 and MIN_SCAN_POINTS == 500


def test_face_index_out_of_range(tmp_path):
    m = body()
    text = obj_text(m.vertices, m.faces) + "f 1 2 9999\n"
    with pytest.raises(ScanError):
        read_scan(*write(tmp_path, "bad.obj", text))
    header = ("ply\nformat binary_little_endian 1.0\nelement vertex 642\nproperty float x\nproperty float y\n"
              "property float z\nelement face 1280\nproperty list uchar int vertex_indices\nend_header\n")
    faces = m.faces.copy()
    faces[7, 2] = 5000
    rows = np.zeros(1280, dtype=[("n", "u1"), ("f", "<i4", 3)])
    rows["n"], rows["f"] = 3, faces
    data = header.encode() + m.vertices.astype("<f4").tobytes() + rows.tobytes()
    with pytest.raises(ScanError, match="vertex 5000"):
        read_scan(data, "bad.ply")
    faces[7, 2] = -3
    rows["f"] = faces
    with pytest.raises(ScanError):
        read_scan(header.encode() + m.vertices.astype("<f4").tobytes() + rows.tobytes(), "neg.ply")


def test_degenerate_extent(tmp_path):
    with pytest.raises(ScanError, match="coincide"):
        read_scan(*write(tmp_path, "same.xyz", "0.5 1.0 2.0\n" * 600))
    g = np.stack(np.meshgrid(np.linspace(0, 1, 30), np.linspace(0, 2, 30)), -1).reshape(-1, 2)
    flat = np.column_stack([g[:, 0], g[:, 1], 0.3 * g[:, 0] - 0.1 * g[:, 1] + 1.0])
    with pytest.raises(ScanError, match="plane"):
        read_scan(*write(tmp_path, "flat.xyz", "".join(f"{a} {b} {c}\n" for a, b, c in flat)))
    line = np.outer(np.linspace(0, 1, 600), [1.0, 2.0, 3.0])
    with pytest.raises(ScanError, match="line"):
        read_scan(*write(tmp_path, "line.xyz", "".join(f"{a} {b} {c}\n" for a, b, c in line)))


def test_stray_points(tmp_path):
    pts = ellipsoid_points(700)
    pts[17] = [3e6, 0.0, 0.0]  # a corrupt coordinate (would otherwise look like a line)
    with pytest.raises(ScanError, match="stray"):
        read_scan(*write(tmp_path, "stray.xyz", "".join(f"{a} {b} {c}\n" for a, b, c in pts)))
    pts[17] = [30.0, 0.0, 0.0]  # an ordinary outlier is the fitting's business
    assert len(read_scan(*write(tmp_path, "ok.xyz", "".join(f"{a} {b} {c}\n" for a, b, c in pts))).points) == 700


def test_mutated_files_only_raise_scan_errors():
    rng = np.random.default_rng(1234)
    for fmt in ("obj", "ply_ascii", "ply_binary", "stl_binary", "glb", "gltf"):
        name, data = _export(fmt)
        for trial in range(12):
            buf = np.frombuffer(data, np.uint8).copy()
            if trial % 3 == 0:
                buf = buf[: int(rng.integers(1, len(buf)))]
            else:
                pos = rng.integers(0, len(buf), size=int(rng.integers(1, 40)))
                buf[pos] = rng.integers(0, 256, size=len(pos))
            try:
                scan = read_scan(buf.tobytes(), name)
            except ScanError as exc:
                assert str(exc)
            else:
                assert np.all(np.isfinite(scan.points)) and len(scan.points) >= MIN_SCAN_POINTS
                if scan.faces is not None:
                    assert scan.faces.min() >= 0 and scan.faces.max() < len(scan.points)
                if scan.normals is not None:
                    assert np.all(np.isfinite(scan.normals))


# -- normals of point clouds -----------------------------------------------------------------
def test_estimate_normals_on_an_ellipsoid():
    pts = ellipsoid_points(5000, seed=3)
    n = estimate_normals(pts)
    assert n.shape == pts.shape and n.dtype == np.float64
    assert np.allclose(np.linalg.norm(n, axis=1), 1.0)
    cos = np.einsum("ij,ij->i", n, true_normals(pts))
    assert (cos > np.cos(np.radians(30))).mean() >= 0.95


def test_estimate_normals_orients_each_component_outward():
    a = ellipsoid_points(1500, seed=4, radii=(0.3, 0.5, 0.2), center=(-2.0, 0.0, 0.0))
    b = ellipsoid_points(1000, seed=5, radii=(0.2, 0.2, 0.4), center=(3.0, 1.0, 0.0))
    pts = np.vstack([a, b])[np.random.default_rng(6).permutation(2500)]
    n = estimate_normals(pts)
    left = pts[:, 0] < 0
    for mask, radii, center in ((left, (0.3, 0.5, 0.2), (-2.0, 0.0, 0.0)), (~left, (0.2, 0.2, 0.4), (3.0, 1.0, 0.0))):
        cos = np.einsum("ij,ij->i", n[mask], true_normals(pts[mask], radii, center))
        assert (cos > np.cos(np.radians(30))).mean() >= 0.95


def test_estimate_normals_matches_mesh_normals_and_is_fast():
    pts = ellipsoid_points(12_500, seed=7)
    estimate_normals(pts[:1000])  # warm the imports
    t0 = time.perf_counter()
    n = estimate_normals(pts)
    seconds = time.perf_counter() - t0
    assert (np.einsum("ij,ij->i", n, true_normals(pts)) > np.cos(np.radians(30))).mean() >= 0.95
    assert seconds < 1.0, f"{seconds:.2f}s for 12,500 points"
    scan = read_scan(_export("glb")[1], "body.glb")
    cos = np.einsum("ij,ij->i", estimate_normals(scan.points), scan.normals)
    assert (cos > np.cos(np.radians(30))).mean() >= 0.95


def test_estimate_normals_small_inputs():
    with pytest.raises(ValueError):
        estimate_normals(np.zeros((2, 3)))
    pts = ellipsoid_points(8, seed=8)
    n = estimate_normals(pts, k=12)  # k larger than the cloud
    assert n.shape == (8, 3) and np.allclose(np.linalg.norm(n, axis=1), 1.0)


# -- queue storage -----------------------------------------------------------------------------
def test_npz_round_trip(tmp_path):
    mesh = read_scan(_export("ply_binary")[1], "body.ply")
    back = scan_from_npz_bytes(scan_to_npz_bytes(mesh))
    assert back.kind == "ply" and back.points.dtype == np.float64 and back.faces.dtype == np.int64
    assert np.array_equal(back.faces, mesh.faces)
    assert np.abs(back.points - mesh.points).max() <= 1e-6 * np.abs(mesh.points).max()
    assert np.abs(back.normals - mesh.normals).max() < 1e-6
    assert np.allclose(np.linalg.norm(back.normals, axis=1), 1.0, atol=1e-12)

    pts = ellipsoid_points(700) + 1000.0  # far from the origin: still float32-relative precision
    cloud = Scan(points=pts, faces=None, normals=None, kind="xyz")
    data = scan_to_npz_bytes(cloud)
    back = scan_from_npz_bytes(data)
    assert back.is_point_cloud and back.normals is None and back.kind == "xyz"
    assert np.abs(back.points - pts).max() < 1e-6
    with np.load(__import__("io").BytesIO(data), allow_pickle=False) as z:  # no pickled objects
        assert {"points", "kind", "origin"} <= set(z.files)
    for bad in (b"", b"not an npz", scan_to_npz_bytes(cloud)[:50]):
        with pytest.raises(ValueError):
            scan_from_npz_bytes(bad)


# -- dense scans simplified (issue 12: a body scanner's raw mesh has 0.2-2 M vertices) -----------
def _cluster_reference(vertices, faces, h, offset, keyed=None):
    """cluster_vertices, slowly: a dict of cells (of the ``keyed`` positions, if given), each
    cell's members nearest to its mean (all of them on a tie: two members are always as near),
    then the faces mapped to cells, collapsed ones dropped, repeats (as cell sets) dropped in
    order. Returns (faces as cell keys, {cell: acceptable representatives}, {vertex: cell})."""
    cells: dict = {}
    for i, v in enumerate(vertices if keyed is None else keyed):
        cells.setdefault(tuple(np.floor((v - offset) / h).astype(int)), []).append(i)
    nearest, cell_of = {}, {}
    for key, members in cells.items():
        mean = vertices[members].mean(0)
        d = [float(((vertices[i] - mean) ** 2).sum()) for i in members]
        nearest[key] = {i for i, di in zip(members, d) if di <= min(d) + 1e-12}
        for i in members:
            cell_of[i] = key
    out, seen = [], set()
    for f in faces:
        keys = tuple(cell_of[int(i)] for i in f)
        if len(set(keys)) < 3 or frozenset(keys) in seen:
            continue
        seen.add(frozenset(keys))
        out.append(keys)
    return out, nearest, cell_of


def _assert_clusters_as_reference(vertices, faces, h, offset, keyed=None):
    keep, F = cluster_vertices(vertices, faces, h, offset, keyed=keyed)
    ref_faces, nearest, cell_of = _cluster_reference(vertices, faces, h, offset, keyed)
    assert [tuple(cell_of[int(keep[i])] for i in f) for f in F] == ref_faces
    assert all(int(i) in nearest[cell_of[int(i)]] for i in keep)
    assert len(set(keep.tolist())) == len(keep) and len(keep) == len({k for f in ref_faces for k in f})


def test_vertex_clustering_against_a_slow_reference():
    m = trimesh.creation.icosphere(subdivisions=3)
    V = m.vertices * [0.3, 0.8, 0.2] + [0.05, 0.9, 0.0]
    for h, off in ((0.05, np.zeros(3)), (0.12, np.array([0.013, 0.07, 0.031]))):
        _assert_clusters_as_reference(V, m.faces, h, off)
        cloud, none = cluster_vertices(V, None, h, off)  # a cloud: one point per occupied cell
        assert none is None and len(cloud) == len({tuple(np.floor((v - off) / h).astype(int)) for v in V})
    keyed = V + np.random.default_rng(0).normal(scale=0.01, size=V.shape)  # cells from other positions
    _assert_clusters_as_reference(V, m.faces, 0.08, np.zeros(3), keyed=keyed)


def test_neighbour_mean_against_a_dense_reference():
    """Each vertex's mean over its edge neighbours, as a dense loop builds it: a shared edge
    counted once, a non-manifold edge (three triangles) too, a vertex on no face 0; each row's
    neighbours summed in descending order (bit for bit the order the smoothing always used)."""
    faces = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4], [5, 6, 7], [7, 6, 5]])
    n = 9  # vertex 8 on no face
    ref = np.zeros((n, n))
    for f in faces:
        for a in f:
            for b in f:
                ref[a, b] = float(a != b) or ref[a, b]
    ref /= np.maximum(ref.sum(1, keepdims=True), 1)
    A = neighbour_mean(faces, n)
    assert A.shape == (n, n) and A.indices.dtype == np.int32
    np.testing.assert_array_equal(A.toarray(), ref)
    for i in range(n):
        row = A.indices[A.indptr[i]:A.indptr[i + 1]]
        assert row.tolist() == sorted(np.flatnonzero(ref[i]).tolist(), reverse=True)
    x = np.random.default_rng(0).normal(size=(n, 3))
    np.testing.assert_allclose(A @ x, ref @ x, rtol=1e-15, atol=1e-15)


def _overshared_edges(faces) -> float:
    """The share of a mesh's edges on more than two triangles."""
    e = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    return float(np.mean(np.unique(e, axis=0, return_counts=True)[1] > 2))


def test_simplify_brings_a_dense_mesh_or_cloud_under_the_cap_on_its_own_surface():
    """Near the cap and never over it, the file's own points, the dense surface within a cell of
    the kept one; on a noisy surface the kept mesh stays manifold: its cells come from the
    smoothed vertices (SIMPLIFY_SMOOTHING), where cells from the raw ones put 12 % of the edges
    on more than two triangles (a speckled scan on the page)."""
    m = trimesh.creation.icosphere(subdivisions=6)  # 40,962 vertices, radius 1
    V = m.vertices * [0.25, 0.85, 0.15]
    keep, F = simplify(V, m.faces, 5_000)
    assert 0.8 * 5_000 <= len(keep) <= 5_000, len(keep)  # near the cap, never over it
    assert F.min() == 0 and F.max() == len(keep) - 1 and len(F) >= 1.8 * len(keep)
    noisy = V + np.random.default_rng(1).normal(scale=0.002, size=V.shape)
    keep_n, F_n = simplify(noisy, m.faces, 5_000)
    assert _overshared_edges(F_n) < 0.01 and len(F_n) < 2.05 * len(keep_n), _overshared_edges(F_n)
    raw = cluster_vertices(noisy, m.faces, 0.02, noisy.min(0))  # about as many cells from the raw vertices
    assert len(raw[0]) < 1.3 * len(keep_n) and _overshared_edges(raw[1]) > 0.05
    assert len(np.unique(keep)) == len(keep) and keep.min() >= 0 and keep.max() < len(V)  # the file's own points
    _, q, _ = closest_points_on_mesh(V, V[keep], F)  # the dense surface is within a cell of it
    assert np.linalg.norm(V - q, axis=1).max() < 0.01
    cloud, none = simplify(V, None, 5_000)
    assert none is None and 0.8 * 5_000 <= len(cloud) <= 5_000
    whole, same = simplify(V, m.faces, len(V))  # small enough: as it is
    assert np.array_equal(whole, np.arange(len(V))) and np.array_equal(same, m.faces)


def test_a_dense_scan_is_kept_simplified_with_its_own_normals(tmp_path):
    m = trimesh.creation.icosphere(subdivisions=5)  # 10,242 vertices
    V = m.vertices * RADII + CENTER
    scan = read_scan(*write(tmp_path, "dense.ply", trimesh.Trimesh(V, m.faces, process=False).export(file_type="ply")))
    small = simplified(scan, 2_000)
    assert small.source_points == len(scan.points) == 10_242 and len(small.points) <= 2_000
    assert small.kind == "ply" and small.faces is not None
    idx = cKDTree(scan.points).query(small.points)[1]
    assert np.array_equal(scan.points[idx], small.points) and np.array_equal(scan.normals[idx], small.normals)
    assert simplified(scan, 20_000) is scan and scan.source_points is None
    round_trip = scan_from_npz_bytes(scan_to_npz_bytes(small))
    assert np.array_equal(round_trip.faces, small.faces) and len(round_trip.points) == len(small.points)


def test_a_dense_mesh_of_slivers_is_refused_when_simplified():
    """700 separate tiny triangles spread over a metre: each collapses into one cell, no surface
    is left, and the scan is refused with a reason rather than stored empty."""
    rng = np.random.default_rng(3)
    centres = rng.uniform(size=(700, 1, 3))
    points = (centres + rng.normal(scale=1e-5, size=(700, 3, 3))).reshape(-1, 3)
    faces = np.arange(len(points)).reshape(-1, 3)
    scan = Scan(points=points, faces=faces, normals=None, kind="obj")
    with pytest.raises(ScanError, match="make no surface"):
        simplified(scan, 600)

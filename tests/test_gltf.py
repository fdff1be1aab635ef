"""GLB writer: Khronos validator reports no errors/warnings; positions/indices round-trip."""
from __future__ import annotations

import struct
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import trimesh

from service.model.gltf import mesh_to_glb, read_glb, vertex_normals
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

"""The OBJ reader (service.model.formats.obj_io) against a slow, obvious line-by-line reference, on tiny
files cut into many slices, on the MakeHuman catalogue's OBJs and on a 45 MB scan (memory)."""
from __future__ import annotations

import tracemalloc

import numpy as np
import pytest
import trimesh

from service.model.formats.obj_io import ObjError, read_obj
from tests.bench.common import shared_data_dir
from tests.test_faults import _person_tube, _text

MH_CLOTHES = shared_data_dir() / "makehuman_clothes"


def reference(data: bytes, uv: bool = False):
    """Line by line, as the OBJ specification reads: (vertices, faces, face_uv, uv)."""
    V, T, F, FT = [], [], [], []
    all_uv = True
    for line in data.decode().splitlines():
        words = line.split()
        if not words:
            continue
        if words[0] == "v":
            V.append([float(w) for w in words[1:4]])
        elif words[0] == "vt":
            T.append([float(w) for w in words[1:3]])
        elif words[0] == "f":
            refs = [w.split("/") for w in words[1:]]
            poly = [int(r[0]) for r in refs]
            poly = [p - 1 if p > 0 else len(V) + p for p in poly]
            tex = [int(r[1]) if len(r) > 1 and r[1] else 0 for r in refs]
            all_uv = all_uv and all(tex)
            tex = [t - 1 if t > 0 else len(T) + t for t in tex]
            for k in range(1, len(poly) - 1):
                F.append([poly[0], poly[k], poly[k + 1]])
                FT.append([tex[0], tex[k], tex[k + 1]])
    V = np.array(V, np.float64).reshape(-1, 3)
    F = np.array(F, np.int64).reshape(-1, 3)
    if uv and all_uv and len(F) and T:
        return V, F, np.array(FT, np.int64), np.array(T, np.float64)
    return V, F, None, None


def same(data: bytes, **kw) -> None:
    for uv in (False, True):
        want = reference(data, uv)
        for size in (1, 7, 64, 1 << 20):
            got = read_obj(data, uv=uv, slice_bytes=size, **kw)
            for a, b in zip(want, (got.vertices, got.faces, got.face_uv, got.uv)):
                assert (a is None) == (b is None)
                if a is not None:
                    assert a.shape == b.shape and np.array_equal(a, b), (uv, size, a, b)


def test_triangles_quads_polygons_and_every_corner_form():
    same(b"# a comment\nmtllib x.mtl\no thing\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 2 1e-3\n"
         b"vt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\nvn 0 0 1\ng part\nusemtl m\ns off\n"
         b"f 1/1/1 2/2/1 3/3/1\nf 1/1 3/3 4/4 5/1\nf 2//1 3//1 5//1\nl 1 2\nf 1 2 3 4 5\n")


def test_relative_indices_colours_w_blanks_and_line_ends():
    same(b"v 0 0 0 0.1 0.2 0.3\r\nv 1 0 0 0.1 0.2 0.3\r\n  v 1 1 0 0.1 0.2 0.3\r\n"
         b"\tvt 0 0 0\r\nvt 1 0 0\r\nvt 1 1 0\r\nf -3/-3 -2/-2 -1/-1\r\n"
         b"v   2  2   0 \t0.1 0.2 0.3\r\n  f -4/1 -3/2 -1/3\r\nf 1/1 2/2 4/3")
    same(b"v 0 0 0 1\nv 1 0 0 1\nv 1 1 0 1\nf -3 -2 -1\nv 5 5 5 1\nf 2 3 -1\n")  # w
    same(b"f 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n")  # faces before their vertices


def test_texture_layout_only_when_every_corner_has_one():
    data = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\nf 2 4 3\n"
    assert read_obj(data, uv=True).face_uv is None
    assert read_obj(data.replace(b"f 2 4 3", b"f 2/2 4/0 3/3"), uv=True).face_uv is None
    assert read_obj(data.replace(b"f 2 4 3", b"f 2/2 4/1 3/3"), uv=True).face_uv.shape == (2, 3)
    same(data)


def test_a_point_cloud_and_nothing():
    got = read_obj(b"v 0 0 0\nv 1 2 3\n")
    assert got.vertices.shape == (2, 3) and got.faces.shape == (0, 3)
    got = read_obj(b"# nothing\n")
    assert got.vertices.shape == (0, 3) and got.faces.shape == (0, 3)
    assert read_obj(b"").vertices.shape == (0, 3)


@pytest.mark.parametrize("data,match", [
    (b"v 0 0 0\nv 1 0 x\nv 0 1 0\nf 1 2 3\n", r"not a number: 'v 1 0 x'"),
    (b"v 0 0 0\nv 1 0\nv 0 1 0\nf 1 2 3\n", r"needs 3 numbers: 'v 1 0'"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3.5\n", r"not a whole number: 'f 1 2 3.5'"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 a\n", r"not a whole number"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", r"index 0"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", r"vertex 4, but the file has 3 vertices"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", r"vertex -4, but the file has 3 vertices"),
    (b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nf 1/1 2/1 3/2\n", r"texture vertex 2, but the file has 1"),
])
def test_malformed_statements_are_named(data, match):
    with pytest.raises(ObjError, match=match):
        read_obj(data, uv=True)


def test_round_trip_of_a_mesh():
    m = trimesh.creation.icosphere(subdivisions=3)
    data = trimesh.exchange.obj.export_obj(m, include_normals=True, include_texture=False).encode()
    got = read_obj(data)
    assert np.allclose(got.vertices, m.vertices, atol=1e-7) and np.array_equal(got.faces, m.faces)


@pytest.mark.slow
@pytest.mark.skipif(not MH_CLOTHES.is_dir(), reason="needs ../shared/data")
def test_the_makehuman_objs_read_as_the_reference_reads_them():
    files = sorted(MH_CLOTHES.rglob("*.obj"))
    assert len(files) >= 8
    for path in files:
        data = path.read_bytes()
        want = reference(data, uv=True)
        got = read_obj(data, uv=True)
        assert np.array_equal(want[0], got.vertices) and np.array_equal(want[1], got.faces), path
        assert np.array_equal(want[2], got.face_uv) and np.array_equal(want[3], got.uv), path


@pytest.mark.slow
def test_a_45_mb_scan_is_read_in_bounded_memory():
    """The test_faults upload scan (500,000 vertices, 1 M faces): the reader's peak allocation
    stays within 2.5x its result (trimesh's loader held ~8x)."""
    pts, faces = _person_tube(1000, 500)
    data = _text(pts, "v %.9f %.9f %.9f") + _text(faces + 1, "f %d %d %d")
    assert len(data) > 40e6
    tracemalloc.start()
    try:
        got = read_obj(data)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    result = got.vertices.nbytes + got.faces.nbytes
    assert np.abs(got.vertices - pts).max() < 1e-9 and np.array_equal(got.faces, faces)
    assert peak < 2.5 * result, (peak / 1e6, result / 1e6)

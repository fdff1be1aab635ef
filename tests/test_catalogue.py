"""The compiled demo catalogue (service/data/catalogue): its format, its loader, its fit to the
example avatars, the helpers it is built with, and a round trip of the build on a subset."""
from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.model.garments.catalogue import DEFAULT_CATALOGUE_DIR, load_catalogue, read_catalogue, render_layout
from service.model.geometry.mesh import closest_point_on_triangles, closest_points_on_mesh, vertex_normals
from service.model.formats.mhclo import parse_obj, parse_obj_faces
from service.model.garments.tryon import example_set, example_vertices
from tests.bench.common import shared_data_dir

REPO = Path(__file__).resolve().parent.parent
SHARED = shared_data_dir()
MAX_BYTES = 6_000_000  # the committed catalogue stays small
NEAR_MEDIAN_M, NEAR_MAX_M = 0.08, 0.40  # the retailer upload's rule (application/garments.py)


@pytest.fixture(scope="module")
def cat():
    return load_catalogue()


@pytest.fixture(scope="module")
def examples(model):
    return example_vertices(model, example_set(model))


# -- the committed data -----------------------------------------------------------------------
def test_catalogue_covers_the_shop(cat):
    g = cat.garments()
    assert len(g) >= 8
    cats = {(i.category, i.gender) for i in g}
    assert {("top", "female"), ("top", "male"), ("bottom", "female"), ("bottom", "male")} <= cats
    assert {i.category for i in g} >= {"top", "bottom", "suit", "shoes", "hat"}
    assert any(i.type == "skirt" for i in g) and any(i.type in ("jeans", "trousers") for i in g)
    assert len(cat.hair()) == 3
    for gender in ("female", "male"):
        look = cat.look(gender)
        assert look["eyes"].kind == "eyes" and look["eyebrows"].kind == "eyebrows" and look["hair"].kind == "hair"
        assert look["base_layer"] and all(i.category == "underwear" and i.layer == 0 for i in look["base_layer"])
        assert look["skin"].material.base_color_factor[3] == 1.0
    assert [i.id for i in cat.base_layer("female")] == ["base-bralette", "base-briefs"]
    assert [i.id for i in cat.base_layer("male")] == ["base-trunks"]
    # layers: underwear < bottoms < tops < jackets/suits < hats
    order = ["underwear", "bottom", "top", "jacket", "hat"]
    layer_of = {name: {i.layer for i in cat.items.values() if i.meta["layer_name"] == name} for name in order}
    assert layer_of["jacket"] == {i.layer for i in cat.items.values() if i.category == "suit"}
    for inner, outer in zip(order, order[1:]):
        assert max(layer_of[inner]) < min(layer_of[outer]), (inner, outer)


def test_items_are_well_formed(cat):
    from PIL import Image

    for it in cat.items.values():
        b = it.binding
        M = it.n_vertices
        assert b.indices.shape == b.weights.shape == b.offsets.shape == (M, 3), it.id
        assert b.indices.min() >= 0 and b.indices.max() < 19158, it.id
        np.testing.assert_allclose(b.weights.sum(axis=1), 1.0, atol=2e-3, err_msg=it.id)
        assert all(0 <= a < 19158 and 0 <= c < 19158 and r > 0 for a, c, r in b.scales), it.id
        assert it.faces.shape == it.face_uv.shape and it.faces.shape[1] == 3, it.id
        assert it.faces.min() >= 0 and it.faces.max() == M - 1, it.id  # every vertex used
        assert it.face_uv.min() >= 0 and it.face_uv.max() == len(it.uv) - 1, it.id
        assert np.all(np.isfinite(it.uv)) and it.uv.min() > -0.01 and it.uv.max() < 1.01, it.id
        assert it.hidden.ndim == 1 and (len(it.hidden) == 0 or it.hidden.max() < 13380), it.id
        m = it.material
        assert len(m.base_color_factor) == 4 and all(0 <= c <= 1 for c in m.base_color_factor), it.id
        assert m.alpha_mode in ("OPAQUE", "MASK", "BLEND") and m.metallic == 0.0
        for tex in (m.base_color_texture, m.normal_texture):
            if tex is None:
                continue
            magic = {"image/jpeg": b"\xff\xd8\xff", "image/png": b"\x89PNG"}[tex.mime]
            assert tex.data.startswith(magic), (it.id, tex.name)
            img = Image.open(io.BytesIO(tex.data))
            img.load()
            assert max(img.size) <= 1024, (it.id, img.size)
            if m.alpha_mode != "OPAQUE" and tex is m.base_color_texture:
                assert tex.mime == "image/png" and ("transparency" in img.info or img.mode in ("RGBA", "LA"))
    garments_textured = [i for i in cat.garments() if i.material.base_color_texture is not None]
    assert len(garments_textured) >= 8


def test_skins(cat, model):
    neutral, textured = cat.skins["skin-neutral"], cat.skins["skin-textured"]
    assert neutral.material.base_color_texture is None and neutral.body_uv is None
    assert textured.body_face_uv.shape == model.body_faces.shape
    assert textured.body_face_uv.max() == len(textured.body_uv) - 1
    lay = textured.render_layout(model.body_faces)
    assert lay.faces.shape == model.body_faces.shape
    np.testing.assert_array_equal(lay.vertex[lay.faces], model.body_faces)


def test_committed_files(cat):
    root = DEFAULT_CATALOGUE_DIR
    total = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert total < MAX_BYTES, total
    prov = (root / "PROVENANCE.md").read_text()
    assert "CC0 1.0" in prov and "8cf9645b975a98eea056b140df11a1d278da0d10" in prov
    assert "EN 13402-3" in prov and "Derived, not the standard" in prov  # the demo size charts
    for iid in list(cat.items) + list(cat.skins):
        assert f"`{iid}`" in prov, iid
    assert "CC0 1.0 Universal" in (root / "LICENSE_CC0.txt").read_text()
    doc = json.loads((root / "catalogue.json").read_text())
    referenced = {m["material"][k] for m in doc["items"] for k in ("base_color_texture", "normal_texture")
                  if m["material"][k]}
    assert referenced == {f"textures/{p.name}" for p in (root / "textures").iterdir()}


def test_loaded_once_per_process(cat):
    assert load_catalogue() is cat
    assert not cat.items["mens-tshirt"].faces.flags.writeable


# -- fitting ------------------------------------------------------------------------------------
@pytest.mark.slow
def test_every_item_fits_every_example_avatar(cat, model, examples):
    nb = model.n_body_vertices
    trees = [cKDTree(E[:nb]) for E in examples]
    for it in cat.items.values():
        for E, tree in zip(examples, trees):
            P = it.fit_to(E)
            assert P.shape == (it.n_vertices, 3) and np.all(np.isfinite(P)), it.id
            d = tree.query(P)[0]
            limit = 0.05 if it.kind in ("eyes", "eyebrows") else NEAR_MAX_M
            assert np.median(d) < NEAR_MEDIAN_M and d.max() < limit, (it.id, float(np.median(d)), float(d.max()))


def test_base_layer_sits_off_the_skin_with_clean_edges(cat, model):
    """On the mean avatar the generated base layer is >= 3 mm off the skin everywhere and its
    edges are smooth curves (a saw-tooth along triangle edges turns by 45-90 degrees)."""
    from worker.build.base_layer import BodySurface, boundary_edges

    X = model.mean.astype(np.float64)
    body = BodySurface(X[: model.n_body_vertices], model.body_faces)
    for it in cat.base_layer("female") + cat.base_layer("male"):
        P = it.fit_to(X)
        _, Q, _, n = body.closest(P)
        assert np.einsum("ij,ij->i", P - Q, n).min() > 0.003, it.id
        E = boundary_edges(it.faces)
        nbr: dict[int, list[int]] = {}
        for a, b in E.tolist():
            nbr.setdefault(a, []).append(b)
            nbr.setdefault(b, []).append(a)
        assert all(len(v) == 2 for v in nbr.values()), it.id  # simple closed loops
        for v, (a, b) in nbr.items():
            d0, d1 = P[v] - P[a], P[b] - P[v]
            turn = np.degrees(np.arccos(np.clip(d0 @ d1 / np.linalg.norm(d0) / np.linalg.norm(d1), -1, 1)))
            assert turn < 30, (it.id, v, turn)
        assert len(it.hidden) > 100, it.id


def test_hair_and_eyebrows_start_outside_the_head(cat, model):
    X = model.mean.astype(np.float64)
    nb = model.n_body_vertices
    normals = vertex_normals(X[:nb], model.body_faces)
    tree = cKDTree(X[:nb])
    for it in cat.hair() + [cat.items["eyebrows"]]:
        P = it.fit_to(X)
        i = tree.query(P)[1]
        h = np.einsum("ij,ij->i", P - X[i], normals[i])
        assert h.min() > -0.0005, (it.id, h.min())


# -- helpers against slow, obvious references ------------------------------------------------------
def test_render_layout_splits_uv_seams():
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    face_uv = np.array([[0, 1, 2], [4, 2, 3]])  # vertex 0 has uv 0 in one face, uv 4 in the other
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1], [0.5, 0.5]], np.float32)
    lay = render_layout(faces, face_uv, uv)
    ref = {}
    for f, t in zip(faces.ravel(), face_uv.ravel()):
        ref.setdefault((int(f), int(t)), len(ref))
    assert len(lay.vertex) == len(ref) == 5
    for k, (f, t) in enumerate(zip(faces.ravel(), face_uv.ravel())):
        r = lay.faces.ravel()[k]
        assert lay.vertex[r] == f
        np.testing.assert_allclose(lay.uv[r], [uv[t, 0], 1 - uv[t, 1]])  # glTF: origin top-left


def test_parse_obj_keeps_per_corner_uvs():
    text = "\n".join(["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 2 0 0",
                      "vt 0 0", "vt 1 0", "vt 1 1", "vt 0 1", "vt 0.5 0.5",
                      "f 1/1 2/2 3/3 4/4", "f -4/-1 5/2 3/3"]) + "\n"
    m = parse_obj(text)
    assert m.n_vertices == 5
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    np.testing.assert_array_equal(m.face_uv, [[0, 1, 2], [0, 2, 3], [4, 1, 2]])
    np.testing.assert_allclose(m.uv[4], [0.5, 0.5])
    n, f = parse_obj_faces(text)
    assert n == 5 and np.array_equal(f, m.faces)
    assert parse_obj("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n").face_uv is None  # no vt: no UVs


def test_closest_points_on_mesh_matches_brute_force():
    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.linspace(0, 1, 7), np.linspace(0, 1, 7)), -1).reshape(-1, 2)
    V = np.c_[g, 0.1 * np.sin(4 * g[:, 0]) * np.cos(3 * g[:, 1])]
    idx = np.arange(49).reshape(7, 7)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    P = rng.uniform([-0.1, -0.1, -0.2], [1.1, 1.1, 0.2], (200, 3))
    face, Q, bary = closest_points_on_mesh(P, V, F)
    tri = V[F]
    allq = closest_point_on_triangles(P[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    dmin = np.linalg.norm(allq - P[:, None], axis=-1).min(axis=1)
    np.testing.assert_allclose(np.linalg.norm(Q - P, axis=1), dmin, atol=1e-12)
    np.testing.assert_allclose(np.einsum("pk,pkd->pd", bary, V[F[face]]), Q, atol=1e-12)


def test_cut_isoline_follows_the_field_without_slivers():
    """A flat grid cut by a circle: the edge lies on the circle, the area is pi r^2, no slivers."""
    from worker.build.base_layer import boundary_edges, compact, cut_isoline

    n = 41
    g = np.stack(np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n)), -1).reshape(-1, 2)
    V = np.c_[g, np.zeros(len(g))]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    F = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    r = 0.63
    field = lambda P: r - np.linalg.norm(P[:, :2], axis=1)  # noqa: E731
    V2, F2 = compact(*cut_isoline(V, F, field(V), snap=0.3))
    bd = np.unique(boundary_edges(F2))
    # on the iso-line of the linearly interpolated field: within the chord error of the circle
    np.testing.assert_allclose(np.linalg.norm(V2[bd, :2], axis=1), r, atol=1e-3)
    e1, e2 = V2[F2[:, 1]] - V2[F2[:, 0]], V2[F2[:, 2]] - V2[F2[:, 0]]
    area = 0.5 * np.cross(e1, e2)[:, 2]
    assert area.min() > 0  # orientation kept, nothing degenerate
    assert abs(area.sum() - np.pi * r * r) < 0.01  # the polygon inscribed in the circle
    h = 2 / (n - 1)
    assert area.min() > 0.02 * h * h  # snapping leaves no slivers


# -- the build itself ---------------------------------------------------------------------------
SUBSET = ["mens-tshirt", "pencil-skirt", "leather-shoes", "eyebrows", "hair-short04", "base-briefs"]


@pytest.mark.slow
def test_build_round_trip_reproduces_the_committed_data(tmp_path):
    if not (SHARED / "makehuman_clothes").is_dir():
        if os.environ.get("CI"):
            pytest.fail("CI must run the catalogue build: ../shared/data is missing")
        pytest.skip("../shared/data (the MakeHuman sources) is not here")
    out = tmp_path / "catalogue"
    cmd = [sys.executable, "-m", "service.cli", "build-catalogue", "--items", ",".join(SUBSET), "--out", str(out)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=600,
                          env=dict(os.environ, PYTHONPATH=str(REPO)))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    new, ref = read_catalogue(out), load_catalogue()
    assert sorted(new.items) == sorted(SUBSET)
    with np.load(out / "arrays.npz") as a, np.load(DEFAULT_CATALOGUE_DIR / "arrays.npz") as b:
        for k in a.files:
            assert a[k].dtype == b[k].dtype, k
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    docs = [json.loads((d / "catalogue.json").read_text()) for d in (out, DEFAULT_CATALOGUE_DIR)]
    assert docs[0]["format"] == docs[1]["format"] and docs[0]["defaults"] == docs[1]["defaults"]
    ref_meta = {m["id"]: m for m in docs[1]["items"]}
    for m in docs[0]["items"]:
        assert m == ref_meta[m["id"]], m["id"]
    for p in (out / "textures").iterdir():
        assert p.read_bytes() == (DEFAULT_CATALOGUE_DIR / "textures" / p.name).read_bytes(), p.name
    assert new.items["mens-tshirt"].material.base_color_texture.data == \
        ref.items["mens-tshirt"].material.base_color_texture.data

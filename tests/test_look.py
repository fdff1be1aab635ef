"""The avatar's look (issue 11): eyes, eyebrows, hair and the base layer fitted from the compiled
catalogue to any avatar; the GLBs that carry them (validator-clean, named nodes, the hair and
underwear choices) and the routes (quick tier: in process on a leased Redis DB)."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.application import look as looks
from service.application import scenes
from service.application.errors import Invalid
from service.model.body.model import load_body_model
from service.model.geometry.mesh import closest_points_on_mesh
from service.model.formats.gltf_read import read_glb
from service.model.garments.look import HEAD_BONE, merge_meshes, transfer_skin_weights, visible_body_faces
from service.model.body.shape import avatar_from_measurements
from service.model.garments.tryon import customer_body
from service.settings import Settings
from tests.conftest import format_issues
from tests.harness import GLB, assert_422, redis_db, redis_url

BODIES = {"f160-55": ("female", 160, 55), "m185-80": ("male", 185, 80), "f165-105": ("female", 165, 105),
          "m200-130": ("male", 200, 130), "m150-45": ("male", 150, 45)}
LOOK_NODES = ["avatar", "eyes", "eyebrows", "hair", "underwear"]


@pytest.fixture(scope="module")
def model():
    return load_body_model()


@pytest.fixture(scope="module")
def bodies(model):
    out = {}
    for name, (g, h, w) in BODIES.items():
        a = avatar_from_measurements(model, {"gender": g, "height_cm": h, "weight_kg": w})
        out[name] = (a.measurements["gender"], customer_body(model, a.weights))
    return out


def _signed_distance(points: np.ndarray, model, X: np.ndarray) -> np.ndarray:
    """Signed distance (P,) of points to the body surface (> 0 outside), exact closest points."""
    nb = model.n_body_vertices
    V = np.asarray(X[:nb], np.float64)
    F = np.asarray(model.body_faces, np.int64)
    face, cp, _ = closest_points_on_mesh(np.asarray(points, np.float64), V, F)
    n = np.cross(V[F[face, 1]] - V[F[face, 0]], V[F[face, 2]] - V[F[face, 0]])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.einsum("ij,ij->i", np.asarray(points, np.float64) - cp, n)


# -- the maths -----------------------------------------------------------------------------------
def test_transfer_skin_weights_is_the_nearest_vertex() -> None:
    rng = np.random.default_rng(0)
    body = rng.normal(size=(50, 3))
    idx = rng.integers(0, 17, size=(50, 4))
    w = rng.random((50, 4))
    pts = rng.normal(size=(20, 3))
    ji, jw = transfer_skin_weights(pts, body, idx, w)
    for p, a, b in zip(pts, ji, jw):
        k = int(np.argmin(((body - p) ** 2).sum(1)))
        assert np.array_equal(a, idx[k]) and np.allclose(b, w[k])


def test_visible_body_faces_and_merge() -> None:
    faces = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4], [3, 4, 5]])
    kept = visible_body_faces(faces, np.array([1, 2, 3]), 6)
    assert kept.tolist() == [[0, 1, 2], [2, 3, 4], [3, 4, 5]]  # only the all-hidden face goes
    a = {"vertices": np.zeros((3, 3)), "faces": np.array([[0, 1, 2]])}
    b = {"vertices": np.ones((4, 3)), "faces": np.array([[0, 1, 2], [1, 2, 3]])}
    m = merge_meshes([a, b])
    assert m["vertices"].shape == (7, 3) and m["faces"].tolist() == [[0, 1, 2], [3, 4, 5], [4, 5, 6]]


def test_look_fits_every_body(model, bodies) -> None:
    """On the five bodies of the issue: hair outside the head, underwear outside the skin, eyes
    in their sockets (not popping out), eyebrows on the skin; head items rigid to the head."""
    cat = looks.catalogue()
    for name, (gender, body) in bodies.items():
        X = body.vertices
        for hair in [h.id for h in cat.hair()]:
            lk = looks.resolve(gender, hair)
            meshes = {m["name"]: m for m in looks.item_meshes(model, X, body.normals, lk)}
            d = _signed_distance(meshes["hair"]["vertices"], model, X)
            # pushed out with 2 mm clearance (at the nearest body vertex's tangent plane: a few
            # vertices of the bob's tips by the neck stay up to 3 mm in; see the report)
            assert (d > 0).mean() > 0.995 and d.min() > -0.003, (name, hair, d.min(), (d <= 0).sum())
            assert np.percentile(d, 1) > 0.0015, (name, hair)
        lk = looks.resolve(gender)
        meshes = {m["name"]: m for m in looks.item_meshes(model, X, body.normals, lk)}
        assert list(meshes) == LOOK_NODES[1:]
        d = _signed_distance(meshes["underwear"]["vertices"], model, X)
        assert np.percentile(d, 1) > 0.002 and d.min() > 0.0, (name, d.min())
        d = _signed_distance(meshes["eyes"]["vertices"], model, X)
        assert -0.03 < d.min() and d.max() < 0.006, (name, d.min(), d.max())  # the cornea just out of the lids
        d = _signed_distance(meshes["eyebrows"]["vertices"], model, X)
        assert np.all(np.abs(d) < 0.006), (name, np.abs(d).max())
        for part in ("eyes", "eyebrows", "hair"):
            assert np.all(meshes[part]["vertex_joints"][:, 0] == HEAD_BONE)
            assert np.all(meshes[part]["vertex_weights"][:, 0] == 1.0)
        head_top = X[: model.n_body_vertices, 1].max()
        assert meshes["eyes"]["vertices"][:, 1].min() > head_top - 0.2  # on the head, wherever the body


def test_underwear_keeps_out_of_a_heavy_crotch(model) -> None:
    """The base layer's push-out on a 179 cm / 111 kg man (the one of 50 held-out ANSUR
    customers whose briefs and trunks went into the body: 30 vertices, up to 3.4 mm): near a
    crease of the mean avatar the items bind to this body's own nearest vertices with the crease
    anchors (``PreparedItem.prone``, ``garment.crease_anchors``), and no vertex is more than
    1 mm inside him (exact closest triangle and winding number, as ``tryon bench tryon``)."""
    from scipy.spatial import cKDTree

    from service.model.geometry.mesh import vertex_faces
    from service.model.garments.tryon import surface_body
    from tests.bench.tryon import penetrations

    a = avatar_from_measurements(model, {
        "gender": "male", "height_cm": 179.1, "weight_kg": 111.4, "chest_cm": 111.5, "waist_cm": 109.1,
        "hip_cm": 113.5, "thigh_cm": 75.5, "calf_cm": 45.1, "waist_height_cm": 106.5, "shoulder_width_cm": 45.9,
        "inseam_cm": 87.8, "arm_length_cm": 62.4})
    body = customer_body(model, a.weights)
    nb = model.n_body_vertices
    X = body.vertices[:nb].astype(np.float64)
    args = (X, body.normals, model.body_faces, cKDTree(X), vertex_faces(model.body_faces, nb))
    cat = looks.catalogue()
    before = after = 0
    for item in ("base-briefs", "base-trunks"):
        p = looks.prepared(model, cat.items[item])
        assert p.prone is not None and 0 < len(p.prone) < 0.1 * len(p.near)
        after += len(penetrations(p.fit_vertices(body.vertices, body.normals, surface_body(model, body.vertices,
                                                                                         body.normals)), *args)[1])
        before += len(penetrations(p.fit_vertices(body.vertices, body.normals), *args)[1])
    assert before >= 10 and after == 0, (before, after)


def test_resolve_choices() -> None:
    cat = looks.catalogue()
    assert looks.resolve("female").hair.id == cat.look("female")["hair"].id
    assert looks.resolve("male").hair.id == cat.look("male")["hair"].id
    assert looks.resolve("male", "none").hair is None
    assert looks.resolve("male", "hair-bob02").hair.id == "hair-bob02"
    assert looks.resolve("female", underwear=False).base_layer == ()
    assert len(looks.resolve("female").hidden) > 0
    with pytest.raises(Invalid) as e:
        looks.resolve("female", "mohawk")
    assert e.value.loc == ("query", "hair")
    keys = {looks.resolve("female", h, u).key for h in (None, "none", "hair-short04") for u in (True, False)}
    assert len(keys) == 6


# -- the GLB ------------------------------------------------------------------------------------
@pytest.mark.parametrize("compression", [None, "quantize", "meshopt"])
def test_avatar_glb_with_look_is_valid(model, bodies, validate_glb, compression) -> None:
    gender, body = bodies["f165-105"]
    data = scenes.avatar_glb(model, body.vertices, compression, normals=body.normals, look=looks.resolve(gender))
    report = validate_glb(data)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, format_issues(report)
    glb = read_glb(data)
    doc = glb["json"]
    assert [doc["nodes"][i]["name"] for i in range(5)] == LOOK_NODES
    assert all(doc["nodes"][i].get("skin") == 0 for i in range(5))
    mats = {m["name"]: m for m in doc["materials"]}
    assert "baseColorTexture" in mats["eyes_material"]["pbrMetallicRoughness"]  # irises
    assert "baseColorTexture" in mats["hair_material"]["pbrMetallicRoughness"]
    assert mats["avatar_material"]["pbrMetallicRoughness"]["baseColorFactor"] != list(scenes.AVATAR_COLOR)
    assert len(doc["images"]) == 3  # eyes, eyebrows, hair
    # the body under the base layer is not drawn
    assert len(glb["indices"]) < len(model.body_faces)


@pytest.mark.slow
def test_renderer_draws_the_avatar_glb_and_preview_scenes(model, bodies, tmp_path) -> None:
    """worker/build/preview.mjs in Chromium (three.js): a GLB as a shop's viewer loads it
    (``--glb``: every look node drawn, skinned, three textured; the front view shows the body,
    the face view the head) and the catalogue build's JSON scenes (``preview.render``)."""
    import json
    import os
    import subprocess
    from pathlib import Path

    from PIL import Image

    from worker.build import preview

    gender, body = bodies["m200-130"]
    data = scenes.avatar_glb(model, body.vertices, None, normals=body.normals, look=looks.resolve(gender))
    (tmp_path / "tall.glb").write_bytes(data)
    script = Path(preview.__file__).with_name("preview.mjs")
    proc = subprocess.run(["node", str(script), "--glb", str(tmp_path / "out"), str(tmp_path / "tall.glb")],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "VIEWS": "front,face"},
                          cwd=script.parent.parent.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    assert out["errors"] == [] and len(out["images"]) == 2
    info = out["scenes"]["tall"]
    assert info["meshes"] == LOOK_NODES and info["skinned"] == 5 and info["textured"] == 3
    assert 1.95 < info["bbox"][1][1] < 2.1  # a 200 cm man
    bg = np.array([242, 242, 242])
    for view, lo, hi in (("front", 0.08, 0.6), ("face", 0.4, 0.98)):
        px = np.asarray(Image.open(tmp_path / "out" / f"tall-{view}.png").convert("RGB"), np.int64)
        drawn = (np.abs(px - bg).sum(-1) > 30).mean()
        assert lo < drawn < hi, (view, drawn)  # the whole body small; the head filling the frame
    mesh = preview.mesh("box", body.vertices[: model.n_body_vertices], model.body_faces, color=(0.8, 0.3, 0.2, 1.0))
    res = preview.render([{"name": "bare", "views": ["front"], "width": 200, "height": 300, "meshes": [mesh]}],
                         tmp_path / "json")
    assert res["errors"] == [] and len(res["images"]) == 1
    px = np.asarray(Image.open(res["images"][0]).convert("RGB"), np.int64)
    assert (np.abs(px - bg).sum(-1) > 30).mean() > 0.05


def test_avatar_glb_choices(model, bodies) -> None:
    gender, body = bodies["m185-80"]
    bare = read_glb(scenes.avatar_glb(model, body.vertices, look=looks.resolve(gender, "none", False)))
    assert [m["name"] for m in bare["meshes"]] == ["avatar", "eyes", "eyebrows"]
    assert len(bare["indices"]) == len(model.body_faces)
    plain = read_glb(scenes.avatar_glb(model, body.vertices))  # no look: the body alone (template)
    assert [m["name"] for m in plain["meshes"]] == ["avatar"]


# -- the routes ---------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("look"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False,  # the catalogue items these tests try on
                            TRYON_DEMO_ITEMS="womens-tshirt,pinstripe-blouse,cropped-tee,womens-jeans,mens-jeans,"
                                             "business-suit")
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def _names(data: bytes) -> list[str]:
    return [m["name"] for m in read_glb(data)["meshes"]]


def test_routes(client: TestClient, validate_glb) -> None:
    looks_doc = client.get("/v1/looks").json()
    ids = [h["id"] for h in looks_doc["hair"]]
    assert {"hair-bob02", "hair-short02"} <= set(ids)
    assert all(set(h) == {"id", "name", "gender", "color"} for h in looks_doc["hair"])
    assert looks_doc["defaults"]["female"] == {"hair": "hair-bob02", "underwear": True}

    r = client.post("/v1/customers", json={"measurements": {"gender": "male", "height_cm": 185, "weight_kg": 80}})
    c = r.json()
    h = {"Authorization": f"Bearer {c['token']}"}
    url = f"/v1/customers/{c['id']}/avatar.glb"
    r = client.get(url, headers=h)
    assert r.status_code == 200 and _names(r.content) == LOOK_NODES  # underwear and hair by default
    report = validate_glb(r.content)
    assert report["issues"]["numErrors"] == 0, format_issues(report)
    tag = r.headers["etag"]
    assert client.get(url, headers={**h, "If-None-Match": tag}).status_code == 304
    r = client.get(url, params={"hair": "none", "underwear": "false"}, headers=h)
    assert _names(r.content) == ["avatar", "eyes", "eyebrows"] and r.headers["etag"] != tag
    r = client.get(url, params={"hair": "hair-short04"}, headers=h)
    assert r.status_code == 200 and _names(r.content) == LOOK_NODES and r.headers["etag"] != tag
    assert_422(client.get(url, params={"hair": "mohawk"}, headers=h), ["query", "hair"], ("unknown hair",))
    assert_422(client.get(url, params={"underwear": "maybe"}, headers=h), ["query", "underwear"])

    r = client.get(f"/v1/customers/{c['id']}/outfit.glb", params={"hair": "none"}, headers=h)
    assert r.status_code == 200 and _names(r.content) == ["avatar", "eyes", "eyebrows", "underwear"]

    r = client.post("/v1/avatars", json={"measurements": {"gender": "female"}}, headers={"Accept": GLB})
    assert _names(r.content) == LOOK_NODES
    r = client.post("/v1/avatars", params={"underwear": "false", "hair": "none"}, json={"measurements": {}},
                    headers={"Accept": GLB})
    assert _names(r.content) == ["avatar", "eyes", "eyebrows"]


def test_outfit_keeps_the_base_layer_under_the_clothes(client: TestClient) -> None:
    """A heavy body in a blouse: the look's underwear is the outfit's innermost layer, pushed
    inside the top where the top covers it (service.model.garments.layering), so no bra shows through;
    measured with the layering figure (share of body vertices covered by both where the inner
    one is outside the outer one)."""
    from service.model.garments.layering import inner_outside_share

    r = client.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 165, "weight_kg": 105}})
    c = r.json()
    h = {"Authorization": f"Bearer {c['token']}"}
    tops = [g for g in client.get("/v1/garments").json() if g.get("category") == "top" and g.get("gender") == "female"]
    assert tops
    for top in tops[:3]:
        r = client.get(f"/v1/customers/{c['id']}/outfit.glb", params={"garments": top["id"], "hair": "none"},
                       headers=h)
        assert r.status_code == 200, r.text
        meshes = {m["name"]: m for m in read_glb(r.content)["meshes"]}
        body, under = meshes["avatar"], meshes["underwear"]
        outer = next(m for name, m in meshes.items() if name not in ("avatar", "eyes", "eyebrows", "underwear"))
        both, outside = inner_outside_share(under["positions"], outer["positions"], outer["indices"],
                                            under["indices"], body["positions"], body["normals"], body["indices"])
        assert both > 100, (top["name"], both)  # the top covers the bra
        # without the base layer in the layering: 325 of 636 (51 %) for the women's T-shirt
        print(f"base layer outside {top['name']}: {outside} of {both}")
        assert outside <= 0.06 * both, (top["name"], outside, both)  # goal 1 %: not met yet (see README)


HEAVY_MAN = {"gender": "male", "height_cm": 179.1, "weight_kg": 111.4, "chest_cm": 111.5, "waist_cm": 109.1,
             "hip_cm": 113.5, "thigh_cm": 75.5, "calf_cm": 45.1, "waist_height_cm": 106.5, "shoulder_width_cm": 45.9,
             "inseam_cm": 87.8, "arm_length_cm": 62.4}


@pytest.mark.slow
def test_nothing_inside_a_heavy_crotch_over_http(client: TestClient, model) -> None:
    """End to end, the crease anchors (``garment.crease_anchors``) in what a shop gets: the
    179 cm / 111 kg man's avatar.glb (its underwear) and try-on GLBs of catalogue bottoms: GLB
    vertices more than 1 mm inside him, without the anchors (``garment.CREASE_COS`` = -2):
    underwear 18, women's jeans 6, men's jeans 3, business suit 4; none now (exact closest
    triangle and winding number against the GLB's own body vertices, as ``tryon bench tryon``)."""
    from scipy.spatial import cKDTree

    from service.model.geometry.mesh import vertex_faces, vertex_normals
    from tests.bench.tryon import penetrations

    c = client.post("/v1/customers", json={"measurements": HEAVY_MAN}).json()
    h = {"Authorization": f"Bearer {c['token']}"}
    r = client.get(f"/v1/customers/{c['id']}/avatar.glb", params={"hair": "none"}, headers=h)
    assert r.status_code == 200
    meshes = {m["name"]: m for m in read_glb(r.content)["meshes"]}
    nb = model.n_body_vertices
    X = np.asarray(meshes["avatar"]["positions"], np.float64)
    assert X.shape == (nb, 3)
    F = np.asarray(model.body_faces, np.int64)
    args = (X, vertex_normals(X, F), F, cKDTree(X), vertex_faces(F, nb))
    inside = {"underwear": len(penetrations(meshes["underwear"]["positions"], *args)[1])}
    ids = {g.get("catalogue_id"): g["id"] for g in client.get("/v1/garments").json()}
    for gid in ("womens-jeans", "mens-jeans", "business-suit"):
        r = client.get(f"/v1/customers/{c['id']}/garments/{ids[gid]}.glb", headers=h)
        assert r.status_code == 200, r.text
        (mesh,) = [m for m in read_glb(r.content)["meshes"] if m["name"] != "avatar"]
        inside[gid] = len(penetrations(mesh["positions"], *args)[1])
    assert not any(inside.values()), inside


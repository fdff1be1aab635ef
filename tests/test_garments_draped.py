"""Garments draped on one body (issue 10) through the API in process (quick tier): the upload's
checks (422 before any job), the building garment in the catalogue, 409 try-ons, delete; and the
build job run in process end to end (a garment on `mean` in cm -> ready -> tried on)."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.application.scenes import obj_text
from service.model.formats.gltf_read import read_glb
from service.settings import Settings
from tests import draped_data as D
from tests.bench.common import shared_data_dir
from tests.harness import RETAILERS, assert_422, redis_db, redis_url

# each test builds garments through the API (seconds each): the full tier
pytestmark = pytest.mark.slow

KEY = {"X-API-Key": RETAILERS["acme"]}


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("draped"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def _post(client: TestClient, garment: bytes, name: str = "g.obj", **form) -> object:
    files = {"garment": (name, garment)}
    if "avatar" in form:
        files["avatar"] = ("avatar.ply", form.pop("avatar"))
    return client.post("/v1/garments", data={"name": "Suit", **form}, files=files, headers=KEY)


def test_bad_draped_uploads_get_422_and_leave_nothing(client: TestClient, model) -> None:
    ctx = client.app.state.context
    before = {g["id"] for g in client.get("/v1/garments").json()}
    good = D.on_mean(model).garment_obj
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    cases = [
        (_post(client, b"\x00garbage\xff" * 50, "g.obj"), ["body", "garment"], ()),
        (_post(client, obj_text(np.full((4, 3), np.nan), faces).encode()), ["body", "garment"], ("non-finite",)),
        (_post(client, b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 1\n"), ["body", "garment"], ("faces",)),
        (_post(client, good, on="nobody"), ["body", "on"], ("unknown example avatar",)),
        (_post(client, good, on="mean", avatar=b"ply"), ["body", "on"], ("either",)),
    ]
    far = D.on_mean(model).reference + [0.0, 0.0, 0.4]
    cases.append((_post(client, obj_text(far, D.binding(model)[1]).encode()), ["body", "garment"],
                  ("not around the body", "cm from the body surface")))
    rng = np.random.default_rng(0)
    box = rng.uniform(-1, 1, size=(3000, 3)) * [0.2, 0.9, 0.15]
    cases.append((_post(client, good, avatar=obj_text(box, faces).encode()), ["body", "avatar"], ()))
    for r, loc, words in cases:
        assert_422(r, loc, words)
    msg = assert_422(cases[5][0])
    assert any(ch.isdigit() for ch in msg)  # the distance is in the message
    assert {g["id"] for g in client.get("/v1/garments").json()} == before
    assert ctx.queue.queue.count == 0
    assert not ctx.conn.keys(ctx.settings.redis_prefix + "garment-upload:*")


def test_draped_garment_builds_and_is_tried_on(client: TestClient, model, validate_glb) -> None:
    ctx = client.app.state.context
    draped = D.on_mean(model, scale=100.0)  # exported in cm
    r = _post(client, draped.garment_obj, "suit.obj", color="#336699", layer="2")
    assert r.status_code == 202, r.text
    g = r.json()
    gid, job = g["id"], g["job"]
    assert g["status"] == "building" and g["source"] == "draped" and g["progress"] == 0.0
    assert job == {"id": f"build-{gid}", "url": f"/v1/jobs/build-{gid}", "status": "queued"}
    assert r.headers["location"] == job["url"] and g["unit"] == "cm" and g["on"] == "mean"
    listed = {x["id"]: x for x in client.get("/v1/garments").json()}[gid]
    assert listed["status"] == "building" and listed["job"]["status"] == "queued"
    assert client.get(job["url"]).status_code == 404  # a retailer's job: its key opens it
    j = client.get(job["url"], headers=KEY).json()
    assert j["kind"] == "garment" and j["garment_id"] == gid and j["status"] == "queued"
    created = client.post("/v1/customers", json={"measurements": {"height_cm": 181, "weight_kg": 92}}).json()
    cust, auth = created["id"], {"Authorization": f"Bearer {created['token']}"}
    for path in (f"/v1/customers/{cust}/garments/{gid}.glb", f"/v1/garments/{gid}/basis.glb",
                 f"/v1/customers/{cust}/outfit.glb?garments={gid}"):
        r = client.get(path, headers=auth)
        assert r.status_code == 409 and "being built" in r.json()["detail"], (path, r.text)
    assert not ctx.bases.path(gid).exists()
    # the job, in process (a worker runs the same use case: worker.jobs.build_garment)
    seen = []
    out = ctx.garments.run_build(gid, lambda f, m: seen.append(f))
    assert out == {"status": "done", "garment_id": gid}
    assert seen == sorted(seen) and seen[-1] == 1.0
    assert ctx.garments.run_build(gid, lambda f, m: None) == out  # idempotent
    g = client.get(f"/v1/garments/{gid}").json()
    assert g["status"] == "ready" and g["n_components"] == 32 and g["etag"]
    r = client.get(f"/v1/customers/{cust}/garments/{gid}.glb", headers=auth)
    assert r.status_code == 200
    glb = read_glb(r.content)
    assert glb["positions"].shape[0] == len(draped.reference)
    report = validate_glb(r.content)
    assert report["issues"]["numErrors"] == 0
    assert not ctx.conn.exists(ctx.garments_repo.upload_key(gid))
    assert client.delete(f"/v1/garments/{gid}", headers=KEY).status_code == 204
    assert not ctx.bases.path(gid).exists() and client.get(f"/v1/garments/{gid}").status_code == 404


def test_delete_while_waiting_removes_upload_and_job(client: TestClient, model) -> None:
    ctx = client.app.state.context
    g = _post(client, D.on_mean(model).garment_obj).json()
    assert ctx.conn.exists(ctx.garments_repo.upload_key(g["id"])) and client.get(g["job"]["url"], headers=KEY).status_code == 200
    assert client.delete(f"/v1/garments/{g['id']}", headers=KEY).status_code == 204
    assert client.get(g["job"]["url"], headers=KEY).status_code == 404
    assert not ctx.conn.exists(ctx.garments_repo.upload_key(g["id"]))
    assert ctx.garments.run_build(g["id"], lambda f, m: None)["status"] == "deleted"  # a late job finds nothing
    assert not ctx.bases.path(g["id"]).exists()


# -- textures (issue 11): uploads keep UVs and textures ------------------------------------------
def _textured_obj(model) -> tuple[bytes, np.ndarray]:
    """The draped test garment as a design tool exports it: its own OBJ (``vt``, quads, ``v/vt``
    corners) with the positions replaced by the garment draped on `mean` (metres)."""
    d = D.shared_data_dir() / "makehuman_clothes" / D.GARMENT
    text = (d / f"{D.GARMENT}.obj").read_text(errors="replace")
    G = D.on_mean(model).reference
    it = iter(G)
    lines = [("v %.6f %.6f %.6f" % tuple(next(it))) if ln.startswith("v ") else ln for ln in text.splitlines()]
    return ("\n".join(lines) + "\n").encode(), G


def _texture() -> bytes:
    from service.model.garments.catalogue import DEFAULT_CATALOGUE_DIR

    return (DEFAULT_CATALOGUE_DIR / "textures" / "womens-tshirt.jpg").read_bytes()


def _assert_textured_glb(glb_bytes: bytes, texture: bytes, validate_glb) -> dict:
    """Validator-clean, the uploaded texture embedded once, and one double-sided mesh with UVs
    in [0, 1] whose base-colour texture is that image (an outfit also carries the avatar's look,
    with images of its own)."""
    from service.application.uploads import read_texture

    texture = read_texture(texture, "t").data  # as stored: decoded and re-encoded
    report = validate_glb(glb_bytes)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, report["issues"]
    glb = read_glb(glb_bytes)
    images = [im["data"] for im in glb["images"]]
    assert images.count(texture) == 1, len(images)
    doc = glb["json"]

    def image_of(m: dict) -> bytes | None:
        if m["uv"] is None or m.get("material") is None:
            return None
        ref = doc["materials"][m["material"]]["pbrMetallicRoughness"].get("baseColorTexture")
        return None if ref is None else images[doc["textures"][ref["index"]]["source"]]

    mesh = next(m for m in glb["meshes"] if image_of(m) == texture)
    assert mesh["uv"].shape == (len(mesh["positions"]), 2) and 0.0 <= mesh["uv"].min() and mesh["uv"].max() <= 1.0
    assert doc["materials"][mesh["material"]]["doubleSided"] is True
    return glb


def test_draped_obj_with_texture_is_tried_on_textured(client: TestClient, model, validate_glb) -> None:
    ctx = client.app.state.context
    obj, G = _textured_obj(model)
    tex = _texture()
    r = client.post("/v1/garments", data={"name": "Textured suit"}, headers=KEY,
                    files={"garment": ("suit.obj", obj), "texture": ("suit.jpg", tex)})
    assert r.status_code == 202, r.text
    gid = r.json()["id"]
    assert r.json()["textured"] is True
    assert ctx.garments.run_build(gid, lambda f, m: None)["status"] == "done"
    created = client.post("/v1/customers", json={"measurements": {"height_cm": 170, "weight_kg": 70}}).json()
    cust, auth = created["id"], {"Authorization": f"Bearer {created['token']}"}
    for comp in (None, "quantize", "meshopt"):
        params = {"compression": comp} if comp else {}
        r = client.get(f"/v1/customers/{cust}/garments/{gid}.glb", params=params, headers=auth)
        assert r.status_code == 200
        glb = _assert_textured_glb(r.content, tex, validate_glb)
        assert len(glb["positions"]) > len(G)  # split at the UV seams
        r = client.get(f"/v1/garments/{gid}/basis.glb", params=params)
        _assert_textured_glb(r.content, tex, validate_glb)
    r = client.get(f"/v1/customers/{cust}/outfit.glb", params={"garments": gid}, headers=auth)
    _assert_textured_glb(r.content, tex, validate_glb)
    assert client.delete(f"/v1/garments/{gid}", headers=KEY).status_code == 204


def test_mhclo_upload_keeps_uvs_and_texture(client: TestClient, model, validate_glb) -> None:
    d = D.shared_data_dir() / "makehuman_clothes" / D.GARMENT
    files = {"mhclo": ("g.mhclo", (d / f"{D.GARMENT}.mhclo").read_bytes()),
             "obj": ("g.obj", (d / f"{D.GARMENT}.obj").read_bytes())}
    tex = _texture()
    r = client.post("/v1/garments", data={"name": "MH suit", "color": "#ffffff"}, headers=KEY,
                    files={**files, "texture": ("t.jpg", tex)})
    assert r.status_code == 201, r.text
    g = r.json()
    assert g["textured"] is True and g["source"] == "mhclo"
    created = client.post("/v1/customers", json={"measurements": {"height_cm": 160, "weight_kg": 55}}).json()
    auth = {"Authorization": f"Bearer {created['token']}"}
    r = client.get(f"/v1/customers/{created['id']}/garments/{g['id']}.glb", headers=auth)
    _assert_textured_glb(r.content, tex, validate_glb)
    # without a texture: UVs kept, no image, the colour
    r = client.post("/v1/garments", data={"name": "MH plain"}, headers=KEY, files=files)
    assert r.status_code == 201 and r.json()["textured"] is False
    plain = read_glb(client.get(f"/v1/customers/{created['id']}/garments/{r.json()['id']}.glb", headers=auth).content)
    assert plain["images"] == [] and plain["uv"] is not None
    for gid in (g["id"], r.json()["id"]):
        assert client.delete(f"/v1/garments/{gid}", headers=KEY).status_code == 204


def test_bad_textures_get_422(client: TestClient, model) -> None:
    from service.application.uploads import MAX_TEXTURE_BYTES

    ctx = client.app.state.context
    before = {g["id"] for g in client.get("/v1/garments").json()}
    obj, _ = _textured_obj(model)
    tex = _texture()
    no_vt = D.on_mean(model).garment_obj

    def post(garment: bytes, texture: bytes, tname: str = "t.png") -> object:
        return client.post("/v1/garments", data={"name": "x"}, headers=KEY,
                           files={"garment": ("g.obj", garment), "texture": (tname, texture)})

    assert_422(post(obj, b"GIF89a" + b"\0" * 100, "t.gif"), ["body", "texture"], ("PNG or JPEG",))
    assert_422(post(obj, b"\x89PNG\r\n\x1a\n" + b"\0" * 10), ["body", "texture"], ("not a readable",))
    assert_422(post(obj, tex[:3] + b"\0" * (MAX_TEXTURE_BYTES + 1)), ["body", "texture"], ("at most",))
    assert_422(post(obj, b""), ["body", "texture"], ("empty",))
    assert_422(post(no_vt, tex), ["body", "texture"], ("texture coordinates",))
    assert {g["id"] for g in client.get("/v1/garments").json()} == before
    assert ctx.queue.queue.count == 0


def test_draped_glb_keeps_embedded_texture_and_its_seams_closed(client: TestClient, model, validate_glb) -> None:
    """A GLB garment, as every glTF exporter writes one: its vertices split at the UV seams (and
    a few on no face). It is draped as one cloth (joined at the seams: its panels do not part;
    the stray vertices dropped) and tried on with its own texture coordinates."""
    from service.model.garments.catalogue import Material, Texture, render_layout
    from service.model.formats.gltf import mesh_to_glb
    from service.model.formats.mhclo import parse_obj

    draped = D.on_mean(model)
    G = draped.reference
    obj = parse_obj((shared_data_dir() / "makehuman_clothes" / D.GARMENT / f"{D.GARMENT}.obj").read_text(errors="replace"))
    split = render_layout(obj.faces, obj.face_uv, obj.uv)  # (R,) render vertices, each a welded vertex's copy
    assert len(split.vertex) > len(G) + 100
    tex = _texture()
    mat = Material((1.0, 1.0, 1.0, 1.0), Texture("cloth.jpg", "image/jpeg", tex), None, "OPAQUE", None, True, 0.0, 0.9)
    stray = G[:3] + [0.0, 0.0, 0.05]  # vertices on no face, as some exporters leave them
    glb = mesh_to_glb(np.vstack([G[split.vertex], stray]).astype(np.float32), split.faces,
                      uv=np.vstack([split.uv, np.full((3, 2), 0.5, np.float32)]), material=mat, name="dress")
    r = client.post("/v1/garments", data={"name": "GLB dress"}, headers=KEY, files={"garment": ("dress.glb", glb)})
    assert r.status_code == 202, r.text
    gid = r.json()["id"]
    assert r.json()["textured"] is True and r.json()["n_vertices"] == len(G)
    assert client.app.state.context.garments.run_build(gid, lambda f, m: None)["status"] == "done"
    created = client.post("/v1/customers", json={"measurements": {"height_cm": 175, "weight_kg": 90}}).json()
    r = client.get(f"/v1/customers/{created['id']}/garments/{gid}.glb",
                   headers={"Authorization": f"Bearer {created['token']}"})
    out = _assert_textured_glb(r.content, tex, validate_glb)
    np.testing.assert_allclose(out["uv"], split.uv, atol=1e-6)
    X = out["positions"]
    assert len(X) == len(split.vertex)
    seam = np.flatnonzero(np.bincount(split.vertex)[split.vertex] > 1)  # render vertices sharing a cloth vertex
    first = np.full(len(G), -1)
    first[split.vertex[::-1]] = np.arange(len(split.vertex))[::-1]
    gap = np.linalg.norm(X[seam] - X[first[split.vertex[seam]]], axis=1)
    assert len(seam) > 100 and gap.max() < 1e-6, gap.max()  # unwelded, its seams opened 22 mm (median)
    assert client.delete(f"/v1/garments/{gid}", headers=KEY).status_code == 204

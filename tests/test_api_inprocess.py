"""The API in process (quick tier): the app with its lifespan on a leased DB of the real Redis,
no worker process. Routes -> use cases -> repositories end to end; the warm try-on's single
Redis round trip; records of another body model refused with 409; error mapping."""
from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.model.formats.gltf_read import read_glb
from service.settings import Settings
from tests.bench.common import shared_data_dir
from tests.harness import GLB, RETAILERS, assert_422, redis_db, redis_url

KEY = {"X-API-Key": RETAILERS["acme"]}
OTHER = {"X-API-Key": RETAILERS["globex"]}
SHOES = shared_data_dir() / "makehuman_clothes" / "shoes01"


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("inproc"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="mens-tshirt,mens-jeans,pencil-skirt",
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


@pytest.fixture(scope="module")
def created(client: TestClient) -> dict:
    r = client.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 170, "weight_kg": 66}})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["status"] == "ready" and body["source"] == "measurements" and len(body["weights"]) == 76
    assert abs(body["measurements"]["height_cm"] - 170) < 1
    assert len(body["token"]) >= 40 and body["owner"] is None
    return body


@pytest.fixture(scope="module")
def customer(created: dict) -> str:
    return created["id"]


@pytest.fixture(scope="module")
def auth(created: dict) -> dict[str, str]:
    return bearer(created["token"])


def test_body_model_and_avatars(client: TestClient) -> None:
    spec = client.get("/v1/body-model").json()
    assert len(spec["bones"]) == 17 and spec["components"] == 76
    r = client.post("/v1/avatars", json={"measurements": {"height_cm": 182}}, headers={"Accept": GLB})
    assert r.status_code == 200 and r.headers["content-type"] == GLB and r.content[:4] == b"glTF"
    assert_422(client.post("/v1/avatars", json={"measurements": {"height_cm": 20}}),
               ["body", "measurements", "height_cm"], ("outside the allowed range",))
    assert client.get("/v1/body-model/template.obj").text.count("\nv ") > 13000


def test_customer_life_cycle(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    shown = client.get(f"/v1/customers/{customer}", headers=auth).json()
    assert shown["id"] == customer and shown["token"] is None and "token_hash" not in shown
    glb = read_glb(client.get(f"/v1/customers/{customer}/avatar.glb", headers=auth).content)
    assert glb["meshes"][0]["name"] == "avatar"
    r = client.post("/v1/customers", json={"measurements": {"chest_cm": 95}})
    cid, h = r.json()["id"], bearer(r.json()["token"])
    assert client.delete(f"/v1/customers/{cid}", headers=h).status_code == 204
    assert client.get(f"/v1/customers/{cid}", headers=h).status_code == 404
    assert client.delete(f"/v1/customers/{cid}", headers=h).status_code == 404
    assert client.get("/v1/customers/..%2Fx/avatar.glb", headers=h).status_code == 404
    # only the token's hash is stored
    raw = client.app.state.context.conn.get(client.app.state.context.customers_repo.key(customer)).decode()
    assert "token_hash" in raw and '"token"' not in raw


def test_customer_routes_need_the_token(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    """No token, a wrong token or another customer's token: the 404 of an unknown id, on every
    customer route (ids cannot be probed); the right token opens them all."""
    gid = client.get("/v1/garments").json()[0]["id"]
    other = client.post("/v1/customers", json={"measurements": {}}).json()
    paths = [f"/v1/customers/{customer}", f"/v1/customers/{customer}/avatar.glb",
             f"/v1/customers/{customer}/garments/{gid}.glb", f"/v1/customers/{customer}/outfit.glb?garments={gid}"]
    unknown = client.get("/v1/customers/nope-nope-nope", headers=auth)
    for headers in ({}, bearer("x" * 43), bearer(other["token"]), {"Authorization": auth["Authorization"][7:]},
                    {"Authorization": "Basic " + auth["Authorization"][7:]}):
        for path in paths:
            r = client.get(path, headers=headers)
            assert r.status_code == 404, (path, headers, r.status_code)
            assert r.json()["detail"] == f"customer '{customer}' not found"
        assert client.delete(f"/v1/customers/{customer}", headers=headers).status_code == 404
    assert unknown.status_code == 404 and unknown.json()["detail"] == "customer 'nope-nope-nope' not found"
    for path in paths:
        assert client.get(path, headers=auth).status_code == 200, path
    assert client.delete(f"/v1/customers/{other['id']}", headers=bearer(other["token"])).status_code == 204


def test_retailer_customers(client: TestClient) -> None:
    """A customer created with a retailer's key belongs to it: that key opens it (and its
    token), another retailer's key does not; an unknown key is refused."""
    r = client.post("/v1/customers", json={"measurements": {"height_cm": 180}}, headers=KEY)
    assert r.status_code == 201 and r.json()["owner"] == "acme"
    cid, token = r.json()["id"], r.json()["token"]
    assert client.get(f"/v1/customers/{cid}", headers=KEY).json()["owner"] == "acme"
    assert client.get(f"/v1/customers/{cid}/avatar.glb", headers=KEY).status_code == 200
    assert client.get(f"/v1/customers/{cid}", headers=bearer(token)).status_code == 200
    assert client.get(f"/v1/customers/{cid}", headers=OTHER).status_code == 404
    assert client.get(f"/v1/customers/{cid}", headers={"X-API-Key": "nope"}).status_code == 403
    assert client.post("/v1/customers", json={"measurements": {}}, headers={"X-API-Key": "nope"}).status_code == 403
    assert client.delete(f"/v1/customers/{cid}", headers=OTHER).status_code == 404
    assert client.delete(f"/v1/customers/{cid}", headers=KEY).status_code == 204


def test_tryon_etag(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    """A try-on carries an ETag from (customer weights, garment etag, options); If-None-Match
    gives 304 without a body; another option, garment or customer gives another ETag."""
    gids = [g["id"] for g in client.get("/v1/garments").json()]
    url = f"/v1/customers/{customer}/garments/{gids[0]}.glb"
    r = client.get(url, headers=auth)
    etag = r.headers["etag"]
    assert r.status_code == 200 and etag.startswith('"') and "private" in r.headers["cache-control"]
    again = client.get(url, headers=auth)
    assert again.headers["etag"] == etag and again.content == r.content
    r304 = client.get(url, headers={**auth, "If-None-Match": etag})
    assert r304.status_code == 304 and r304.content == b"" and r304.headers["etag"] == etag
    assert client.get(url, headers={**auth, "If-None-Match": f'"x", W/{etag}'}).status_code == 304
    assert client.get(url, headers={**auth, "If-None-Match": '"other"'}).status_code == 200
    tags = {etag, client.get(url + "?compression=quantize", headers=auth).headers["etag"],
            client.get(f"/v1/customers/{customer}/garments/{gids[1]}.glb", headers=auth).headers["etag"]}
    other = client.post("/v1/customers", json={"measurements": {"height_cm": 190}}).json()
    tags.add(client.get(f"/v1/customers/{other['id']}/garments/{gids[0]}.glb",
                        headers=bearer(other["token"])).headers["etag"])
    assert len(tags) == 4
    outfit = f"/v1/customers/{customer}/outfit.glb?garments={gids[0]},{gids[1]}"
    tag = client.get(outfit, headers=auth).headers["etag"]
    assert client.get(outfit, headers={**auth, "If-None-Match": tag}).status_code == 304
    tag = client.get(f"/v1/customers/{customer}/avatar.glb", headers=auth).headers["etag"]
    assert client.get(f"/v1/customers/{customer}/avatar.glb",
                      headers={**auth, "If-None-Match": tag}).status_code == 304
    # a wrong token never learns whether the ETag matched
    assert client.get(url, headers={"If-None-Match": etag}).status_code == 404


def test_tryon_pose_correctives(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    """``pose_correctives=true`` gives every garment of a try-on and an outfit one morph target
    per page pose (``pose:<name>``, the presets of ``/poses``) and its own ETag; without it, none."""
    gids = [g["id"] for g in client.get("/v1/garments").json()][:2]
    poses = list(client.get(f"/v1/customers/{customer}/poses", headers=auth).json())
    url = f"/v1/customers/{customer}/garments/{gids[0]}.glb"
    plain, pc = client.get(url, headers=auth), client.get(url + "?pose_correctives=true", headers=auth)
    assert pc.status_code == 200 and pc.headers["etag"] != plain.headers["etag"]
    assert read_glb(plain.content)["meshes"][0]["targets"] is None
    assert read_glb(pc.content)["meshes"][0]["target_names"] == [f"pose:{p}" for p in poses]
    outfit = read_glb(client.get(f"/v1/customers/{customer}/outfit.glb", headers=auth,
                                 params={"garments": ",".join(gids), "pose_correctives": "1"}).content)
    garments = [m for m in outfit["meshes"][1:] if m["targets"] is not None]
    # the avatar's own targets, if any skin shows through the clothes (correctives.body_tucks), are pose targets too
    avatar = outfit["meshes"][0]
    assert len(garments) == 2 and avatar["name"] == "avatar"
    assert avatar["targets"] is None or avatar["target_names"] == [f"pose:{p}" for p in poses]


def test_catalogue_upload_tryon_and_basis(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    demo = client.get("/v1/garments").json()
    assert {g["catalogue_id"] for g in demo} >= {"mens-tshirt", "mens-jeans", "pencil-skirt"}
    files = {"mhclo": ("shoes01.mhclo", (SHOES / "shoes01.mhclo").read_bytes()),
             "obj": ("shoes01.obj", (SHOES / "shoes01.obj").read_bytes())}
    assert client.post("/v1/garments", data={"name": "Shoes"}, files=files).status_code == 401
    # the cloth (issue 43): woven, knit or stretch, else 422; the demo's jersey tops are knit
    assert {g["catalogue_id"]: g["fabric"] for g in demo}["mens-tshirt"] == "knit"
    assert_422(client.post("/v1/garments", data={"name": "Shoes", "fabric": "silk"}, files=files, headers=KEY),
               ["body", "fabric"])
    r = client.post("/v1/garments", data={"name": "Shoes", "color": "#223344", "layer": "0", "fabric": "stretch"},
                    files=files, headers=KEY)
    assert r.status_code == 201, r.text
    shoes = r.json()
    assert shoes["owner"] == "acme" and shoes["source"] == "mhclo" and shoes["n_components"] == 32
    assert shoes["fabric"] == "stretch" and client.get(f"/v1/garments/{shoes['id']}").json()["fabric"] == "stretch"
    glb = read_glb(client.get(f"/v1/customers/{customer}/garments/{shoes['id']}.glb", headers=auth).content)
    assert glb["meshes"][0]["name"] == "Shoes"
    ids = ",".join([shoes["id"], demo[0]["id"]])
    outfit = read_glb(client.get(f"/v1/customers/{customer}/outfit.glb", params={"garments": ids},
                                 headers=auth).content)
    # the avatar and its look (issue 11), then the garments, layer 0 first
    assert [m["name"] for m in outfit["meshes"]][:6] == ["avatar", "eyes", "eyebrows", "hair", "underwear", "Shoes"]
    r = client.get(f"/v1/garments/{shoes['id']}/basis.glb")
    etag = r.headers["etag"]
    assert r.status_code == 200 and client.get(f"/v1/garments/{shoes['id']}/basis.glb",
                                                headers={"If-None-Match": etag}).status_code == 304
    assert client.delete(f"/v1/garments/{shoes['id']}", headers=OTHER).status_code == 403
    assert client.delete(f"/v1/garments/{shoes['id']}", headers=KEY).status_code == 204
    assert client.get(f"/v1/customers/{customer}/garments/{shoes['id']}.glb", headers=auth).status_code == 404
    assert not (Path(client.app.state.context.bases.path(shoes["id"]))).exists()


def test_warm_tryon_is_one_redis_round_trip(client: TestClient, customer: str, auth: dict[str, str]) -> None:
    ctx = client.app.state.context
    gids = [g["id"] for g in client.get("/v1/garments").json()][:3]
    url = f"/v1/customers/{customer}/outfit.glb?garments={','.join(gids)}"
    assert client.get(url, headers=auth).status_code == 200  # warms the body and basis caches
    pool = ctx.conn.connection_pool
    real = pool.get_connection
    calls = []

    def counting(*a, **k):
        calls.append(1)
        return real(*a, **k)

    pool.get_connection = counting
    try:
        assert client.get(url, headers=auth).status_code == 200
        assert client.get(f"/v1/customers/{customer}/garments/{gids[0]}.glb", headers=auth).status_code == 200
    finally:
        del pool.get_connection
    assert len(calls) == 2  # one per try-on


def test_records_of_another_body_model_are_refused(client: TestClient, customer: str) -> None:
    ctx = client.app.state.context
    rec = ctx.customers_repo.get(customer)
    stale = rec.model_copy(update={"id": "stale-1", "body_model": "bm-000000000000", "owner": "acme"})
    ctx.customers_repo.put(stale)
    r = client.get("/v1/customers/stale-1/avatar.glb", headers=KEY)
    assert r.status_code == 409 and "another body model" in r.json()["detail"]
    gid = client.get("/v1/garments").json()[0]["id"]
    r = client.get(f"/v1/customers/stale-1/garments/{gid}.glb", headers=KEY)
    assert r.status_code == 409
    ctx.customers_repo.delete("stale-1")


def test_scan_upload_queues_a_job(client: TestClient) -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(-1, 1, size=(2000, 3)) * [0.2, 0.85, 0.12] + [0, 0.9, 0]  # a person-sized cloud
    text = "\n".join(f"{x:.5f} {y:.5f} {z:.5f}" for x, y, z in pts).encode()
    r = client.post("/v1/customers", files={"mesh": ("person.xyz", text)}, data={"clothed": "false"})
    assert r.status_code == 202, r.text
    body = r.json()
    h = bearer(body["token"])
    assert body["status"] == "fitting" and body["job"]["status"] == "queued" and r.headers["location"] == body["job"]["url"]
    job = client.get(body["job"]["url"], headers=h).json()
    assert job["status"] == "queued" and job["customer_id"] == body["id"] and job["kind"] == "fit"
    assert client.get(body["job"]["url"]).status_code == 404  # the customer's job needs its token too
    assert client.get(body["job"]["url"], headers=KEY).status_code == 404
    r = client.get(f"/v1/customers/{body['id']}/avatar.glb", headers=h)
    assert r.status_code == 409 and "being fitted" in r.json()["detail"]
    assert client.delete(f"/v1/customers/{body['id']}", headers=h).status_code == 204
    assert client.get(body["job"]["url"], headers=h).status_code == 404  # the waiting job went with the customer
    assert_422(client.post("/v1/customers", files={"mesh": ("x.xyz", b"1 2 3\n")}), ["body", "mesh"])
    assert_422(client.post("/v1/customers", files={"mesh": ("x.xyz", text)}, data={"clothed": "maybe"}),
               ["body", "clothed"])

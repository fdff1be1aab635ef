"""The per-customer exact drape (issue 43), end to end in process: ``GET
/v1/customers/{cid}/garments/{gid}.glb?drape=exact`` queues the customer's drape as a job (202,
the same job while it waits), the queue's job is run by an rq worker in this process (the
worker's entry point ``worker.jobs.drape_garment`` on this app's context), then the draped
garment is served (200, its own ETag, validator-clean, outside the body); a failed drape is a
409 with its reason; a changed body queues a new drape; the cap of queued jobs applies; deleting the customer or the garment
removes its drapes. One small demo garment, few solver iterations. Slow: the app's start and
the drapes take seconds."""
from __future__ import annotations

from collections.abc import Iterator
from unittest import mock

import numpy as np
import pytest
from fastapi.testclient import TestClient
from rq import SimpleWorker

from service.app import create_app
from service.model.drape import DrapeError
from service.model.formats.gltf_read import read_glb
from service.model.geometry.mesh import closest_points_on_mesh, winding_numbers
from service.settings import Settings
from tests.conftest import valid_glb
from tests.harness import RETAILERS, assert_422, bearer, redis_db, redis_url

pytestmark = pytest.mark.slow

DRAPE_ITERATIONS = 40  # enough to move the cloth, few enough to be quick (the default is 400)
MAX_INSIDE_M = 0.001


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("exact"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="mens-tshirt,mens-jeans",
                            TRYON_DRAPE_ITERATIONS=DRAPE_ITERATIONS,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def _demo(client: TestClient, catalogue_id: str) -> dict:
    (g,) = [g for g in client.get("/v1/garments").json() if g["catalogue_id"] == catalogue_id]
    return g


@pytest.fixture(scope="module")
def gid(client: TestClient) -> str:
    g = _demo(client, "mens-tshirt")
    assert g["fabric"] == "knit"
    return g["id"]


def _customer(client: TestClient, **measurements: float) -> dict:
    r = client.post("/v1/customers", json={"measurements": {"gender": "male", **measurements}})
    assert r.status_code == 201, r.text
    return r.json()


def _work(client: TestClient) -> None:
    """Run every queued job as a ``tryon worker`` would, in this process on this app's context."""
    ctx = client.app.state.context
    with mock.patch("worker.jobs.worker_context", return_value=ctx):
        SimpleWorker([ctx.queue.queue], connection=ctx.conn).work(burst=True)


def _url(cid: str, gid: str) -> str:
    return f"/v1/customers/{cid}/garments/{gid}.glb"


def test_exact_drape_is_queued_then_served(client: TestClient, gid: str, model, validate_glb) -> None:
    ctx = client.app.state.context
    cust = _customer(client, height_cm=186, weight_kg=98)
    cid, auth = cust["id"], bearer(cust)
    basis = client.get(_url(cid, gid), headers=auth)
    assert basis.status_code == 200
    assert client.get(_url(cid, gid), params={"drape": "basis"}, headers=auth).content == basis.content
    assert_422(client.get(_url(cid, gid), params={"drape": "loose"}, headers=auth), ["query", "drape"])
    r = client.get(_url(cid, gid), params={"drape": "exact"})
    assert r.status_code == 404  # the customer's token (or its retailer's key) opens it, as the try-on
    # the first request queues the drape
    r = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["id"].startswith("drape-") and job["url"] == f"/v1/jobs/{job['id']}" and job["status"] == "queued"
    assert r.headers["location"] == job["url"]
    # asked again while it waits: the same job, nothing more queued
    again = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    assert again.status_code == 202 and again.json() == job
    assert ctx.queue.queue.count == 1
    assert client.get(job["url"]).status_code == 404  # the customer's job: its token opens it
    j = client.get(job["url"], headers=auth).json()
    assert (j["kind"], j["status"], j["customer_id"], j["garment_id"]) == ("drape", "queued", cid, gid)
    # the worker drapes it
    _work(client)
    j = client.get(job["url"], headers=auth).json()
    assert j["status"] == "done" and j["progress"] == 1.0, j
    r = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    assert r.status_code == 200 and r.headers["content-type"] == "model/gltf-binary"
    assert r.headers["etag"] not in (basis.headers["etag"], None)
    draped, tried = valid_glb(validate_glb, r.content), read_glb(basis.content)
    assert [m["name"] for m in draped["meshes"]] == [m["name"] for m in tried["meshes"]]
    assert draped["positions"].shape == tried["positions"].shape
    assert np.array_equal(draped["indices"], tried["indices"])
    moved = np.linalg.norm(draped["positions"] - tried["positions"], axis=1)
    assert np.median(moved) > 1e-4 and moved.max() > 2e-3, (np.median(moved), moved.max())
    # none of the draped garment more than 1 mm inside the customer's body
    body = ctx.customers.body(ctx.customers_repo.get(cid))
    V, F = np.asarray(body.vertices[: model.n_body_vertices], np.float64), model.body_faces
    p = np.asarray(draped["positions"], np.float64)
    inside = winding_numbers(p, V, F) > 0.5
    depth = np.linalg.norm(p[inside] - closest_points_on_mesh(p[inside], V, F)[1], axis=1) if inside.any() \
        else np.zeros(0)
    assert depth.max(initial=0.0) <= MAX_INSIDE_M, depth.max()
    # cached: no new job, If-None-Match -> 304
    r2 = client.get(_url(cid, gid), params={"drape": "exact"}, headers={**auth, "If-None-Match": r.headers["etag"]})
    assert r2.status_code == 304 and ctx.queue.queue.count == 0
    q = client.get(_url(cid, gid), params={"drape": "exact", "compression": "quantize"}, headers=auth)
    assert q.status_code == 200 and q.headers["etag"] != r.headers["etag"]
    # deleting the customer removes its drapes
    drapes = ctx.drape_store.root / cid
    assert any(drapes.rglob("*.npy"))
    assert client.delete(f"/v1/customers/{cid}", headers=auth).status_code == 204
    assert not drapes.exists()


def test_an_outfit_of_exact_drapes(client: TestClient, gid: str, validate_glb) -> None:
    """outfit.glb?drape=exact: every garment's drape queued at the first request (202 with the
    first job while any waits), then the layered outfit of the drapes; a garment whose drape
    failed is worn from its basis."""
    ctx = client.app.state.context
    jeans = _demo(client, "mens-jeans")["id"]
    cust = _customer(client, height_cm=180, weight_kg=85)
    cid, auth = cust["id"], bearer(cust)
    url = f"/v1/customers/{cid}/outfit.glb"
    params = {"garments": f"{jeans},{gid}"}
    basis = client.get(url, params=params, headers=auth)
    assert basis.status_code == 200
    assert_422(client.get(url, params={**params, "drape": "tight"}, headers=auth), ["query", "drape"])
    r = client.get(url, params={**params, "drape": "exact"}, headers=auth)
    assert r.status_code == 202 and r.json()["id"].startswith("drape-") and r.headers["location"] == r.json()["url"]
    assert ctx.queue.queue.count == 2  # both garments' drapes, at once
    again = client.get(url, params={**params, "drape": "exact"}, headers=auth)
    assert again.status_code == 202 and again.json()["id"] == r.json()["id"] and ctx.queue.queue.count == 2
    _work(client)
    r = client.get(url, params={**params, "drape": "exact"}, headers=auth)
    assert r.status_code == 200 and r.headers["etag"] != basis.headers["etag"]
    exact, tried = valid_glb(validate_glb, r.content), read_glb(basis.content)
    assert [m["name"] for m in exact["meshes"]] == [m["name"] for m in tried["meshes"]]
    # each garment is its drape (the one garment's exact GLB), layered: the shirt over the jeans
    shirt = read_glb(client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).content)
    (i,) = [k for k, m in enumerate(exact["meshes"]) if m["positions"].shape == shirt["positions"].shape]
    moved = np.linalg.norm(exact["meshes"][i]["positions"] - tried["meshes"][i]["positions"], axis=1)
    assert np.median(moved) > 1e-4, np.median(moved)
    assert r.headers["etag"] == client.get(url, params={**params, "drape": "exact"}, headers=auth).headers["etag"]
    # a garment that cannot be draped on a body is worn from its basis in the exact outfit
    other = _customer(client, height_cm=170, weight_kg=64)
    cid2, auth2 = other["id"], bearer(other)
    url2 = f"/v1/customers/{cid2}/outfit.glb"
    assert client.get(url2, params={**params, "drape": "exact"}, headers=auth2).status_code == 202
    with mock.patch("service.application.drapes.precompute", side_effect=DrapeError("the cloth tore (test)")):
        _work(client)
    r = client.get(url2, params={**params, "drape": "exact"}, headers=auth2)
    plain = client.get(url2, params=params, headers=auth2)
    assert r.status_code == 200 and r.headers["etag"] != plain.headers["etag"]
    for a, b in zip(read_glb(r.content)["meshes"], read_glb(plain.content)["meshes"]):
        np.testing.assert_array_equal(a["positions"], b["positions"])
    # at the requester's cap of queued jobs: as many drapes as it allows, the rest at later requests
    third = _customer(client, height_cm=175, weight_kg=75)
    cid3, auth3 = third["id"], bearer(third)
    url3 = f"/v1/customers/{cid3}/outfit.glb"
    settings = ctx.limits.settings
    ctx.limits.settings = settings.model_copy(update={"max_queued_client": 1})
    try:
        for _ in range(2):
            r = client.get(url3, params={**params, "drape": "exact"}, headers=auth3)
            assert r.status_code == 202 and ctx.queue.queue.count == 1, (r.status_code, ctx.queue.queue.count)
            _work(client)
        assert client.get(url3, params={**params, "drape": "exact"}, headers=auth3).status_code == 200
    finally:
        ctx.limits.settings = settings


def test_a_changed_body_is_draped_again(client: TestClient, gid: str) -> None:
    ctx = client.app.state.context
    cust = _customer(client, height_cm=172, weight_kg=70)
    cid, auth = cust["id"], bearer(cust)
    first = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).json()
    _work(client)
    assert client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).status_code == 200
    # the customer's shape changes (as an edit stored on the record would): the cached drape is stale
    record = ctx.customers_repo.get(cid)
    w = list(record.weights)
    w[0] += 0.5
    ctx.customers_repo.put(record.model_copy(update={"weights": w}))
    r = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    assert r.status_code == 202 and r.json()["id"] != first["id"]
    _work(client)
    assert client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).status_code == 200
    assert len(list((ctx.drape_store.root / cid / gid).glob("*.npy"))) == 1  # the stale drape was dropped


def test_a_failed_drape_is_409_with_its_reason(client: TestClient, gid: str) -> None:
    cust = _customer(client, height_cm=160, weight_kg=60)
    cid, auth = cust["id"], bearer(cust)
    job = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).json()
    with mock.patch("service.application.drapes.precompute", side_effect=DrapeError("the cloth tore (test)")):
        _work(client)
    j = client.get(job["url"], headers=auth).json()
    assert j["status"] == "failed" and "cannot be draped" in j["error"] and "cloth tore" in j["error"], j
    r = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    assert r.status_code == 409 and "cloth tore" in r.json()["detail"], r.text
    # the basis try-on is unaffected
    assert client.get(_url(cid, gid), headers=auth).status_code == 200


def test_the_queued_job_cap_applies(client: TestClient, gid: str) -> None:
    ctx = client.app.state.context
    cust = _customer(client, height_cm=165, weight_kg=58)
    cid, auth = cust["id"], bearer(cust)
    settings = ctx.limits.settings
    ctx.limits.settings = settings.model_copy(update={"max_queued_client": 0})
    try:
        r = client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    finally:
        ctx.limits.settings = settings
    assert r.status_code == 429 and "Retry-After" in r.headers, r.text
    assert ctx.queue.queue.count == 0  # nothing queued
    assert client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).status_code == 202
    _work(client)


def test_deleting_the_garment_removes_its_drapes(client: TestClient, gid: str) -> None:
    ctx = client.app.state.context
    cust = _customer(client, height_cm=178, weight_kg=80)
    cid, auth = cust["id"], bearer(cust)
    client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth)
    _work(client)
    assert client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).status_code == 200
    assert (ctx.drape_store.root / cid / gid).exists()
    ctx.garments.delete(gid, "demo")  # the demo catalogue's owner (retailers' keys cannot delete it)
    assert not (ctx.drape_store.root / cid / gid).exists()
    assert client.get(_url(cid, gid), params={"drape": "exact"}, headers=auth).status_code == 404

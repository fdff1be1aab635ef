"""Editing avatars (issue 13) through the API in process: a customer from measurements (its body
is edited, quick), and a clothed scan customer fitted by the job in process (its scan is
edited through the warping graph; slow): POST /v1/customers/{id}/edit (GLB) and the WebSocket."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from service.app import create_app
from service.model.fitting import scan_cleanup as SC
from service.model.formats.gltf_read import read_glb
from service.settings import Settings
from tests.bench import synthetic_scans as S
from tests.bench.common import heldout_people
from tests.harness import RETAILERS, assert_422, redis_db, redis_url


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("edit"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="",
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


@pytest.fixture(scope="module")
def scan_customer(client: TestClient, model) -> tuple[str, S.SyntheticScan]:
    """A clothed mesh scan standing on a scanner's floor, uploaded over HTTP, fitted by the job's
    use case in process."""
    p = heldout_people(model, 2)[1]
    scan = S.make_scan(model, np.random.default_rng(5), p["weights"], p["gender"], clothed=True, point_cloud=False,
                       n_points=8000, max_pose_deg=15.0, unit="cm", up="+y")
    n_person = len(scan.points)
    scan = S.with_floor(scan, np.random.default_rng(6), "scanner")  # the points after n_person
    r = client.post("/v1/customers", files={"mesh": ("scan.ply", S.scan_file_bytes(scan, "ply"))})
    assert r.status_code == 202, r.text
    cid = r.json()["id"]
    out = client.app.state.context.customers.run_fit(cid, lambda f, m: None)
    assert out["status"] == "done", out
    return cid, scan, {"Authorization": f"Bearer {r.json()['token']}"}, n_person


def _glb(r) -> dict:
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "model/gltf-binary"
    return read_glb(r.content)


def _customer(client: TestClient, measurements: dict) -> tuple[str, dict]:
    c = client.post("/v1/customers", json={"measurements": measurements}).json()
    return c["id"], {"Authorization": f"Bearer {c['token']}"}


def test_edit_a_measurement_customer(client: TestClient, model) -> None:
    cid, auth = _customer(client, {"gender": "male", "height_cm": 178, "weight_kg": 75})
    c = {"id": cid}

    def post(body: dict):
        return client.post(f"/v1/customers/{cid}/edit", json=body, headers=auth)

    assert client.post(f"/v1/customers/{cid}/edit", json={}).status_code == 404  # no token
    base = _glb(post({}))["positions"]
    assert base.shape == (model.n_body_vertices, 3)
    heavier = _glb(post({"measurements": {"weight_kg": 95}}))["positions"]
    X = heavier.astype(np.float64)
    assert abs(model.measure(np.vstack([X, model.mean[len(X):]]), "male")["weight_kg"] - 95) < 3
    assert abs((X[:, 1].max() - X[:, 1].min()) - (base[:, 1].max() - base[:, 1].min())) < 0.01  # height held
    bent = _glb(post({"pose": {"forearm_l": [0, 0, 1.2]}}))["positions"]
    moved = np.linalg.norm(bent - base, axis=1)
    assert moved.max() > 0.1 and np.median(moved) < 1e-4  # the left forearm and hand only
    for body, loc, words in (
            ({"pose": {"tail": [0, 0, 1]}}, ["body", "pose", "tail"], ("unknown bone",)),
            ({"pose": {"head": [0, 0, 4]}}, ["body", "pose", "head"], ("allowed range",)),
            ({"measurements": {"weight_kg": 500}}, ["body", "measurements", "weight_kg"], ("allowed range",)),
            ({"measurements": {"gender": "female"}}, ["body", "measurements", "gender"], ("cannot be edited",))):
        assert_422(post(body), loc, words)
    assert client.post("/v1/customers/nobody/edit", json={}, headers=auth).status_code == 404
    del c


def test_edit_websocket_of_a_measurement_customer(client: TestClient, model) -> None:
    cid, auth = _customer(client, {"height_cm": 165})
    with client.websocket_connect(f"/v1/customers/{cid}/edit/ws") as ws:  # no token: as if unknown
        assert ws.receive_json()["error"] == 404
    token = auth["Authorization"][7:]
    with client.websocket_connect(f"/v1/customers/{cid}/edit/ws?token={token}") as ws:
        head = ws.receive_json()
        assert head == {"vertices": model.n_body_vertices, "faces": len(model.body_faces), "kind": "avatar"}
        faces = np.frombuffer(ws.receive_bytes(), "<u4").reshape(-1, 3)
        assert np.array_equal(faces, model.body_faces)
        v0 = np.frombuffer(ws.receive_bytes(), "<f4").reshape(-1, 3)
        ws.send_json({"measurements": {"height_cm": 180}})
        v1 = np.frombuffer(ws.receive_bytes(), "<f4").reshape(-1, 3)
        assert (v1[:, 1].max() - v1[:, 1].min()) - (v0[:, 1].max() - v0[:, 1].min()) > 0.1
        ws.send_json({"pose": {"nose": [0, 0, 0]}})
        err = ws.receive_json()
        assert err["error"] == 422 and err["detail"][0]["loc"] == ["body", "pose", "nose"]
        ws.send_text("not json")
        assert ws.receive_json()["error"] == 422
    with client.websocket_connect("/v1/customers/nobody/edit/ws") as ws:
        assert ws.receive_json()["error"] == 404
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_text()
        assert exc.value.code == 4404


@pytest.mark.slow
def test_edit_a_clothed_scan(client: TestClient, scan_customer, model, validate_glb) -> None:
    cid, scan, auth, n_person = scan_customer
    rec = client.get(f"/v1/customers/{cid}", headers=auth).json()
    assert rec["editable"] is True and rec["status"] == "ready"
    base = _glb(client.post(f"/v1/customers/{cid}/edit", json={}, headers=auth))
    # the scan's own vertices, in order, without the floor the fit dropped (the same cleaning)
    kept = SC.clean_scan(scan.points * 0.01, scan.normals, scan.faces)[3].kept
    assert kept[n_person:].mean() < 0.002 and kept[:n_person].mean() > 0.98
    assert base["positions"].shape == (kept.sum(), 3)
    # no edit: the scan itself, moved rigidly into the model frame (distances between its
    # vertices, in metres, as in the file in cm)
    back = base["positions"].astype(np.float64)
    d = np.linalg.norm(np.diff(back, axis=0), axis=1) - np.linalg.norm(np.diff(scan.points[kept] * 0.01, axis=0), axis=1)
    assert np.abs(d).max() < 1e-4
    heavier = _glb(client.post(f"/v1/customers/{cid}/edit?compression=meshopt",
                               json={"measurements": {"weight_kg": rec["measurements"]["weight_kg"] + 10}},
                               headers=auth))
    grown = heavier["positions"] - base["positions"]
    assert np.median(np.linalg.norm(grown, axis=1)) > 0.002  # the clothes follow the body out
    report = validate_glb(client.post(f"/v1/customers/{cid}/edit", json={"pose": {"upper_arm_r": [0, 0, -0.5]}},
                                      headers=auth).content)
    assert report["issues"]["numErrors"] == 0
    with client.websocket_connect(f"/v1/customers/{cid}/edit/ws", headers=auth) as ws:
        head = ws.receive_json()
        assert head["kind"] == "scan" and head["vertices"] == kept.sum()
        ws.receive_bytes()
        ws.receive_bytes()
        ws.send_json({"pose": {"thigh_l": [0.4, 0, 0]}})
        v = np.frombuffer(ws.receive_bytes(), "<f4").reshape(-1, 3)
        assert v.shape == (kept.sum(), 3) and np.isfinite(v).all()
    assert client.delete(f"/v1/customers/{cid}", headers=auth).status_code == 204
    assert not client.app.state.context.meshes.path(cid).exists()

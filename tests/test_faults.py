"""Faults injected into a real `tryon serve` (slow tier): SIGKILL of everything loses no
acknowledged customer; a SIGKILLed `tryon serve` leaves no orphan (its redis-server, server
processes and embedded worker end with it); a Redis restart under traffic gives only 503s (with
Retry-After), then the service recovers by itself (a remote Redis reconnected, the embedded one
restarted by its owner); six concurrent 45 MB scan uploads keep the server under 1.5 GB."""
from __future__ import annotations

import os
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import numpy as np
import psutil
import pytest

from service.storage.supervise import kill_process_tree
from tests.harness import Server, bearer, own_redis, run_server

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)

MEMORY_LIMIT = 1.5e9


def _tree(pid: int) -> list[psutil.Process]:
    try:
        root = psutil.Process(pid)
        return [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _alive(procs: list[psutil.Process]) -> list[psutil.Process]:
    out = []
    for p in procs:
        try:
            if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                out.append(p)
        except psutil.NoSuchProcess:
            pass
    return out


def _cmd(p: psutil.Process) -> str:
    try:
        return " ".join(p.cmdline())
    except psutil.Error:  # ended, or a zombie
        return ""


def _redis_pid(data_dir: Path) -> int:
    return int((data_dir / "redis" / "redis.pid").read_text())


# -- SIGKILL -----------------------------------------------------------------------------------
def test_sigkill_of_everything_loses_no_acknowledged_customer(tmp_path: Path) -> None:
    """Customers are created by 4 threads while `tryon serve` (2 processes, embedded Redis with
    AOF) and its redis-server are SIGKILLed together; after a restart on the same data directory
    every customer that was answered 201 is there, and its token still opens it."""
    data = tmp_path / "data"
    acked: list[tuple[str, str]] = []
    with run_server(data, "embedded", workers=2, check_log=False) as server:
        stop = threading.Event()

        def create(k: int) -> None:
            with httpx.Client(base_url=server.base_url, timeout=10) as c:
                while not stop.is_set():
                    try:
                        r = c.post("/v1/customers", json={"measurements": {"height_cm": 150 + k}})
                    except httpx.HTTPError:
                        continue
                    if r.status_code == 201:
                        acked.append((r.json()["id"], r.json()["token"]))

        threads = [threading.Thread(target=create, args=(k,)) for k in range(4)]
        for t in threads:
            t.start()
        deadline = time.monotonic() + 60
        while len(acked) < 40 and time.monotonic() < deadline:
            time.sleep(0.05)
        redis_pid = _redis_pid(data)
        os.kill(redis_pid, signal.SIGKILL)  # everything at once: Redis and the whole server tree
        kill_process_tree(server.proc.pid)
        stop.set()
        for t in threads:
            t.join()
    assert len(acked) >= 40
    with run_server(data, "embedded", workers=1, check_log=False) as server:
        missing = [cid for cid, token in acked
                   if server.client.get(f"/v1/customers/{cid}", headers=bearer(token)).status_code != 200]
    print(f"acknowledged customers lost after SIGKILL of server + Redis: {len(missing)} of {len(acked)}")
    assert missing == []


def test_sigkilled_serve_leaves_no_orphan(tmp_path: Path) -> None:
    """SIGKILL of `tryon serve`'s main process only: its redis-server (parent-death signal), its
    server processes and the embedded worker all end within seconds; the data directory can be
    served again at once."""
    data = tmp_path / "data"
    with run_server(data, "embedded", workers=2, check_log=False) as server:
        procs = _alive(_tree(server.proc.pid)[1:])
        names = Counter("redis-server" if "redis-server" in _cmd(p) else
                        "worker" if " worker " in _cmd(p) + " " else "python" for p in procs)
        assert names["redis-server"] == 1 and names["worker"] >= 1 and names["python"] >= 2, names
        server.proc.send_signal(signal.SIGKILL)
        server.proc.wait()
        deadline = time.monotonic() + 30
        while _alive(procs) and time.monotonic() < deadline:
            time.sleep(0.2)
        left = [(p.pid, _cmd(p)[:120]) for p in _alive(procs)]
        assert left == [], left
        time.sleep(2)  # and no redis-server of this data directory was (re)started meanwhile
        ours = [p.pid for p in psutil.process_iter(["cmdline"]) if str(data) in " ".join(p.info["cmdline"] or [])]
        assert ours == [], ours
    with run_server(data, "embedded", workers=1) as server:
        assert server.client.get("/v1/garments").status_code == 200


# -- Redis outage under traffic ----------------------------------------------------------------
def _traffic(server: Server, stop: threading.Event, log: list[tuple[float, int, str | None]]) -> None:
    """Try-ons, customer reads and new customers, one client, as fast as answered."""
    with httpx.Client(base_url=server.base_url, timeout=30) as c:
        created = c.post("/v1/customers", json={"measurements": {"height_cm": 172}}).json()
        h = bearer(created)
        gid = c.get("/v1/garments").json()[0]["id"]
        requests: list[Callable[[], httpx.Response]] = [
            lambda: c.get(f"/v1/customers/{created['id']}/garments/{gid}.glb", headers=h),
            lambda: c.get(f"/v1/customers/{created['id']}", headers=h),
            lambda: c.post("/v1/customers", json={"measurements": {"weight_kg": 70}}),
            lambda: c.get("/v1/garments"),
        ]
        i = 0
        while not stop.is_set():
            r = requests[i % len(requests)]()
            i += 1
            log.append((time.monotonic(), r.status_code, r.headers.get("retry-after")))


@pytest.mark.parametrize("where", ["remote", "embedded"])
def test_redis_restart_under_traffic(tmp_path: Path, where: str) -> None:
    """Redis SIGKILLed under traffic, back 3 s later (remote: restarted by us on the same
    port; embedded: by the server that owns it): only 503s with Retry-After while it is away,
    never another 5xx; then the traffic succeeds again without any restart of the API."""
    log: list[tuple[float, int, str | None]] = []
    stop = threading.Event()

    def run(server: Server, kill: Callable[[], None], revive: Callable[[], None]) -> float:
        t = threading.Thread(target=_traffic, args=(server, stop, log))
        t.start()
        time.sleep(3)
        kill()
        time.sleep(3)
        revive()
        back = time.monotonic()
        time.sleep(6)
        stop.set()
        t.join()
        return back

    if where == "remote":
        with own_redis(tmp_path / "redis") as rs, run_server(tmp_path / "data", "embedded", workers=2,
                                                             check_log=False, REDIS_URL=rs.url) as server:
            back = run(server, rs.stop, rs.start)
    else:
        with run_server(tmp_path / "data", "embedded", workers=2, check_log=False) as server:
            back = run(server, lambda: os.kill(_redis_pid(server.data_dir), signal.SIGKILL), lambda: None)
            log_text = server.log_path.read_text(errors="replace")
        assert "restarting it" in log_text
    codes = Counter(code for _, code, _ in log)
    print(f"Redis restart under traffic ({where}): {dict(codes)} over {len(log)} requests")
    # A remote Redis is away for 3 s: some requests must see its outage as 503s. The embedded one
    # is restarted by its owner at once and requests may well ride through it without any.
    assert codes[503] > 0 or where == "embedded", codes
    assert all(ra is not None for _, code, ra in log if code == 503)
    assert not [c for c in codes if c >= 500 and c != 503], codes
    assert set(codes) <= {200, 201, 503}, codes
    tail = [code for t, code, _ in log if t > back + 2]
    assert tail and all(code in (200, 201) for code in tail), Counter(tail)


# -- concurrent large uploads ------------------------------------------------------------------
def _person_tube(n_around: int, n_up: int) -> tuple[np.ndarray, np.ndarray]:
    """A person-sized tube mesh (metres): n_around x n_up vertices, about twice as many faces."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n_around, endpoint=False), np.linspace(0, 1.7, n_up))
    r = 0.15 + 0.05 * np.sin(3 * v)
    pts = np.stack([1.3 * r * np.cos(u), v, r * np.sin(u)], -1).reshape(-1, 3)
    pts += np.random.default_rng(0).normal(scale=1e-4, size=pts.shape)
    i, j = np.arange(n_up - 1)[:, None] * n_around, np.arange(n_around)[None, :]
    a, b = (i + j).ravel(), (i + (j + 1) % n_around).ravel()
    return pts, np.concatenate([np.stack([a, b, a + n_around], 1), np.stack([b, b + n_around, a + n_around], 1)])


def _text(rows: np.ndarray, fmt: str) -> bytes:
    return ("\n".join(fmt % tuple(r) for r in rows) + "\n").encode()


def big_uploads() -> list[tuple[str, bytes]]:
    """Six ~45 MB scans: three OBJ meshes of 500,000 vertices (~1 M faces, 9 decimals; kept
    simplified to ``KEPT_SCAN_POINTS``) and three XYZ clouds of 2.4 M points in millimetres
    (over the 2,000,000-point limit)."""
    pts, faces = _person_tube(1000, 500)
    obj = _text(pts, "v %.9f %.9f %.9f") + _text(faces + 1, "f %d %d %d")
    cloud = np.random.default_rng(1).uniform(size=(2_400_000, 3)) * [400, 1700, 300]
    xyz = _text(cloud, "%.1f %.1f %.1f")
    return [("scan.obj", obj)] * 3 + [("cloud.xyz", xyz)] * 3


def test_six_concurrent_45mb_uploads_stay_under_1_5_gb(tmp_path: Path) -> None:
    """Six 45 MB scans sent at once to a default `tryon serve` (one process per core, the
    embedded worker off so that only the API's memory is measured): the server's process tree
    (API processes, uvicorn's, redis-server) stays under 1.5 GB; each upload is answered 202
    (the meshes) or 422 (the clouds over the point limit), after 503 + Retry-After when the
    server was reading others; nothing else. The six come from one address, so the per-client
    caps on queued jobs and expensive requests (tested in test_hostile.py) are raised to six:
    this test measures memory, and a 429 for the sixth would hide whether it was read."""
    files = big_uploads()
    assert all(40e6 < len(d) < 50e6 for _, d in files), [len(d) for _, d in files]
    with run_server(tmp_path / "data", "embedded", workers=None, TRYON_EMBEDDED_WORKER="0",
                    TRYON_MAX_QUEUED_CLIENT="6", TRYON_MAX_EXPENSIVE_CLIENT="6") as server:
        peak, stop = [0.0], threading.Event()

        def sample() -> None:
            while not stop.is_set():
                total = 0
                for p in _tree(server.proc.pid):
                    try:
                        total += p.memory_info().rss
                    except psutil.NoSuchProcess:
                        pass
                peak[0] = max(peak[0], total)
                time.sleep(0.05)

        def upload(name: str, data: bytes) -> list[int]:
            codes = []
            with httpx.Client(base_url=server.base_url, timeout=300) as c:
                for _ in range(100):
                    r = c.post("/v1/customers", files={"mesh": (name, data)}, data={"clothed": "false"})
                    codes.append(r.status_code)
                    if r.status_code != 503:
                        return codes
                    time.sleep(float(r.headers["retry-after"]))
            return codes

        base = sum(p.memory_info().rss for p in _tree(server.proc.pid))
        sampler = threading.Thread(target=sample)
        sampler.start()
        t0 = time.monotonic()
        with ThreadPoolExecutor(len(files)) as pool:
            results = list(pool.map(lambda f: upload(*f), files))
        seconds = time.monotonic() - t0
        stop.set()
        sampler.join()
    finals = [r[-1] for r in results]
    print(f"6 concurrent 45 MB uploads: server memory peak {peak[0] / 1e9:.2f} GB (idle {base / 1e9:.2f} GB), "
          f"answers {finals}, 503s {sum(len(r) - 1 for r in results)}, {seconds:.1f} s")
    assert finals == [202, 202, 202, 422, 422, 422], results
    assert all(set(r[:-1]) <= {503} for r in results), results
    assert peak[0] <= MEMORY_LIMIT, peak[0]

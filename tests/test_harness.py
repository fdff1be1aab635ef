"""The test harness touches nothing it did not start: the ``redis`` back end is a DB of the
session's own redis-server on a private unix socket, leased DBs are empty and apart, and every
redis-server the harness starts is gone at the end, even when the test process is SIGKILLed."""
from __future__ import annotations

import os
import shutil
import signal
import stat
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

from tests.harness import REPO, SESSION_REDIS, SessionRedis, own_redis, redis_db, redis_url


def _gone(pid: int, timeout: float = 10.0) -> bool:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            if psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                return True
        except psutil.NoSuchProcess:
            return True
        time.sleep(0.05)
    return False


def test_redis_back_end_is_the_sessions_own_server_on_a_private_socket() -> None:
    with redis_db() as a, redis_db() as b:
        assert a != b
        url = redis_url(a)
        assert url.startswith("unix://") and "6379" not in url and "127.0.0.1" not in url
        server = SESSION_REDIS.server()
        assert server.socket is not None and server.port is None
        assert stat.S_IMODE(server.socket.parent.stat().st_mode) == 0o700  # a private directory
        assert psutil.Process(server.proc.pid).ppid() == os.getpid()  # started by this test run
        with server.client(a) as ca, server.client(b) as cb:
            assert ca.dbsize() == 0 and cb.dbsize() == 0
            ca.set("k", "a")
            assert cb.get("k") is None  # leases are apart
    with redis_db() as again, server.client(again) as c:
        assert c.dbsize() == 0  # flushed when given back


def test_session_server_stops_and_leaves_nothing(tmp_path: Path) -> None:
    session = SessionRedis()
    db = session.lease()
    server = session.server()
    pid, sock = server.proc.pid, server.socket
    session.release(db)
    session.stop()
    assert _gone(pid) and not sock.parent.exists() and not session.running


def test_own_redis_outage_keeps_acknowledged_writes(tmp_path: Path) -> None:
    with own_redis(tmp_path / "redis") as rs:
        assert rs.url.startswith("redis://127.0.0.1:") and rs.port != 6379
        with rs.client() as c:
            c.set("k", "v")
        rs.stop()  # SIGKILL: an outage
        rs.start()
        with rs.client() as c:
            assert c.get("k") == b"v"  # append-only with an fsync per write


@pytest.mark.parametrize("where", ["session", "own"])
def test_redis_servers_die_with_a_killed_test_process(tmp_path: Path, where: str) -> None:
    """A test process SIGKILLed (a CI timeout) leaves no redis-server behind: the kernel's
    parent-death signal ends it."""
    start = ("from tests.harness import redis_db, SESSION_REDIS\ncm = redis_db(); cm.__enter__()\n"
             "rs = SESSION_REDIS.server()" if where == "session" else
             f"from tests.harness import RedisServer\nrs = RedisServer({str(tmp_path)!r}); rs.start()")
    code = start + "\nprint(rs.proc.pid, rs.dir, flush=True)\nimport time\ntime.sleep(60)\n"
    proc = subprocess.Popen([sys.executable, "-c", code], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        pid, data_dir = proc.stdout.readline().split()
        pid = int(pid)
        assert psutil.pid_exists(pid)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=10)
        assert _gone(pid), f"redis-server {pid} outlived its test process"
        shutil.rmtree(data_dir)  # what a SIGKILLed process cannot clean up: the server's files
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()

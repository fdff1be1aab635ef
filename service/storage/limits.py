"""Rate limits shared by every process and host of the service: one Redis key per bucket
(``<prefix>rate:<bucket>``) holding the theoretical arrival time of the generic cell rate
algorithm (GCRA: a token bucket in one number), checked and updated by one Lua script (one
round trip, atomic, Redis's own clock)."""
from __future__ import annotations

import math
import time

import redis

from .queue import JobQueue

# KEYS[1] bucket; ARGV[1] emission interval (us per request), ARGV[2] burst (requests).
# Returns 0 when allowed, else the microseconds until a request would be.
_GCRA = """
if redis.replicate_commands then pcall(redis.replicate_commands) end
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000000 + tonumber(t[2])
local interval = tonumber(ARGV[1])
local tolerance = interval * tonumber(ARGV[2])
local tat = tonumber(redis.call('GET', KEYS[1]) or now)
if tat < now then tat = now end
local new_tat = tat + interval
local wait = new_tat - now - tolerance
if wait > 0 then return wait end
redis.call('SET', KEYS[1], new_tat, 'PX', math.ceil((new_tat - now) / 1000) + 1)
return 0
"""


class RateLimiter:
    """``hit(bucket, rate, burst)``: count one request against ``bucket`` (``rate`` per second,
    bursts of ``burst``); returns 0.0 when allowed, else the seconds to wait."""

    def __init__(self, conn: redis.Redis, prefix: str):
        self.conn = conn
        self.prefix = prefix
        self._script = conn.register_script(_GCRA)

    def hit(self, bucket: str, rate: float, burst: float) -> float:
        if rate <= 0:
            return 0.0
        interval_us = max(int(1_000_000 / rate), 1)
        wait_us = int(self._script(keys=[f"{self.prefix}rate:{bucket}"], args=[interval_us, max(burst, 1.0)]))
        return wait_us / 1_000_000


ENDED_JOB_STATES = ("finished", "failed", "stopped", "canceled")


class JobTracker:
    """The jobs each requester (a bucket: ``client:<ip>`` or ``retailer:<id>``) has queued or
    running, shared by every process: one sorted set per bucket (``<prefix>jobs:<bucket>``) of
    job ids scored by the time they were queued."""

    def __init__(self, conn: redis.Redis, prefix: str, queue: JobQueue):
        self.conn = conn
        self.prefix = prefix
        self.queue = queue

    def _key(self, bucket: str) -> str:
        return f"{self.prefix}jobs:{bucket}"

    def live(self, bucket: str, max_age_s: float) -> int:
        """How many of the bucket's tracked jobs are still queued or running; ended, vanished
        and older than ``max_age_s`` ones are forgotten."""
        key = self._key(bucket)
        self.conn.zremrangebyscore(key, "-inf", time.time() - max_age_s)
        live = 0
        for raw in self.conn.zrange(key, 0, -1):
            job_id = raw.decode() if isinstance(raw, bytes) else str(raw)
            job = self.queue.fetch(job_id)
            status = None if job is None else job.get_status(refresh=False)
            if job is None or str(getattr(status, "value", status)) in ENDED_JOB_STATES:
                self.conn.zrem(key, job_id)
            else:
                live += 1
        return live

    def track(self, bucket: str, job_id: str, max_age_s: float) -> None:
        """Count a job just queued against the bucket (the set expires after ``max_age_s``)."""
        key = self._key(bucket)
        self.conn.zadd(key, {job_id: time.time()})
        self.conn.expire(key, int(math.ceil(max_age_s)))

"""Adapted pose sets in Redis (``<prefix>poses:<digest>``, JSON with a TTL: derived data, a
cache) and the cross-process lock under which one process computes a missing set."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import redis

from service.storage.redis import lock


class PoseStore:
    """``get``/``put``/``delete`` of a pose set's JSON by key, ``lock(key)`` around computing it."""

    def __init__(self, conn: redis.Redis, prefix: str):
        self.conn = conn
        self.prefix = prefix

    def get(self, key: str) -> bytes | None:
        return self.conn.get(key)

    def put(self, key: str, value: str, ttl_s: int) -> None:
        self.conn.set(key, value, ex=ttl_s)

    def delete(self, key: str) -> None:
        self.conn.delete(key)

    @contextmanager
    def lock(self, key: str, ttl: int, wait: float) -> Iterator[bool]:
        """The cross-process lock of computing ``key`` (``<key>:lock``)."""
        with lock(self.conn, key + ":lock", ttl=ttl, wait=wait) as held:
            yield held

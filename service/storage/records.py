"""Repositories of typed records (:mod:`service.records`) in Redis.

Keys (prefix ``TRYON_REDIS_PREFIX``, default ``tryon:``): ``customer:<id>`` and ``garment:<id>``
(JSON), ``scan:<customer id>`` (an uploaded scan waiting for its fitting job, bytes, expiring),
``garment-upload:<garment id>`` (a draped garment waiting for its build job, bytes, expiring),
``garments`` (sorted set id -> creation time: the catalogue index), ``demo:<name>`` (the id of
a demo garment), ``lock:<name>``; ``poses:<digest>`` (a body's adapted page poses, JSON, expiring:
:mod:`service.application.poses`). Every call is one Redis round trip (pipelines and MGET);
:func:`fetch` reads a customer and garments together, once.
"""
from __future__ import annotations

import json
import re
import secrets
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Generic, TypeVar

import redis

from service.records import Customer, Garment, Record
from service.storage import redis as R

ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
SCAN_TTL = 3 * 86400  # seconds an uploaded scan waits for its fitting job

T = TypeVar("T", bound=Record)


def new_id() -> str:
    """A random URL-safe id (96 bits)."""
    return secrets.token_urlsafe(12)


def valid_id(value: str) -> bool:
    return bool(ID_RE.match(value or ""))


class Repo(Generic[T]):
    """JSON records of one kind under ``<prefix><kind>:<id>``."""

    kind = ""
    record_type: type[T]

    def __init__(self, conn: redis.Redis, prefix: str):
        self.conn = conn
        self.prefix = prefix

    def key(self, rid: str) -> str:
        return f"{self.prefix}{self.kind}:{rid}"

    def parse(self, raw: bytes | str | None) -> T | None:
        """A stored record; records written before schemas existed parse as schema 0."""
        if raw is None:
            return None
        data = json.loads(raw)
        data.setdefault("schema_version", 0)
        return self.record_type.model_validate(data)

    @staticmethod
    def dump(record: Record) -> str:
        return record.model_dump_json()

    def get(self, rid: str) -> T | None:
        return self.parse(self.conn.get(self.key(rid))) if valid_id(rid) else None

    def put(self, record: T) -> None:
        self.conn.set(self.key(record.id), self.dump(record))

    def replace_if_exists(self, record: T, *also_delete: str) -> bool:
        """Replace an existing record atomically unless it was deleted meanwhile (WATCH): a
        job's result never resurrects a deleted record. ``also_delete``: keys deleted in the
        same transaction. Returns whether it was written."""
        key = self.key(record.id)
        with self.conn.pipeline(transaction=True) as pipe:
            while True:
                try:
                    pipe.watch(key)
                    if not pipe.exists(key):
                        pipe.unwatch()
                        return False
                    pipe.multi()
                    pipe.set(key, self.dump(record))
                    for k in also_delete:
                        pipe.delete(k)
                    pipe.execute()
                    return True
                except redis.WatchError:
                    continue


class CustomerRepo(Repo[Customer]):
    """Customers, and the scans waiting for their fitting job."""

    kind = "customer"
    record_type = Customer

    def scan_key(self, cid: str) -> str:
        return f"{self.prefix}scan:{cid}"

    def put_with_scan(self, record: Customer, scan: bytes, ttl: int = SCAN_TTL) -> None:
        """Store a scan customer and its scan together (one transaction)."""
        pipe = self.conn.pipeline(transaction=True)
        pipe.set(self.scan_key(record.id), scan, ex=ttl)
        pipe.set(self.key(record.id), self.dump(record))
        pipe.execute()

    def get_scan(self, cid: str) -> bytes | None:
        return self.conn.get(self.scan_key(cid)) if valid_id(cid) else None

    def delete(self, cid: str) -> Customer | None:
        """Delete the customer and its stored scan; returns the deleted record (None: unknown)."""
        if not valid_id(cid):
            return None
        pipe = self.conn.pipeline(transaction=True)
        pipe.get(self.key(cid))
        pipe.delete(self.key(cid))
        pipe.delete(self.scan_key(cid))
        raw, existed, _ = pipe.execute()
        return self.parse(raw) if existed else None

    def complete(self, record: Customer) -> bool:
        """A fitting job's outcome: replace the customer (if it still exists) and drop its scan."""
        return self.replace_if_exists(record, self.scan_key(record.id))


class GarmentRepo(Repo[Garment]):
    """Garments and the catalogue index (creation order)."""

    kind = "garment"
    record_type = Garment

    @property
    def index_key(self) -> str:
        return f"{self.prefix}garments"

    def upload_key(self, gid: str) -> str:
        return f"{self.prefix}garment-upload:{gid}"

    def publish(self, record: Garment, upload: bytes | None = None, ttl: int = SCAN_TTL) -> None:
        """Store the garment and list it in the catalogue (one transaction); ``upload``: the
        uploaded files a build job will read (``garment-upload:<id>``, expiring)."""
        pipe = self.conn.pipeline(transaction=True)
        pipe.set(self.key(record.id), self.dump(record))
        pipe.zadd(self.index_key, {record.id: time.time()})
        if upload is not None:
            pipe.set(self.upload_key(record.id), upload, ex=ttl)
        pipe.execute()

    def get_upload(self, gid: str) -> bytes | None:
        return self.conn.get(self.upload_key(gid)) if valid_id(gid) else None

    def complete(self, record: Garment) -> bool:
        """A build job's outcome: replace the garment (if it still exists) and drop its upload."""
        return self.replace_if_exists(record, self.upload_key(record.id))

    def list(self) -> list[Garment]:
        """Every listed garment, oldest first (two round trips: the index, then MGET)."""
        ids = [i.decode() for i in self.conn.zrange(self.index_key, 0, -1)]
        if not ids:
            return []
        return [g for g in (self.parse(r) for r in self.conn.mget([self.key(i) for i in ids])) if g is not None]

    def delete(self, gid: str) -> bool:
        if not valid_id(gid):
            return False
        pipe = self.conn.pipeline(transaction=True)
        pipe.delete(self.key(gid))
        pipe.zrem(self.index_key, gid)
        pipe.delete(self.upload_key(gid))
        return bool(pipe.execute()[0])

    def demo_id(self, name: str) -> str | None:
        raw = self.conn.get(f"{self.prefix}demo:{name}")
        return None if raw is None else raw.decode()

    def set_demo_id(self, name: str, gid: str) -> None:
        self.conn.set(f"{self.prefix}demo:{name}", gid)

    @contextmanager
    def lock(self, name: str, ttl: int = 120, wait: float = 120.0) -> Iterator[bool]:
        with R.lock(self.conn, f"{self.prefix}lock:{name}", ttl, wait) as held:
            yield held


def fetch(customers: CustomerRepo, cid: str, garments: GarmentRepo,
          gids: list[str]) -> tuple[Customer | None, list[Garment | None]]:
    """A customer and garments in one round trip (MGET): the try-on's only Redis call."""
    keys = [customers.key(cid)] + [garments.key(g) for g in gids]
    ok = [valid_id(cid)] + [valid_id(g) for g in gids]
    raws = customers.conn.mget([k for k, good in zip(keys, ok) if good]) if any(ok) else []
    it = iter(raws)
    values = [next(it) if good else None for good in ok]
    return customers.parse(values[0]), [garments.parse(v) for v in values[1:]]

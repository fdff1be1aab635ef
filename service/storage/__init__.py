"""Persistent state, split by what it stores:

* :mod:`service.storage.redis` -- the Redis connection (``REDIS_URL``, else an embedded
  redis-server under ``TRYON_DATA_DIR``, with AOF, owned by one process and restarted when it
  dies) and cross-process locks;
* :mod:`service.storage.limits` -- rate-limit buckets (GCRA) in Redis;
* :mod:`service.storage.records` -- repositories of typed records in Redis (customers with
  their waiting scans, garments with the catalogue index) and one-round-trip fetches;
* :mod:`service.storage.bases` -- garment bases as memory-mapped ``.npy`` files, cached;
* :mod:`service.storage.queue` -- the rq job queue and the jobs' state as typed records;
* :mod:`service.storage.supervise` -- worker processes: ``tryon worker``, the embedded worker
  of ``tryon serve``, killing process trees;
* :mod:`service.storage.cache` -- the in-process versioned LRU.
"""

"""In-process caches."""
from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any


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

"""Independent per-pose work on a few threads of the process: an outfit's pose targets and posed
bodies (``scenes``), one pose per call. The compiled closest points, the k-d trees and numpy's
array work release the GIL, so on an idle machine the poses run side by side (a new customer's
first outfit ~25 % sooner, see "Clothes that move like clothes" in the README); the results are
those of one thread, in order. (The page poses' adaptation to a body gained nothing on threads:
151 / 150 ms per body, one / two threads, 8 customers; it stays on the request's thread.)"""
from __future__ import annotations

import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

WORKERS = 2  # threads per server process (``TRYON_POSE_WORKERS``; 1: everything on the calling thread)
_pool: tuple[int, ThreadPoolExecutor] | None = None  # (workers, the pool), made on first use per process
_lock = threading.Lock()


def per_pose(fn: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
    """``[fn(x) for x in items]``, on ``WORKERS`` threads when there are several items."""
    global _pool
    items = list(items)
    if WORKERS <= 1 or len(items) <= 1:
        return [fn(x) for x in items]
    with _lock:
        if _pool is None or _pool[0] != WORKERS:
            _pool = (WORKERS, ThreadPoolExecutor(WORKERS, thread_name_prefix="pose"))
        pool = _pool[1]
    return list(pool.map(fn, items))

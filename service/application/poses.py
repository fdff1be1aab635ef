"""The page's pose presets adapted to a customer's body (``GET /v1/customers/{id}/poses``).

The adaptation (``service.model.poses.adapted_poses``: more shoulder abduction until no arm
vertex is inside the torso or thighs) takes ~0.5 s per body in process (seconds over HTTP on a
loaded 2-core machine), so results are kept per
(body model, weights) in a small LRU shared by the process (also read by the try-on's pose
correctives: the same poses the page applies)."""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

from service.application.auth import Credentials
from service.application.customers import CustomerService
from service.model.body import BONES
from service.model.poses import adapted_poses

POSES_CACHE_SIZE = 256
_cache: OrderedDict = OrderedDict()
_lock = threading.Lock()


def record_poses(customers: CustomerService, record) -> dict[str, dict[str, list[float]]]:
    """{preset name: {bone: [x, y, z] axis-angle}} of a ready customer record (cached)."""
    key = (customers.model.version, tuple(record.weights or ()))
    with _lock:
        hit = _cache.get(key)
        if hit is not None:
            _cache.move_to_end(key)
            return hit
    poses = adapted_poses(customers.model, customers.body(record).vertices)
    out = {name: {b: [float(x) for x in np.asarray(p)[i]] for i, b in enumerate(BONES)} for name, p in poses.items()}
    with _lock:
        _cache[key] = out
        while len(_cache) > POSES_CACHE_SIZE:
            _cache.popitem(last=False)
    return out


def pose_arrays(poses: dict[str, dict[str, list[float]]]) -> dict[str, np.ndarray]:
    """:func:`record_poses` as {name: (17, 3) axis-angle in ``BONES`` order}."""
    return {name: np.array([p[b] for b in BONES], np.float64) for name, p in poses.items()}


def customer_poses(customers: CustomerService, cid: str, creds: Credentials) -> dict[str, dict[str, list[float]]]:
    """{preset name: {bone: [x, y, z] axis-angle radians (local rotation, rest frames = world
    axes)}} for every bone, in ``BONES`` order (404 unknown customer, 409 not ready)."""
    record = customers.require_ready(customers.open(customers.repo.get(cid), cid, creds), cid)
    return record_poses(customers, record)

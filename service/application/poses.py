"""The page's pose presets adapted to a customer's body (``GET /v1/customers/{id}/poses``).

The adaptation (``service.model.body.poses.adapted_poses``: more shoulder abduction until no arm
vertex is inside the torso or thighs) takes ~0.5 s of CPU per body, so its result is computed
once per body for the whole service: kept in the store (Redis, ``<prefix>poses:<digest>`` of the
body model, the weights, the presets and ``ADAPTATION_VERSION``, for ``POSES_TTL_S``), computed
under a cross-process lock (a second server process asked for the same body meanwhile waits for
it instead of computing it again), and in a small LRU per process (also read by the try-on's
pose correctives: the same poses the page applies). The store is only a cache: a missing or
malformed entry is computed again."""
from __future__ import annotations

import hashlib
import json
import logging
import threading
from collections import OrderedDict

import numpy as np

from service.model.body.model import BodyModel, BONES
from service.model.body.poses import ADAPTATION_VERSION, adapted_poses, presets
from service.records import Customer
from service.storage.poses import PoseStore

from .bodies import BodyCache

log = logging.getLogger(__name__)

POSES_CACHE_SIZE = 256
POSES_TTL_S = 30 * 24 * 3600  # seconds an adapted pose set stays in the store (derived data)
POSES_LOCK_TTL_S = 60  # seconds one computation may hold the lock (it takes ~0.5 s)
POSES_LOCK_WAIT_S = 30.0  # seconds a request waits for another process's computation, then computes
_cache: OrderedDict = OrderedDict()
_lock = threading.Lock()


def store_key(prefix: str, model_version: str, weights) -> str:
    """The store's key of the adapted poses of a body (its model version and weights) under the
    current presets and adaptation."""
    h = hashlib.sha1(f"{ADAPTATION_VERSION}|{model_version}|".encode())
    h.update(json.dumps(presets(), sort_keys=True).encode())
    h.update(np.asarray(weights, np.float64).tobytes())
    return f"{prefix}poses:{h.hexdigest()}"


def _valid(poses) -> bool:
    """A stored pose set as :meth:`Poses.record_poses` returns it: {name: {bone: [3 finite floats]}}
    for every bone."""
    try:
        return isinstance(poses, dict) and len(poses) > 0 and all(
            isinstance(p, dict) and set(p) == set(BONES)
            and all(len(v) == 3 and all(isinstance(x, float) and np.isfinite(x) for x in v) for v in p.values())
            for p in poses.values())
    except TypeError:
        return False


def _load(store: PoseStore, key: str):
    raw = store.get(key)
    if raw is None:
        return None
    try:
        poses = json.loads(raw)
    except ValueError:
        poses = None
    if not _valid(poses):
        log.warning("poses: malformed entry %s in the store; computing it again", key)
        return None
    return poses


class Poses:
    """The adapted poses of customers' bodies: the process LRU, the store (``store``), the
    bodies (``bodies``) of the body model ``model``."""

    def __init__(self, model: BodyModel, store: PoseStore, bodies: BodyCache):
        self.model = model
        self.store = store
        self.bodies = bodies

    def record_poses(self, record: Customer) -> dict[str, dict[str, list[float]]]:
        """{preset name: {bone: [x, y, z] axis-angle}} of a ready customer record: from the process
        LRU, else the store, else computed (once across processes) and stored."""
        key = (self.model.version, tuple(record.weights or ()))
        with _lock:
            hit = _cache.get(key)
            if hit is not None:
                _cache.move_to_end(key)
                return hit
        skey = store_key(self.store.prefix, self.model.version, record.weights or ())
        out = _load(self.store, skey)
        if out is None:
            # whether or not the lock came within the wait, the poses are then there or computed here
            with self.store.lock(skey, ttl=POSES_LOCK_TTL_S, wait=POSES_LOCK_WAIT_S):
                out = _load(self.store, skey)  # computed by another process while this one waited
                if out is None:
                    assert record.weights is not None
                    poses = adapted_poses(self.model, self.bodies.get(record.id, record.weights).vertices)
                    out = {name: {b: [float(x) for x in np.asarray(p)[i]] for i, b in enumerate(BONES)}
                           for name, p in poses.items()}
                    self.store.put(skey, json.dumps(out), POSES_TTL_S)
        with _lock:
            _cache[key] = out
            while len(_cache) > POSES_CACHE_SIZE:
                _cache.popitem(last=False)
        return out

    def forget(self, record: Customer) -> None:
        """Drop a deleted customer's adapted poses: from the store and this process's LRU (other
        processes' LRUs are keyed by the body alone and answer only for a ready record)."""
        self.store.delete(store_key(self.store.prefix, self.model.version, record.weights or ()))
        with _lock:
            _cache.pop((self.model.version, tuple(record.weights or ())), None)


def pose_arrays(poses: dict[str, dict[str, list[float]]]) -> dict[str, np.ndarray]:
    """:meth:`Poses.record_poses` as {name: (17, 3) axis-angle in ``BONES`` order}."""
    return {name: np.array([p[b] for b in BONES], np.float64) for name, p in poses.items()}

"""The customers' bodies (:class:`CustomerBody`: the body model's surface at a customer's
weights), cached per process."""
from __future__ import annotations

import numpy as np

from service.model.body.model import BodyModel
from service.model.garments.tryon import CustomerBody, customer_body
from service.storage.cache import VersionedLRU

BODY_CACHE_SIZE = 64


class BodyCache:
    """LRU of :class:`CustomerBody` per customer id, valid while its weights are unchanged."""

    def __init__(self, model: BodyModel, size: int = BODY_CACHE_SIZE):
        self.model = model
        self._lru = VersionedLRU(size)

    def get(self, cid: str, weights: list[float]) -> CustomerBody:
        key = tuple(weights)
        body = self._lru.get(cid, key)
        if body is None:
            body = customer_body(self.model, np.asarray(weights, np.float64))
            self._lru.put(cid, key, body)
        return body

    def drop(self, cid: str) -> None:
        self._lru.drop(cid)

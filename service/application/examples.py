"""The example avatars of the body model (``service.model.garments.tryon.example_set``): their listing
order, vertices and k-d trees of their body surfaces, built once per process."""
from __future__ import annotations

import threading

import numpy as np
from scipy.spatial import cKDTree

from service.model.body.model import BodyModel
from service.model.garments.tryon import example_set, example_vertices


class Examples:
    """The example avatars of a model: ``vertices`` (1 + 2N, V, 3) in listing order (``ids``)."""

    def __init__(self, model: BodyModel):
        self.model = model
        self.set = example_set(model)
        self.vertices = example_vertices(model, self.set)
        self.listing = self.set.listing()
        self.ids = [e["id"] for e in self.listing]
        self._trees: dict[int, cKDTree] = {}
        self._lock = threading.Lock()

    def tree(self, i: int) -> cKDTree:
        """k-d tree of example i's body surface vertices (built on first use)."""
        with self._lock:
            if i not in self._trees:
                self._trees[i] = cKDTree(self.model.body_vertices(self.vertices[i]).astype(np.float64))
            return self._trees[i]

    def index(self, example_id: str) -> int | None:
        try:
            return self.ids.index(example_id)
        except ValueError:
            return None

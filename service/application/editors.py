"""The per-process cache of clothed-avatar editors (``service.model.nonrigid.editing.
ClothedAvatarEditor``), each built once per customer from the mesh its fitting job stored
(``storage.meshes``), and of those meshes' faces."""
from __future__ import annotations

import threading

import numpy as np

from service.model.body.model import BONES
from service.model.nonrigid.editing import ClothedAvatarEditor
from service.records import Customer
from service.storage.cache import VersionedLRU
from service.storage.meshes import MeshStore

from .errors import Conflict

EDITOR_CACHE_SIZE = 8  # clothed-avatar editors kept per process (each ~50-100 MB for a 12k scan)


class Editors:
    def __init__(self, model, meshes: MeshStore):
        self.model = model
        self.meshes = meshes
        self._editors = VersionedLRU(EDITOR_CACHE_SIZE)
        self._locks: dict[str, threading.Lock] = {}
        self._locks_guard = threading.Lock()

    def editor(self, record: Customer) -> ClothedAvatarEditor | None:
        """The clothed-avatar editor of a customer fitted from a mesh (built on first use, then
        cached per process); None for customers without a stored scan mesh."""
        if not record.editable:
            return None
        version = (record.body_model, tuple(record.weights or ()))
        hit = self._editors.get(record.id, version)
        if hit is not None:
            return hit
        with self._locks_guard:
            lock = self._locks.setdefault(record.id, threading.Lock())
        with lock:  # one build per customer, whatever the number of concurrent first edits
            hit = self._editors.get(record.id, version)
            if hit is not None:
                return hit
            arrays = self.meshes.load(record.id)
            if arrays is None:
                raise Conflict(f"customer '{record.id}' has lost its scan mesh: delete it and upload the scan again")
            editor = build_editor(self.model, record, arrays)
            self._editors.put(record.id, version, editor)
        return editor

    def scan_faces(self, record: Customer) -> np.ndarray:
        hit = self._editors.get(record.id + ":faces", record.body_model)
        if hit is None:
            arrays = self.meshes.load(record.id)
            hit = np.asarray(arrays["faces"], np.int32) if arrays is not None else np.zeros((0, 3), np.int32)
            self._editors.put(record.id + ":faces", record.body_model, hit)
        return hit

    def forget(self, cid: str) -> None:
        self._editors.drop(cid)


def build_editor(model, record: Customer, arrays: dict[str, np.ndarray]) -> ClothedAvatarEditor:
    """The editor of a fitted clothed scan from its stored mesh (deterministic)."""
    pose = np.array([record.pose[b] for b in BONES], np.float64) if record.pose else None
    gender = str((record.measurements or {}).get("gender") or "female")
    return ClothedAvatarEditor(model, np.asarray(record.weights, np.float64), pose,
                               np.asarray(record.translation or [0.0, 0.0, 0.0], np.float64),
                               np.asarray(arrays["vertices"], np.float64), np.asarray(arrays["faces"], np.int64),
                               gender=gender)

"""Per-customer exact drapes as files: ``TRYON_DATA_DIR/drapes/<customer id>/<garment id>/<key>.npy``,
the garment's draped vertices (M, 3) float32 on that customer's body. ``key`` is a digest of
everything the drape is made of (the customer's shape, the garment's basis, its size, fabric,
the body model, the drape's settings): a stale drape is never found, and saving a new one for a
(customer, garment) removes the older ones. Written atomically (a temporary file renamed into
place) by the drape job; removed with the customer or the garment. With several hosts the data
directory must be shared storage, as for the garment bases."""
from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np

from service.storage.files import atomic_write
from service.storage.records import valid_id

SUFFIX = ".npy"


class DrapeStore:
    def __init__(self, data_dir: Path):
        self.root = Path(data_dir).resolve() / "drapes"
        self.root.mkdir(parents=True, exist_ok=True)

    def _dir(self, cid: str, gid: str) -> Path:
        if not (valid_id(cid) and valid_id(gid)):
            raise ValueError("invalid customer or garment id")
        return self.root / cid / gid

    def path(self, cid: str, gid: str, key: str) -> Path:
        if not valid_id(key):
            raise ValueError("invalid drape key")
        return self._dir(cid, gid) / f"{key}{SUFFIX}"

    def load(self, cid: str, gid: str, key: str) -> np.ndarray | None:
        """The draped vertices (M, 3) float32 under ``key``, or None."""
        try:
            v = np.load(self.path(cid, gid, key), allow_pickle=False)
        except FileNotFoundError:
            return None
        return np.asarray(v, np.float32)

    def save(self, cid: str, gid: str, key: str, vertices: np.ndarray) -> None:
        """Store the drape under ``key`` (atomically) and drop this pair's older drapes."""
        directory = self._dir(cid, gid)
        directory.mkdir(parents=True, exist_ok=True)
        target = self.path(cid, gid, key)
        buf = io.BytesIO()
        np.save(buf, np.ascontiguousarray(vertices, np.float32))
        atomic_write(target, buf.getvalue())
        for old in directory.glob(f"*{SUFFIX}"):
            if old != target and not old.name.startswith(".tmp-"):
                old.unlink(missing_ok=True)

    def delete(self, cid: str, gid: str, key: str) -> None:
        self.path(cid, gid, key).unlink(missing_ok=True)

    def delete_customer(self, cid: str) -> None:
        """Every drape of the customer."""
        if valid_id(cid):
            shutil.rmtree(self.root / cid, ignore_errors=True)

    def delete_garment(self, gid: str) -> None:
        """Every customer's drape of the garment (one directory per customer is looked at)."""
        if not valid_id(gid):
            return
        for customer in self.root.iterdir():
            if customer.is_dir():
                shutil.rmtree(customer / gid, ignore_errors=True)

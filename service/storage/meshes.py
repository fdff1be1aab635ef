"""Customers' own meshes as files: ``TRYON_DATA_DIR/customers/<id>/mesh.npz``, the uploaded
clothed scan (in the model frame) that the clothed-avatar editor carries along (issue 13).
Written atomically (a temporary file renamed into place) by the fitting job before the customer
becomes ready; removed with the customer. With several hosts the data directory must be shared
storage, as for the garment bases."""
from __future__ import annotations

import io
import shutil
from pathlib import Path

import numpy as np

from service.storage.files import atomic_write

MESH_FILE = "mesh.npz"


class MeshStore:
    def __init__(self, data_dir: Path):
        self.root = Path(data_dir).resolve() / "customers"
        self.root.mkdir(parents=True, exist_ok=True)

    def path(self, cid: str) -> Path:
        return self.root / cid / MESH_FILE

    def save(self, cid: str, arrays: dict[str, np.ndarray]) -> None:
        directory = self.root / cid
        directory.mkdir(parents=True, exist_ok=True)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        atomic_write(directory / MESH_FILE, buf.getvalue())

    def load(self, cid: str) -> dict[str, np.ndarray] | None:
        try:
            with np.load(self.path(cid), allow_pickle=False) as z:
                return {k: z[k] for k in z.files}
        except FileNotFoundError:
            return None

    def delete(self, cid: str) -> None:
        shutil.rmtree(self.root / cid, ignore_errors=True)

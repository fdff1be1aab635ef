"""Garment bases as files: ``TRYON_DATA_DIR/garments/<id>/`` (``.npy`` arrays and meta.json),
written atomically (``GarmentBasis.save``: a temporary sibling renamed into place) before the
garment's record is published, memory-mapped by every API process and cached per process
while the garment's etag is unchanged. With several hosts, the data directory must be shared
storage."""
from __future__ import annotations

import shutil
from pathlib import Path

from service.model.garments.tryon import GarmentBasis
from service.storage.cache import VersionedLRU


class BasisStore:
    def __init__(self, data_dir: Path, cache_size: int = 32):
        self.root = Path(data_dir).resolve() / "garments"
        self.root.mkdir(parents=True, exist_ok=True)
        self._cache = VersionedLRU(cache_size)

    def path(self, gid: str) -> Path:
        return self.root / gid

    def save(self, gid: str, basis: GarmentBasis) -> None:
        basis.save(self.path(gid))

    def load(self, gid: str, etag: str) -> GarmentBasis | None:
        """The basis of garment ``gid`` at version ``etag`` (memory-mapped, cached); None when
        its files are missing."""
        hit = self._cache.get(gid, etag)
        if hit is not None:
            return hit
        try:
            basis = GarmentBasis.load(self.path(gid), mmap=True)
        except FileNotFoundError:
            return None
        self._cache.put(gid, etag, basis)
        return basis

    def delete(self, gid: str) -> None:
        self._cache.drop(gid)
        shutil.rmtree(self.path(gid), ignore_errors=True)

    def ids(self) -> set[str]:
        """Ids of the bases on disk (for clean-ups)."""
        return {p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")}

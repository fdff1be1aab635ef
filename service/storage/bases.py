"""Garment bases as files: ``TRYON_DATA_DIR/garments/<id>/`` (``.npy`` arrays and meta.json),
written atomically (``GarmentBasis.save``: a temporary sibling renamed into place) before the
garment's record is published, memory-mapped by every API process and cached per process
while the garment's etag is unchanged. With several hosts, the data directory must be shared
storage.

A garment in several sizes keeps one basis per size: ``garments/<id>/size-<i>/`` (i: the
size's index in its chart), all written in one temporary directory renamed into place."""
from __future__ import annotations

import shutil
from pathlib import Path

from service.model.garments.tryon import GarmentBasis, atomic_directory
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

    def save_sizes(self, gid: str, bases: list[GarmentBasis]) -> None:
        """One basis per size (chart order), written together atomically."""
        with atomic_directory(self.path(gid)) as tmp:
            for i, basis in enumerate(bases):
                basis.save(tmp / f"size-{i}")
        for i in range(len(bases)):
            self._cache.drop(f"{gid}#{i}")
        self._cache.drop(gid)

    def load(self, gid: str, etag: str, size: int | None = None) -> GarmentBasis | None:
        """The basis of garment ``gid`` at version ``etag`` (memory-mapped, cached); with
        ``size``, that size's basis of a garment in sizes (a garment in one size: its basis);
        None when its files are missing."""
        sized = size is not None and (self.path(gid) / f"size-{size}").is_dir()
        key = f"{gid}#{size}" if sized else gid
        hit = self._cache.get(key, etag)
        if hit is not None:
            return hit
        try:
            basis = GarmentBasis.load(self.path(gid) / f"size-{size}" if sized else self.path(gid), mmap=True)
        except FileNotFoundError:
            return None
        self._cache.put(key, etag, basis)
        return basis

    def delete(self, gid: str) -> None:
        self._cache.drop(gid)
        for i in range(32):
            self._cache.drop(f"{gid}#{i}")
        shutil.rmtree(self.path(gid), ignore_errors=True)

    def ids(self) -> set[str]:
        """Ids of the bases on disk (for clean-ups)."""
        return {p.name for p in self.root.iterdir() if p.is_dir() and not p.name.startswith(".")}

"""Garment bases on disk and the try-on itself (pure numpy; no web or queue imports).

``GarmentBasis`` holds everything a try-on needs for one garment: the mean garment g (M, 3),
the clothing basis B (N, M, 3), faces (F, 3), the push-out binding (M, k) to body vertices,
skinning transferred from the body (M, 4) + (M, 4), a colour and a layer. It is stored as
plain ``.npy`` files in one directory and memory-mapped by every API process.
"""
from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from service.model import garment as G
from service.model.geometry import face_incidence, vertex_normals

# Example avatars: E0 and E(i, +/-) = m +/- c sqrt(lambda_i) U_i for i < N. N and c were chosen
# with `tryon bench tryon` (garment accuracy on held-out avatars; see README "Figures").
EXAMPLES = {"n": 32, "c": 0.5}
ARRAYS = ("g", "B", "faces", "binding", "skin_idx", "skin_w", "gn", "Bn")
OPTIONAL = ("gn", "Bn")  # normal basis: bases saved before it existed load without it


def example_set(model, n: int | None = None, c: float | None = None) -> G.ExampleSet:
    n = min(n or EXAMPLES["n"], model.n_components)
    return G.ExampleSet(n=n, c=float(c or EXAMPLES["c"]), sigma=np.sqrt(model.variances[:n]))


def example_vertices(model, examples: G.ExampleSet) -> np.ndarray:
    """(1 + 2N, V, 3) float32 example avatars in listing order."""
    W = np.zeros((1 + 2 * examples.n, model.n_components))
    W[:, : examples.n] = examples.weights()
    return model.vertices(W)


@dataclass
class GarmentBasis:
    g: np.ndarray
    B: np.ndarray
    faces: np.ndarray
    binding: np.ndarray
    skin_idx: np.ndarray
    skin_w: np.ndarray
    gn: np.ndarray | None = None  # (M, 3) normals of the mean garment
    Bn: np.ndarray | None = None  # (N, M, 3) their basis (central differences, like B)
    meta: dict = field(default_factory=dict)
    _smoother: object = None
    _incidence: object = None

    @property
    def n_vertices(self) -> int:
        return int(self.g.shape[0])

    def smoother(self):
        if self._smoother is None:
            self._smoother = G.laplacian_smoother(np.asarray(self.faces), self.n_vertices)
        return self._smoother

    def normals(self, vertices: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Unit vertex normals (M, 3) float32 of the garment. With the customer's ``weights``
        and a normal basis: synthesized like the positions (gn + w Bn, renormalised; 3MN
        multiply-adds) instead of recomputed from the mesh."""
        if weights is not None and self.gn is not None:
            n = G.synthesize(np.asarray(self.gn), np.asarray(self.Bn), weights)
            return n / np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]
        if self._incidence is None:
            self._incidence = face_incidence(np.asarray(self.faces), self.n_vertices)
        return vertex_normals(vertices, self.faces, self._incidence)

    def save(self, directory: Path) -> None:
        """Write atomically: a temporary sibling directory renamed into place."""
        directory = Path(directory)
        directory.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=directory.parent))
        try:
            for k in ARRAYS:
                if getattr(self, k) is not None:
                    np.save(tmp / f"{k}.npy", np.ascontiguousarray(getattr(self, k)))
            (tmp / "meta.json").write_text(json.dumps(self.meta, sort_keys=True))
            if directory.exists():
                shutil.rmtree(directory)
            os.replace(tmp, directory)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise

    @classmethod
    def load(cls, directory: Path, mmap: bool = True) -> "GarmentBasis":
        directory = Path(directory)
        arrs = {k: np.load(directory / f"{k}.npy", mmap_mode="r" if mmap else None) for k in ARRAYS
                if k not in OPTIONAL or (directory / f"{k}.npy").exists()}
        meta = json.loads((directory / "meta.json").read_text())
        return cls(**arrs, meta=meta)

    def etag(self) -> str:
        return self.meta.get("etag", "")


def build_garment_basis(model, fits: np.ndarray, faces: np.ndarray, examples: G.ExampleSet,
                        meta: dict | None = None) -> GarmentBasis:
    """fits: (1 + 2N, M, 3) the garment fitted to each example avatar (listing order)."""
    g, B = G.build_basis(fits, examples)
    inc = face_incidence(np.asarray(faces), fits.shape[1])
    gn, Bn = G.build_basis(np.stack([vertex_normals(f, faces, inc) for f in fits]), examples)
    nb = model.n_body_vertices
    body0 = model.mean[:nb]
    binding = G.bind_to_body(g, body0)
    near = binding[:, 0]
    meta = dict(meta or {})
    meta.update({"n_vertices": int(g.shape[0]), "n_faces": int(len(faces)), "n_components": int(examples.n),
                 "examples_c": examples.c})
    h = hashlib.sha256()
    for a in (g, B, np.asarray(faces, np.int32)):
        h.update(np.ascontiguousarray(a).tobytes())
    meta["etag"] = h.hexdigest()[:32]
    return GarmentBasis(g=g, B=B, faces=np.asarray(faces, np.int32), binding=binding,
                        skin_idx=model.lbs_indices[near].copy(), skin_w=model.lbs_weights[near].copy(),
                        gn=gn, Bn=Bn, meta=meta)


@dataclass
class CustomerBody:
    """What a try-on needs of a customer's body, computed once per customer (and, lazily,
    once per garment: the exact nearest body vertex of each synthesized garment vertex)."""

    weights: np.ndarray  # (K,)
    vertices: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (n_body, 3) float32
    _tree: object = None
    _bindings: dict = field(default_factory=dict)

    def binding(self, basis: "GarmentBasis", garment: np.ndarray) -> np.ndarray:
        """(M, 1) nearest body vertex of each garment vertex on this body (cached per garment)."""
        key = basis.etag() or id(basis)
        hit = self._bindings.get(key)
        if hit is None:
            if self._tree is None:
                self._tree = cKDTree(self.vertices[: len(self.normals)])
            hit = self._tree.query(garment)[1].astype(np.int32)[:, None]
            if len(self._bindings) >= MAX_BINDINGS_PER_BODY:
                self._bindings.pop(next(iter(self._bindings)))
            self._bindings[key] = hit
        return hit


MAX_BINDINGS_PER_BODY = 32


def customer_body(model, weights: np.ndarray) -> CustomerBody:
    X = model.vertices(weights)
    nb = model.n_body_vertices
    n = vertex_normals(X[:nb], model.body_faces).astype(np.float32)
    return CustomerBody(np.asarray(weights, np.float64), X, n)


def try_on(basis: GarmentBasis, body: CustomerBody, layer: int = 0) -> tuple[np.ndarray, int]:
    """The fitted garment (M, 3) float32 for a customer and how many vertices were pushed out.

    Synthesis g + w B (3MN multiply-adds), then push-out of the customer's body with a
    clearance growing with the layer (outer garments over inner ones). The first try-on of a
    garment on a body also finds each garment vertex's nearest body vertex (a k-d tree query,
    cached on the body)."""
    v = G.synthesize(np.asarray(basis.g), np.asarray(basis.B), body.weights)
    clearance = G.CLEARANCE + layer * G.LAYER_GAP
    return G.push_out(v, body.vertices, body.normals, body.binding(basis, v), basis.smoother(), clearance)

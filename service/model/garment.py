"""Clothing bases and try-on synthesis (seed: PCA clothes fitting). Pure numpy.

A garment is fitted offline to the example avatars E0 = m and E(i, +/-) = m +/- c sqrt(l_i) U_i
(i < N). Its clothing basis row i is the change of the garment per unit PCA weight i, by
central differences (the paper normalises the clothes fitted to each principal component;
with +/- examples the central difference is exact for anything linear and second-order
accurate otherwise):

    g = G0,   B_i = (G(i,+) - G(i,-)) / (2 c sqrt(l_i))                       (basis)
    garment(w) = g + sum_i w_i B_i            (3MN multiply-adds, the paper's cost)    (try-on)

A linear basis can push cloth into the body, so every try-on is followed by a push-out: each
garment vertex is tested against a few body vertices bound to it offline (nearest on the mean
avatar); any vertex closer than ``CLEARANCE`` to the customer's body along the body normal is
moved out, and the displacement is smoothed over the garment (``SMOOTHING``).

Shapes: garment vertices (M, 3) float32, faces (F, 3) int32, basis (N, M, 3) float32, body
vertices (V, 3), weights (K,) (only the first N used).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.geometry import row_dot

CLEARANCE = 0.003  # metres between skin and cloth after push-out
LAYER_GAP = 0.004  # extra clearance per layer (outer garments over inner ones)
# Body vertices bound per garment vertex. Garment and body move with the same weights, so the
# nearest body vertex on the mean avatar stays the right one (checked by `tryon bench tryon`'s
# exact penetration test); more candidates cost a gather and an argmin per try-on.
BIND_K = 1
SMOOTHING = {"iterations": 3, "alpha": 0.5}


@dataclass
class ExampleSet:
    """The example avatars: E0 and E(i, +/-) for i < n, coefficient c (in std units)."""

    n: int
    c: float
    sigma: np.ndarray  # (n,) sqrt(variance_i)

    def weights(self) -> np.ndarray:
        """(1 + 2n, K_used=n) weights of the examples, in the order of /v1/example-avatars:
        E0, E(0,+), E(0,-), E(1,+), E(1,-), ..."""
        W = np.zeros((1 + 2 * self.n, self.n))
        for i in range(self.n):
            W[1 + 2 * i, i] = self.c * self.sigma[i]
            W[2 + 2 * i, i] = -self.c * self.sigma[i]
        return W

    def listing(self) -> list[dict]:
        out = [{"id": "mean", "component": None, "sign": 0, "coefficient": 0.0}]
        for i in range(self.n):
            for sign, tag in ((1, "plus"), (-1, "minus")):
                out.append({"id": f"pc{i:02d}-{tag}", "component": i, "sign": sign,
                            "coefficient": float(sign * self.c * self.sigma[i])})
        return out


def build_basis(fits: np.ndarray, examples: ExampleSet) -> tuple[np.ndarray, np.ndarray]:
    """fits: (1 + 2N, M, 3) garment fitted to each example (listing order) ->
    (mean garment g (M, 3), basis B (N, M, 3)) by central differences."""
    fits = np.asarray(fits, np.float64)
    g = fits[0]
    plus, minus = fits[1::2], fits[2::2]
    step = (2 * examples.c * examples.sigma)[:, None, None]
    return g.astype(np.float32), ((plus - minus) / step).astype(np.float32)


def synthesize(g: np.ndarray, B: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Garment for weights w: g + sum_i w_i B_i (M, 3) float32 (3MN multiply-adds)."""
    n = B.shape[0]
    return g + (np.asarray(w[:n], np.float32) @ B.reshape(n, -1)).reshape(g.shape)


def bind_to_body(garment: np.ndarray, body: np.ndarray, k: int = BIND_K) -> np.ndarray:
    """Offline: the k nearest body vertices of each garment vertex on the mean avatar.

    garment (M, 3), body (Vb, 3) -> (M, k) int32."""
    _, idx = cKDTree(body).query(garment, k=k)
    return idx.reshape(len(garment), k).astype(np.int32)


def laplacian_smoother(faces: np.ndarray, n_vertices: int) -> sp.csc_matrix:
    """The displacement diffusion operator S = ((1 - a) I + a A)^k (CSC), A the uniform
    (row-normalised) adjacency, a and k from ``SMOOTHING``. Precompute once per garment."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.concatenate([e, e[:, ::-1]])
    A = sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n_vertices, n_vertices))
    A.data[:] = 1.0
    deg = np.asarray(A.sum(1)).ravel()
    A = sp.diags(1.0 / np.maximum(deg, 1)) @ A
    step = (1 - SMOOTHING["alpha"]) * sp.identity(n_vertices, format="csr") + SMOOTHING["alpha"] * A
    S = sp.identity(n_vertices, format="csr")
    for _ in range(SMOOTHING["iterations"]):
        S = S @ step
    return S.tocsc().astype(np.float32)


def push_out(garment: np.ndarray, body: np.ndarray, body_normals: np.ndarray, binding: np.ndarray,
             smoother: sp.csc_matrix | None = None, clearance: float = CLEARANCE) -> tuple[np.ndarray, int]:
    """Move garment vertices that are inside the body (or within ``clearance`` of it) out
    along the body normal, then smooth the displacement so the garment stays smooth.

    garment (M, 3); body (Vb, 3) and body_normals (Vb, 3) of the customer; binding (M, k)
    body vertices per garment vertex (the nearest of them is used; with k = 1, pass the
    nearest body vertex of this body, see ``tryon.CustomerBody.binding``). The distance to the
    skin is that to the bound vertex's tangent plane.
    Returns (garment (M, 3) float32, number of vertices moved)."""
    G = np.asarray(garment, np.float32)
    body = np.asarray(body, np.float32)
    if binding.shape[1] == 1:
        nb = binding[:, 0]
    else:
        diff = body[binding] - G[:, None, :]  # (M, k, 3)
        j = np.argmin(np.einsum("ijk,ijk->ij", diff, diff), axis=1)
        nb = binding[np.arange(len(G)), j]
    p, n = np.take(body, nb, axis=0), np.take(body_normals, nb, axis=0)  # ~4x faster than body[nb]
    depth = clearance - row_dot(G - p, n)  # > 0: too close or inside
    bad = np.flatnonzero(depth > 0)
    if not len(bad):
        return G, 0
    d, nbad = depth[bad], np.take(n, bad, axis=0)
    required = d[:, None] * nbad
    if smoother is not None:
        # diffuse the pushes to the neighbours (only the pushed vertices' columns of S), and
        # keep each pushed vertex's full push: the garment stays smooth and outside
        disp = np.asarray(smoother[:, bad] @ required, np.float32)
    else:
        disp = np.zeros_like(G)
    # each pushed vertex ends at least ``clearance`` out along its body normal
    short = d - row_dot(np.take(disp, bad, axis=0), nbad)
    disp[bad] += np.maximum(short, 0)[:, None] * nbad
    return (G + disp).astype(np.float32, copy=False), len(bad)

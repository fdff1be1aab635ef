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

from service.model.geometry import kernels
from service.model.geometry.mesh import closest_points_on_mesh, face_bounds, neighbour_mean, row_dot

CLEARANCE = 0.003  # metres between skin and cloth after push-out
LAYER_GAP = 0.004  # extra clearance per layer (outer garments over inner ones)
# Body vertices bound per garment vertex. Garment and body move with the same weights, so the
# nearest body vertex on the mean avatar stays the right one (checked by `tryon bench tryon`'s
# exact penetration test); more candidates cost a gather and an argmin per try-on.
BIND_K = 1
SMOOTHING = {"iterations": 3, "alpha": 0.5}

COMPILED = True  # the push-out's diffusion of its pushes in a compiled loop (geometry.kernels) where numba is there


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


# Ridge weight of the regressed basis (dimensionless: per unit of a component's squared std):
# small enough not to bias a well-sampled basis, large enough to keep a thinly sampled one finite.
REGRESSION_RIDGE = 1e-3


def regress_basis(fits: np.ndarray, weights: np.ndarray, sigma: np.ndarray,
                  ridge: float = REGRESSION_RIDGE) -> tuple[np.ndarray, np.ndarray]:
    """The clothing basis as the least-squares line through garments fitted to many bodies:
    fits (K, M, 3) on bodies of weights (K, N) (the examples and population bodies), sigma (N,)
    each component's std -> (g (M, 3), B (N, M, 3)) minimising

        sum_k || g + sum_i w_ki B_i - fit_k ||^2 + ridge K sum_i sigma_i^2 ||B_i||^2

    (the ridge per unit std of each component and per body). The try-on is the
    same arithmetic as with :func:`build_basis`; where the fits are not linear in the body
    (cloth that is tight on large bodies and hangs on small ones) the line is fitted over the
    bodies a shop will see instead of through two examples half a std from the mean."""
    fits = np.asarray(fits, np.float64)
    W = np.asarray(weights, np.float64)
    K, n = W.shape
    if len(fits) != K or K < n + 1:
        raise ValueError(f"need at least {n + 1} fitted bodies for {n} components and one fit per body; "
                         f"got {len(fits)} fits for {K} bodies")
    A = np.hstack([np.ones((K, 1)), W / sigma[None, :]])  # columns in std units: one ridge for all
    reg = ridge * K * np.diag(np.r_[0.0, np.ones(n)])
    sol = np.linalg.solve(A.T @ A + reg, A.T @ fits.reshape(K, -1))
    g = sol[0].reshape(fits.shape[1:])
    B = (sol[1:] / sigma[:, None]).reshape(n, *fits.shape[1:])
    return g.astype(np.float32), B.astype(np.float32)


def example_equivalent(g: np.ndarray, B: np.ndarray, examples: ExampleSet) -> np.ndarray:
    """(1 + 2N, M, 3): the example fits whose central differences (:func:`build_basis`) are
    exactly the basis (g, B): g, g +/- c sigma_i B_i (a regressed basis stored like any other)."""
    W = examples.weights()
    return (g[None].astype(np.float64) + np.einsum("ki,imd->kmd", W, np.asarray(B, np.float64))).astype(np.float32)


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
    A = neighbour_mean(faces, n_vertices)
    step = (1 - SMOOTHING["alpha"]) * sp.identity(n_vertices, format="csr") + SMOOTHING["alpha"] * A
    S = sp.identity(n_vertices, format="csr")
    for _ in range(SMOOTHING["iterations"]):
        S = S @ step
    return S.tocsc().astype(np.float32)


CREASE_K = 4  # nearest body vertices looked at for facing skin (crease_anchors)
CREASE_COS = -0.5  # two of them facing each other: normals' cosine below this
CREASE_PROBE_M = 0.01  # how far out from a crease's skin the facing skin is looked for


def in_crease(nearest: np.ndarray, body_normals: np.ndarray, k: int = CREASE_K) -> np.ndarray:
    """Garment vertices in a crease (see :func:`crease_anchors`): nearest (M, >= k) body vertex
    ids of each garment vertex, nearest first (the first k looked at), body_normals (Vb, 3)
    unit -> (R,) int64 garment vertex ids."""
    n0 = np.take(body_normals, nearest[:, 0], axis=0)
    cos = np.einsum("mkd,md->mk", np.take(body_normals, nearest[:, 1:k], axis=0), n0)
    return np.flatnonzero((cos < CREASE_COS).any(axis=1)).astype(np.int64)


def crease_anchors(garment: np.ndarray, idx: np.ndarray, nearest: np.ndarray, body: np.ndarray,
                   body_normals: np.ndarray, faces: np.ndarray, tree, vert_faces: np.ndarray,
                   bounds: tuple | None = None) -> tuple[np.ndarray, ...]:
    """Where the nearest body vertex's tangent plane is the wrong skin for a push-out: garment
    vertices in a crease (crotch, armpit, heavy thighs or a belly fold), where skin faces skin
    and a vertex can be outside one side's plane but inside the other side. A garment vertex
    is in a crease when one of its ``CREASE_K`` nearest body vertices has a normal facing the
    nearest one's (cosine < ``CREASE_COS``); its skin is then the exact closest point of the
    body surface (``geometry.closest_points_on_mesh``) with that triangle's normal, and the
    push-out's clearance there is at most half the gap to the facing skin along that normal
    (the nearer of the facing vertices' tangent planes and the plane of the facing triangle
    closest to a point ``CREASE_PROBE_M`` out): in a slit narrower than twice the clearance
    the vertex stops in the middle instead of being pushed into the other side.

    garment (M, 3); idx: :func:`in_crease`; nearest (M, k) body vertex ids, nearest first; body (Vb, 3),
    body_normals (Vb, 3) unit; faces (F, 3); tree over body; vert_faces of faces; bounds:
    ``geometry.face_bounds`` of the body (made here when None; its unit normals are the
    triangles' normals used here).
    Returns (garment vertex ids (R,) int64, skin points (R, 3) float32, unit normals (R, 3)
    float32, largest clearance (R,) float32, inf where no skin faces), the ``anchors`` of
    :func:`push_out`."""
    idx = np.asarray(idx, np.int64)
    if not len(idx):
        return idx, np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    V = np.asarray(body, np.float64)
    F = np.asarray(faces, np.int64)
    bounds = face_bounds(V, F) if bounds is None else bounds
    face, q, _ = closest_points_on_mesh(np.asarray(garment, np.float64)[idx], V, F, tree=tree, vert_faces=vert_faces,
                                        bounds=bounds)
    fn = bounds[1][face]  # the closest triangles' unit normals
    # the facing skin along fn: the tangent plane of each of the nearest vertices that faces fn,
    # and the triangle closest to a probe CREASE_PROBE_M out along fn when it faces fn
    near = nearest[idx, :CREASE_K]
    nj = np.take(body_normals, near, axis=0).astype(np.float64)  # (R, K, 3)
    facing = np.einsum("rkd,rd->rk", nj, fn)
    reach = np.einsum("rkd,rkd->rk", V[near] - q[:, None, :], nj) / np.minimum(facing, -1e-6)
    gap = np.where((facing < CREASE_COS) & (reach > 0), reach, np.inf).min(axis=1)
    face2, q2, _ = closest_points_on_mesh(q + CREASE_PROBE_M * fn, V, F, tree=tree, vert_faces=vert_faces,
                                          bounds=bounds)
    n2 = bounds[1][face2]
    facing2 = np.einsum("rd,rd->r", n2, fn)
    reach2 = np.einsum("rd,rd->r", q2 - q, n2) / np.minimum(facing2, -1e-6)
    gap = np.minimum(gap, np.where((facing2 < CREASE_COS) & (reach2 > 0), reach2, np.inf))
    return idx, q.astype(np.float32), fn.astype(np.float32), (0.5 * gap).astype(np.float32)


_NO_ANCHORS = (np.zeros(0, np.int64), np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
               np.zeros(0, np.float32))


def push_out(garment: np.ndarray, body: np.ndarray, body_normals: np.ndarray, binding: np.ndarray,
             smoother: sp.csc_matrix | None = None, clearance: float = CLEARANCE,
             anchors: tuple[np.ndarray, ...] | None = None,
             under: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
             faces: np.ndarray | None = None) -> tuple[np.ndarray, int]:
    """Move garment vertices that are inside the body (or within ``clearance`` of it) out
    along the body normal, then smooth the displacement so the garment stays smooth.

    garment (M, 3); body (Vb, 3) and body_normals (Vb, 3) of the customer; binding (M, k)
    body vertices per garment vertex (the nearest of them is used; with k = 1, pass the
    nearest body vertex of this body, see ``tryon.CustomerBody.binding``). The distance to the
    skin is that to the bound vertex's tangent plane, or, for the garment vertices of
    ``anchors`` = (indices (R,), skin points (R, 3), unit normals (R, 3), largest clearance
    (R,)), to the plane of their own skin point, with at most that clearance
    (:func:`crease_anchors`: where facing skin makes the bound vertex's plane wrong). Then, with
    ``under`` = (body vertex indices (R,), garment faces (R,), barycentric weights (R, 3) of
    the body vertex's closest point in them: ``correctives.skin_under_faces``) and the
    garment's ``faces``, the body vertices under a
    face's inside clear it too (a body detail between the garment's vertices otherwise shows
    through a tight garment): the face's vertices move out along the body vertex's normal, each
    by its barycentric share (PBD's point-triangle constraint, Mueller et al. 2007 Sec. 4.4;
    the drape solver's ``push_faces``), the largest move per vertex. Returns (garment (M, 3)
    float32, number of vertices moved)."""
    G = np.asarray(garment, np.float32)
    body = np.asarray(body, np.float32)
    if (COMPILED and kernels.AVAILABLE and binding.shape[1] == 1 and sp.isspmatrix_csc(smoother)
            and body_normals.dtype == np.float32 and smoother.dtype == np.float32):
        # the vertex pass below in one compiled loop (the same float32 operations in the same
        # order: the same result bit for bit, without numpy's temporaries)
        if anchors is not None and len(anchors[0]):
            a, q, qn, most = (np.asarray(anchors[0], np.int64), np.asarray(anchors[1], np.float32),
                              np.asarray(anchors[2], np.float32), np.asarray(anchors[3], np.float32))
        else:
            a, q, qn, most = _NO_ANCHORS
        disp = np.zeros_like(G)
        n_bad = kernels.push_vertices(G, body, body_normals, np.ascontiguousarray(binding[:, 0]), np.float32(clearance),
                                      a, q, qn, most, smoother.indptr, smoother.indices, smoother.data, disp)
        if not n_bad:
            return _push_faces(G, body, body_normals, under, faces, clearance)
        out, n_faces = _push_faces(G + disp, body, body_normals, under, faces, clearance)
        return out, n_bad + n_faces
    if binding.shape[1] == 1:
        nb = binding[:, 0]
    else:
        diff = body[binding] - G[:, None, :]  # (M, k, 3)
        j = np.argmin(np.einsum("ijk,ijk->ij", diff, diff), axis=1)
        nb = binding[np.arange(len(G)), j]
    p, n = np.take(body, nb, axis=0), np.take(body_normals, nb, axis=0)  # ~4x faster than body[nb]
    depth = clearance - row_dot(G - p, n)  # > 0: too close or inside
    if anchors is not None and len(anchors[0]):
        a, q, qn, most = anchors
        p[a], n[a] = q, qn
        depth[a] = np.minimum(most, clearance) - row_dot(G[a] - q, qn)
    bad = np.flatnonzero(depth > 0)
    if not len(bad):
        return _push_faces(G, body, body_normals, under, faces, clearance)
    d, nbad = depth[bad], np.take(n, bad, axis=0)
    required = d[:, None] * nbad
    if smoother is not None:
        # diffuse the pushes to the neighbours (only the pushed vertices' columns of S), and
        # keep each pushed vertex's full push: the garment stays smooth and outside
        if COMPILED and kernels.AVAILABLE and sp.isspmatrix_csc(smoother):
            disp = np.zeros_like(G)
            kernels.columns_product(smoother.indptr, smoother.indices, smoother.data, bad,
                                    np.ascontiguousarray(required, np.float32), disp)
        else:
            disp = np.asarray(smoother[:, bad] @ required, np.float32)
    else:
        disp = np.zeros_like(G)
    # each pushed vertex ends at least ``clearance`` out along its body normal
    short = d - row_dot(np.take(disp, bad, axis=0), nbad)
    disp[bad] += np.maximum(short, 0)[:, None] * nbad
    out, n_faces = _push_faces((G + disp).astype(np.float32, copy=False), body, body_normals, under, faces, clearance)
    return out, len(bad) + n_faces


def face_pass_depths(G: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                     under: tuple[np.ndarray, np.ndarray, np.ndarray], faces: np.ndarray,
                     clearance: float) -> np.ndarray:
    """(R,) how far each pair of ``under`` (:func:`push_out`) has its garment face point (of G
    (M, 3)) short of ``clearance`` out of its body vertex, along the body vertex's normal
    (> 0: :func:`push_out`'s face pass lifts the face)."""
    b, f, w = under
    q = np.einsum("rkc,rk->rc", G[faces[f]], w)
    return clearance - row_dot(q - np.take(body, b, axis=0), np.take(body_normals, b, axis=0))


def _push_faces(G: np.ndarray, body: np.ndarray, body_normals: np.ndarray,
                under: tuple[np.ndarray, np.ndarray, np.ndarray] | None, faces: np.ndarray | None,
                clearance: float) -> tuple[np.ndarray, int]:
    """:func:`push_out`'s body-vertex / garment-face pass: G (M, 3) float32, returned moved, and
    how many garment vertices moved."""
    if under is None or faces is None or not len(under[0]):
        return G, 0
    b, f, w = under
    tri = faces[f]
    depth = face_pass_depths(G, body, body_normals, under, faces, clearance)
    hit = depth > 0
    if not hit.any():
        return G, 0
    tri, w, nb, depth = tri[hit], w[hit], np.take(body_normals, b[hit], axis=0), depth[hit]
    amount = (w * (depth / (w ** 2).sum(1))[:, None]).ravel()  # the face point moves by depth
    idx, inv = np.unique(tri.ravel(), return_inverse=True)  # the touched vertices only (a try-on's budget)
    move = np.zeros(len(idx))
    np.maximum.at(move, inv, amount)
    best = amount >= move[inv] - 1e-12  # each vertex along the normal of its deepest pair
    dirs = np.zeros((len(idx), 3))
    dirs[inv[best]] = np.repeat(nb, 3, axis=0)[best]
    out = G.copy()
    out[idx] += (move[:, None] * dirs).astype(np.float32)
    return out, int((move > 0).sum())

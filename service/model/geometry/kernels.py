"""Compiled inner loops (numba) of the geometry helpers that every try-on, outfit, pose
adaptation and fit spends most of its time in. Each geometry kernel computes exactly what its
numpy reference in ``service.model.geometry.mesh`` computes (the same float operations in the same
order, so the same results bit for bit; the tests compare them), one query point at a time with
no temporaries. The fitting's kernels (:func:`pose_jacobian_into`, :func:`pair_rows`) compute
what ``fitting._pose_jacobian`` and ``nonrigid.point_to_plane_normal_equations`` compute with
numpy, summed in their own order (equal to ~1e-15 relative; the tests compare them); so do the
cloth drape's (:func:`membrane`, :func:`vertex_normals`, :func:`strain_limit_pass`,
:func:`contact_project`: what ``drape.solver`` computes with numpy and sparse products). The
try-on's push-out (:func:`push_vertices`, :func:`columns_product`) and the drape's trust region
(:func:`clamp_steps`, :func:`max_move`) compute what numpy and scipy compute there, in their order.
``AVAILABLE`` is False where numba is not installed (or ``TRYON_NO_KERNELS`` is set): callers
then use the numpy path.

numba is imported and the kernels compiled on a process's first use (:func:`_compiled`), not
at import: they cost ~105 MB of memory per process (numba ~54 MB, LLVM and the loaded code
~51 MB), which a process that never needs them (one that only reads uploads, a CLI) does not
pay. Compiled once per machine into numba's on-disk cache (next to this file, or
``NUMBA_CACHE_DIR``; the Docker image compiles them at build time, :func:`warm`), then loaded in
~0.2 s."""
from __future__ import annotations

import importlib.util
import logging
import os
import threading
from types import SimpleNamespace

import numpy as np

log = logging.getLogger(__name__)

AVAILABLE = not os.environ.get("TRYON_NO_KERNELS") and importlib.util.find_spec("numba") is not None
PRUNE_SLACK = 1e-9  # the same slack as geometry's pruning (rounding of the bound itself)
PRUNE_SLACK_SQ = 1e-18
JIT_OPTIONS = {"cache": True, "nogil": True, "fastmath": False, "error_model": "numpy"}
_compiled_kernels: SimpleNamespace | None = None
_load_lock = threading.Lock()


def _compiled() -> SimpleNamespace:
    """The compiled kernels (numba dispatchers), made on the first call in the process."""
    global _compiled_kernels
    if _compiled_kernels is None:
        with _load_lock:
            if _compiled_kernels is None:
                import numba

                jit = numba.njit(**JIT_OPTIONS)
                # the helper first: the kernels that call it resolve it from this module's
                # globals when they are compiled
                globals()["_closest_on_triangle"] = jit(_closest_on_triangle)
                globals()["_add_column"] = jit(_add_column)
                globals()["_pair_crosses"] = jit(_pair_crosses)
                globals()["_cell_table"] = jit(_cell_table)
                globals()["_cell_run"] = jit(_cell_run)
                globals()["_one_side"] = jit(_one_side)
                _compiled_kernels = SimpleNamespace(closest_faces=jit(_closest_faces), face_bounds=jit(_face_bounds),
                                                    winding_numbers=jit(_winding_numbers),
                                                    pose_jacobian_into=jit(_pose_jacobian_into),
                                                    pair_rows=jit(_pair_rows), membrane=jit(_membrane),
                                                    vertex_normals=jit(_vertex_normals),
                                                    strain_limit_pass=jit(_strain_limit_pass),
                                                    faces_cross=jit(_faces_cross),
                                                    contact_project=jit(_contact_project),
                                                    columns_product=jit(_columns_product),
                                                    push_vertices=jit(_push_vertices),
                                                    clamp_steps=jit(_clamp_steps), max_move=jit(_max_move),
                                                    close_pairs=jit(_close_pairs),
                                                    crossing_pairs=jit(_crossing_pairs),
                                                    cell_entries=jit(_cell_entries),
                                                    face_boxes=jit(_face_boxes))
    return _compiled_kernels


def closest_faces(p, V, F, nn, vert_faces, c, n, r):
    """Compiled :func:`_closest_faces`."""
    return _compiled().closest_faces(p, V, F, nn, vert_faces, c, n, r)


def face_bounds(V, F):
    """Compiled :func:`_face_bounds`."""
    return _compiled().face_bounds(V, F)


def winding_numbers(p, V, F):
    """Compiled :func:`_winding_numbers`."""
    return _compiled().winding_numbers(p, V, F)


def pose_jacobian_into(rest, G, W, sel, q, J):
    """Compiled :func:`_pose_jacobian_into`."""
    return _compiled().pose_jacobian_into(rest, G, W, sel, q, J)


def pair_rows(J, vi, nn):
    """Compiled :func:`_pair_rows`."""
    return _compiled().pair_rows(J, vi, nn)


def membrane(x, faces, C, w, rhs):
    """Compiled :func:`_membrane`."""
    return _compiled().membrane(x, faces, C, w, rhs)


def vertex_normals(x, faces, out):
    """Compiled :func:`_vertex_normals`."""
    return _compiled().vertex_normals(x, faces, out)


def strain_limit_pass(x, edges, edge_max, inv_mass, acc, count):
    """Compiled :func:`_strain_limit_pass`."""
    return _compiled().strain_limit_pass(x, edges, edge_max, inv_mass, acc, count)


def faces_cross(V, F, pairs, c, r, hit):
    """Compiled :func:`_faces_cross`."""
    return _compiled().faces_cross(V, F, pairs, c, r, hit)


def contact_project(x, q, n, clearance, x_prev, slide, friction, out, contact):
    """Compiled :func:`_contact_project`."""
    return _compiled().contact_project(x, q, n, clearance, x_prev, slide, friction, out, contact)


def close_pairs(x, radius, exclude_indptr, exclude_indices):
    """The pairs (P, 2) int64 (i < j, sorted) of rows of x (N, 3) float64 at most ``radius``
    apart, as ``scipy.spatial.cKDTree(x).query_pairs(radius)``, without those that the sparsity
    pattern (``exclude_indptr`` (N + 1,), ``exclude_indices``: a CSR matrix's, each row's
    indices sorted) holds: a uniform grid of cells ``radius`` wide, each occupied cell's vertices
    against its own and its 13 neighbours of larger key (:func:`_close_pairs`, compiled)."""
    x = np.ascontiguousarray(x, np.float64)
    if not len(x):
        return np.zeros((0, 2), np.int64)
    cell = np.floor((x - x.min(axis=0)) / radius).astype(np.int64)
    dims = cell.max(axis=0) + 1
    key = (cell[:, 0] * dims[1] + cell[:, 1]) * dims[2] + cell[:, 2]
    order = np.argsort(key, kind="stable")
    fn = _compiled().close_pairs
    args = (x, dims, key[order], order, float(radius), np.asarray(exclude_indptr, np.int64),
            np.asarray(exclude_indices, np.int64))
    out = np.empty((len(x), 2), np.int64)
    count = fn(*args, out)
    if count > len(out):
        out = np.empty((count, 2), np.int64)
        fn(*args, out)
    out = out[:count]
    return out[np.argsort(out[:, 0] * len(x) + out[:, 1], kind="stable")]


def crossing_pairs(V, F, among=None):
    """The intersecting face pairs (K, 2) int64 (a < b, sorted) of one mesh (V (N, 3) float64,
    F (M, 3) int64) that ``geometry.intersecting_face_pairs`` finds, with ``among`` (S,) only
    those with one of those faces. No list of candidate pairs is made (a 44k-vertex garment has
    5.5 million face centres within twice the largest face's radius of each other, a few hundred
    of its faces cross): the faces (those of ``among``) are entered in a uniform grid by their
    bounding boxes (:func:`_face_boxes`; cells as wide as the median face's box, or 1/8 of the
    largest), every face then meets those sharing a cell with its box (:func:`_crossing_pairs`,
    each pair once, in the first cell of the boxes' overlap), and the pairs whose boxes overlap
    are tested (:func:`_pair_crosses`)."""
    V = np.ascontiguousarray(V, np.float64)
    F = np.ascontiguousarray(F, np.int64)
    m = len(F)
    if not m:
        return np.zeros((0, 2), np.int64)
    k = _compiled()
    c, lo, hi = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
    r = np.empty(m)
    k.face_boxes(V, F, c, r, lo, hi)
    extent = (hi - lo).max(axis=1)
    width = max(float(np.median(extent)), float(extent.max()) / 8.0)
    if not width > 0.0:
        width = 1.0  # every face a point: none crosses, any cell width finds that
    origin = lo.min(axis=0)
    cl = np.floor((lo - origin) / width).astype(np.int64)
    ch = np.floor((hi - origin) / width).astype(np.int64)
    dims = ch.max(axis=0) + 1
    selected = np.ones(m, bool) if among is None else np.zeros(m, bool)
    if among is not None:
        selected[np.asarray(among, np.int64)] = True
    sel = np.flatnonzero(selected)
    span = ch[sel] - cl[sel] + 1
    keys = np.empty(int(np.prod(span, axis=1).sum()), np.int64)
    owner = np.empty(len(keys), np.int64)
    k.cell_entries(cl, ch, dims, sel, keys, owner)
    order = np.argsort(keys, kind="stable")
    out = k.crossing_pairs(V, F, c, r, lo, hi, cl, ch, dims, keys[order], owner[order], selected)
    return out[np.argsort(out[:, 0] * m + out[:, 1], kind="stable")]


def columns_product(indptr, indices, data, cols, X, out):
    """Compiled :func:`_columns_product`."""
    return _compiled().columns_product(indptr, indices, data, cols, X, out)


def _closest_on_triangle(px, py, pz, V, F, f):
    """Ericson's closest point on triangle f (Real-Time Collision Detection 5.1.5), as
    ``geometry.closest_point_on_triangles`` evaluates it (its region order, its arithmetic)."""
    i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
    a0, a1, a2 = V[i0, 0], V[i0, 1], V[i0, 2]
    b0, b1, b2 = V[i1, 0], V[i1, 1], V[i1, 2]
    c0, c1, c2 = V[i2, 0], V[i2, 1], V[i2, 2]
    ab0, ab1, ab2 = b0 - a0, b1 - a1, b2 - a2
    ac0, ac1, ac2 = c0 - a0, c1 - a1, c2 - a2
    ap0, ap1, ap2 = px - a0, py - a1, pz - a2
    d1 = ab0 * ap0 + ab1 * ap1 + ab2 * ap2
    d2 = ac0 * ap0 + ac1 * ap1 + ac2 * ap2
    bp0, bp1, bp2 = px - b0, py - b1, pz - b2
    d3 = ab0 * bp0 + ab1 * bp1 + ab2 * bp2
    d4 = ac0 * bp0 + ac1 * bp1 + ac2 * bp2
    cp0, cp1, cp2 = px - c0, py - c1, pz - c2
    d5 = ab0 * cp0 + ab1 * cp1 + ab2 * cp2
    d6 = ac0 * cp0 + ac1 * cp1 + ac2 * cp2
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    if d1 <= 0 and d2 <= 0:  # vertex a
        return a0 + ab0 * 0.0 + ac0 * 0.0, a1 + ab1 * 0.0 + ac1 * 0.0, a2 + ab2 * 0.0 + ac2 * 0.0
    if d3 >= 0 and d4 <= d3:  # vertex b
        return b0, b1, b2
    if d6 >= 0 and d5 <= d6:  # vertex c
        return c0, c1, c2
    if vc <= 0 and d1 >= 0 and d3 <= 0:  # edge ab
        v = d1 / (d1 - d3)
        return a0 + ab0 * v + ac0 * 0.0, a1 + ab1 * v + ac1 * 0.0, a2 + ab2 * v + ac2 * 0.0
    if vb <= 0 and d2 >= 0 and d6 <= 0:  # edge ac
        w = d2 / (d2 - d6)
        return a0 + ab0 * 0.0 + ac0 * w, a1 + ab1 * 0.0 + ac1 * w, a2 + ab2 * 0.0 + ac2 * w
    if va <= 0 and (d4 - d3) >= 0 and (d5 - d6) >= 0:  # edge bc
        t = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return b0 + (c0 - b0) * t, b1 + (c1 - b1) * t, b2 + (c2 - b2) * t
    den = 1.0 / (va + vb + vc)  # inside
    v = vb * den
    w = vc * den
    return a0 + ab0 * v + ac0 * w, a1 + ab1 * v + ac1 * w, a2 + ab2 * v + ac2 * w


def _closest_faces(p, V, F, nn, vert_faces, c, n, r):
    """The nearest of each point's candidate faces and the closest point on it: points p (P, 3)
    float64, mesh V (V, 3) float64 and F (F, 3) int64; the candidates are the faces around each
    point's nearest vertices nn (P, k) int64, ``vert_faces`` (V, valence) int64 (-1 padded), in
    the order of ``vert_faces[nn].reshape(P, -1)``, whose first appearance wins ties (a face
    appears around up to 3 of the vertices); the faces' bounding disks
    (``geometry.face_bounds``: c (F, 3), n (F, 3), r (F,)). A candidate whose distance lower
    bound (``geometry.face_distance_bounds``) exceeds the best distance so far cannot win and
    is skipped. Returns (face (P,) int64, closest points (P, 3) float64); a row with no
    candidate gets face 0 (as the numpy path's padding)."""
    P, k = nn.shape
    C = vert_faces.shape[1]
    face = np.empty(P, np.int64)
    q = np.empty((P, 3))
    for i in range(P):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        best = np.inf
        bf = -1
        bx = by = bz = 0.0
        for m in range(k * C):
            f = vert_faces[nn[i, m // C], m % C]
            if f < 0:
                continue
            ux, uy, uz = px - c[f, 0], py - c[f, 1], pz - c[f, 2]
            pd = ux * n[f, 0] + uy * n[f, 1] + uz * n[f, 2]
            pd2 = pd * pd
            ip = ux * ux + uy * uy + uz * uz - pd2
            e = (np.sqrt(ip) if ip > 0.0 else 0.0) - r[f]
            lb = pd2 + (e * e if e > 0.0 else 0.0)
            if lb > best * (1 + PRUNE_SLACK) + PRUNE_SLACK_SQ:
                continue
            x, y, z = _closest_on_triangle(px, py, pz, V, F, f)
            dx, dy, dz = x - px, y - py, z - pz
            d = dx * dx + dy * dy + dz * dz
            if d < best:  # strict: of equally near faces, the first in raw wins
                best, bf, bx, by, bz = d, f, x, y, z
        if bf < 0:
            bf = 0
            bx, by, bz = _closest_on_triangle(px, py, pz, V, F, 0)
        face[i] = bf
        q[i, 0], q[i, 1], q[i, 2] = bx, by, bz
    return face, q


def _face_bounds(V, F):
    """Each triangle's bounding disk, as ``geometry.face_bounds``: centroids (F, 3), unit
    normals (F, 3) (0 when degenerate), radii (F,) (the largest vertex distance from the
    centroid). Only ever a pruning bound (``closest_faces`` skips a face whose bound exceeds
    the best distance, with a relative slack of 1e-9): rounding differences from the numpy
    path cannot change which face wins."""
    nf = F.shape[0]
    c = np.empty((nf, 3))
    n = np.empty((nf, 3))
    r = np.empty(nf)
    for f in range(nf):
        i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
        rr = 0.0
        for k in range(3):
            c[f, k] = (V[i0, k] + V[i1, k] + V[i2, k]) / 3.0
        for i in (i0, i1, i2):
            dx, dy, dz = V[i, 0] - c[f, 0], V[i, 1] - c[f, 1], V[i, 2] - c[f, 2]
            rr = max(rr, dx * dx + dy * dy + dz * dz)
        r[f] = np.sqrt(rr)
        e0, e1, e2 = V[i1, 0] - V[i0, 0], V[i1, 1] - V[i0, 1], V[i1, 2] - V[i0, 2]
        g0, g1, g2 = V[i2, 0] - V[i0, 0], V[i2, 1] - V[i0, 1], V[i2, 2] - V[i0, 2]
        x, y, z = e1 * g2 - e2 * g1, e2 * g0 - e0 * g2, e0 * g1 - e1 * g0
        ln = max(np.sqrt(x * x + y * y + z * z), 1e-300)
        n[f, 0], n[f, 1], n[f, 2] = x / ln, y / ln, z / ln
    return c, n, r


def _winding_numbers(p, V, F):
    """Generalised winding numbers (P,) of points p (P, 3) float64 with respect to the closed
    triangle mesh V (V, 3) float64, F (F, 3) int64: the solid angles of Van Oosterom and
    Strackee summed over the faces, / 4 pi, as ``geometry.winding_numbers`` (its per-face
    terms; the sum over faces in order, where numpy's is pairwise: equal to ~1e-15)."""
    P = p.shape[0]
    out = np.empty(P)
    for i in range(P):
        px, py, pz = p[i, 0], p[i, 1], p[i, 2]
        total = 0.0
        for f in range(F.shape[0]):
            i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
            a0, a1, a2 = V[i0, 0] - px, V[i0, 1] - py, V[i0, 2] - pz
            b0, b1, b2 = V[i1, 0] - px, V[i1, 1] - py, V[i1, 2] - pz
            c0, c1, c2 = V[i2, 0] - px, V[i2, 1] - py, V[i2, 2] - pz
            la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
            lb = np.sqrt(b0 * b0 + b1 * b1 + b2 * b2)
            lc = np.sqrt(c0 * c0 + c1 * c1 + c2 * c2)
            num = a0 * (b1 * c2 - b2 * c1) + a1 * (b2 * c0 - b0 * c2) + a2 * (b0 * c1 - b1 * c0)
            den = (la * lb * lc + (a0 * b0 + a1 * b1 + a2 * b2) * lc + (b0 * c0 + b1 * c1 + b2 * c2) * la
                   + (c0 * a0 + c1 * a1 + c2 * a2) * lb)
            total += np.arctan2(num, den)
        out[i] = total / (2 * np.pi)
    return out


def _pose_jacobian_into(rest, G, W, sel, q, J):
    """The pose columns of ``fitting._pose_jacobian``, written into J (m, 3, >= 3 + 3 nb)
    float64: columns 0-2 the translation (the identity), then per selected bone b the
    cross-product matrix -[arm_b]x of arm_b(i) = S_b(i) - W_b(i) q_b, with S_b(i) = sum over
    the joints j of b's subtree of w_ij G_j(x_i) and W_b(i) the sum of those w_ij. rest (m, 3)
    the rest vertices x_i, G (J, 4, 4) the global transforms, W (m, J) the skin weights,
    sel (nb, J) 1 where joint j is in selected bone b's subtree, q (nb, 3) the selected bones'
    posed joints. Each vertex visits only its non-zero weights; the other columns of J are
    left as they are."""
    m = rest.shape[0]
    nj = W.shape[1]
    nb = sel.shape[0]
    S = np.empty((nb, 3))
    sw = np.empty(nb)
    for i in range(m):
        x0, x1, x2 = rest[i, 0], rest[i, 1], rest[i, 2]
        S[:] = 0.0
        sw[:] = 0.0
        for j in range(nj):
            w = W[i, j]
            if w == 0.0:
                continue
            g0 = x0 * G[j, 0, 0] + x1 * G[j, 0, 1] + x2 * G[j, 0, 2] + G[j, 0, 3]
            g1 = x0 * G[j, 1, 0] + x1 * G[j, 1, 1] + x2 * G[j, 1, 2] + G[j, 1, 3]
            g2 = x0 * G[j, 2, 0] + x1 * G[j, 2, 1] + x2 * G[j, 2, 2] + G[j, 2, 3]
            for b in range(nb):
                if sel[b, j] != 0.0:
                    S[b, 0] += w * g0
                    S[b, 1] += w * g1
                    S[b, 2] += w * g2
                    sw[b] += w
        for a in range(3):
            for c in range(3):
                J[i, a, c] = 1.0 if a == c else 0.0
        for b in range(nb):
            a0 = S[b, 0] - sw[b] * q[b, 0]
            a1 = S[b, 1] - sw[b] * q[b, 1]
            a2 = S[b, 2] - sw[b] * q[b, 2]
            c = 3 + 3 * b
            J[i, 0, c], J[i, 0, c + 1], J[i, 0, c + 2] = 0.0, a2, -a1
            J[i, 1, c], J[i, 1, c + 1], J[i, 1, c + 2] = -a2, 0.0, a0
            J[i, 2, c], J[i, 2, c + 1], J[i, 2, c + 2] = a1, -a0, 0.0


def _pair_rows(J, vi, nn):
    """The point-to-plane rows n_k^T J_{vi_k} (k, P) of ``nonrigid.point_to_plane_normal_equations``:
    J (m, 3, P) float64, vi (k,) int64, nn (k, 3) float64; no gathered copy of J."""
    k = vi.shape[0]
    P = J.shape[2]
    rows = np.empty((k, P))
    for t in range(k):
        v = vi[t]
        n0, n1, n2 = nn[t, 0], nn[t, 1], nn[t, 2]
        for c in range(P):
            rows[t, c] = n0 * J[v, 0, c] + n1 * J[v, 1, c] + n2 * J[v, 2, c]
    return rows


def _membrane(x, faces, C, w, rhs):
    """The drape's membrane projection (``drape.solver.Draper._local``, PD Eq. 13): for each
    triangle t its deformation gradient F_t = sum_k x[faces[t, k]] C[t, k] (3 x 2), the closest
    rotation R_t = F_t (F_t^T F_t)^(-1/2) (the closed form of ``drape.solver._polar``), R_t's
    columns added into rhs (N, 3) float64 as G^T (w R) (rhs[faces[t, k]] += w_t sum_c C[t, k, c]
    R_t[:, c]). x (N, 3) float64, faces (T, 3) int64, C (T, 3, 2) float64, w (T,) float64.
    Returns sum_t w_t / 2 ||F_t - R_t||^2 (J)."""
    T = faces.shape[0]
    e = 0.0
    for t in range(T):
        a0 = a1 = a2 = b0 = b1 = b2 = 0.0
        for k in range(3):
            v = faces[t, k]
            ck0, ck1 = C[t, k, 0], C[t, k, 1]
            a0 += x[v, 0] * ck0
            a1 += x[v, 1] * ck0
            a2 += x[v, 2] * ck0
            b0 += x[v, 0] * ck1
            b1 += x[v, 1] * ck1
            b2 += x[v, 2] * ck1
        c00 = a0 * a0 + a1 * a1 + a2 * a2
        c01 = a0 * b0 + a1 * b1 + a2 * b2
        c11 = b0 * b0 + b1 * b1 + b2 * b2
        det = max(c00 * c11 - c01 * c01, 0.0)
        s = np.sqrt(det)
        tt = np.sqrt(max(c00 + c11 + 2 * s, 1e-300))
        m00, m01, m11 = c00 + s, c01, c11 + s
        inv_det = tt / max(m00 * m11 - m01 * m01, 1e-300)
        i00, i01, i11 = m11 * inv_det, -m01 * inv_det, m00 * inv_det
        r0, r1, r2 = a0 * i00 + b0 * i01, a1 * i00 + b1 * i01, a2 * i00 + b2 * i01
        q0, q1, q2 = a0 * i01 + b0 * i11, a1 * i01 + b1 * i11, a2 * i01 + b2 * i11
        wt = w[t]
        e += 0.5 * wt * ((a0 - r0) ** 2 + (a1 - r1) ** 2 + (a2 - r2) ** 2
                         + (b0 - q0) ** 2 + (b1 - q1) ** 2 + (b2 - q2) ** 2)
        for k in range(3):
            v = faces[t, k]
            ck0, ck1 = wt * C[t, k, 0], wt * C[t, k, 1]
            rhs[v, 0] += ck0 * r0 + ck1 * q0
            rhs[v, 1] += ck0 * r1 + ck1 * q1
            rhs[v, 2] += ck0 * r2 + ck1 * q2
    return e


def _vertex_normals(x, faces, out):
    """Area-weighted unit vertex normals into out (N, 3) float64, as ``drape.solver._normals``:
    x (N, 3) float64, faces (T, 3) int64."""
    out[:] = 0.0
    for t in range(faces.shape[0]):
        i, j, k = faces[t, 0], faces[t, 1], faces[t, 2]
        u0, u1, u2 = x[j, 0] - x[i, 0], x[j, 1] - x[i, 1], x[j, 2] - x[i, 2]
        v0, v1, v2 = x[k, 0] - x[i, 0], x[k, 1] - x[i, 1], x[k, 2] - x[i, 2]
        n0, n1, n2 = u1 * v2 - u2 * v1, u2 * v0 - u0 * v2, u0 * v1 - u1 * v0
        for v in (i, j, k):
            out[v, 0] += n0
            out[v, 1] += n1
            out[v, 2] += n2
    for v in range(out.shape[0]):
        ln = max(np.sqrt(out[v, 0] ** 2 + out[v, 1] ** 2 + out[v, 2] ** 2), 1e-30)
        out[v, 0] /= ln
        out[v, 1] /= ln
        out[v, 2] /= ln


def _strain_limit_pass(x, edges, edge_max, inv_mass, acc, count):
    """One Jacobi pass of the drape's strain limit (``drape.solver.Draper._strain_limit``):
    every edge longer than edge_max (E,) shortened to it, the correction shared by the ends'
    inverse masses inv_mass (N,), each vertex moved by the mean of its corrections. x (N, 3)
    float64 in place, edges (E, 2) int64; acc (N, 3) and count (N,) float64 scratch. Returns
    the number of over-stretched edges."""
    acc[:] = 0.0
    count[:] = 0.0
    n_over = 0
    for k in range(edges.shape[0]):
        a, b = edges[k, 0], edges[k, 1]
        d0, d1, d2 = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
        ln = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if ln <= edge_max[k]:
            continue
        n_over += 1
        wa, wb = inv_mass[a], inv_mass[b]
        wsum = max(wa + wb, 1e-12)
        f = (ln - edge_max[k]) / ln
        sa, sb = wa / wsum * f, wb / wsum * f
        acc[a, 0] += sa * d0
        acc[a, 1] += sa * d1
        acc[a, 2] += sa * d2
        acc[b, 0] -= sb * d0
        acc[b, 1] -= sb * d1
        acc[b, 2] -= sb * d2
        count[a] += 1.0
        count[b] += 1.0
    if n_over:
        for v in range(x.shape[0]):
            if count[v] > 0:
                x[v, 0] += acc[v, 0] / count[v]
                x[v, 1] += acc[v, 1] / count[v]
                x[v, 2] += acc[v, 2] / count[v]
    return n_over


def _contact_project(x, q, n, clearance, x_prev, slide, friction, out, contact):
    """The drape's body contact (``drape.solver._Body.project``): each vertex i of x (N, 3) float64
    closer than ``clearance[i]`` (N,) to its tangent plane (closest body point q (N, 3), unit normal n
    (N, 3)) moved out along n; with ``friction``, its tangential move since x_prev (N, 3) cancelled
    up to slide (N,) times that correction. out (N, 3) float64 and contact (N,) bool out.
    Returns the number of vertices in contact."""
    hits = 0
    for i in range(x.shape[0]):
        n0, n1, n2 = n[i, 0], n[i, 1], n[i, 2]
        x0, x1, x2 = x[i, 0], x[i, 1], x[i, 2]
        depth = clearance[i] - ((x0 - q[i, 0]) * n0 + (x1 - q[i, 1]) * n1 + (x2 - q[i, 2]) * n2)
        if not depth > 0:
            contact[i] = False
            out[i, 0], out[i, 1], out[i, 2] = x0, x1, x2
            continue
        contact[i] = True
        hits += 1
        x0 += depth * n0
        x1 += depth * n1
        x2 += depth * n2
        if friction:
            dx0, dx1, dx2 = x0 - x_prev[i, 0], x1 - x_prev[i, 1], x2 - x_prev[i, 2]
            dn = dx0 * n0 + dx1 * n1 + dx2 * n2
            t0, t1, t2 = dx0 - dn * n0, dx1 - dn * n1, dx2 - dn * n2
            lt = np.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
            hold = slide[i] * depth
            scale = 1.0 if lt <= hold else hold / max(lt, 1e-30)
            x0 -= scale * t0
            x1 -= scale * t1
            x2 -= scale * t2
        out[i, 0], out[i, 1], out[i, 2] = x0, x1, x2
    return hits


def _faces_cross(V, F, pairs, c, r, hit):
    """Which candidate face pairs (K, 2) int64 of one mesh (V (N, 3) float64, F (M, 3) int64)
    intersect (``geometry.intersecting_face_pairs``): bounding spheres (centres c (M, 3), radii
    r (M,)) overlapping, no shared vertex, and an edge of one face crossing the other
    (:func:`_pair_crosses`). hit (K,) bool out."""
    for k in range(pairs.shape[0]):
        hit[k] = _pair_crosses(V, F, c, r, pairs[k, 0], pairs[k, 1])


def _pair_crosses(V, F, c, r, a, b):
    """Whether faces a and b of one mesh intersect: their bounding spheres (centres c (M, 3),
    radii r (M,)) overlap, they share no vertex, and an edge of one crosses the other
    (Moller-Trumbore, the same float operations as the numpy reference)."""
    dc0, dc1, dc2 = c[a, 0] - c[b, 0], c[a, 1] - c[b, 1], c[a, 2] - c[b, 2]
    if np.sqrt(dc0 * dc0 + dc1 * dc1 + dc2 * dc2) > r[a] + r[b]:
        return False
    for i in range(3):
        for j in range(3):
            if F[a, i] == F[b, j]:
                return False
    if _one_side(V, F, a, b, r[b]) or _one_side(V, F, b, a, r[a]):
        return False
    for s in range(2):
        P, Q = (a, b) if s == 0 else (b, a)
        t0, t1, t2 = F[Q, 0], F[Q, 1], F[Q, 2]
        e10, e11, e12 = V[t1, 0] - V[t0, 0], V[t1, 1] - V[t0, 1], V[t1, 2] - V[t0, 2]
        e20, e21, e22 = V[t2, 0] - V[t0, 0], V[t2, 1] - V[t0, 1], V[t2, 2] - V[t0, 2]
        for m in range(3):
            i, j = F[P, m], F[P, (m + 1) % 3]
            o0, o1, o2 = V[i, 0], V[i, 1], V[i, 2]
            d0, d1, d2 = V[j, 0] - o0, V[j, 1] - o1, V[j, 2] - o2
            h0, h1, h2 = d1 * e22 - d2 * e21, d2 * e20 - d0 * e22, d0 * e21 - d1 * e20
            det = e10 * h0 + e11 * h1 + e12 * h2
            if abs(det) <= 1e-14:
                continue
            inv = 1.0 / det
            s0, s1, s2 = o0 - V[t0, 0], o1 - V[t0, 1], o2 - V[t0, 2]
            u = (s0 * h0 + s1 * h1 + s2 * h2) * inv
            q0, q1, q2 = s1 * e12 - s2 * e11, s2 * e10 - s0 * e12, s0 * e11 - s1 * e10
            v = (d0 * q0 + d1 * q1 + d2 * q2) * inv
            tt = (e20 * q0 + e21 * q1 + e22 * q2) * inv
            if u >= 0 and v >= 0 and u + v <= 1 and tt >= 0 and tt <= 1:
                return True
    return False


def _face_boxes(V, F, c, r, lo, hi):
    """Each face's centre c (M, 3) (its vertices' mean), bounding-sphere radius r (M,) (the
    centre's distance to its farthest vertex) and bounding box lo, hi (M, 3), written in place:
    what ``geometry.intersecting_face_pairs`` computes with numpy."""
    for f in range(F.shape[0]):
        i0, i1, i2 = F[f, 0], F[f, 1], F[f, 2]
        for d in range(3):
            a, b, e = V[i0, d], V[i1, d], V[i2, d]
            c[f, d] = (a + b + e) / 3.0
            lo[f, d] = min(a, min(b, e))
            hi[f, d] = max(a, max(b, e))
        best = 0.0
        for i in (i0, i1, i2):
            d0, d1, d2 = V[i, 0] - c[f, 0], V[i, 1] - c[f, 1], V[i, 2] - c[f, 2]
            best = max(best, np.sqrt(d0 * d0 + d1 * d1 + d2 * d2))
        r[f] = best


def _cell_entries(cl, ch, dims, sel, keys, owner):
    """The grid cells of the faces ``sel`` (S,): each face's cells from cl to ch (M, 3) (its
    bounding box's first and last cell per axis; dims (3,) cells per axis) written as cell keys
    into ``keys`` and the face into ``owner`` (both (sum of the boxes' cell counts,))."""
    t = 0
    for s in range(sel.shape[0]):
        a = sel[s]
        for x in range(cl[a, 0], ch[a, 0] + 1):
            for y in range(cl[a, 1], ch[a, 1] + 1):
                for z in range(cl[a, 2], ch[a, 2] + 1):
                    keys[t] = (x * dims[1] + y) * dims[2] + z
                    owner[t] = a
                    t += 1


SIDE_MARGIN = 1e-9  # _one_side: a face clear of a plane by more than this x its radius (no rounding can cross it)


def _one_side(V, F, p, q, rq):
    """Whether the vertices of face q (radius rq) all lie on one side of face p's plane, farther
    from it than ``SIDE_MARGIN`` x rq: then no edge of either face crosses the other and the
    Moller-Trumbore tests (which would say so after rounding) are skipped."""
    i0, i1, i2 = F[p, 0], F[p, 1], F[p, 2]
    e10, e11, e12 = V[i1, 0] - V[i0, 0], V[i1, 1] - V[i0, 1], V[i1, 2] - V[i0, 2]
    e20, e21, e22 = V[i2, 0] - V[i0, 0], V[i2, 1] - V[i0, 1], V[i2, 2] - V[i0, 2]
    n0, n1, n2 = e11 * e22 - e12 * e21, e12 * e20 - e10 * e22, e10 * e21 - e11 * e20
    tol = SIDE_MARGIN * rq * np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    above, below = 0, 0
    for m in range(3):
        j = F[q, m]
        d = n0 * (V[j, 0] - V[i0, 0]) + n1 * (V[j, 1] - V[i0, 1]) + n2 * (V[j, 2] - V[i0, 2])
        if d > tol:
            above += 1
        elif d < -tol:
            below += 1
    return above == 3 or below == 3


def _crossing_pairs(V, F, c, r, lo, hi, cl, ch, dims, skeys, sowner, selected):
    """:func:`crossing_pairs`' loop: returns the pairs (P, 2) int64. lo, hi (M, 3) the faces' bounding
    boxes, cl, ch (M, 3) their first and last cells; skeys, sowner the grid's entries
    (:func:`_cell_entries`) sorted by key; selected (M,) bool the faces entered. Every face
    against the entered faces in the cells of its box: a pair is taken in the first cell of the
    two boxes' overlap only, a pair of two entered faces from its larger face only, and tested
    when the boxes overlap (:func:`_pair_crosses`)."""
    table, mask = _cell_table(skeys)
    out = np.empty((64, 2), np.int64)
    count = 0
    for b in range(F.shape[0]):
        for x in range(cl[b, 0], ch[b, 0] + 1):
            for y in range(cl[b, 1], ch[b, 1] + 1):
                for z in range(cl[b, 2], ch[b, 2] + 1):
                    e0, e1 = _cell_run(table, mask, skeys, (x * dims[1] + y) * dims[2] + z)
                    for e in range(e0, e1):
                        a = sowner[e]
                        if a == b or (selected[b] and b < a):
                            continue
                        if (max(cl[a, 0], cl[b, 0]) != x or max(cl[a, 1], cl[b, 1]) != y
                                or max(cl[a, 2], cl[b, 2]) != z):
                            continue  # met in another cell too: counted there
                        if (lo[a, 0] > hi[b, 0] or lo[b, 0] > hi[a, 0] or lo[a, 1] > hi[b, 1]
                                or lo[b, 1] > hi[a, 1] or lo[a, 2] > hi[b, 2] or lo[b, 2] > hi[a, 2]):
                            continue
                        if _pair_crosses(V, F, c, r, a, b):
                            if count == out.shape[0]:
                                grown = np.empty((2 * count, 2), np.int64)
                                grown[:count] = out
                                out = grown
                            out[count, 0], out[count, 1] = min(a, b), max(a, b)
                            count += 1
    return out[:count]


def _cell_table(skeys):
    """An open-addressing hash table (linear probing, at least twice as many slots as keys) of
    the runs of equal keys in ``skeys`` (N,) sorted: (table (T,) int64, slot -> the first index of
    its key's run, -1 where empty; mask T - 1)."""
    n = skeys.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    mask = size - 1
    table = np.full(size, -1, np.int64)
    for s in range(n):
        if s > 0 and skeys[s] == skeys[s - 1]:
            continue
        h = (skeys[s] * 2654435761) & mask
        while table[h] >= 0:
            h = (h + 1) & mask
        table[h] = s
    return table, mask


def _cell_run(table, mask, skeys, k):
    """The run (lo, hi) of key k in ``skeys`` through :func:`_cell_table`'s table; (0, 0) if absent."""
    n = skeys.shape[0]
    h = (k * 2654435761) & mask
    while table[h] >= 0:
        lo = table[h]
        if skeys[lo] == k:
            hi = lo + 1
            while hi < n and skeys[hi] == k:
                hi += 1
            return lo, hi
        h = (h + 1) & mask
    return 0, 0


def push_vertices(G, body, normals, nb, clearance, a, q, qn, most, indptr, indices, data, disp):
    """Compiled :func:`_push_vertices`."""
    return _compiled().push_vertices(G, body, normals, nb, clearance, a, q, qn, most, indptr, indices, data, disp)


def clamp_steps(g, x, max_step):
    """Compiled :func:`_clamp_steps`."""
    return _compiled().clamp_steps(g, x, max_step)


def max_move(g, x):
    """Compiled :func:`_max_move`."""
    return _compiled().max_move(g, x)


def warm() -> None:
    """Compile (or load from the on-disk cache) every kernel for the argument types the
    service passes: the Docker build runs it, so that no process of the image compiles them
    (a process loads them on first use)."""
    if not AVAILABLE:
        return
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    F = np.array([[0, 1, 2]], np.int64)
    c = V.mean(axis=0, keepdims=True)
    closest_faces(np.zeros((1, 3)), V, F, np.zeros((1, 1), np.int64), np.zeros((3, 1), np.int64), c,
                  np.array([[0.0, 0.0, 1.0]]), np.ones(1))
    winding_numbers(np.zeros((1, 3)), V, F)
    face_bounds(V, F)
    J = np.zeros((1, 3, 6))
    pose_jacobian_into(np.zeros((1, 3)), np.tile(np.eye(4), (2, 1, 1)), np.ones((1, 2)), np.ones((1, 2)),
                       np.zeros((1, 3)), J)
    pair_rows(J, np.zeros(1, np.int64), np.ones((1, 3)))
    C = np.zeros((1, 3, 2))
    membrane(V, F, C, np.ones(1), np.zeros((3, 3)))
    vertex_normals(V, F, np.zeros((3, 3)))
    e = np.array([[0, 1]], np.int64)
    strain_limit_pass(V.copy(), e, np.ones(1), np.ones(3), np.zeros((3, 3)), np.zeros(3))
    faces_cross(V, F, np.zeros((1, 2), np.int64), c, np.ones(1), np.zeros(1, bool))
    V32, z1 = V.astype(np.float32), np.zeros(1, np.float32)
    S = (np.arange(4, dtype=np.int32), np.arange(3, dtype=np.int32), np.ones(3, np.float32))
    columns_product(*S, np.zeros(1, np.int64), np.zeros((1, 3), np.float32), np.zeros((3, 3), np.float32))
    clamp_steps(V.copy(), V, 0.01)
    max_move(V, V)
    close_pairs(V, 1.0, np.zeros(4, np.int64), np.zeros(0, np.int64))
    crossing_pairs(V, F)
    crossing_pairs(V, F, among=np.zeros(1, np.int64))
    push_vertices(V32, V32, V32, np.zeros(3, np.int32), np.float32(0.0), np.zeros(1, np.int64), V32[:1], V32[:1], z1,
                  *S, np.zeros((3, 3), np.float32))


def _columns_product(indptr, indices, data, cols, X, out):
    """out (M, 3) += S[:, cols] @ X for a CSC matrix S (M, M) (indptr, indices, data) and X
    (len(cols), 3): what scipy's ``S[:, cols] @ X`` computes (the columns in the order of cols,
    each column's entries in stored order: the same sums, bit for bit), without building the
    column slice (the try-on's push-out diffuses the pushes of the vertices it moved)."""
    for c in range(cols.shape[0]):
        _add_column(indptr, indices, data, cols[c], X[c, 0], X[c, 1], X[c, 2], out)


def _add_column(indptr, indices, data, j, x0, x1, x2, out):
    """out (M, 3) += S[:, j] * (x0, x1, x2) for a CSC matrix S (indptr, indices, data), its
    entries in stored order."""
    for k in range(indptr[j], indptr[j + 1]):
        i = indices[k]
        v = data[k]
        out[i, 0] += v * x0
        out[i, 1] += v * x1
        out[i, 2] += v * x2


def _push_vertices(G, body, normals, nb, clearance, a, q, qn, most, indptr, indices, data, disp):
    """The vertex pass of ``garment.push_out`` in one loop, with what numpy computes there, in
    its order and float32 (the same results bit for bit; the tests compare them): each garment
    vertex of G (M, 3) float32 is ``clearance`` (float32) out of the tangent plane of its body
    vertex nb (M,) of body / normals (Vb, 3) float32, or for the anchors a (R,) of the plane of
    their skin point q (R, 3) / unit normal qn (R, 3) with at most the clearance most (R,); the
    vertices short of it ("bad") are pushed along their normal, the pushes diffused through
    their columns of the smoother S (CSC: indptr, indices, data float32, M x M) into disp
    (M, 3) float32 (zeros in), and each bad vertex's own push topped up to its full depth.
    Returns the number of bad vertices."""
    M = G.shape[0]
    depth = np.empty(M, np.float32)
    N = np.empty((M, 3), np.float32)
    for i in range(M):
        j = nb[i]
        n0, n1, n2 = normals[j, 0], normals[j, 1], normals[j, 2]
        N[i, 0], N[i, 1], N[i, 2] = n0, n1, n2
        depth[i] = clearance - ((G[i, 0] - body[j, 0]) * n0 + (G[i, 1] - body[j, 1]) * n1 + (G[i, 2] - body[j, 2]) * n2)
    for r in range(a.shape[0]):
        i = a[r]
        n0, n1, n2 = qn[r, 0], qn[r, 1], qn[r, 2]
        N[i, 0], N[i, 1], N[i, 2] = n0, n1, n2
        c = most[r] if most[r] < clearance else clearance
        depth[i] = c - ((G[i, 0] - q[r, 0]) * n0 + (G[i, 1] - q[r, 1]) * n1 + (G[i, 2] - q[r, 2]) * n2)
    nbad = 0
    for j in range(M):
        d = depth[j]
        if d > 0:
            nbad += 1
            _add_column(indptr, indices, data, j, d * N[j, 0], d * N[j, 1], d * N[j, 2], disp)
    for j in range(M):
        d = depth[j]
        if d > 0:
            short = d - (disp[j, 0] * N[j, 0] + disp[j, 1] * N[j, 1] + disp[j, 2] * N[j, 2])
            if short > 0:
                disp[j, 0] += short * N[j, 0]
                disp[j, 1] += short * N[j, 1]
                disp[j, 2] += short * N[j, 2]
    return nbad


def _close_pairs(x, dims, skeys, order, radius, ex_ptr, ex_idx, out):
    """:func:`close_pairs`' loop: writes the pairs into ``out`` (P_max, 2) and returns their
    number P (more than P_max: ``out`` was too small, call again with P rows). dims (3,) the
    grid's cells per axis, skeys (N,) the vertices' cell keys sorted, order (N,) the vertices in
    that order. Cell by cell (each a run of ``skeys``): its vertices against each other and against
    its 13 neighbours of larger key, whose runs an open-addressing hash table (linear probing,
    at least twice as many slots as vertices) finds."""
    n = x.shape[0]
    table, mask = _cell_table(skeys)  # slot -> the first index of its cell's run in skeys
    r2 = radius * radius
    count = 0
    runs = np.empty((14, 2), np.int64)  # the runs (start, end) of the cell itself and its 13 neighbours
    s0 = 0
    while s0 < n:
        k0 = skeys[s0]
        s1 = s0 + 1
        while s1 < n and skeys[s1] == k0:
            s1 += 1
        cz0 = k0 % dims[2]
        cy0 = (k0 // dims[2]) % dims[1]
        cx0 = k0 // (dims[2] * dims[1])
        nr = 0
        for a in range(0, 2):
            cx = cx0 + a
            if cx >= dims[0]:
                continue
            for b in range(-1, 2):
                cy = cy0 + b
                if cy < 0 or cy >= dims[1] or (a == 0 and b < 0):
                    continue
                for c in range(-1, 2):
                    cz = cz0 + c
                    if cz < 0 or cz >= dims[2] or (a == 0 and b == 0 and c <= 0):
                        continue
                    lo, hi = _cell_run(table, mask, skeys, (cx * dims[1] + cy) * dims[2] + cz)
                    if hi > lo:
                        runs[nr, 0], runs[nr, 1] = lo, hi
                        nr += 1
        for si in range(s0, s1):
            i0 = order[si]
            for r in range(nr + 1):
                lo, hi = (si + 1, s1) if r == nr else (runs[r, 0], runs[r, 1])
                for sj in range(lo, hi):
                    j0 = order[sj]
                    d0, d1, d2 = x[j0, 0] - x[i0, 0], x[j0, 1] - x[i0, 1], x[j0, 2] - x[i0, 2]
                    if d0 * d0 + d1 * d1 + d2 * d2 > r2:
                        continue
                    i, j = (i0, j0) if i0 < j0 else (j0, i0)
                    p, e = ex_ptr[i], ex_ptr[i + 1]  # j among row i's sorted excluded indices
                    while p < e:
                        mid = (p + e) >> 1
                        if ex_idx[mid] < j:
                            p = mid + 1
                        else:
                            e = mid
                    if p < ex_ptr[i + 1] and ex_idx[p] == j:
                        continue
                    if count < out.shape[0]:
                        out[count, 0], out[count, 1] = i, j
                    count += 1
        s0 = s1
    return count


def _clamp_steps(g, x, max_step):
    """The drape's trust region (``drape.solver.Draper.solve``): each row of g (N, 3) float64
    farther than max_step from its row of x moved back onto that distance along its step,
    in place, with numpy's operations there (the same result bit for bit). Returns how many."""
    n = 0
    for i in range(g.shape[0]):
        d0, d1, d2 = g[i, 0] - x[i, 0], g[i, 1] - x[i, 1], g[i, 2] - x[i, 2]
        step = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        if step > max_step:
            s = max_step / step
            g[i, 0], g[i, 1], g[i, 2] = x[i, 0] + d0 * s, x[i, 1] + d1 * s, x[i, 2] + d2 * s
            n += 1
    return n


def _max_move(g, x):
    """The largest row distance between g and x (N, 3) float64, as numpy's
    ``sqrt(((g - x) ** 2).sum(1).max())``."""
    best = 0.0
    for i in range(g.shape[0]):
        d0, d1, d2 = g[i, 0] - x[i, 0], g[i, 1] - x[i, 1], g[i, 2] - x[i, 2]
        q = d0 * d0 + d1 * d1 + d2 * d2
        if q > best or q != q:
            best = q
    return np.sqrt(best)

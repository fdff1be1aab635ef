"""Meshes with known answers for the drape engine's tests and bench: open tubes, closed
cylinders (bodies of revolution), a square sheet. Y up, metres, faces counter-clockwise seen
from outside."""
from __future__ import annotations

import numpy as np


def tube(radius: float, height: float, n_around: int = 64, n_height: int = 20, y0: float = 0.0):
    """An open tube around the Y axis from y0 to y0 + height: vertices (n_height+1)*n_around,
    ring k at y0 + height * k / n_height (ring 0 at the bottom)."""
    a = 2 * np.pi * np.arange(n_around) / n_around
    ys = y0 + height * np.arange(n_height + 1) / n_height
    V = np.array([[radius * np.cos(t), y, -radius * np.sin(t)] for y in ys for t in a])
    F = []
    for k in range(n_height):
        for i in range(n_around):
            a0, a1 = k * n_around + i, k * n_around + (i + 1) % n_around
            b0, b1 = a0 + n_around, a1 + n_around
            F += [[a0, a1, b1], [a0, b1, b0]]
    return V, np.array(F, np.int64)


def revolved_body(profile_y: np.ndarray, profile_r: np.ndarray, n_around: int = 96):
    """A closed body of revolution around Y: rings of radius profile_r at heights profile_y
    (ascending), capped at both ends."""
    a = 2 * np.pi * np.arange(n_around) / n_around
    V = [[r * np.cos(t), y, -r * np.sin(t)] for y, r in zip(profile_y, profile_r) for t in a]
    K = len(profile_y)
    F = []
    for k in range(K - 1):
        for i in range(n_around):
            a0, a1 = k * n_around + i, k * n_around + (i + 1) % n_around
            b0, b1 = a0 + n_around, a1 + n_around
            F += [[a0, a1, b1], [a0, b1, b0]]
    bot, top = len(V), len(V) + 1
    V += [[0.0, profile_y[0], 0.0], [0.0, profile_y[-1], 0.0]]
    last = (K - 1) * n_around
    for i in range(n_around):
        F += [[bot, (i + 1) % n_around, i], [top, last + i, last + (i + 1) % n_around]]
    return np.array(V), np.array(F, np.int64)


def cylinder(radius: float, y0: float, y1: float, n_around: int = 96, n_height: int = 24):
    ys = np.linspace(y0, y1, n_height + 1)
    return revolved_body(ys, np.full_like(ys, radius), n_around)


def ring_girth(V: np.ndarray, ring: int, n_around: int) -> float:
    """The perimeter of ring ``ring`` of a :func:`tube`-ordered mesh."""
    p = V[ring * n_around:(ring + 1) * n_around]
    return float(np.linalg.norm(p - np.roll(p, -1, axis=0), axis=1).sum())


def square(size: float, n: int, y: float = 0.0):
    """A horizontal square sheet (n x n vertices) in the XZ plane at height y, centred; faces
    facing +Y. Corner indices: 0, n-1, n*(n-1), n*n-1."""
    s = np.linspace(-size / 2, size / 2, n)
    X, Z = np.meshgrid(s, s)
    V = np.stack([X.ravel(), np.full(n * n, y), Z.ravel()], 1)
    F = []
    for r in range(n - 1):
        for c in range(n - 1):
            a, b, d, e = r * n + c, r * n + c + 1, (r + 1) * n + c, (r + 1) * n + c + 1
            F += [[a, d, b], [b, d, e]]
    return V, np.array(F, np.int64)


def reference_static(draper, start: np.ndarray) -> np.ndarray:
    """A slow reference solve of the same energy (``Draper.energy``: stretch, bending, gravity;
    no body) by L-BFGS from ``start`` with the pinned vertices held: the minimiser (N, 3)."""
    from scipy.optimize import minimize

    free = np.setdiff1d(np.arange(draper.n), draper.pinned)
    x = np.array(start, np.float64)

    def f(z):
        y = x.copy()
        y[free] = z.reshape(-1, 3)
        e, g = draper.energy(y)
        return e, g[free].ravel()

    res = minimize(f, x[free].ravel(), jac=True, method="L-BFGS-B",
                   options={"maxiter": 50000, "maxfun": 100000, "ftol": 1e-16, "gtol": 1e-12})
    y = x.copy()
    y[free] = res.x.reshape(-1, 3)
    return y


def hanging_start(V: np.ndarray, pin_y: float) -> np.ndarray:
    """A square sheet (:func:`square`, pinned along its z = min edge's corners) turned to hang
    down in the XY plane: the start of a reference solve."""
    z0 = V[:, 2].min()
    out = V.copy()
    out[:, 1] = pin_y - (V[:, 2] - z0)
    out[:, 2] = z0
    return out


def square_sag(n: int = 7, size: float = 0.2, fabric: str = "knit", config=None):
    """The square (n x n, ``size`` m) pinned at its two corners on one edge, settled by the
    drape engine from flat and by :func:`reference_static` from hanging: (sag m, reference sag
    m, drape result, reference vertices). Sag: pin height minus the lowest point."""
    from service.model.drape import Config, precompute

    V, F = square(size, n, y=1.0)
    d = precompute(V, F, fabric, config or Config(max_iterations=3000, tolerance_m=5e-7), pinned=[0, n - 1])
    r = d.solve(None, None, V)
    y = reference_static(d, hanging_start(V, 1.0))
    return 1.0 - float(r.vertices[:, 1].min()), 1.0 - float(y[:, 1].min()), r, y


def subdivide(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Midpoint subdivision (each face into four): vertices, faces and the (E, 2) parents of
    each new vertex (to carry any positions along: the mean of its two parents)."""
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(e, axis=0, return_inverse=True)
    inv = inv.reshape(3, -1).T + len(V)  # (F, 3): midpoints of edges 01, 12, 20
    a, b, c = F[:, 0], F[:, 1], F[:, 2]
    m01, m12, m20 = inv[:, 0], inv[:, 1], inv[:, 2]
    F2 = np.concatenate([np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1), np.stack([m20, m12, c], 1),
                         np.stack([m01, m12, m20], 1)])
    V2 = np.vstack([V, 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])])
    return V2, F2, uniq

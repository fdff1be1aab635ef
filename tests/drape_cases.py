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

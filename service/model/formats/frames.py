"""Units and axes of uploaded geometry: the one unit and axis detector used by avatar, scan and
garment uploads. Pure numpy/scipy.

Our frame: metres, Y up, facing +Z (glTF's). Uploads come in metres, centimetres or
millimetres, Y or Z up (either sign), facing anywhere.

Shapes: points (P, 3) float64; rotations (3, 3).
"""
from __future__ import annotations

import itertools

import numpy as np
from scipy.spatial import cKDTree

# unit name -> metres per unit
UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001}
# largest extent of a person standing, sitting or crouching (metres)
PERSON_MIN_M, PERSON_MAX_M = 0.9, 2.6


class UnitError(ValueError):
    """The unit of an upload cannot be told; the message says why."""


def detect_unit(points: np.ndarray, lo: float = PERSON_MIN_M, hi: float = PERSON_MAX_M,
                what: str = "the scan") -> tuple[str, float]:
    """(unit, metres per unit) that makes the points' largest extent a person's size
    (``lo``..``hi`` metres). Raises :class:`UnitError`."""
    ext = float(np.ptp(np.asarray(points, np.float64), axis=0).max())
    for name, scale in UNITS.items():
        if lo <= ext * scale <= hi:
            return name, scale
    raise UnitError(f"cannot tell the units: {what} is {ext:g} units across (expected a person "
                    f"{lo:g}-{hi:g} m tall in metres, centimetres or millimetres)")


def unit_against(points: np.ndarray, reference: cKDTree) -> tuple[str, float, float]:
    """(unit, metres per unit, median distance in metres) that puts ``points`` (a garment)
    closest to a reference surface in metres (the body it is fitted to)."""
    best = None
    for name, scale in UNITS.items():
        d, _ = reference.query(np.asarray(points, np.float64) * scale)
        med = float(np.median(d))
        if best is None or med < best[2]:
            best = (name, scale, med)
    assert best is not None
    return best


def kabsch(src: np.ndarray, dst: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) and translation t (3,) minimising |R src + t - dst| (no scaling)."""
    cs, cd = src.mean(0), dst.mean(0)
    H = (src - cs).T @ (dst - cd)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1.0, 1.0, d]) @ U.T
    return R, cd - R @ cs


def _axis_rotations() -> np.ndarray:
    """The 24 rotations that map coordinate axes to coordinate axes (24, 3, 3)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            M = np.zeros((3, 3))
            M[range(3), perm] = signs
            if np.linalg.det(M) > 0:
                out.append(M)
    return np.array(out)


AXIS_ROTATIONS = _axis_rotations()


def nearest_axis_rotation(R: np.ndarray) -> np.ndarray:
    """The axis-aligned rotation closest to R (largest trace of R^T Q)."""
    return AXIS_ROTATIONS[np.argmax(np.einsum("ij,kij->k", R, AXIS_ROTATIONS))]


def rotation_to_y(u: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking the coordinate axis ``u`` (a signed unit axis) to +Y."""
    y = np.array([0.0, 1.0, 0.0])
    if np.allclose(u, y):
        return np.eye(3)
    if np.allclose(u, -y):
        return np.diag([1.0, -1.0, -1.0])
    k = np.cross(u, y)
    k = k / np.linalg.norm(k) * (np.pi / 2)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]]) / (np.pi / 2)
    return np.eye(3) + K + K @ K  # Rodrigues at a quarter turn: sin = 1, 1 - cos = 1


def up_candidates(points: np.ndarray) -> list[tuple[str, np.ndarray]]:
    """Candidate rotations taking an upload's up axis to +Y: the coordinate axis closest to the
    principal axis of the points, either sign. [(label like '+z', R (3, 3))]."""
    c = np.asarray(points, np.float64)
    c = c - c.mean(0)
    _, _, Vt = np.linalg.svd(c[:: max(1, len(c) // 5000)], full_matrices=False)
    ax = int(np.argmax(np.abs(Vt[0])))
    out = []
    for sign in (1.0, -1.0):
        u = np.zeros(3)
        u[ax] = sign
        out.append(("+-"[int(sign < 0)] + "xyz"[ax], rotation_to_y(u)))
    return out


def up_label(R: np.ndarray) -> str:
    """The file axis that an axis-aligned rotation R (file -> our frame) takes to +Y."""
    v = R.T @ np.array([0.0, 1.0, 0.0])
    ax = int(np.argmax(np.abs(v)))
    return "+-"[int(v[ax] < 0)] + "xyz"[ax]


def orient_outward(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Flip all normals when most point towards the points' centre (an inside-out file)."""
    c = points.mean(0)
    return normals if np.mean(np.einsum("ij,ij->i", normals, points - c) > 0) >= 0.5 else -normals

"""Tailor measurements on an avatar in template topology, with analytic Jacobians.

Pure numpy/scipy. Every measurement is defined as a tailor (or the ANSUR II survey) takes it:

=====================  ==========================  ===============================================
API name               ANSUR II column             definition on the mesh
=====================  ==========================  ===============================================
height_cm              stature                     top of head (vertex) above the floor
weight_kg              weightkg / 10               enclosed volume of the body surface x density
chest_cm               chestcircumference          tape at nipple level (horizontal plane section)
waist_cm               waistcircumference          tape at the omphalion (navel) level
hip_cm                 buttockcircumference        tape at crotch + 0.23 (navel - crotch) height
thigh_cm               thighcircumference          left thigh, plane perpendicular to the
                                                   hip-knee axis at crotch height
calf_cm                calfcircumference           left calf, largest horizontal section 15-55 %
                                                   down the shin
waist_height_cm        waistheightomphalion        navel above the floor
shoulder_width_cm      biacromialbreadth           distance between the two acromion points
inseam_cm              crotchheight                crotch point above the floor
arm_length_cm          sleeveoutseam               acromion -> radiale -> stylion (outer arm)
gender                 Gender                      "female" / "male" (not measured: given)
=====================  ==========================  ===============================================

A girth is the perimeter of the convex hull of the plane section (how a tape lies), computed
exactly from the mesh edges that cross the plane. The floor is the lowest sole vertex.
Extra measurements (breadths and depths of the chest, waist and hip sections, acromion height)
are used by the offline population fit only.

All functions take ``vertices: (V, 3)`` in metres (Y up, facing +Z) and return metres (or kg);
``measure_attributes`` converts to API units (cm, kg).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp
from scipy.spatial import ConvexHull, QhullError

# API attributes in order; index 0 is gender (categorical, not measured).
ATTRIBUTES: tuple[str, ...] = (
    "gender", "height_cm", "weight_kg", "chest_cm", "waist_cm", "hip_cm", "thigh_cm",
    "calf_cm", "waist_height_cm", "shoulder_width_cm", "inseam_cm", "arm_length_cm",
)
ANSUR_COLUMNS: dict[str, str] = {
    "gender": "Gender", "height_cm": "stature", "weight_kg": "weightkg",
    "chest_cm": "chestcircumference", "waist_cm": "waistcircumference",
    "hip_cm": "buttockcircumference", "thigh_cm": "thighcircumference",
    "calf_cm": "calfcircumference", "waist_height_cm": "waistheightomphalion",
    "shoulder_width_cm": "biacromialbreadth", "inseam_cm": "crotchheight",
    "arm_length_cm": "sleeveoutseam",
}
DESCRIPTIONS: dict[str, str] = {
    "gender": "female or male",
    "height_cm": "standing height, floor to the top of the head, barefoot",
    "weight_kg": "body mass",
    "chest_cm": "tape around the chest at nipple level, horizontal",
    "waist_cm": "tape around the waist at the navel, horizontal",
    "hip_cm": "tape around the fullest part of the buttocks, horizontal",
    "thigh_cm": "tape around the upper thigh just below the crotch",
    "calf_cm": "tape around the fullest part of the calf",
    "waist_height_cm": "floor to the navel, standing",
    "shoulder_width_cm": "straight distance between the two bony shoulder tips",
    "inseam_cm": "floor to the crotch, standing",
    "arm_length_cm": "shoulder tip over the elbow to the wrist bone, arm hanging",
}
# Extra measurements (metres) used by the population fit: name -> ANSUR column.
EXTRA_ANSUR: dict[str, str] = {
    "chest_breadth": "chestbreadth", "chest_depth": "chestdepth",
    "waist_breadth": "waistbreadth", "waist_depth": "waistdepth",
    "hip_breadth": "hipbreadth", "acromion_height": "acromialheight",
}
# Order of the raw measurement vector returned by ``measure``: 11 API measurements (metres,
# weight in kg) then the extras.
RAW_NAMES: tuple[str, ...] = ATTRIBUTES[1:] + tuple(EXTRA_ANSUR)
# Body densities (kg/m^3) that make the mean mass of avatars fitted to ANSUR right
# (../shared/NOTES.md: 1007 men, 1064 women).
DENSITY = {"male": 1007.0, "female": 1064.0}
# ISO 20685-1 maximum allowable errors, metres (kg for weight).
ISO_TOLERANCE: dict[str, float] = {
    "height_cm": 0.004, "weight_kg": 0.5, "chest_cm": 0.009, "waist_cm": 0.009,
    "hip_cm": 0.009, "thigh_cm": 0.009, "calf_cm": 0.009, "waist_height_cm": 0.004,
    "shoulder_width_cm": 0.004, "inseam_cm": 0.004, "arm_length_cm": 0.005,
}
# Calf: horizontal sections at these fractions of the knee -> ankle drop.
CALF_FRACTIONS = np.linspace(0.15, 0.55, 9)
CALF_EXACT_CANDIDATES = 2  # calf levels ranked by a support-function estimate, then exact
SUPPORT_DIRECTIONS = 32  # directions of that estimate
HIP_LEVEL_FRACTION = 0.23  # buttock level between crotch (0) and navel (1)
# Candidate edges of a horizontal section: those whose endpoints lie within this distance of
# the section's level on the mean avatar (sections move with the landmarks that define them).
SECTION_BAND = 0.15


@dataclass
class MeasurementSpec:
    """Landmarks and candidate section edges, fixed for the template topology.

    faces: (F, 3) int body triangles (watertight); landmark indices are hm08 vertex ids;
    ``*_edges``: (E, 2) int mesh edges that may cross that section's plane;
    ``joint_regressor``: (17, V) sparse, for the hip/knee/ankle axes.
    """

    faces: np.ndarray
    top: int
    soles: np.ndarray
    nipples: np.ndarray  # (2,)
    navel: int
    crotch: int
    acromion: np.ndarray  # (2,) left, right
    elbow: int  # left radiale
    wrist: int  # left stylion
    torso_edges: np.ndarray
    hip_edges: np.ndarray
    thigh_edges: np.ndarray
    calf_edges: np.ndarray
    joint_regressor: sp.csr_matrix
    joint_ids: dict[str, int] = field(default_factory=dict)  # hip_l, knee_l, ankle_l rows
    chest_edges: np.ndarray | None = None  # band-limited subsets (see ``restrict_to_bands``)
    waist_edges: np.ndarray | None = None
    volume_vertices: np.ndarray | None = None

    def __post_init__(self):
        if self.chest_edges is None:
            self.chest_edges = self.torso_edges
        if self.waist_edges is None:
            self.waist_edges = self.torso_edges
        if self.volume_vertices is None:
            self.volume_vertices = np.unique(self.faces)

    def restrict_to_bands(self, mean: np.ndarray, band: float = SECTION_BAND) -> "MeasurementSpec":
        """Limit each horizontal section's candidate edges to a band around its level on the
        ``mean`` avatar (V, 3): same sections, far fewer edges to test."""
        y = mean[:, 1]

        def near(edges, level):
            keep = (np.abs(y[edges[:, 0]] - level) < band) | (np.abs(y[edges[:, 1]] - level) < band)
            return edges[keep]

        f = HIP_LEVEL_FRACTION
        self.chest_edges = near(self.torso_edges, float(y[self.nipples].mean()))
        self.waist_edges = near(self.torso_edges, float(y[self.navel]))
        self.hip_edges = near(self.hip_edges, float((1 - f) * y[self.crotch] + f * y[self.navel]))
        return self

    def restrict(self) -> tuple["MeasurementSpec", np.ndarray]:
        """The same measurements on only the vertices they read: landmarks, soles, the
        sections' candidate edges and the hip/knee/ankle regressor columns; all but weight,
        which needs the whole surface (the restricted spec has no faces and measures 0).

        Returns (spec over those vertices, their ids (R,) in this spec's vertex order), so that
        ``measure(restricted, vertices[ids])`` equals ``measure(self, vertices)`` but weight."""
        joints = [self.joint_ids[k] for k in ("hip", "knee", "ankle")]
        jreg = sp.csr_matrix(self.joint_regressor)[joints]
        ids = np.unique(np.concatenate([
            self.chest_edges.ravel(), self.waist_edges.ravel(), self.hip_edges.ravel(),
            self.thigh_edges.ravel(), self.calf_edges.ravel(), self.soles, self.nipples, self.acromion,
            [self.top, self.navel, self.crotch, self.elbow, self.wrist], jreg.indices,
        ]).astype(np.int64))
        new = np.full(self.joint_regressor.shape[1], -1, np.int64)
        new[ids] = np.arange(len(ids))
        restricted = MeasurementSpec(
            faces=np.zeros((0, 3), np.int64), top=int(new[self.top]), soles=new[self.soles],
            nipples=new[self.nipples], navel=int(new[self.navel]), crotch=int(new[self.crotch]),
            acromion=new[self.acromion], elbow=int(new[self.elbow]), wrist=int(new[self.wrist]),
            torso_edges=new[np.vstack([self.chest_edges, self.waist_edges])],
            hip_edges=new[self.hip_edges], thigh_edges=new[self.thigh_edges],
            calf_edges=new[self.calf_edges], joint_regressor=sp.csr_matrix(jreg[:, ids]),
            joint_ids={"hip": 0, "knee": 1, "ankle": 2},
            chest_edges=new[self.chest_edges], waist_edges=new[self.waist_edges],
        )
        return restricted, ids

    @classmethod
    def from_arrays(cls, data: dict, meta: dict) -> "MeasurementSpec":
        lm = meta["landmarks"]
        jreg = sp.csr_matrix(
            (data["jreg_data"], data["jreg_indices"], data["jreg_indptr"]),
            shape=(17, data["mean"].shape[0]),
        )
        return cls(
            faces=data["body_faces"].astype(np.int64),
            top=int(lm["top"]), soles=np.asarray(data["lm_soles"], np.int64),
            nipples=np.asarray(lm["nipples"], np.int64), navel=int(lm["navel"]),
            crotch=int(lm["crotch"]), acromion=np.asarray(lm["acromion"], np.int64),
            elbow=int(lm["elbow"]), wrist=int(lm["wrist"]),
            torso_edges=data["edges_torso"].astype(np.int64),
            hip_edges=data["edges_hip"].astype(np.int64),
            thigh_edges=data["edges_thigh"].astype(np.int64),
            calf_edges=data["edges_calf"].astype(np.int64),
            joint_regressor=jreg,
            joint_ids={"hip": 11, "knee": 12, "ankle": 13},
        ).restrict_to_bands(data["mean"].astype(np.float64))

    def to_arrays(self) -> tuple[dict, dict]:
        """Inverse of ``from_arrays`` (minus faces/regressor, stored by the body model)."""
        arrays = {
            "lm_soles": self.soles.astype(np.int32),
            "edges_torso": self.torso_edges.astype(np.int32),
            "edges_hip": self.hip_edges.astype(np.int32),
            "edges_thigh": self.thigh_edges.astype(np.int32),
            "edges_calf": self.calf_edges.astype(np.int32),
        }
        lm = {
            "top": int(self.top), "nipples": [int(i) for i in self.nipples],
            "navel": int(self.navel), "crotch": int(self.crotch),
            "acromion": [int(i) for i in self.acromion], "elbow": int(self.elbow),
            "wrist": int(self.wrist),
        }
        return arrays, lm


# -- geometric primitives ------------------------------------------------------------------
Y = np.array([0.0, 1.0, 0.0])  # the up axis: horizontal sections have this normal
_Y_BASIS = (np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.0, -1.0]))  # what _plane_basis(Y) computes


class _Grad:
    """Accumulates d(measurement)/d(vertices) as sparse (row, vertex, axis, value) triplets.
    Given a ``basis`` (3 V, K) (d vertices / d parameters, e.g. PCA components), ``matrix``
    returns d(measurement)/d(parameters) as a dense (n_rows, K) array instead."""

    def __init__(self, n_rows: int, n_vertices: int, basis: np.ndarray | None = None):
        self.n_rows, self.n_vertices = n_rows, n_vertices
        self.basis = basis
        self.rows: list[np.ndarray] = []
        self.vids: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []

    def add(self, row: int, vids: np.ndarray, grads: np.ndarray) -> None:
        """vids: (n,) vertex ids; grads: (n, 3) d(row)/d(vertex)."""
        vids = np.asarray(vids).reshape(-1)
        self.rows.append(np.full(len(vids), row))
        self.vids.append(vids)
        self.vals.append(np.asarray(grads, np.float64).reshape(-1, 3))

    def matrix(self) -> sp.csr_matrix | np.ndarray:
        """(n_rows, 3 V) CSR, duplicates summed; with a basis the dense (n_rows, K) product."""
        shape = (self.n_rows, 3 * self.n_vertices)
        if not self.rows:
            J = sp.csr_matrix(shape)
        else:
            rows = np.repeat(np.concatenate(self.rows), 3)
            cols = (np.concatenate(self.vids).astype(np.int64)[:, None] * 3 + _XYZ).reshape(-1)
            J = sp.csr_matrix((np.concatenate(self.vals).reshape(-1), (rows, cols)), shape=shape)
        return J if self.basis is None else np.asarray(J @ self.basis)


_XYZ = np.arange(3)


def plane_section(
    vertices: np.ndarray, edges: np.ndarray, normal: np.ndarray, offset: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points where candidate mesh edges cross the plane ``normal . x = offset``.

    vertices: (V, 3); edges: (E, 2); normal: (3,) unit. Returns (points (n, 3), edge ids
    (n, 2), t (n,), sa (n,), sb (n,)) for the n crossing edges, point = a + t (b - a),
    sa/sb the signed distances of the endpoints."""
    e0, e1 = edges[:, 0], edges[:, 1]
    if normal is Y:  # horizontal: the signed distance is the height (same numbers, less work)
        y = vertices[:, 1]
        sa, sb = y.take(e0) - offset, y.take(e1) - offset
    else:
        sa = vertices[e0] @ normal - offset
        sb = vertices[e1] @ normal - offset
    # a vertex on the plane counts (t = 0 or 1): landmarks often define the plane
    cross = ((sa * sb) <= 0) & ((sa != 0) | (sb != 0))
    ec = edges[cross]
    a, b, sa, sb = vertices[ec[:, 0]], vertices[ec[:, 1]], sa[cross], sb[cross]
    t = sa / (sa - sb)
    pts = a + t[:, None] * (b - a)
    return pts, ec, t, sa, sb


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to ``normal`` (e1 close to +X)."""
    if normal is Y:
        return _Y_BASIS
    ref = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = ref - normal * (ref @ normal)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return e1, e2


def hull_perimeter(points2d: np.ndarray, grad: bool = True) -> tuple[float, np.ndarray, np.ndarray | None]:
    """Perimeter of the convex hull of 2-D points (how a tape lies).

    points2d: (n, 2). Returns (perimeter, hull vertex ids (h,), d perimeter / d hull vertex
    (h, 2), None unless ``grad``)."""
    if len(points2d) < 3:
        return 0.0, np.zeros(0, np.int64), np.zeros((0, 2))
    try:
        hv = ConvexHull(points2d).vertices
    except QhullError:
        return 0.0, np.zeros(0, np.int64), np.zeros((0, 2))
    q = points2d[hv]
    nxt = np.empty_like(q)  # q_{j+1} - q_j, cyclically
    nxt[:-1] = q[1:] - q[:-1]
    nxt[-1] = q[0] - q[-1]
    ln = np.sqrt(nxt[:, 0] * nxt[:, 0] + nxt[:, 1] * nxt[:, 1])
    if not grad:
        return float(ln.sum()), hv, None
    u = nxt / np.maximum(ln, 1e-12)[:, None]
    return float(ln.sum()), hv, np.roll(u, 1, axis=0) - u  # d|q_{j}-q_{j-1}| + d|q_{j+1}-q_j|


def _section_grad(
    g: _Grad, row: int, g3: np.ndarray, e: np.ndarray, t: np.ndarray, sa: np.ndarray,
    sb: np.ndarray, a: np.ndarray, b: np.ndarray, normal: np.ndarray,
    offset_grad: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[float, np.ndarray]:
    """Chain rule from d(measure)/d(section points) ``g3`` (n, 3) to the edge endpoints and,
    through the plane offset, to the landmark vertices that define it.

    Returns (d measure / d offset, d measure / d normal (3,)) for callers whose plane itself
    depends on the vertices (the thigh; None when ``offset_grad`` is given)."""
    denom = sa - sb
    gab = np.einsum("ij,ij->i", g3, b - a)
    c = gab / denom**2
    g.add(row, e.T.reshape(-1), np.concatenate([(1 - t)[:, None] * g3 - (c * sb)[:, None] * normal,
                                                 t[:, None] * g3 + (c * sa)[:, None] * normal]))
    d_off = -float(np.sum(gab / denom))
    if offset_grad is not None:
        vids, coeffs = offset_grad
        g.add(row, vids, d_off * coeffs)
        return d_off, None
    return d_off, (c[:, None] * (sa[:, None] * b - sb[:, None] * a)).sum(axis=0)


@dataclass
class _Section:
    """A plane section and its hull: points (n, 3), crossing edges (n, 2), t / sa / sb (n,)
    (see ``plane_section``), points in plane coordinates (n, 2), hull perimeter, hull vertex
    ids (h,) and d perimeter / d hull vertex (h, 2) (None without gradient)."""

    pts: np.ndarray
    e: np.ndarray
    t: np.ndarray
    sa: np.ndarray
    sb: np.ndarray
    p2: np.ndarray
    perimeter: float
    hv: np.ndarray
    hgrad: np.ndarray | None


def _hull_section(vertices: np.ndarray, edges: np.ndarray, normal: np.ndarray, offset: float,
                  grad: bool) -> _Section:
    pts, e, t, sa, sb = plane_section(vertices, edges, normal, offset)
    if normal is Y:  # (pts . e1, pts . e2) for _Y_BASIS: the same numbers
        p2 = pts[:, ::2] * _FLIP_Z
    else:
        e1, e2 = _plane_basis(normal)
        p2 = np.stack([pts @ e1, pts @ e2], axis=1)
    return _Section(pts, e, t, sa, sb, p2, *hull_perimeter(p2, grad=grad))


_FLIP_Z = np.array([1.0, -1.0])


def _girth(
    g: _Grad | None, rows: dict[str, int], vertices: np.ndarray, edges: np.ndarray,
    normal: np.ndarray, offset: float, offset_grad, extent_rows: dict[str, tuple[int, int]] | None = None,
    section: _Section | None = None,
) -> dict[str, float]:
    """Girth (and optional extents along the plane axes) of one plane section (``section``
    when already cut)."""
    sec = section or _hull_section(vertices, edges, normal, offset, grad=g is not None)
    e1, e2 = _plane_basis(normal)
    e, t, sa, sb, p2, hv = sec.e, sec.t, sec.sa, sec.sb, sec.p2, sec.hv
    out = {"girth": sec.perimeter}
    if g is not None:
        a, b = vertices[e[:, 0]], vertices[e[:, 1]]
    if g is not None and len(hv) and "girth" in rows:
        g3 = sec.hgrad[:, :1] * e1 + sec.hgrad[:, 1:] * e2
        out["d_offset"], out["d_normal"] = _section_grad(
            g, rows["girth"], g3, e[hv], t[hv], sa[hv], sb[hv], a[hv], b[hv], normal, offset_grad)
    if extent_rows and len(p2):
        for name, (axis, _) in extent_rows.items():
            ev = (e1, e2)[axis]
            hi, lo = int(np.argmax(p2[:, axis])), int(np.argmin(p2[:, axis]))
            out[name] = float(p2[hi, axis] - p2[lo, axis])
            if g is not None:
                for idx, sign in ((hi, 1.0), (lo, -1.0)):
                    _section_grad(g, rows[name], sign * ev[None, :], e[[idx]], t[[idx]],
                                  sa[[idx]], sb[[idx]], a[[idx]], b[[idx]], normal, offset_grad)
    return out


_DIRS = np.stack([np.cos(np.linspace(0, 2 * np.pi, SUPPORT_DIRECTIONS, endpoint=False)),
                  np.sin(np.linspace(0, 2 * np.pi, SUPPORT_DIRECTIONS, endpoint=False))], axis=1)


def _rank_levels(vertices: np.ndarray, edges: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """Horizontal section levels (L,) ordered by estimated hull perimeter, largest first.

    The estimate integrates the support function of the section points over
    ``SUPPORT_DIRECTIONS`` directions (Cauchy's formula: perimeter = integral of h)."""
    y = vertices[:, 1]
    sa = y.take(edges[:, 0])[None, :] - levels[:, None]  # (L, E)
    sb = y.take(edges[:, 1])[None, :] - levels[:, None]
    lv, ei = np.nonzero(((sa * sb) <= 0) & ((sa != 0) | (sb != 0)))  # crossings, by level
    sa, sb = sa[lv, ei], sb[lv, ei]
    t = sa / (sa - sb)
    a, b = vertices[edges[ei, 0]], vertices[edges[ei, 1]]
    px = a[:, 0] + t * (b[:, 0] - a[:, 0])
    pz = a[:, 2] + t * (b[:, 2] - a[:, 2])
    proj = px[:, None] * _DIRS[:, 0] + pz[:, None] * _DIRS[:, 1]  # (n, D)
    est = np.full((len(levels), SUPPORT_DIRECTIONS), -np.inf)
    counts = np.bincount(lv, minlength=len(levels))
    some = counts > 0
    if some.any():  # the largest projection per level (lv is sorted)
        est[some] = np.maximum.reduceat(proj, (np.cumsum(counts) - counts)[some], axis=0)
    return np.argsort(-est.sum(axis=1))  # (L,) estimates proportional to perimeter


def volume(vertices: np.ndarray, faces: np.ndarray, grad: bool = False):
    """Enclosed volume (m^3) of a closed triangle surface; with ``grad`` also d vol / d
    vertices (V, 3) (only rows of vertices used by ``faces`` are non-zero)."""
    if not grad:  # sum of a . (b x c) / 6 over the faces, one coordinate array at a time
        x, y, z = (np.ascontiguousarray(vertices[:, k], np.float64) for k in range(3))
        i, j, k = faces[:, 0], faces[:, 1], faces[:, 2]
        bx, by, bz, cx, cy, cz = x.take(j), y.take(j), z.take(j), x.take(k), y.take(k), z.take(k)
        det = x.take(i) * (by * cz - bz * cy) + y.take(i) * (bz * cx - bx * cz) + z.take(i) * (bx * cy - by * cx)
        return float(det.sum()) / 6.0
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    bc = np.cross(b, c)
    vol = float(np.einsum("ij,ij->", a, bc)) / 6.0
    gv = np.zeros_like(vertices, dtype=np.float64)
    for k, cr in ((0, bc), (1, np.cross(c, a)), (2, np.cross(a, b))):
        for ax in range(3):
            gv[:, ax] += np.bincount(faces[:, k], weights=cr[:, ax], minlength=len(vertices))
    return vol, gv / 6.0


# -- the measurements ----------------------------------------------------------------------
def measure(
    spec: MeasurementSpec, vertices: np.ndarray, gender: str, jacobian: bool = False, *,
    basis: np.ndarray | None = None, extras: bool = True, names=None,
):
    """Raw measurements of one avatar.

    vertices: (V, 3) metres. Returns values (len(RAW_NAMES),) float64 in metres (weight in
    kg); with ``jacobian`` also d values / d vertices as CSR (len(RAW_NAMES), 3 V), or, given
    ``basis`` (3 V, K) = d vertices / d parameters, d values / d parameters as a dense
    (len(RAW_NAMES), K) array. Only the ``names`` (of ``RAW_NAMES``; default all) are
    measured, and the breadths and depths only with ``extras``; the others are left 0. A spec
    without faces (``MeasurementSpec.restrict``) measures no weight (0)."""
    X = np.asarray(vertices, np.float64)
    n = len(RAW_NAMES)
    row = _ROW
    want = set(RAW_NAMES if names is None else names) - (set() if extras else set(EXTRA_ANSUR))
    g = _Grad(n, len(X), basis) if jacobian else None
    out = np.zeros(n)

    soles_y = X[spec.soles, 1]
    floor_id = int(spec.soles[np.argmin(soles_y)])
    floor = float(X[floor_id, 1])
    al, ar = int(spec.acromion[0]), int(spec.acromion[1])
    for name, vid in (("height_cm", spec.top), ("waist_height_cm", spec.navel), ("inseam_cm", spec.crotch),
                      ("acromion_height", al)):
        if name in want:
            out[row[name]] = X[vid, 1] - floor
            if g is not None:
                g.add(row[name], np.array([vid, floor_id]), _UP_DOWN)

    # biacromial breadth: straight distance between the acromia
    if "shoulder_width_cm" in want:
        d = X[al] - X[ar]
        ln = float(np.linalg.norm(d))
        out[row["shoulder_width_cm"]] = ln
        if g is not None:
            g.add(row["shoulder_width_cm"], np.array([al, ar]), np.stack([d / ln, -d / ln]))

    # sleeve outseam: acromion -> radiale -> stylion
    if "arm_length_cm" in want:
        chain = [al, spec.elbow, spec.wrist]
        total = 0.0
        for p, q in zip(chain[:-1], chain[1:]):
            d = X[q] - X[p]
            ln = float(np.linalg.norm(d))
            total += ln
            if g is not None:
                g.add(row["arm_length_cm"], np.array([q, p]), np.stack([d / ln, -d / ln]))
        out[row["arm_length_cm"]] = total

    # weight = volume x density
    rho = DENSITY[gender]
    if "weight_kg" not in want or not len(spec.faces):
        vol = 0.0  # not asked, or a restricted spec: no surface, no weight
    elif g is not None:
        vol, gv = volume(X, spec.faces, grad=True)
        used = spec.volume_vertices
        g.add(row["weight_kg"], used, rho * gv[used])
    else:
        vol = volume(X, spec.faces)
    out[row["weight_kg"]] = rho * vol

    def section(girth: str, edges, normal, offset, offset_grad, extents: dict[str, int]) -> dict:
        """One girth and its extents (name -> plane axis), those of them wanted, into ``out``."""
        extents = {k: (axis, 0) for k, axis in extents.items() if k in want}
        if girth not in want and not extents:
            return {}
        rows = {k: row[k] for k in extents}
        if girth in want:
            rows["girth"] = row[girth]
        r = _girth(g, rows, X, edges, normal, offset, offset_grad, extents)
        for k in rows:
            out[rows[k]] = r.get(k, 0.0)
        return r

    # chest: horizontal section at nipple level (mean of both nipples)
    nip = spec.nipples
    section("chest_cm", spec.chest_edges, Y, float(X[nip, 1].mean()), (nip, np.tile([0, 0.5, 0], (len(nip), 1))),
            {"chest_breadth": 0, "chest_depth": 1})
    # waist: horizontal at the omphalion
    section("waist_cm", spec.waist_edges, Y, float(X[spec.navel, 1]),
            (np.array([spec.navel]), np.array([[0, 1.0, 0]])), {"waist_breadth": 0, "waist_depth": 1})
    # hip (buttock circumference): crotch + f (navel - crotch)
    f = HIP_LEVEL_FRACTION
    lvl = (1 - f) * X[spec.crotch, 1] + f * X[spec.navel, 1]
    section("hip_cm", spec.hip_edges, Y, float(lvl),
            (np.array([spec.crotch, spec.navel]), np.array([[0, 1 - f, 0], [0, f, 0]])), {"hip_breadth": 0})
    if not {"thigh_cm", "calf_cm"} & want:
        return (out, g.matrix()) if jacobian else out

    # thigh: plane perpendicular to the left hip-knee axis through the axis at crotch height.
    # The plane moves with the joints (regressed from vertices) and the crotch: full chain rule.
    J = np.asarray(spec.joint_regressor @ X)
    ih, ik, ia = (spec.joint_ids[k] for k in ("hip", "knee", "ankle"))
    hip, knee, ankle = J[ih], J[ik], J[ia]
    u = hip - knee
    lu = float(np.linalg.norm(u))
    nrm = u / lu
    cy = X[spec.crotch, 1]
    s = (cy - knee[1]) / (hip[1] - knee[1])
    origin = knee + s * u
    r = section("thigh_cm", spec.thigh_edges, nrm, float(nrm @ origin), None, {})
    if g is not None and "d_offset" in r:
        d_off, d_n = r["d_offset"], r["d_normal"]
        g_o = d_off * nrm  # offset = n . origin
        g_n = d_n + d_off * origin
        g_u = (g_n - nrm * (nrm @ g_n)) / lu + s * g_o  # through n = u / |u| and origin
        dy = hip[1] - knee[1]
        ey = np.array([0.0, 1.0, 0.0])
        gu_o = float(g_o @ u)
        g_hip = g_u + gu_o * (-s / dy) * ey
        g_knee = -g_u + g_o + gu_o * ((cy - hip[1]) / dy**2) * ey
        g.add(row["thigh_cm"], np.array([spec.crotch]), (gu_o / dy * ey)[None])
        jr = spec.joint_regressor
        for jid, gj in ((ih, g_hip), (ik, g_knee)):
            lo, hi = jr.indptr[jid], jr.indptr[jid + 1]
            g.add(row["thigh_cm"], jr.indices[lo:hi], jr.data[lo:hi, None] * gj[None])

    # calf: the largest of horizontal sections 15-55 % down the shin. Levels are ranked by
    # a support-function estimate of their hull perimeters, the best few measured exactly (no
    # gradient through the choice of level: the max is locally one section).
    if "calf_cm" in want:
        levels = knee[1] + CALF_FRACTIONS * (ankle[1] - knee[1])
        ranked = _rank_levels(X, spec.calf_edges, levels)
        best = max((_hull_section(X, spec.calf_edges, Y, float(lv), grad=g is not None)
                    for lv in levels[ranked[:CALF_EXACT_CANDIDATES]]), key=lambda sec: sec.perimeter)
        if g is not None:
            _girth(g, {"girth": row["calf_cm"]}, X, spec.calf_edges, Y, 0.0, None, section=best)
        out[row["calf_cm"]] = best.perimeter

    return (out, g.matrix()) if jacobian else out


_ROW = {name: i for i, name in enumerate(RAW_NAMES)}
_UP_DOWN = np.array([[0, 1.0, 0], [0, -1.0, 0]])  # d height / d (vertex, floor vertex)


def to_api_units(raw: np.ndarray, gender: str) -> dict[str, float | str]:
    """Raw measurement vector (metres, kg) -> the 12 API attributes (cm, kg)."""
    res: dict[str, float | str] = {"gender": gender}
    for i, name in enumerate(ATTRIBUTES[1:]):
        res[name] = float(raw[i]) if name == "weight_kg" else float(raw[i]) * 100.0
    return res


def api_scale(name: str) -> float:
    """Multiplier from raw units (m, kg) to API units (cm, kg)."""
    return 1.0 if name == "weight_kg" else 100.0


def measure_attributes(spec: MeasurementSpec, vertices: np.ndarray, gender: str) -> dict:
    """The 12 API attributes of an avatar (cm, kg)."""
    return to_api_units(measure(spec, vertices, gender, extras=False), gender)


@dataclass(frozen=True)
class AttributeSpec:
    """One biometric attribute. ``min``/``max`` is the accepted range (population range plus a
    margin); ``unit`` is ``"cm"``, ``"kg"`` or ``None`` for the categorical ``gender``."""

    name: str
    unit: str | None
    min: float | None
    max: float | None
    ansur_column: str
    description: str


def attribute_specs(ranges: dict[str, list[float]]) -> list[AttributeSpec]:
    """AttributeSpec list from the artifact's accepted ranges (API units)."""
    specs = []
    for name in ATTRIBUTES:
        if name == "gender":
            specs.append(AttributeSpec(name, None, None, None, ANSUR_COLUMNS[name], DESCRIPTIONS[name]))
        else:
            lo, hi = ranges[name]
            unit = "kg" if name == "weight_kg" else "cm"
            specs.append(AttributeSpec(name, unit, float(lo), float(hi), ANSUR_COLUMNS[name],
                                       DESCRIPTIONS[name]))
    return specs


def dumps_meta(meta: dict) -> str:
    return json.dumps(meta, sort_keys=True)


# -- volume as a polynomial of the shape weights ---------------------------------------------
@dataclass(frozen=True)
class VolumePolynomial:
    """The enclosed volume of ``mean + sum_k w_k components_k`` as a polynomial of w (K,):

        vol(w) = constant + linear . w + w^T quadratic w + cubic[w_n, w_n, w_n]

    with w_n the first n weights. ``volume`` is sum a . (b x c) / 6 over the faces, a cubic
    form of the vertices, so with n = K this is exact; the cubic terms dropped with n < K
    (components of small variance) are worth grams (n = 20 of 76: at most ~0.05 kg over the
    population). Arrays float64: linear (K,), quadratic (K, K) and cubic (n, n, n) symmetric."""

    constant: float
    linear: np.ndarray
    quadratic: np.ndarray
    cubic: np.ndarray

    @classmethod
    def fit(cls, mean: np.ndarray, components: np.ndarray, faces: np.ndarray, n_cubic: int,
            chunk: int = 2048) -> "VolumePolynomial":
        """mean: (V, 3); components: (K, V, 3); faces: (F, 3) of the closed surface. Each term
        of a . (b x c) with a, b, c = mean + components . w, summed face block by face block;
        cubic terms of the first ``n_cubic`` components only."""
        K, n = len(components), n_cubic
        const, lin = 0.0, np.zeros(K)
        quad, cubic = np.zeros((K, K)), np.zeros((n, n * n))
        for s in range(0, len(faces), chunk):
            f = faces[s:s + chunk]
            ma, mb, mc = (np.asarray(mean[f[:, k]], np.float64) for k in range(3))  # (B, 3)
            Ua, Ub, Uc = (np.asarray(components[:, f[:, k]], np.float64) for k in range(3))  # (K, B, 3)
            const += float(np.einsum("ij,ij->", ma, np.cross(mb, mc)))
            lin += (Ua.reshape(K, -1) @ np.cross(mb, mc).reshape(-1) + Ub.reshape(K, -1) @ np.cross(mc, ma).reshape(-1)
                    + Uc.reshape(K, -1) @ np.cross(ma, mb).reshape(-1))
            # w_i w_j terms: ma . (Ub_i x Uc_j) + Ua_i . (mb x Uc_j) + Ua_i . (Ub_j x mc)
            quad += Ub.reshape(K, -1) @ np.cross(Uc, ma).reshape(K, -1).T
            quad += Ua.reshape(K, -1) @ (np.cross(mb, Uc) + np.cross(Ub, mc)).reshape(K, -1).T
            # w_i w_j w_l terms: Ua_i . (Ub_j x Uc_l)
            B = len(f)
            for x, (y, z) in enumerate(((1, 2), (2, 0), (0, 1))):
                by, bz = Ub[:n, :, y].T[:, :, None], Ub[:n, :, z].T[:, :, None]  # (B, n, 1)
                cy, cz = Uc[:n, :, y].T[:, None, :], Uc[:n, :, z].T[:, None, :]  # (B, 1, n)
                cubic += Ua[:n, :, x] @ (by * cz - bz * cy).reshape(B, n * n)
        cubic = cubic.reshape(n, n, n)
        cubic = sum(cubic.transpose(p) for p in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)))
        return cls(const / 6, lin / 6, (quad + quad.T) / 12, cubic / 36)

    def __call__(self, w: np.ndarray) -> tuple[float, np.ndarray]:
        """(volume m^3, d volume / d w (K,)) at weights w (K,)."""
        w = np.asarray(w, np.float64)
        n = len(self.cubic)
        Tww = (self.cubic @ w[:n]) @ w[:n]
        Qw = self.quadratic @ w
        grad = self.linear + 2 * Qw
        grad[:n] += 3 * Tww
        return float(self.constant + self.linear @ w + Qw @ w + Tww @ w[:n]), grad


# -- slow, obvious reference (tests and benchmarks) ----------------------------------------
def _region_mesh(spec: MeasurementSpec, vertices: np.ndarray, edges: np.ndarray):
    """trimesh of the body faces whose three vertices all belong to ``edges``' vertices."""
    import trimesh

    keep = np.zeros(len(vertices), bool)
    keep[np.unique(edges)] = True
    faces = spec.faces[keep[spec.faces].all(axis=1)]
    return trimesh.Trimesh(vertices, faces, process=False)


def _reference_girth(mesh, normal: np.ndarray, origin: np.ndarray) -> float:
    from trimesh.intersections import mesh_plane

    seg = mesh_plane(mesh, plane_normal=normal, plane_origin=origin)
    if len(seg) == 0:
        return 0.0
    e1, e2 = _plane_basis(normal / np.linalg.norm(normal))
    pts = seg.reshape(-1, 3)
    p2 = np.stack([pts @ e1, pts @ e2], axis=1)
    h = ConvexHull(p2)
    q = p2[h.vertices]
    return float(np.linalg.norm(np.roll(q, -1, axis=0) - q, axis=1).sum())


def reference_measure(spec: MeasurementSpec, vertices: np.ndarray, gender: str) -> np.ndarray:
    """The raw measurements by plane slicing with trimesh (``mesh_plane``) and trimesh's mesh
    volume: independent of the edge bookkeeping and Jacobians of ``measure``. Slow."""
    import trimesh

    X = np.asarray(vertices, np.float64)
    out = measure(spec, X, gender)  # lengths and heights: same one-line definitions
    row = {n: i for i, n in enumerate(RAW_NAMES)}
    body = trimesh.Trimesh(X, spec.faces, process=False)
    out[row["weight_kg"]] = DENSITY[gender] * float(body.volume)
    torso = _region_mesh(spec, X, spec.torso_edges)
    out[row["chest_cm"]] = _reference_girth(torso, Y, np.array([0, X[spec.nipples, 1].mean(), 0]))
    out[row["waist_cm"]] = _reference_girth(torso, Y, np.array([0, X[spec.navel, 1], 0]))
    f = HIP_LEVEL_FRACTION
    lvl = (1 - f) * X[spec.crotch, 1] + f * X[spec.navel, 1]
    out[row["hip_cm"]] = _reference_girth(_region_mesh(spec, X, spec.hip_edges), Y, np.array([0, lvl, 0]))
    J = np.asarray(spec.joint_regressor @ X)
    hip, knee, ankle = (J[spec.joint_ids[k]] for k in ("hip", "knee", "ankle"))
    nrm = (hip - knee) / np.linalg.norm(hip - knee)
    s = (X[spec.crotch, 1] - knee[1]) / (hip[1] - knee[1])
    out[row["thigh_cm"]] = _reference_girth(_region_mesh(spec, X, spec.thigh_edges), nrm, knee + s * (hip - knee))
    calf = _region_mesh(spec, X, spec.calf_edges)
    out[row["calf_cm"]] = max(
        _reference_girth(calf, Y, np.array([0, knee[1] + fr * (ankle[1] - knee[1]), 0]))
        for fr in CALF_FRACTIONS
    )
    return out

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
class _Grad:
    """Accumulates d(measurement)/d(vertices) as sparse (row, vertex, axis, value) triplets."""

    def __init__(self, n_rows: int, n_vertices: int):
        self.n_rows, self.n_vertices = n_rows, n_vertices
        self.rows: list[np.ndarray] = []
        self.cols: list[np.ndarray] = []
        self.vals: list[np.ndarray] = []

    def add(self, row: int, vids: np.ndarray, grads: np.ndarray) -> None:
        """vids: (n,) vertex ids; grads: (n, 3) d(row)/d(vertex)."""
        vids = np.asarray(vids, np.int64).reshape(-1)
        grads = np.asarray(grads, np.float64).reshape(-1, 3)
        cols = (vids[:, None] * 3 + np.arange(3)).reshape(-1)
        self.rows.append(np.full(cols.shape, row, np.int64))
        self.cols.append(cols)
        self.vals.append(grads.reshape(-1))

    def matrix(self) -> sp.csr_matrix:
        """(n_rows, 3 V) CSR, duplicates summed."""
        if not self.rows:
            return sp.csr_matrix((self.n_rows, 3 * self.n_vertices))
        return sp.csr_matrix(
            (np.concatenate(self.vals), (np.concatenate(self.rows), np.concatenate(self.cols))),
            shape=(self.n_rows, 3 * self.n_vertices),
        )


def plane_section(
    vertices: np.ndarray, edges: np.ndarray, normal: np.ndarray, offset: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Points where candidate mesh edges cross the plane ``normal . x = offset``.

    vertices: (V, 3); edges: (E, 2); normal: (3,) unit. Returns (points (n, 3), edge ids
    (n, 2), t (n,), sa (n,), sb (n,)) for the n crossing edges, point = a + t (b - a),
    sa/sb the signed distances of the endpoints."""
    a = vertices[edges[:, 0]]
    b = vertices[edges[:, 1]]
    sa = a @ normal - offset
    sb = b @ normal - offset
    # a vertex on the plane counts (t = 0 or 1): landmarks often define the plane
    cross = ((sa * sb) <= 0) & ((sa != 0) | (sb != 0))
    a, b, sa, sb = a[cross], b[cross], sa[cross], sb[cross]
    t = sa / (sa - sb)
    pts = a + t[:, None] * (b - a)
    return pts, edges[cross], t, sa, sb


def _plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to ``normal`` (e1 close to +X)."""
    ref = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    e1 = ref - normal * (ref @ normal)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(normal, e1)
    return e1, e2


def hull_perimeter(points2d: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Perimeter of the convex hull of 2-D points (how a tape lies).

    points2d: (n, 2). Returns (perimeter, hull vertex ids (h,), d perimeter / d hull vertex
    (h, 2))."""
    if len(points2d) < 3:
        return 0.0, np.zeros(0, np.int64), np.zeros((0, 2))
    try:
        hv = ConvexHull(points2d).vertices
    except QhullError:
        return 0.0, np.zeros(0, np.int64), np.zeros((0, 2))
    q = points2d[hv]
    nxt = np.roll(q, -1, axis=0) - q
    ln = np.linalg.norm(nxt, axis=1)
    u = nxt / np.maximum(ln, 1e-12)[:, None]
    grad = np.roll(u, 1, axis=0) - u  # d|q_{j}-q_{j-1}| + d|q_{j+1}-q_j|
    return float(ln.sum()), hv, grad


def _section_grad(
    g: _Grad, row: int, g3: np.ndarray, e: np.ndarray, t: np.ndarray, sa: np.ndarray,
    sb: np.ndarray, a: np.ndarray, b: np.ndarray, normal: np.ndarray,
    offset_grad: tuple[np.ndarray, np.ndarray] | None,
) -> tuple[float, np.ndarray]:
    """Chain rule from d(measure)/d(section points) ``g3`` (n, 3) to the edge endpoints and,
    through the plane offset, to the landmark vertices that define it.

    Returns (d measure / d offset, d measure / d normal (3,)) for callers whose plane itself
    depends on the vertices (the thigh)."""
    denom = sa - sb
    gab = np.einsum("ij,ij->i", g3, b - a)
    g.add(row, e[:, 0], (1 - t)[:, None] * g3 + (gab * (-sb) / denom**2)[:, None] * normal)
    g.add(row, e[:, 1], t[:, None] * g3 + (gab * sa / denom**2)[:, None] * normal)
    d_off = float(np.sum(-gab / denom))
    d_n = (((gab / denom**2)[:, None]) * (-sb[:, None] * a + sa[:, None] * b)).sum(axis=0)
    if offset_grad is not None:
        vids, coeffs = offset_grad
        g.add(row, vids, d_off * coeffs)
    return d_off, d_n


def _girth(
    g: _Grad | None, rows: dict[str, int], vertices: np.ndarray, edges: np.ndarray,
    normal: np.ndarray, offset: float, offset_grad, extent_rows: dict[str, tuple[int, int]] | None = None,
) -> dict[str, float]:
    """Girth (and optional extents along the plane axes) of one plane section."""
    pts, e, t, sa, sb = plane_section(vertices, edges, normal, offset)
    e1, e2 = _plane_basis(normal)
    p2 = np.stack([pts @ e1, pts @ e2], axis=1)
    per, hv, hgrad = hull_perimeter(p2)
    out = {"girth": per}
    a, b = vertices[e[:, 0]], vertices[e[:, 1]]
    if g is not None and len(hv):
        g3 = hgrad[:, :1] * e1 + hgrad[:, 1:] * e2
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
    a, b = vertices[edges[:, 0]], vertices[edges[:, 1]]
    sa = a[:, 1:2] - levels[None, :]  # (E, L)
    sb = b[:, 1:2] - levels[None, :]
    cross = ((sa * sb) <= 0) & ((sa != 0) | (sb != 0))
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(cross, sa / (sa - sb), 0.0)
    px = a[:, None, 0] + t * (b[:, None, 0] - a[:, None, 0])
    pz = a[:, None, 2] + t * (b[:, None, 2] - a[:, None, 2])
    proj = px[..., None] * _DIRS[:, 0] + pz[..., None] * _DIRS[:, 1]  # (E, L, D)
    proj = np.where(cross[..., None], proj, -np.inf)
    est = proj.max(axis=0).sum(axis=1)  # (L,) proportional to perimeter
    return np.argsort(-est)


def volume(vertices: np.ndarray, faces: np.ndarray, grad: bool = False):
    """Enclosed volume (m^3) of a closed triangle surface; with ``grad`` also d vol / d
    vertices (V, 3) (only rows of vertices used by ``faces`` are non-zero)."""
    a, b, c = vertices[faces[:, 0]], vertices[faces[:, 1]], vertices[faces[:, 2]]
    bc = np.cross(b, c)
    vol = float(np.einsum("ij,ij->", a, bc)) / 6.0
    if not grad:
        return vol
    gv = np.zeros_like(vertices, dtype=np.float64)
    for k, cr in ((0, bc), (1, np.cross(c, a)), (2, np.cross(a, b))):
        for ax in range(3):
            gv[:, ax] += np.bincount(faces[:, k], weights=cr[:, ax], minlength=len(vertices))
    return vol, gv / 6.0


# -- the measurements ----------------------------------------------------------------------
Y = np.array([0.0, 1.0, 0.0])


def measure(
    spec: MeasurementSpec, vertices: np.ndarray, gender: str, jacobian: bool = False
):
    """Raw measurements of one avatar.

    vertices: (V, 3) metres. Returns values (len(RAW_NAMES),) float64 in metres (weight in
    kg); with ``jacobian`` also d values / d vertices as CSR (len(RAW_NAMES), 3 V)."""
    X = np.asarray(vertices, np.float64)
    n = len(RAW_NAMES)
    row = {name: i for i, name in enumerate(RAW_NAMES)}
    g = _Grad(n, len(X)) if jacobian else None
    out = np.zeros(n)

    soles_y = X[spec.soles, 1]
    floor_id = int(spec.soles[np.argmin(soles_y)])
    floor = float(X[floor_id, 1])

    def height_of(name: str, vid: int) -> None:
        out[row[name]] = X[vid, 1] - floor
        if g is not None:
            g.add(row[name], np.array([vid, floor_id]), np.array([[0, 1.0, 0], [0, -1.0, 0]]))

    height_of("height_cm", spec.top)
    height_of("waist_height_cm", spec.navel)
    height_of("inseam_cm", spec.crotch)
    al, ar = int(spec.acromion[0]), int(spec.acromion[1])
    height_of("acromion_height", al)

    # biacromial breadth: straight distance between the acromia
    d = X[al] - X[ar]
    ln = float(np.linalg.norm(d))
    out[row["shoulder_width_cm"]] = ln
    if g is not None:
        g.add(row["shoulder_width_cm"], np.array([al, ar]), np.stack([d / ln, -d / ln]))

    # sleeve outseam: acromion -> radiale -> stylion
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
    if g is not None:
        vol, gv = volume(X, spec.faces, grad=True)
        used = spec.volume_vertices
        g.add(row["weight_kg"], used, rho * gv[used])
    else:
        vol = volume(X, spec.faces)
    out[row["weight_kg"]] = rho * vol

    # chest: horizontal section at nipple level (mean of both nipples)
    nip = spec.nipples
    r = _girth(g, {"girth": row["chest_cm"], "chest_breadth": row["chest_breadth"],
                   "chest_depth": row["chest_depth"]}, X, spec.chest_edges, Y,
               float(X[nip, 1].mean()),
               (nip, np.tile([0, 0.5, 0], (len(nip), 1))),
               {"chest_breadth": (0, 0), "chest_depth": (1, 0)})
    out[row["chest_cm"]] = r["girth"]
    out[row["chest_breadth"]] = r.get("chest_breadth", 0.0)
    out[row["chest_depth"]] = r.get("chest_depth", 0.0)

    # waist: horizontal at the omphalion
    r = _girth(g, {"girth": row["waist_cm"], "waist_breadth": row["waist_breadth"],
                   "waist_depth": row["waist_depth"]}, X, spec.waist_edges, Y,
               float(X[spec.navel, 1]), (np.array([spec.navel]), np.array([[0, 1.0, 0]])),
               {"waist_breadth": (0, 0), "waist_depth": (1, 0)})
    out[row["waist_cm"]] = r["girth"]
    out[row["waist_breadth"]] = r.get("waist_breadth", 0.0)
    out[row["waist_depth"]] = r.get("waist_depth", 0.0)

    # hip (buttock circumference): crotch + f (navel - crotch)
    f = HIP_LEVEL_FRACTION
    lvl = (1 - f) * X[spec.crotch, 1] + f * X[spec.navel, 1]
    r = _girth(g, {"girth": row["hip_cm"], "hip_breadth": row["hip_breadth"]}, X,
               spec.hip_edges, Y, float(lvl),
               (np.array([spec.crotch, spec.navel]), np.array([[0, 1 - f, 0], [0, f, 0]])),
               {"hip_breadth": (0, 0)})
    out[row["hip_cm"]] = r["girth"]
    out[row["hip_breadth"]] = r.get("hip_breadth", 0.0)

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
    r = _girth(g, {"girth": row["thigh_cm"]}, X, spec.thigh_edges, nrm, float(nrm @ origin), None)
    out[row["thigh_cm"]] = r["girth"]
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
    levels = knee[1] + CALF_FRACTIONS * (ankle[1] - knee[1])
    ranked = _rank_levels(X, spec.calf_edges, levels)
    best, best_level = -1.0, None
    for lv in levels[ranked[:CALF_EXACT_CANDIDATES]]:
        per = _girth(None, {}, X, spec.calf_edges, Y, float(lv), None)["girth"]
        if per > best:
            best, best_level = per, lv
    if g is not None and best_level is not None:
        _girth(g, {"girth": row["calf_cm"]}, X, spec.calf_edges, Y, float(best_level), None)
    out[row["calf_cm"]] = best

    if jacobian:
        return out, g.matrix()
    return out


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
    return to_api_units(measure(spec, vertices, gender), gender)


def attribute_specs(ranges: dict[str, list[float]]):
    """AttributeSpec list from the artifact's accepted ranges (API units)."""
    from service.model.body import AttributeSpec

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

"""Quasi-static cloth drape by projective dynamics (Bouaziz et al., "Projective Dynamics: Fusing
Constraint Projections for Fast Simulation", SIGGRAPH 2014; "PD" below).

The garment's rest shape (edge lengths, angles, curvature as uploaded) is its size. The energy

    E(x) = sum_t  k_s A_t / 2 ||F_t(x) - R_t||^2               in-plane stretch and shear (PD Sec. 5, Eq. 13: triangle strain)
         + sum_i  B / (2 A_i) ||(L x)_i - h0_i n_i(x)||^2      bending against the rest mean curvature (PD Sec. 5, Eq. 15)
         - sum_i  m_i g . x_i                                  gravity
         + sum_k  w_k / 2 ||(T x)_k - h_k n_k(x)||^2           layer ties (where pieces of cloth lie on each other)

is minimised subject to a strain limit (no edge longer than the fabric's stretch limit allows:
Provot, "Deformation constraints in a mass-spring model to describe rigid cloth behavior", GI
1995, edges shortened after each step), one-sided body contact (every vertex at least
``clearance`` outside the body), Coulomb friction against the body and vertex-vertex
self-contact. F_t is the deformation gradient of triangle t (3 x 2, against its rest frame),
R_t its closest rotation, L the rest cotangent Laplacian, h0_i the rest signed mean-curvature
magnitude, n_i the current vertex normal, m_i = rho A_i. A layer tie k (``layer_ties``) holds
a vertex of one piece of cloth to its closest point on another piece at rest, (T x)_k being the
vertex's offset from that point (barycentric in the anchor face), n_k the anchor face's normal
and h_k the offset's height along it, kept on its rest side and at least its rest gap: the
layers may part, not slide along each other (PD's projection onto a set that moves with x, as
the bending's).

Static equilibrium is reached by proximal local/global iterations: each iteration adds
w_i / 2 ||x_i - x_i^k||^2 with w_i = m_i / h^2 (an implicit Euler step with all velocity damped,
PD Eq. 8-9 without momentum; h smaller at the fabric's stiffness than in the soft levels:
``Config.final_step_s``), so the global matrix

    K = sum_t k_s A_t G_t^T G_t + L^T diag(B / A_i) L + diag(m_i / h^2)          (PD Eq. 10)

depends on the garment only and is factored once (``geometry.solvers.factor_spd``: CHOLMOD
where scikit-sparse is installed, else SuperLU) and reused for every body and every iteration.
A fixed point is a stationary point of E alone (the proximal term vanishes there). PD's fixed
matrix is as stiff against rotations as against stretch, so stiff cloth that has to turn
converges slowly: the membrane stiffness is continued from soft to the fabric's (one factor per
level), and solves without a body are Anderson-accelerated (Peng et al. 2018). With a body the
softest level runs without friction and every soft level with part of the cloth's weight: the
warp fit it starts from is made to measure (stretched on a body larger than the garment,
compressed on a smaller one), and there the cloth lets that go and finds its place on the body
before friction holds it. Contact and
friction are position projections after each global step (the strain limit first, then
self-contact, then the body; Macklin et al., "Unified Particle Physics for Real-Time
Applications", 2014, Sec. 6.1 friction: tangential displacement cancelled up to mu times the
penetration depth). An optional first stage (``Config.release_iterations``, off by default)
runs at the fabric's stiffness without friction or gravity, so that a start made to measure (the
warp fit, stretched on a body larger than the garment) lets go of that stretch before friction
holds the cloth where it lies (a vertex whose move there would make its face cross another part
of the cloth goes back where it was). Where the settled cloth still crosses itself (two layers pressed together
between an arm and the torso), the crossing is smoothed out locally (``geometry.untangle``) and
the body contact applied again; before that, the strain limit and the body contact in turn for a
few rounds (the contact passes pull edges long in the crease between arm and torso), then the
vertices left inside a crease moved out against closest points found afresh
(``Config.outside_passes``). Where the body faces itself across a narrow gap (an armpit) the
clearance shrinks to what leaves room for a layer on each side (:func:`body_room`,
``Config.narrow_min_clearance_m``). A solve that
still ends inside the body (a size too small for the body, pulled into the armpits once the soft
levels let go of its start) runs again with friction and the full weight at every level
(``Config.fallbacks``).

Shapes: rest and current vertices (N, 3) metres, Y up; faces (F, 3) int; body (B, 3), (G, 3).
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.geometry import kernels, mesh as geometry
from service.model.geometry.solvers import factor_spd

from .fabrics import Fabric, fabric as _fabric

GRAVITY_M_S2 = 9.81  # standard gravity
FACE_CONTACT_MIN_COS = 0.5  # body-vertex / cloth-face contact only where both rest on skin facing within 60 degrees
FACE_CONTACT_MAX_LATERAL_M = 0.004  # ... and where the cloth point is within this of the body vertex's normal line
TIE_MIN_COS = 0.8  # layers lie along each other: a tied vertex's normal within ~37 degrees of its anchor face's (either
# way), and the offset between them along both
TIE_MIN_PATCH = 4  # ... over a patch of at least this many neighbouring vertices (fewer: a touch, not a layer)
COMPILED = True  # the local step and the strain limit in compiled loops (geometry.kernels) where numba is there


class DrapeError(ValueError):
    """The garment cannot be draped: a degenerate rest shape, or the solve cannot settle."""


class _InsideError(DrapeError):
    """The settled cloth ends inside the body (:meth:`Draper.solve` may try again)."""


@dataclass(frozen=True)
class Config:
    """Solver settings (SI units)."""
    clearance_m: float = 0.0005  # cloth rests this far outside the body surface (the hoop figure allows ~c / R) ...
    narrow_min_clearance_m: float | None = 0.002  # ... or less where the body faces itself across a gap narrower than
    # two clearances and the self-contact's (an armpit, between heavy thighs): there half of what the self-contact leaves
    # of the gap, at least this (`body_room`); at full clearance the layers on either side (a sleeve on the arm, the side
    # panel on the torso) are pushed into each other and cross. None: the clearance everywhere
    max_inside_m: float = 0.001  # a result with any vertex deeper than this inside the body fails
    step_s: float = 0.01  # proximal step h: the weight m / h^2 that ties an iteration to the last
    final_step_s: float | None = 0.002  # ... at the fabric's stiffness (None: step_s). The contact projection after each
    # step moves the cloth back along the body's normals, not to the constrained minimum: a small step keeps the
    # global step near the body, so the projection corrects little and the fixed points are nearer the energy's
    # resting states. A step moves free cloth g h^2 (0.04 mm at 2 ms): the soft levels hang and slide it. Chosen
    # by measurement against Newton (docs/drape.md, "Where the two drapes differ")
    anderson: int = 5  # Anderson acceleration history (0: plain PD iterations)
    anderson_energy_slack_j: float = 1e-9  # an accelerated point raising the energy more than this is refused
    stiffness_levels: tuple[float, ...] = (1e-3, 1e-2, 1e-1, 1.0)  # membrane stiffness continuation (last: the fabric)
    level_floor_drop_m: float = 1.0  # the softest level still holds this drop of cloth within its stretch limit
    level_tolerance_factor: float = 10.0  # the soft levels stop at this multiple of the tolerance
    limit_passes: int = 2  # strain-limit passes over the over-stretched edges per iteration
    max_iterations: int = 400
    tolerance_m: float = 2e-6  # settled: the largest move in an iteration below this (m) ...
    settle_window: int = 5  # ... for this many consecutive iterations
    friction_gain: float = 10.0  # the penetration of one step read as this many steps' normal force
    max_step_m: float = 0.01  # no vertex moves farther than this in one iteration
    contact_refresh: int = 50  # closest body points of every vertex every this many iterations ...
    contact_near_m: float = 0.02  # ... and in between of those that may be this close to the body ...
    contact_moved_m: float = 0.002  # ... and have moved more than this since their last refresh (a tangent plane 2 mm
    # away is off a body of radius R by (2 mm)^2 / 2R: 0.04 mm on a 5 cm limb) ...
    contact_walk_m: float = 0.005  # ... by a walk from their last closest face if they moved less than this, else afresh
    contact_k: int = 8  # nearest body vertices whose faces are searched for the closest point
    overlap_min_vertices: int = 5000  # garments this large run the local step in a thread while the closest points
    # are searched (2 cores; the 11k-vertex T-shirt 0.1-0.4 s faster of ~4.5 s, the 810-vertex one 0.31 -> 0.33-0.37 s
    # slower from the thread hand-offs)
    face_contact_m: float = 0.008  # body vertices this close to a settled garment's face are pushed out of it (0: off) ...
    face_contact_passes: int = 3  # ... in this many passes
    self_contact_m: float = 0.003  # garment vertices of distant parts kept at least this far apart
    self_rings: int = 2  # vertices within this many edges of each other never self-collide
    self_refresh: int = 10  # the self-contact's close pairs found afresh every this many iterations
    release_iterations: int = 0  # with a body, first this many (at most max_iterations / 8) at the fabric's stiffness
    # without friction or gravity: a start made to measure (the warp fit, stretched on a body larger than the garment)
    # lets go of that stretch before friction holds the cloth where it lies; without gravity nothing that friction alone
    # holds up slides down meanwhile. Off by default: it makes drapes less repeatable (the same drape from a start
    # moved by 2 mm ended 5.8 mm apart instead of 2.4 with friction at every stiffness level: docs/drape.md)
    frictionless_levels: int = 1  # with a body, the softest this many stiffness levels run without friction ...
    soft_gravity_power: float = 0.5  # ... and each level below the fabric's carries level ** this of the cloth's
    # weight: there the cloth lets go of the made-to-measure start's stretch and compression before friction holds it.
    # Chosen by measurement on the men's T-shirt and 5 people against Newton (docs/drape.md, "The soft levels"):
    # powers 0 / 0.5 / 1 put its hem up to 4.2 / 0.6 / 1.3 cm from Newton's (friction at every level: 3.3 cm)
    fallbacks: tuple[tuple[int, float], ...] = ((0, 0.0),)  # (frictionless_levels, soft_gravity_power) of the solves
    # tried, in turn, after one that ends inside the body (Draper.solve): with friction and the full weight at every
    # level a size too small for the body stays about where its start put it instead of being pulled into a crease
    # (docs/drape.md); (): none
    release_guard_rounds: int = 8  # in that stage, vertices of faces that newly cross another part of the cloth go back
    # to where they were, and their neighbours too, over up to this many widening rounds (0: no guard)
    final_limit_rounds: int = 20  # the strain limit and the body contact in turn up to this many times before the
    # untangling (and once in each of its rounds): the contact passes after the iterations pull edges long in creases
    outside_passes: int = 4  # before the untangling, the closest points of every vertex found afresh and those inside
    # moved out, up to this many times (0: off)
    untangle_rounds: int = 40  # the settled cloth's self-intersections smoothed out in up to this many rounds (0: off)
    gravity: tuple[float, float, float] = (0.0, -GRAVITY_M_S2, 0.0)
    diverge_m: float = 1.0  # a vertex moving farther than this from its start: the solve diverged
    part_max_extent_m: float = 0.05  # a connected piece of the garment no larger than this (a button, a buckle, a
    # label) does not drape: it rides on the cloth nearest to it at the start (its vertices keep their place in that
    # cloth's faces' frames), or, farther than `part_attach_m` from any, stays where the start put it on the body;
    # draped it would fall, held by nothing (its thread is not in the mesh)
    part_attach_m: float = 0.05
    tie_m: float = 0.01  # a vertex lying within this of another layer of the cloth at rest (another piece: a bib over
    # a shirt; or its own piece far along the cloth: a placket, a folded collar; `layer_ties`) is tied to its closest
    # point there: it may part from that layer but not slide along it (the friction between layers that holds them
    # where they lie together; 0: off) ...
    tie_stiffness: float = 1.0  # ... with this multiple of the membrane's stiffness at the vertex (k_s A_i / l_i^2)
    min_face_area_m2: float = 1e-10  # a rest face smaller than this is degenerate
    proxy_max_vertices: int | None = 8000  # a garment with more vertices is draped as a simulation mesh of about this
    # many and carried on it (`proxy`: a pattern tool's 44k-vertex export takes 18-20 s a drape on 2 cores); None: never


@dataclass
class DrapeResult:
    """The garment at static equilibrium: vertices (N, 3) float32 and solver statistics."""
    vertices: np.ndarray
    stats: dict[str, Any] = field(default_factory=dict)


# -- rest-shape operators ------------------------------------------------------------------------

def _check_rest(rest: np.ndarray, faces: np.ndarray, cfg: Config) -> None:
    if rest.ndim != 2 or rest.shape[1] != 3 or not len(rest):
        raise DrapeError(f"rest vertices must be (N, 3); got {rest.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces):
        raise DrapeError(f"faces must be (F, 3); got {faces.shape}")
    if not np.all(np.isfinite(rest)):
        raise DrapeError("the garment's rest shape has non-finite vertex positions")
    if faces.min() < 0 or faces.max() >= len(rest):
        raise DrapeError(f"faces index vertices outside 0..{len(rest) - 1}")
    tri = rest[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    bad = np.flatnonzero(area < cfg.min_face_area_m2)
    if len(bad):
        raise DrapeError(f"the garment has {len(bad)} zero-area faces (e.g. face {int(bad[0])}: area "
                         f"{area[bad[0]]:.2e} m2); remove or repair them before uploading")
    _, counts = geometry.edge_counts(faces)
    if (counts > 2).any():
        raise DrapeError(f"the garment has {int((counts > 2).sum())} non-manifold edges (shared by more than two "
                         "faces); cloth needs each edge on at most two faces")
    used = np.zeros(len(rest), bool)
    used[faces.reshape(-1)] = True
    if not used.all():
        raise DrapeError(f"{int((~used).sum())} garment vertices are on no face")


def _strain_operator(rest: np.ndarray, faces: np.ndarray) -> tuple[sp.csr_matrix, np.ndarray, np.ndarray]:
    """G (2T, N): rows 2t and 2t+1 give the two columns of triangle t's deformation gradient
    F_t = [x1 - x0, x2 - x0] D_t^-1 (D_t: the rest edges in the triangle's own 2D frame), the
    rest areas A_t (T,), and G's entries per triangle C (T, 3 vertices, 2 columns)."""
    tri = rest[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    n = np.cross(e1, e2)
    area = 0.5 * np.linalg.norm(n, axis=1)
    u = e1 / np.linalg.norm(e1, axis=1, keepdims=True)
    v = np.cross(n / (2 * area[:, None]), u)
    Dm = np.stack([np.stack([(e1 * u).sum(1), (e2 * u).sum(1)], 1),
                   np.stack([(e1 * v).sum(1), (e2 * v).sum(1)], 1)], 1)  # (T, 2, 2), columns = edges
    Dinv = np.linalg.inv(Dm)
    E = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    C = np.einsum("kj,tjl->tkl", E, Dinv)  # (T, 3 vertices, 2 columns)
    T = len(faces)
    rows = (2 * np.arange(T)[:, None, None] + np.arange(2)[None, None, :]).repeat(3, axis=1)
    cols = np.broadcast_to(faces[:, :, None], (T, 3, 2))
    G = sp.csr_matrix((C.reshape(-1), (rows.reshape(-1), cols.reshape(-1))), shape=(2 * T, len(rest)))
    return G, area, np.ascontiguousarray(C)


def _cotangent_laplacian(rest: np.ndarray, faces: np.ndarray) -> sp.csr_matrix:
    """(N, N) cotangent Laplacian, (L x)_i = sum_j (cot a_ij + cot b_ij) / 2 (x_i - x_j) = 2 A_i H_i n_i
    (Meyer et al. 2003, Eq. 8)."""
    N = len(rest)
    I, J, W = [], [], []
    for a, b, c in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):  # the angle at c faces edge (a, b)
        pa, pb, pc = rest[faces[:, a]], rest[faces[:, b]], rest[faces[:, c]]
        u, v = pa - pc, pb - pc
        cot = (u * v).sum(1) / np.maximum(np.linalg.norm(np.cross(u, v), axis=1), 1e-30)
        I += [faces[:, a], faces[:, b]]
        J += [faces[:, b], faces[:, a]]
        W += [0.5 * cot, 0.5 * cot]
    Wm = sp.csr_matrix((np.concatenate(W), (np.concatenate(I), np.concatenate(J))), shape=(N, N))
    return (sp.diags(np.asarray(Wm.sum(axis=1)).ravel()) - Wm).tocsr()


def _normals(x: np.ndarray, faces: np.ndarray, incidence: sp.csr_matrix) -> np.ndarray:
    """Area-weighted unit vertex normals (N, 3) float64."""
    fn = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    acc = incidence @ fn
    return acc / np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-30)


def _scatter_add(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """(n, 3): the sum of the rows of ``values`` (K, 3) at each of their ``index`` (K,)."""
    return np.stack([np.bincount(index, values[:, c], minlength=n) for c in range(3)], axis=1)


def _polar(Fm: np.ndarray) -> np.ndarray:
    """The closest rotations (T, 3, 2) (orthonormal columns, U V^T of the thin SVD) to
    deformation gradients (T, 3, 2), in closed form: R = F (F^T F)^(-1/2), the 2 x 2 square root
    sqrt(C) = (C + sqrt(det C) I) / sqrt(tr C + 2 sqrt(det C)) (~20x faster than batched SVD)."""
    a, b = Fm[:, :, 0], Fm[:, :, 1]
    c00, c01, c11 = (a * a).sum(1), (a * b).sum(1), (b * b).sum(1)
    det = np.maximum(c00 * c11 - c01 * c01, 0.0)
    s = np.sqrt(det)
    t = np.sqrt(np.maximum(c00 + c11 + 2 * s, 1e-300))
    # (C + s I)^-1 * t
    m00, m01, m11 = c00 + s, c01, c11 + s
    inv_det = t / np.maximum(m00 * m11 - m01 * m01, 1e-300)
    i00, i01, i11 = m11 * inv_det, -m01 * inv_det, m00 * inv_det
    R = np.empty_like(Fm)
    R[:, :, 0] = a * i00[:, None] + b * i01[:, None]
    R[:, :, 1] = a * i01[:, None] + b * i11[:, None]
    return R


# -- the solver -----------------------------------------------------------------------------------

class Draper:
    """A garment's drape system, factored once (:func:`precompute`); :meth:`solve` per body."""

    def __init__(self, rest: np.ndarray, faces: np.ndarray, fab: Fabric, cfg: Config, pinned: np.ndarray):
        t0 = time.perf_counter()
        self.rest, self.faces, self.fabric, self.config = rest, faces, fab, cfg
        N = len(rest)
        self.n = N
        G, area, self.C = _strain_operator(rest, faces)
        self.G, self.area = G, area
        self.vertex_area = np.bincount(faces.reshape(-1), np.repeat(area / 3.0, 3), minlength=N)
        self.mass = fab.density_kg_per_m2 * self.vertex_area  # (N,) kg, lumped
        ks = fab.stretch_stiffness_n_per_m
        self.w_triangle = ks * area  # (T,) membrane weight of each triangle (of each of its gradient's columns)
        self.w_stretch = np.repeat(self.w_triangle, 2)  # (2T,) per gradient column
        self.edges = geometry.mesh_edges(faces)
        self.edge_rest = np.linalg.norm(rest[self.edges[:, 0]] - rest[self.edges[:, 1]], axis=1)
        self.edge_max = self.edge_rest * (1.0 + fab.stretch_limit_pct / 100.0)
        L = _cotangent_laplacian(rest, faces)
        self.incidence = sp.csr_matrix((np.ones(faces.size), (faces.reshape(-1), np.repeat(np.arange(len(faces)), 3))),
                                       shape=(N, len(faces)))
        interior = ~geometry.boundary_vertices(faces, N)
        nrest = _normals(rest, faces, self.incidence)
        self.h0 = np.where(interior, ((L @ rest) * nrest).sum(1), 0.0)  # signed rest curvature, 2 A_i H_i
        self.w_bend = np.where(interior, fab.bending_stiffness_nm / self.vertex_area, 0.0)
        self.L = L
        self.pinned = pinned
        free = np.ones(N, bool)
        free[pinned] = False
        self.free = np.flatnonzero(free)
        self._pin_mask = ~free
        self.parts, host = small_parts(rest, faces, cfg.part_max_extent_m)
        self.cloth_faces = faces[host]  # (H, 3) the faces the parts ride on (all faces without parts)
        self.part_face = np.ones(len(faces), bool)  # (F,) True on the parts' faces
        self.part_face[host] = False
        # layer ties: T (K, N) gives each tied vertex's offset from its anchor point on the other layer
        self.tie_vertex, self.tie_face, self.tie_bary = layer_ties(rest, self.cloth_faces, cfg.tie_m)
        K_ties = len(self.tie_vertex)
        cols = np.concatenate([self.tie_vertex[:, None], self.tie_face], axis=1)  # (K, 4)
        vals = np.concatenate([np.ones((K_ties, 1)), -self.tie_bary], axis=1)
        self.T = sp.csr_matrix((vals.ravel(), (np.repeat(np.arange(K_ties), 4), cols.ravel())), shape=(K_ties, N))
        mean_edge = np.bincount(self.edges.ravel(), np.repeat(self.edge_rest, 2), minlength=N) / np.maximum(
            np.bincount(self.edges.ravel(), minlength=N), 1)
        iv = self.tie_vertex
        # each tied vertex's signed height over its anchor face at rest (its side of the other layer), at most
        # the self-contact's gap
        d0, n0 = self._tie_offsets(rest)
        h0 = (d0 * n0).sum(1)
        self.tie_gap = np.where(h0 >= 0, 1.0, -1.0) * np.minimum(np.abs(h0), cfg.self_contact_m)  # (K,) m
        self.w_tie = cfg.tie_stiffness * ks * self.vertex_area[iv] / np.maximum(mean_edge[iv], 1e-6) ** 2  # (K,) N/m
        Ks = (G.T @ sp.diags(self.w_stretch) @ G).tocsr()
        Kr = (L.T @ sp.diags(self.w_bend) @ L + self.T.T @ sp.diags(self.w_tie) @ self.T).tocsr()
        # stiffness continuation: one factor per level (the membrane scaled by `level`, PD's
        # matrix with the same bending and proximal terms); the soft levels let the cloth turn
        # and hang (PD's fixed matrix is as stiff against rotations as against stretch), the last
        # is the fabric itself
        # no level so soft that the cloth's own weight would stretch a 1 m drop past its limit
        floor = fab.density_kg_per_m2 * GRAVITY_M_S2 * cfg.level_floor_drop_m / (
            fab.stretch_stiffness_n_per_m * fab.stretch_limit_pct / 100.0)
        levels = sorted({min(max(lv, floor), 1.0) for lv in cfg.stiffness_levels} | {1.0})
        self.levels = []
        self.level_prox = []  # (N,) each level's proximal weight m / h^2 (its step h: `final_step_s` at the fabric's)
        for level in levels:
            h = cfg.final_step_s if (level == 1.0 and cfg.final_step_s) else cfg.step_s
            self.level_prox.append(self.mass / h ** 2)
            K = (level * Ks + Kr + sp.diags(self.level_prox[-1])).tocsr()
            K_fp = K[self.free][:, pinned] if len(pinned) else None
            # friction: Coulomb's |f_t| <= mu |f_n| with both forces read from the correction
            # (Macklin et al. 2014 Sec. 6.1): a slide up to mu times the penetration is cancelled.
            # One proximal step resolves only part of the normal force (the rest of the hoop
            # tension comes over the next steps), hence `friction_gain`
            slide = np.full(N, fab.friction * cfg.friction_gain)
            # simplicial: its back-substitution of 3 right-hand sides, once per iteration, is ~2x the
            # supernodal one's speed at garment sizes (10k vertices: 4.2 vs 8.0 ms)
            self.levels.append((float(level), factor_spd(K[self.free][:, self.free], mode="simplicial"), K_fp, slide))
        self.factor = self.levels[-1][1]
        self._no_slide = np.zeros(N)
        self.gravity_force = self.mass[:, None] * np.asarray(cfg.gravity, np.float64)[None, :]
        # self-contact exclusions: vertex pairs within `self_rings` edges (always close in any drape)
        A = (self.incidence @ self.incidence.T).astype(bool).astype(np.int32)
        near = A
        for _ in range(cfg.self_rings - 1):
            near = (near @ A).astype(bool).astype(np.int32)
        self.near = near.tocsr()
        self.near.sort_indices()
        self._near_rows = (self.near.indptr.astype(np.int64), self.near.indices.astype(np.int64))  # close_pairs
        self.precompute_s = time.perf_counter() - t0

    # energy and gradient (for references and diagnostics) ------------------------------------
    def _residuals(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The energy's residuals at x (N, 3): membrane (2T, 3) F_t - R_t by gradient column,
        bending (N, 3) (L x)_i - h0_i n_i, layer ties (K, 3)."""
        Gx = (self.G @ x).reshape(-1, 2, 3).transpose(0, 2, 1)
        r_s = (Gx - _polar(Gx)).transpose(0, 2, 1).reshape(-1, 3)
        n = _normals(x, self.faces, self.incidence)
        r_b = self.L @ x - self.h0[:, None] * n
        d, p = self._tie_projection(x)
        return r_s, r_b, d - p

    def energy_terms(self, x: np.ndarray) -> dict[str, float]:
        """The terms of E(x) (J) at x (N, 3): ``membrane`` (in-plane stretch and shear against
        the rest shape), ``bending``, ``ties`` and ``gravity`` (the potential, -sum m_i g . x_i);
        e.g. to compare drapes of the same garment from different solvers under one energy."""
        x = np.asarray(x, np.float64)
        return self._terms(x, *self._residuals(x))

    def _terms(self, x: np.ndarray, r_s: np.ndarray, r_b: np.ndarray, r_t: np.ndarray) -> dict[str, float]:
        return {"membrane": float(0.5 * (self.w_stretch * (r_s ** 2).sum(1)).sum()),
                "bending": float(0.5 * (self.w_bend * (r_b ** 2).sum(1)).sum()),
                "ties": float(0.5 * (self.w_tie * (r_t ** 2).sum(1)).sum()),
                "gravity": float(-(self.gravity_force * x).sum())}

    def energy(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """E(x) (J) and its gradient (N, 3) without contact and strain limit (the PD energy the solver minimises;
        the projections are minimisers, so their derivative terms vanish: PD Sec. 3)."""
        r_s, r_b, r_t = self._residuals(x)
        e = sum(self._terms(x, r_s, r_b, r_t).values())
        g = (self.G.T @ (self.w_stretch[:, None] * r_s)
             + self.L.T @ (self.w_bend[:, None] * r_b) + self.T.T @ (self.w_tie[:, None] * r_t) - self.gravity_force)
        return float(e), g

    def principal_stretches(self, x: np.ndarray) -> np.ndarray:
        """(T, 2) each triangle's principal stretches at x (N, 3), largest first: the singular
        values of its deformation gradient F_t against the rest shape (1: at rest; below 1:
        compressed in-plane, which cloth does not sustain: it buckles instead)."""
        F = (self.G @ np.asarray(x, np.float64)).reshape(-1, 2, 3)  # (T, 2 columns, 3)
        c00, c01, c11 = (F[:, 0] ** 2).sum(1), (F[:, 0] * F[:, 1]).sum(1), (F[:, 1] ** 2).sum(1)
        half_tr, det = 0.5 * (c00 + c11), c00 * c11 - c01 ** 2
        root = np.sqrt(np.maximum(half_tr ** 2 - det, 0.0))  # the eigenvalues of F^T F: half_tr +- root
        return np.sqrt(np.maximum(np.stack([half_tr + root, half_tr - root], 1), 0.0))

    def _layer_clearance(self, body: "_Body", x: np.ndarray) -> np.ndarray:
        """(N,) m: each vertex's clearance off the body, ``Config.clearance_m`` plus, for a tied
        vertex of the outer layer at the start x (N, 3) (farther from the body than its anchor
        point), its gap over the inner one (:attr:`tie_gap`): the body contact does not press
        the outer layer into the inner one where both rest on the body."""
        out = np.full(self.n, self.config.clearance_m)
        if not len(self.tie_vertex):
            return out
        body.refresh(x)
        sd_vertex = body.signed_distance(x)[self.tie_vertex]
        anchor = (x[self.tie_face] * self.tie_bary[:, :, None]).sum(1)
        q, n, _ = body._query(anchor)
        outer = sd_vertex > ((anchor - q) * n).sum(1)
        out[self.tie_vertex[outer]] += np.abs(self.tie_gap[outer])
        return out

    def _tie_offsets(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The layer ties' offsets d = T x (K, 3) (each tied vertex from its anchor point on the
        other layer) and their anchor faces' unit normals (K, 3) at x (N, 3)."""
        t = x[self.tie_face]  # (K, 3 corners, 3)
        n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
        return self.T @ x, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)

    def _tie_projection(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The layer ties' offsets d (K, 3) (:meth:`_tie_offsets`) and their projections (K, 3)
        onto the anchor face's current normal line: the closest offsets that part the layers
        without sliding one along the other."""
        if not len(self.tie_vertex):
            return np.zeros((0, 3)), np.zeros((0, 3))
        d, n = self._tie_offsets(x)
        # on the side of the other layer it lies on at rest, at least as far off it (up to the self-contact's gap)
        side = np.sign(self.tie_gap)
        h = side * np.maximum(side * (d * n).sum(1), np.abs(self.tie_gap))
        return d, h[:, None] * n

    def _tie_rhs(self, x: np.ndarray, energy: bool) -> tuple[np.ndarray | float, float]:
        """The ties' share of the local step's right-hand side, T^T W p (N, 3) (0.0 without
        ties), and of the energy (J; NaN unless ``energy``)."""
        if not len(self.tie_vertex):
            return 0.0, 0.0
        d, p = self._tie_projection(x)
        e = 0.5 * float((self.w_tie * ((d - p) ** 2).sum(1)).sum()) if energy else np.nan
        return self.T.T @ (self.w_tie[:, None] * p), e

    def _local(self, x: np.ndarray, level: float = 1.0, gravity: float = 1.0,
               energy: bool = True) -> tuple[np.ndarray, float]:
        """The local step's projections folded into the global right-hand side (N, 3) (PD Eq. 10
        right side, without the proximal term), and the energy E(x) (J) from the same residuals
        (``gravity``: the share of the cloth's weight in both, 0: none; ``energy`` False: NaN
        instead of the energy, which only Anderson's safeguard reads: the bending residual's
        sparse product saved).
        With ``COMPILED`` (and numba there) the membrane and the normals in compiled loops
        (``geometry.kernels.membrane``, ``vertex_normals``: equal to ~1e-15 relative)."""
        if COMPILED and kernels.AVAILABLE:
            x = np.ascontiguousarray(x, np.float64)
            rhs = np.zeros((self.n, 3))
            e_s = kernels.membrane(x, self.faces, self.C, level * self.w_triangle, rhs)
            n = np.empty((self.n, 3))
            kernels.vertex_normals(x, self.faces, n)
            pb = self.h0[:, None] * n
            rhs += self.L.T @ (self.w_bend[:, None] * pb)
            r_t, e_t = self._tie_rhs(x, energy)
            rhs += r_t
            if not energy:
                return rhs + gravity * self.gravity_force, np.nan
            e = (e_s + 0.5 * float((self.w_bend * ((self.L @ x - pb) ** 2).sum(1)).sum()) + e_t
                 - float((self.gravity_force * x).sum()) * gravity)
            return rhs + gravity * self.gravity_force, e
        Gxr = self.G @ x  # (2T, 3)
        Gx = Gxr.reshape(-1, 2, 3).transpose(0, 2, 1)  # (T, 3, 2)
        R = _polar(Gx).transpose(0, 2, 1).reshape(-1, 3)
        ws = level * self.w_stretch
        rhs = self.G.T @ (ws[:, None] * R)
        n = _normals(x, self.faces, self.incidence)
        pb = self.h0[:, None] * n
        rhs += self.L.T @ (self.w_bend[:, None] * pb)
        r_t, e_t = self._tie_rhs(x, True)
        rhs += r_t
        e = (0.5 * float((ws * ((Gxr - R) ** 2).sum(1)).sum()) + e_t
             + 0.5 * float((self.w_bend * ((self.L @ x - pb) ** 2).sum(1)).sum())
             - float((self.gravity_force * x).sum()) * gravity)
        return rhs + gravity * self.gravity_force, e

    def _global(self, rhs: np.ndarray, x_pinned: np.ndarray, k: int) -> np.ndarray:
        """PD's global step with level ``k``'s factor (pinned vertices eliminated)."""
        _, factor, K_fp, _ = self.levels[k]
        if K_fp is None:
            return factor.solve(rhs)
        out = np.empty((self.n, 3))
        out[self.pinned] = x_pinned
        out[self.free] = factor.solve(rhs[self.free] - K_fp @ x_pinned)
        return out

    def solve(self, body_vertices: np.ndarray | None, body_faces: np.ndarray | None,
              init_vertices: np.ndarray, fallbacks: bool = True) -> DrapeResult:
        """The garment at static equilibrium on one body, from ``init_vertices`` (N, 3) (e.g. the
        warp fit; pinned vertices stay where they are there). ``body_vertices`` None: no body.
        Raises :class:`DrapeError` when it diverges or ends inside the body.

        A solve that ends inside the body (a size too small for it: the cloth let go of its
        made-to-measure start in the soft levels and was pulled into a crease) is solved again
        with the soft levels of each of ``Config.fallbacks`` in turn (friction and the full weight
        at every level: the cloth stays about where that start put it) until one ends outside;
        its stats say ``fallback`` (the soft levels it ran) and count every solve's time. Only
        then: drapes from the other soft levels rest differently, and a clothing basis fitted
        through a mix of both misses direct drapes by more (docs/drape.md). ``fallbacks`` False:
        none is tried (a build's population bodies, whose drapes that need one it leaves out)."""
        cfg = self.config
        t0 = time.perf_counter()
        own = (cfg.frictionless_levels, cfg.soft_gravity_power)
        failure: _InsideError | None = None
        for soft in [own] + [tuple(f) for f in cfg.fallbacks if fallbacks and tuple(f) != own]:
            try:
                r = self._solve(body_vertices, body_faces, init_vertices, *soft)
            except _InsideError as exc:
                failure = failure or exc
                continue
            if soft != own:
                r.stats.update(fallback={"frictionless_levels": soft[0], "soft_gravity_power": soft[1]},
                               seconds=time.perf_counter() - t0)
            return r
        raise failure

    def _solve(self, body_vertices: np.ndarray | None, body_faces: np.ndarray | None, init_vertices: np.ndarray,
               frictionless_levels: int, soft_gravity_power: float) -> DrapeResult:
        """:meth:`solve` with the soft levels' friction and weight given (``Config``'s
        ``frictionless_levels`` and ``soft_gravity_power``)."""
        t0 = time.perf_counter()
        cfg, fab = self.config, self.fabric
        x = np.array(init_vertices, np.float64).reshape(-1, 3)
        if x.shape != (self.n, 3) or not np.all(np.isfinite(x)):
            raise DrapeError(f"the start shape must be {self.n} finite vertices (N, 3); got {x.shape}")
        start = x.copy()
        body = _Body(body_vertices, body_faces, cfg) if body_vertices is not None and len(body_vertices) else None
        x_pinned = x[self.pinned]
        if body is not None:
            body.clearance = self._layer_clearance(body, x)
            x = body.outside(x)
        parts = _PartBinding.of(x, self.cloth_faces, self.parts, body is not None, cfg.part_attach_m)
        moves: list[float] = []
        it = 0
        n_self = n_over = 0
        t_local = t_global = t_contact = 0.0
        restarts = 0
        settled_run = 0
        n_levels = len(self.levels)
        # Anderson's extrapolation fights the contact projections (it re-enters the body and
        # undoes friction): used for solves without a body (pinned sheets) only
        anderson = cfg.anderson > 0 and body is None
        # the stages: (stiffness level index, friction per unit depth, iteration budget, share of
        # the cloth's weight); with a body, the softest levels without friction and every level
        # below the fabric's with part of the weight (`frictionless_levels`, `soft_gravity_power`);
        # with `release_iterations`, first a stage at the fabric's stiffness without friction or
        # gravity: the start's stretch retracts, nothing slides down
        soft = body is not None
        stages = [(k, self._no_slide if soft and k < min(frictionless_levels, n_levels - 1) else slide, None,
                   level ** soft_gravity_power if soft and k < n_levels - 1 else 1.0)
                  for k, (level, _, _, slide) in enumerate(self.levels)]
        if soft and cfg.release_iterations > 0:
            stages.insert(0, (n_levels - 1, self._no_slide, min(cfg.release_iterations, cfg.max_iterations // 8), 0.0))
        n_reverted = 0
        # with a body, the next step's local projections run in a thread while the body's closest
        # points of its start are searched (both in compiled loops that release the GIL)
        overlap = ThreadPoolExecutor(1) if (body is not None and not anderson
                                            and 0 < cfg.overlap_min_vertices <= self.n) else None
        searched = False  # the body's closest points of x already searched (by the last iteration)
        try:
            for stage, (k, slide, budget, gravity) in enumerate(stages):
                level = self.levels[k][0]
                last = stage == len(stages) - 1
                tol = cfg.tolerance_m * (1.0 if last else cfg.level_tolerance_factor)
                if budget is None:
                    budget = cfg.max_iterations - it if last else max(cfg.max_iterations // (2 * n_levels), 1)
                dF: list[np.ndarray] = []  # Anderson history: differences of residuals and of map values
                dG: list[np.ndarray] = []
                f_prev = g_prev = None
                settled_run = 0
                # the release stage retracts the cloth fast: a face that comes to cross another part
                # of it (a sleeve pressed through the side panel in an armpit) would stay crossed, so
                # its vertices are held back where they were (the crossings of the start are allowed)
                guard = gravity == 0 and cfg.release_guard_rounds > 0
                crossing0 = self._crossing_keys(x) if guard else None
                rhs, e_x = self._local(x, level, gravity, anderson)
                for _ in range(budget):
                    it += 1
                    # one fixed-point map g = G(x): local/global step, then the position projections
                    tb = time.perf_counter()
                    g = self._global(rhs + self.level_prox[k][:, None] * x, x_pinned, k)
                    tc = time.perf_counter()
                    # a trust region: no vertex jumps across a limb in one step
                    if COMPILED and kernels.AVAILABLE:
                        kernels.clamp_steps(g, x, cfg.max_step_m)
                    else:
                        step = np.linalg.norm(g - x, axis=1)
                        far = step > cfg.max_step_m
                        if far.any():
                            g[far] = x[far] + (g[far] - x[far]) * (cfg.max_step_m / step[far])[:, None]
                    n_over = self._strain_limit(g)
                    n_self = self._self_contact(g, refresh=(it - 1) % cfg.self_refresh == 0)
                    self._tie_contact(g)
                    if body is not None:
                        # tangent planes at the closest points of the (outside) start of the step
                        if not searched:
                            self._search_body(body, x, it)
                        searched = False
                        g, _ = body.project(g, x, slide)
                    if guard:
                        n_reverted += self._hold_back(g, x, crossing0)
                    if len(self.pinned):
                        g[self.pinned] = x_pinned
                    if parts is not None:
                        parts.place(g)
                    if anderson or not (COMPILED and kernels.AVAILABLE):
                        f = g - x
                        move = float(np.sqrt((f ** 2).sum(1).max()))
                    else:  # (the residual f is read by Anderson's extrapolation only)
                        f, move = None, float(kernels.max_move(g, x))
                    # Anderson acceleration of the fixed-point map (Peng et al., "Anderson Acceleration
                    # for Geometry Optimization and Physics Simulation", SIGGRAPH 2018, Alg. 1: an
                    # accelerated point that raises the energy is replaced by the plain step)
                    x_next = g
                    if anderson and f_prev is not None:
                        dF.append((f - f_prev).ravel())
                        dG.append((g - g_prev).ravel())
                        if len(dF) > cfg.anderson:
                            dF.pop(0)
                            dG.pop(0)
                        gamma = np.linalg.lstsq(np.stack(dF, 1), f.ravel(), rcond=None)[0]
                        x_next = g - (np.stack(dG, 1) @ gamma).reshape(-1, 3)
                        if body is not None:
                            x_next, _ = body.project(x_next, None, None)
                        if len(self.pinned):
                            x_next[self.pinned] = x_pinned
                        if parts is not None:
                            parts.place(x_next)
                    f_prev, g_prev = f, g
                    td = time.perf_counter()
                    t_contact += td - tc
                    t_global += tc - tb
                    if overlap is not None:
                        # the next step's local projections (compiled, without the GIL) in a thread
                        # while this one searches the body's closest points of its start
                        pending = overlap.submit(self._local, x_next, level, gravity, anderson)
                        self._search_body(body, x_next, it + 1)
                        rhs_next, e_next = pending.result()
                        searched = True
                    else:
                        rhs_next, e_next = self._local(x_next, level, gravity, anderson)
                    if x_next is not g and e_next > e_x + cfg.anderson_energy_slack_j:
                        x_next = g
                        rhs_next, e_next = self._local(g, level, gravity)
                        dF.clear()
                        dG.clear()
                        restarts += 1
                    rhs, e_x = rhs_next, e_next
                    t_local += time.perf_counter() - td
                    x = x_next
                    moves.append(move)
                    # (a vertex moves at most max_step_m an iteration with a body: its distance from the
                    # start is checked every 10th)
                    if not np.isfinite(move) or ((anderson or it % 10 == 0)
                                                 and float(np.sqrt(((x - start) ** 2).sum(1).max())) > cfg.diverge_m):
                        raise DrapeError(f"the drape diverged after {it} iterations (a vertex moved more than "
                                         f"{cfg.diverge_m:.2f} m): check the garment's scale (metres) and its rest shape")
                    settled_run = settled_run + 1 if move < tol else 0
                    if settled_run >= cfg.settle_window:
                        break
        finally:
            if overlap is not None:
                overlap.shutdown()
        settled = settled_run >= cfg.settle_window
        max_inside = 0.0
        if body is not None:
            body.refresh(x)
            x, _ = body.project(x, None, None)
            if cfg.face_contact_m > 0:
                # body details between the cloth's vertices (a nipple, a shoulder blade) pushed out
                # of the settled cloth, once: inside the iterations the pushes fight the membrane
                # and fold the cloth where an arm meets the torso
                body.refresh_faces(x, self.faces, cfg.face_contact_m)
                for _ in range(cfg.face_contact_passes):
                    if not body.push_faces(x, self.faces):
                        break
                # a face pushed along one body vertex's normal may tilt another of its vertices
                # into the body (in a concave fold: the armpit): the vertices outside again
                body.refresh(x)
                x, _ = body.project(x, None, None)
            # the contact passes above stretch the cloth where the arm meets the torso (both
            # sides pushed out, the edges between them pulled long): the strain limit and the
            # contact in turn, the contact last
            for _ in range(cfg.final_limit_rounds):
                if not self._strain_limit(x):
                    break
                body.refresh_near(x, cfg.contact_near_m, 0.0, cfg.contact_walk_m)
                x, _ = body.project(x, None, None)
        if body is not None:
            # in a crease (the crotch, an armpit) a vertex moved out of one surface along the normal of
            # a closest point found a while ago can end inside the other: closest points afresh for
            # every vertex and the vertices inside moved out, until none is
            for _ in range(cfg.outside_passes):
                if body.signed_distance(x, exact=True).min() >= 0:
                    break
                x, _ = body.project(x, None, None)
        tangled = self._untangle(x, body)
        part_crossings = 0
        if parts is not None:
            parts.place(x)
            # the parts' faces crossing the cloth (a button sewn through it, as the asset may have it at rest)
            part_crossings = int(self.part_face[geometry.intersecting_face_pairs(x, self.faces)].any(axis=1).sum())
        if body is not None:
            d = body.signed_distance(x, exact=True)
            max_inside = float(max(0.0, -d.min()))
            if max_inside > cfg.max_inside_m:
                raise _InsideError(f"the drape ends with garment vertices {1000 * max_inside:.1f} mm inside the body "
                                 f"(limit {1000 * cfg.max_inside_m:.1f} mm): the garment cannot be placed on it")
        e, _ = self.energy(x)
        stats = {"iterations": it, "settled": bool(settled), "last_move_mm": 1000 * moves[-1] if moves else 0.0,
                 "max_penetration_mm": 1000 * max_inside, "self_contact_pairs": int(n_self),
                 "over_limit_edges": int(n_over), "untangled_pairs": tangled[0], "self_intersections": tangled[1],
                 "small_parts": len(self.parts), "part_crossings": int(part_crossings),
                 "layer_ties": int(len(self.tie_vertex)),
                 "anderson_restarts": restarts, "held_back": n_reverted, "energy_j": e,
                 "seconds": time.perf_counter() - t0, "precompute_s": self.precompute_s, "local_s": t_local,
                 "global_s": t_global, "contact_s": t_contact, "factor": self.factor.backend, "levels": n_levels,
                 "fabric": fab.name}
        return DrapeResult(vertices=x.astype(np.float32), stats=stats)

    def _search_body(self, body: "_Body", x: np.ndarray, it: int) -> None:
        """The body's closest points of iteration ``it``'s start x (N, 3): of every vertex every
        ``contact_refresh`` iterations, in between of those near the body that moved."""
        cfg = self.config
        if (it - 1) % cfg.contact_refresh == 0:
            body.refresh(x)
        else:
            body.refresh_near(x, cfg.contact_near_m, cfg.contact_moved_m, cfg.contact_walk_m)

    def _crossing_keys(self, x: np.ndarray) -> np.ndarray:
        """The intersecting face pairs of ``x`` (N, 3) as sorted keys a * F + b (K,) int64."""
        P = np.sort(geometry.intersecting_face_pairs(x, self.faces), axis=1)
        return np.unique(P[:, 0] * len(self.faces) + P[:, 1])

    def _hold_back(self, g: np.ndarray, x: np.ndarray, allowed: np.ndarray) -> int:
        """Vertices of the faces of ``g`` (N, 3) that cross another face and did not in ``allowed``
        (keys, :meth:`_crossing_keys`) set back to ``x`` (N, 3), the region widened by one ring of
        neighbours each round until no new crossing is left (up to ``release_guard_rounds``;
        then every vertex goes back). In place; returns the vertices set back."""
        held = np.zeros(self.n, bool)
        for _ in range(self.config.release_guard_rounds):
            keys = self._crossing_keys(g)
            new = keys[~np.isin(keys, allowed)]
            if not len(new):
                return int(held.sum())
            faces = np.unique(np.concatenate([new // len(self.faces), new % len(self.faces)]))
            if held[self.faces[faces].ravel()].all():
                held |= (self.incidence @ (self.incidence.T @ held.astype(np.float64))) > 0
            held[self.faces[faces].ravel()] = True
            g[held] = x[held]
        g[:] = x
        return self.n

    def _untangle(self, x: np.ndarray, body: "_Body | None") -> tuple[int, int]:
        """The settled cloth's self-intersections (where its parts were pressed together, as the
        sleeve and the side panel in an armpit: the vertex-vertex self-contact does not hold
        faces apart) smoothed out locally (``geometry.untangle``; pinned vertices stay), the body
        contact applied after each round (it may push the layers into each other again). The
        small parts (:func:`small_parts`) are left out: they are placed after. In place; returns
        the intersecting face pairs of the cloth before and after."""
        cfg = self.config
        if cfg.untangle_rounds <= 0:
            return 0, 0
        cloth = self.cloth_faces
        pairs = geometry.intersecting_face_pairs(x, cloth)
        if not len(pairs):
            return 0, 0

        def contact(v: np.ndarray) -> np.ndarray:
            # the smoothing pulls edges long in the crease: the strain limit first, the contact last
            # (closest points searched again for the vertices that moved, as in the end rounds)
            self._strain_limit(v)
            body.refresh_near(v, cfg.contact_near_m, 0.0, cfg.contact_walk_m)
            return body.project(v, None, None)[0]

        x[:], left = geometry.untangle(x, cloth, cfg.untangle_rounds, keep=self._pin_mask,
                                       after=contact if body is not None else None, pairs=pairs)
        return len(pairs), left

    def _strain_limit(self, x: np.ndarray) -> int:
        """Edges longer than the fabric's stretch limit shortened to it, both ends moving
        (pinned ends not), averaged over each vertex's edges (Jacobi; Provot 1995). In place;
        returns the number of over-stretched edges of the first pass."""
        first = 0
        inv_mass = np.ones(self.n)
        inv_mass[self.pinned] = 0.0
        e = self.edges
        if COMPILED and kernels.AVAILABLE:
            acc, count = np.empty((self.n, 3)), np.empty(self.n)
            for k in range(self.config.limit_passes):
                n_over = kernels.strain_limit_pass(x, e, self.edge_max, inv_mass, acc, count)
                first = n_over if k == 0 else first
                if not n_over:
                    break
            return first
        for k in range(self.config.limit_passes):
            d = x[e[:, 1]] - x[e[:, 0]]
            length = np.linalg.norm(d, axis=1)
            over = np.flatnonzero(length > self.edge_max)
            if k == 0:
                first = len(over)
            if not len(over):
                break
            a, b = e[over, 0], e[over, 1]
            wa, wb = inv_mass[a], inv_mass[b]
            wsum = np.maximum(wa + wb, 1e-12)
            corr = ((length[over] - self.edge_max[over]) / length[over])[:, None] * d[over]
            ends = np.concatenate([a, b])
            acc = _scatter_add(ends, np.concatenate([(wa / wsum)[:, None] * corr, -(wb / wsum)[:, None] * corr]),
                               self.n)
            x += acc / np.maximum(np.bincount(ends, minlength=self.n), 1)[:, None]
        return first

    def _tie_contact(self, x: np.ndarray) -> int:
        """Tied vertices that came nearer to their anchor face than their rest gap (or through
        it) pushed back, half the vertex, half the anchor face's corners (by their barycentric
        weights), along the face normal (position-based, as the self-contact). In place; returns
        the ties pushed."""
        if not len(self.tie_vertex):
            return 0
        d, n = self._tie_offsets(x)
        side = np.sign(self.tie_gap)
        short = np.abs(self.tie_gap) - side * (d * n).sum(1)  # (K,) m: how far it is to be pushed
        k = np.flatnonzero(short > 0)
        if not len(k):
            return 0
        push = (0.5 * short[k] * side[k])[:, None] * n[k]
        b = self.tie_bary[k]
        wsum = (b ** 2).sum(1, keepdims=True)  # the anchor point moves by -push with the corners moved b_j / |b|^2
        idx = np.concatenate([self.tie_vertex[k], self.tie_face[k].ravel()])
        val = np.concatenate([push, (-(b / wsum)[:, :, None] * push[:, None, :]).reshape(-1, 3)])
        cnt = np.bincount(idx, minlength=self.n)
        x += _scatter_add(idx, val, self.n) / np.maximum(cnt, 1)[:, None]
        return len(k)

    def _self_contact(self, x: np.ndarray, refresh: bool) -> int:
        """Push apart garment vertices of distant parts (not within ``self_rings`` edges) that are
        closer than ``self_contact_m`` (or than they are at rest, if closer), half each along
        their separation (position-based, Macklin et al. 2014 Sec. 5). Pairs found on refresh."""
        r = self.config.self_contact_m
        if r <= 0:
            return 0
        if refresh or not hasattr(self, "_pairs"):
            if COMPILED and kernels.AVAILABLE:
                pairs = kernels.close_pairs(x, 1.5 * r, *self._near_rows)
            else:
                pairs = cKDTree(x).query_pairs(1.5 * r, output_type="ndarray")
                if len(pairs):
                    keep = np.asarray(self.near[pairs[:, 0], pairs[:, 1]]).ravel() == 0
                    pairs = pairs[keep]
            if len(pairs):
                rest_d = np.linalg.norm(self.rest[pairs[:, 0]] - self.rest[pairs[:, 1]], axis=1)
                self._pair_gap = np.minimum(r, 0.9 * rest_d)
            else:
                self._pair_gap = np.zeros(0)
            self._pairs = pairs
        pairs = self._pairs
        if not len(pairs):
            return 0
        i, j = pairs[:, 0], pairs[:, 1]
        d = x[j] - x[i]
        dist = np.linalg.norm(d, axis=1)
        close = dist < self._pair_gap
        if not close.any():
            return 0
        i, j, d, dist, gap = i[close], j[close], d[close], dist[close], self._pair_gap[close]
        u = d / np.maximum(dist, 1e-12)[:, None]
        push = 0.5 * (gap - dist)[:, None] * u
        x += _scatter_add(np.concatenate([i, j]), np.concatenate([-push, push]), len(x))
        return int(close.sum())


def small_parts(rest: np.ndarray, faces: np.ndarray, max_extent_m: float) -> tuple[list[np.ndarray], np.ndarray]:
    """The garment's (rest (N, 3), faces (F, 3)) connected pieces whose bounding box is at most
    ``max_extent_m`` on every side (buttons, buckles, labels), as vertex index arrays, and the
    indices (H,) of the faces of the other pieces (the cloth they ride on); ([], all faces) when
    every piece is that small (a garment of buttons drapes as cloth)."""
    label = geometry.vertex_components(faces, len(rest))
    used = np.unique(faces)
    small = []
    for c in np.unique(label[used]):
        ids = np.flatnonzero(label == c)
        if np.ptp(rest[ids], axis=0).max() <= max_extent_m:
            small.append(ids)
    host = ~np.isin(label[faces[:, 0]], [label[p[0]] for p in small])
    if not small or not host.any():
        return [], np.arange(len(faces))
    return small, np.flatnonzero(host)


def layer_ties(rest: np.ndarray, faces: np.ndarray, tie_m: float, apart_m: float | None = None,
               min_cos: float = TIE_MIN_COS, min_patch: int = TIE_MIN_PATCH) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the garment's cloth (rest (N, 3); ``faces`` (F, 3): the cloth's, without the small
    parts) lies on itself in layers: every vertex within ``tie_m`` of a face that lies along it
    (the face's normal within ``min_cos`` of the vertex's, either way, and the offset to it
    along both: across a gap, not beside the vertex on the same sheet) and belongs to another
    connected piece, or to its own piece but farther than ``apart_m`` (default 3 ``tie_m``)
    from it along the cloth (a lapel folded over the front it is cut from, a shirt front under
    a jacket sewn to it at the collar; not the two sides of a fold or a seam), with that face's
    closest point to it; only where such vertices make patches of ``min_patch`` or more (over
    the cloth's edges): a layer, not a touch. Returns the tied vertices (K,) int64, their anchor
    faces' vertices (K, 3) int64 and the anchor points' barycentric weights there (K, 3) float64
    (empty where nothing lies in layers, or ``tie_m`` 0)."""
    none = np.zeros(0, np.int64), np.zeros((0, 3), np.int64), np.zeros((0, 3))
    if tie_m <= 0 or not len(faces):
        return none
    from scipy.sparse.csgraph import connected_components, dijkstra

    apart = 3 * tie_m if apart_m is None else apart_m
    n = len(rest)
    label = geometry.vertex_components(faces, n)
    centre, fn, radius = geometry.face_bounds(rest, faces)
    vn = geometry.vertex_normals(rest, faces)
    used = np.unique(faces)
    # candidate (vertex, face) pairs: the faces whose bounding disks come within tie_m
    near = cKDTree(rest[used]).sparse_distance_matrix(cKDTree(centre), tie_m + float(radius.max()),
                                                       output_type="ndarray")
    vi, fi = used[near["i"]], near["j"].astype(np.int64)
    # a cheap bound first: the offset to the closest point runs along the face normal within min_cos only if the
    # vertex's projection onto the face's plane is within tan(acos(min_cos)) |h| of the face's disk (h: its height
    # over the plane); a face beside the vertex on the same sheet (h ~ 0) is not
    w = rest[vi] - centre[fi]
    h = np.abs(np.einsum("ij,ij->i", w, fn[fi]))
    lateral = np.sqrt(np.maximum(np.einsum("ij,ij->i", w, w) - h * h, 0.0))
    slope = np.sqrt(max(1.0 / min_cos ** 2 - 1.0, 0.0))
    keep = (h < tie_m) & (lateral - radius[fi] <= slope * h + 1e-12)
    vi, fi = vi[keep], fi[keep]
    keep = (faces[fi] != vi[:, None]).all(1) & (np.abs((vn[vi] * fn[fi]).sum(1)) >= min_cos)
    vi, fi = vi[keep], fi[keep]
    tri = rest[faces[fi]]
    q = geometry.closest_point_on_triangles(rest[vi], tri[:, 0], tri[:, 1], tri[:, 2])
    u = q - rest[vi]
    d = np.linalg.norm(u, axis=1)
    u /= np.maximum(d, 1e-12)[:, None]
    # ... across the gap between them (the offset along both normals), not beside the vertex on the same sheet
    keep = (d < tie_m) & (np.abs((u * vn[vi]).sum(1)) >= min_cos) & (np.abs((u * fn[fi]).sum(1)) >= min_cos)
    vi, fi, q, d = vi[keep], fi[keep], q[keep], d[keep]
    if not len(vi):
        return none
    same = label[vi] == label[faces[fi, 0]]
    edges = geometry.mesh_edges(faces)
    if same.any():
        # one piece's own layers: only faces farther than `apart` along the cloth (graph distance over the edges)
        graph = geometry.edge_length_graph(rest, faces)
        sources, inverse = np.unique(vi[same], return_inverse=True)
        close = np.zeros(int(same.sum()), bool)
        rows = np.flatnonzero(same)
        for start in range(0, len(sources), 256):  # 256 sources' distance rows at a time
            chunk = sources[start:start + 256]
            dist = dijkstra(graph, indices=chunk, limit=apart)
            sel = np.flatnonzero((inverse >= start) & (inverse < start + len(chunk)))
            close[sel] = np.isfinite(dist[(inverse[sel] - start)[:, None], faces[fi[rows[sel]]]]).any(1)
        keep = np.ones(len(vi), bool)
        keep[rows[close]] = False
        vi, fi, q, d = vi[keep], fi[keep], q[keep], d[keep]
    if not len(vi):
        return none
    order = np.lexsort((fi, d, vi))  # each vertex's nearest face first (of equals, the first face)
    first = np.ones(len(order), bool)
    first[1:] = vi[order][1:] != vi[order][:-1]
    pick = order[first]
    # layers are patches: a tied vertex whose tied neighbours (over the cloth's edges) make a patch of fewer than
    # `min_patch` vertices is a touch (a sleeve's underside on the side panel in the armpit), not a layer
    tied = np.zeros(n, bool)
    tied[vi[pick]] = True
    e = edges[tied[edges[:, 0]] & tied[edges[:, 1]]]
    _, comp = connected_components(sp.csr_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    size = np.bincount(comp[vi[pick]], minlength=n)
    pick = pick[size[comp[vi[pick]]] >= min_patch]
    if not len(pick):
        return none
    tri = rest[faces[fi[pick]]]
    bary = np.clip(geometry.barycentric(q[pick], tri[:, 0], tri[:, 1], tri[:, 2]), 0.0, 1.0)
    return vi[pick], faces[fi[pick]].astype(np.int64), bary / bary.sum(1, keepdims=True)


@dataclass
class _PartBinding:
    """Where a solve carries the garment's small parts (:func:`small_parts`): the vertices
    ``ride`` (K,) on the cloth faces ``face`` (K, 3) (vertex ids), at barycentric ``bary`` (K, 3)
    plus ``offset`` (K, 3) in the face's frame (edge, in-plane normal to it, face normal); the
    vertices ``stay`` (S,) at ``fixed`` (S, 3) (beside the body, away from any cloth)."""
    ride: np.ndarray
    face: np.ndarray
    bary: np.ndarray
    offset: np.ndarray
    stay: np.ndarray
    fixed: np.ndarray

    @classmethod
    def of(cls, x: np.ndarray, hf: np.ndarray, parts: list[np.ndarray], body: bool,
           attach_m: float) -> "_PartBinding | None":
        """The binding of the small ``parts`` at the start x (N, 3): each part rides on the cloth
        (faces ``hf`` (H, 3)) when its vertices are within ``attach_m`` of the cloth point
        nearest its centre (median; or when there is no body), else stays where it is. None
        without parts."""
        if not parts:
            return None
        hv, local = np.unique(hf, return_inverse=True)
        ids = np.concatenate(parts)
        # each part rigidly in the frame of the cloth face nearest to its centre (per vertex, the
        # faces under a button would shear it through the cloth when the cloth folds)
        centre = np.stack([x[p].mean(axis=0) for p in parts])
        fi, q, bary = geometry.closest_points_on_mesh(centre, x[hv], local.reshape(-1, 3))
        dist = np.array([np.median(np.linalg.norm(x[p] - qp, axis=1)) for p, qp in zip(parts, q)])
        per = np.repeat(np.arange(len(parts)), [len(p) for p in parts])  # (K,) the part of each vertex
        ride = ((not body) | (dist <= attach_m))[per]
        face = hf[fi[per[ride]]]
        offset = np.einsum("kij,kj->ki", geometry.face_frames(x, face), x[ids[ride]] - q[per[ride]])
        return cls(ids[ride], face, bary[per[ride]], offset, ids[~ride], x[ids[~ride]].copy())

    def place(self, x: np.ndarray) -> None:
        """Put the parts where the binding says on the cloth x (N, 3), in place."""
        if len(self.ride):
            q = np.einsum("kc,kcj->kj", self.bary, x[self.face])
            x[self.ride] = q + np.einsum("kij,ki->kj", geometry.face_frames(x, self.face), self.offset)
        if len(self.stay):
            x[self.stay] = self.fixed


class _Body:
    """A body's surface for contact: closest points by the project's kernels
    (``geometry.closest_points_on_mesh``), tangent planes cached between refreshes."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, cfg: Config):
        V = np.asarray(vertices, np.float64)
        F = np.asarray(faces, np.int64)
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or not np.all(np.isfinite(V)):
            raise DrapeError(f"the body must be finite (B, 3) vertices and (G, 3) faces; got {V.shape}, {F.shape}")
        self.V, self.F, self.cfg = V, F, cfg
        self.tree = cKDTree(V)
        self.vf = geometry.vertex_faces(F, len(V))
        self.bounds = geometry.face_bounds(V, F)
        inc = sp.csr_matrix((np.ones(F.size), (F.reshape(-1), np.repeat(np.arange(len(F)), 3))), shape=(len(V), len(F)))
        self.normals = _normals(V, F, inc)
        self.q = self.n = self.face = None
        self.clearance: np.ndarray | None = None  # (N,) m per garment vertex (None: cfg.clearance_m for every one) ...
        # ... at most the body's narrow-gap cap where the vertex's closest point is (`Config.narrow_min_clearance_m`):
        # per body vertex (B,) and per body face (G,) (the least of its vertices'), and per garment vertex (N,)
        self.vertex_cap = np.full(len(V), np.inf)
        if cfg.narrow_min_clearance_m is not None:
            room = body_room(V, self.normals, 2 * cfg.clearance_m + cfg.self_contact_m)
            self.vertex_cap = np.maximum(0.5 * (room - cfg.self_contact_m), cfg.narrow_min_clearance_m)
        self.face_cap = self.vertex_cap[F].min(axis=1)
        self.cap: np.ndarray | None = None
        self.face_pairs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # refresh_faces

    def refresh_faces(self, x: np.ndarray, faces: np.ndarray, near_m: float) -> None:
        """Body vertices within ``near_m`` of the garment (x (N, 3), faces (F, 3)) whose closest
        garment point lies inside a face (not on its edges: a body vertex beyond a hem or a
        cuff is not under the cloth): the pairs :meth:`push_faces` keeps apart."""
        d, _ = cKDTree(x).query(self.V, distance_upper_bound=near_m + 0.05)
        cand = np.flatnonzero(np.isfinite(d))
        self.face_pairs = None
        if not len(cand):
            return
        face, q, bary = geometry.closest_points_on_mesh(self.V[cand], x, faces, k=self.cfg.contact_k)
        dist = np.linalg.norm(q - self.V[cand], axis=1)
        keep = (dist < near_m) & (bary.min(axis=1) > 0.02)
        if keep.any():
            self.face_pairs = (cand[keep], face[keep], bary[keep])

    def push_faces(self, x: np.ndarray, faces: np.ndarray) -> int:
        """Body-vertex / cloth-face contact (the other half of two-way contact): where a body
        vertex is closer than ``clearance`` to the cloth point above it along its normal (or
        through the cloth: a nipple or a shoulder blade between garment vertices), the face's
        three vertices move out along that normal, each by its barycentric share (PBD's
        point-triangle constraint, Mueller et al. 2007 Sec. 4.4), the largest move per vertex.
        In place; returns the number of pairs pushed."""
        if self.face_pairs is None:
            return 0
        b, f, w = self.face_pairs
        p, n = self.V[b], self.normals[b]
        tri = faces[f]
        q = (x[tri] * w[:, :, None]).sum(1)
        depth = np.minimum(self.cfg.clearance_m, self.vertex_cap[b]) - ((q - p) * n).sum(1)
        # only cloth lying on the same skin: the face's vertices rest on body points facing the
        # same way (not an arm pressed against the side panel of a shirt, which would push the
        # panel into the torso and the torso push it back)
        same = (self.n[tri] * n[:, None, :]).sum(2).min(axis=1) > FACE_CONTACT_MIN_COS
        # ... and only the cloth right above the body vertex, along its normal
        d = q - p
        lateral = np.linalg.norm(d - (d * n).sum(1, keepdims=True) * n, axis=1)
        hit = (depth > 0) & same & (lateral < FACE_CONTACT_MAX_LATERAL_M)
        if not hit.any():
            return 0
        tri, w, n, depth = tri[hit], w[hit], n[hit], depth[hit]
        # the face point moves by depth when each vertex moves w_i depth / sum(w^2)
        amount = w * (depth / (w ** 2).sum(1))[:, None]  # (H, 3)
        move = np.zeros(len(x))
        np.maximum.at(move, tri.ravel(), amount.ravel())
        dirs = np.zeros((len(x), 3))
        best = amount >= move[tri] - 1e-15  # each vertex along the normal of its deepest pair
        dirs[tri[best]] = np.repeat(n[:, None, :], 3, axis=1)[best]
        x += move[:, None] * dirs
        return int(hit.sum())

    def refresh(self, x: np.ndarray) -> None:
        """Closest points and normals of every vertex of x (N, 3)."""
        self.q, self.n, self.face = self._query(x)
        self.reach = np.abs(((x - self.q) * self.n).sum(1))  # how far each may move before its plane is stale
        self.x_at = x.copy()
        self.cap = self.face_cap[self.face]

    def refresh_near(self, x: np.ndarray, near_m: float, moved_m: float, walk_m: float) -> None:
        """Refresh only the vertices that may be within ``near_m`` of the body (their distance
        at their last refresh minus how far they moved since: the others cannot reach it) and
        have moved more than ``moved_m`` since (a resting vertex keeps its plane). Those that
        moved less than ``walk_m`` search the faces around their last closest face's vertices
        (a walk on the surface, no nearest-vertex search); the others search afresh, as
        :meth:`refresh` does for every vertex."""
        moved = np.linalg.norm(x - self.x_at, axis=1)
        idx = np.flatnonzero((self.reach - moved < near_m) & (moved > moved_m))
        if not len(idx):
            return
        walk = moved[idx] < walk_m
        for sel, near in ((idx[walk], True), (idx[~walk], False)):
            if len(sel):
                q, n, face = self._query(x[sel], near=self.F[self.face[sel]] if near else None)
                self.q[sel], self.n[sel], self.face[sel] = q, n, face
                self.cap[sel] = self.face_cap[face]
                self.reach[sel] = np.abs(((x[sel] - q) * n).sum(1))
                self.x_at[sel] = x[sel]

    def _query(self, x: np.ndarray, near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest body points (P, 3), interpolated unit normals there (P, 3) and faces (P,) of x
        (P, 3); ``near``: candidate vertices (P, k) instead of the ``contact_k`` nearest."""
        face, q, bary = geometry.closest_points_on_mesh(x, self.V, self.F, k=self.cfg.contact_k, tree=self.tree,
                                                        vert_faces=self.vf, bounds=self.bounds, near=near)
        n = (self.normals[self.F[face]] * bary[:, :, None]).sum(1)
        return q, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30), face

    def outside(self, x: np.ndarray) -> np.ndarray:
        """x (N, 3) with every vertex within ``clearance`` of the body (or inside) moved out along
        the normal at its closest body point (a fresh search for every vertex)."""
        self.refresh(x)
        return self.project(x, None, None)[0]

    def signed_distance(self, x: np.ndarray, exact: bool = False) -> np.ndarray:
        if exact:
            self.refresh(x)
        return ((x - self.q) * self.n).sum(1)

    def project(self, x: np.ndarray, x_prev: np.ndarray | None, slide: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Vertices within their clearance (:attr:`clearance`, else ``cfg.clearance_m``) of the
        body (or inside) moved out along the surface normal; with ``x_prev``, their tangential
        move since then cancelled up to ``slide`` (N,) times the correction (Coulomb friction as in Macklin et al. 2014 Eq. 24-25, the ratio
        from the forces: :attr:`Draper.slide_per_depth`). Returns (x, contact mask)."""
        clearance = np.minimum(self.clearance if self.clearance is not None else self.cfg.clearance_m, self.cap)
        if COMPILED and kernels.AVAILABLE:
            out, c = np.empty((len(x), 3)), np.empty(len(x), np.bool_)
            friction = x_prev is not None and slide is not None
            if not kernels.contact_project(np.ascontiguousarray(x, np.float64), self.q, self.n, clearance,
                                           x_prev if friction else x, slide if friction else self.reach, friction,
                                           out, c):
                return x, c
            return out, c
        d = self.signed_distance(x)
        depth = clearance - d
        c = depth > 0
        if not c.any():
            return x, c
        x = x.copy()
        n = self.n[c]
        x[c] += depth[c, None] * n
        if x_prev is not None and slide is not None:
            dx = x[c] - x_prev[c]
            dt = dx - (dx * n).sum(1, keepdims=True) * n
            lt = np.linalg.norm(dt, axis=1)
            hold = slide[c] * depth[c]
            scale = np.where(lt <= hold, 1.0, hold / np.maximum(lt, 1e-30))
            x[c] -= scale[:, None] * dt
        return x, c


def body_room(vertices: np.ndarray, normals: np.ndarray, reach_m: float) -> np.ndarray:
    """(B,) m: for each body vertex (vertices (B, 3), unit normals (B, 3)), the room in front of
    it: the distance along its normal to the nearest other vertex of the body within a 45-degree
    cone about that normal whose normal faces back (dot < 0): the arm across an armpit from the
    torso, the other thigh. inf where there is none within ``reach_m``."""
    V = np.asarray(vertices, np.float64)
    n = np.asarray(normals, np.float64)
    room = np.full(len(V), np.inf)
    pairs = cKDTree(V).query_pairs(reach_m, output_type="ndarray")
    if len(pairs):  # facing pairs first (most neighbours lie on the same sheet, facing alike)
        pairs = pairs[np.einsum("ij,ij->i", n[pairs[:, 0]], n[pairs[:, 1]]) < 0]
    if not len(pairs):
        return room
    i = np.concatenate([pairs[:, 0], pairs[:, 1]])
    j = np.concatenate([pairs[:, 1], pairs[:, 0]])
    d = V[j] - V[i]
    t = np.einsum("ij,ij->i", d, n[i])
    ok = (t > 0) & (np.einsum("ij,ij->i", d, d) <= 2 * t * t)  # within 45 degrees of the normal
    np.minimum.at(room, i[ok], t[ok])
    return room


def start_outside(init_vertices: np.ndarray, body_vertices: np.ndarray, body_faces: np.ndarray,
                  config: Config | None = None) -> np.ndarray:
    """A drape's start (N, 3) as :meth:`Draper.solve` takes it: the vertices inside the body
    (B, 3), (G, 3) or within ``config.clearance_m`` of it moved out along the body's normal
    (N, 3) float64; e.g. for another solver started where this one starts."""
    cfg = config or Config()
    return _Body(body_vertices, body_faces, cfg).outside(np.array(init_vertices, np.float64).reshape(-1, 3))


def precompute(rest_vertices: np.ndarray, faces: np.ndarray, fabric: "str | Fabric" = "woven",
               config: Config | None = None, pinned: np.ndarray | None = None) -> Draper:
    """The drape system of one garment (rest shape (N, 3) m, faces (F, 3) int) in one fabric
    (a :data:`FABRICS` name or a :class:`Fabric`), factored once; ``pinned``: vertex indices
    held at their start positions in every solve. Raises :class:`DrapeError` on a degenerate
    rest shape. The garment as it is, however dense: the package's ``precompute``
    (``proxy.precompute``) drapes one over ``config.proxy_max_vertices`` through a simulation
    mesh."""
    cfg = config or Config()
    rest = np.asarray(rest_vertices, np.float64)
    F = np.asarray(faces)
    if not np.issubdtype(F.dtype, np.integer):
        raise DrapeError("faces must be integer vertex indices")
    F = F.astype(np.int64)
    _check_rest(rest, F, cfg)
    try:
        fab = _fabric(fabric)
    except ValueError as exc:
        raise DrapeError(str(exc)) from None
    pins = np.unique(np.asarray(pinned if pinned is not None else [], np.int64))
    if len(pins) and (pins.min() < 0 or pins.max() >= len(rest)):
        raise DrapeError("pinned vertex indices out of range")
    return Draper(rest, F, fab, cfg, pins)


def edge_strain(rest_vertices: np.ndarray, faces: np.ndarray, vertices: np.ndarray) -> np.ndarray:
    """Per-vertex stretch (N,): the mean over a vertex's edges of (length / rest length - 1);
    positive stretched, negative compressed (strain maps)."""
    rest = np.asarray(rest_vertices, np.float64)
    e = geometry.mesh_edges(np.asarray(faces))
    return geometry.vertex_mean_strain(vertices, e, np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1))

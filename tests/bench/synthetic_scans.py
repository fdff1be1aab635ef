"""Synthetic 3D scans of people with a known body: the ground truth of the fitting benchmark
(``tryon bench fitting``) and of its tests. Pure numpy/scipy/trimesh; tests and benchmarks only
(not part of the service package).

What :func:`make_scan` builds, in this order (every random choice comes from ``rng``, drawn in
a fixed order, so one seed gives the same person, pose, frame and garments whether clothed or
not):

1. **Body.** ``model.vertices(weights)`` (all 19,158 vertices, rest pose), measured with
   ``model.measure`` (the truth of the 12 attributes).
2. **Pose** (:func:`random_pose`): every bone but the root gets a uniformly random axis and an
   angle uniform in ``[0, max_pose_deg]``; the root gets a whole-body yaw uniform in
   [-180, 180) degrees (the fitter does not know the facing anyway) composed with a tilt of at
   most 10 degrees about a random horizontal axis (a standing person: a 45-degree root tilt
   would lay the body down). With ``anatomical=True`` a bone drawn outside the joint limits (a
   knee bent sideways) is drawn again until it is inside, and the thighs and shins are drawn
   again while the legs pass through each other (:func:`separate_legs`). The posed body is
   lifted so that its lowest vertex is at y = 0.
3. **Clothes** (``clothed=True``): a MakeHuman CC0 suit (one of the ``*suit*`` folders, of the
   body's gender when there is one), plus, with probability 1/2, shoes (40 %) or a fedora
   (10 %). Each garment is fitted in the rest pose with its ``.mhclo`` binding
   (``mhclo.Binding.fit`` on the full rest vertices), pushed out of the body as a try-on does
   (``garment.push_out``, 3 mm clearance), and posed with the body: a garment vertex moves
   with the blend, by its binding weights, of the skinning transforms of its three bound
   base-mesh vertices (helper geometry included), i.e. it is skinned like the body it is
   bound to. Head, hands and whatever skin the garments leave uncovered stay visible.
4. **Outer surface only.** A real scanner sees neither skin under a shirt nor the inside of a
   garment. A body face is dropped when (a) two of its three vertices are covered: the
   nearest garment surface sample q (normal n) is within 5 mm (contact, either side: posing
   can push skin through cloth), or within 4 cm with the cloth in front of the skin,
   ``(q - p) . n >= 0.5 |q - p|`` (which keeps the skin just past a cuff), or (b) a virtual
   scanner sees it without the clothes but not with them (legs under a skirt, skin further
   under loose cloth). The virtual scanner is an orthographic z-buffer over 25 views (8
   azimuths at elevations -20, 10 and 45 degrees, plus one from above) of ~4 mm surface
   samples with 8 mm pixels (3 x 3 max filter against splatting holes, 1 cm depth
   tolerance); a face is seen when any of its samples is. Garment faces seen by no view are
   dropped too (inner layers, cloth pushed into the body by posing). Body faces that the
   scanner cannot see even unclothed (armpits, soles) stay unless (a) applies, so clothed
   and unclothed scans differ only by what the clothes cover. ``clothed=False`` scans are the
   whole watertight body surface.
5. **Re-meshing** (``point_cloud=False``): the merged visible mesh is subdivided (edges <
   0.6 h) and re-meshed by vertex clustering (Rossignac-Borrel) on a randomly offset grid of
   voxel size h, tuned so that about ``n_points`` vertices remain; each cluster is
   represented by its member nearest to the cluster's mean (so vertices lie on the true
   surface), triangles collapsed by the clustering are removed, and the vertex order is
   shuffled. The topology is unrelated to the template (thin gaps such as cloth over skin may
   fuse, as in a real scanner's mesh). Normals: smooth vertex normals of the noisy mesh.
   ``point_cloud=True``: ``n_points`` points sampled evenly on the merged visible surface
   (``trimesh.sample.sample_surface_even``, topped up with area-weighted samples if short),
   normals of the triangles they were sampled on; no faces.
6. **Noise and frame.** Gaussian noise of ``noise_mm`` per coordinate (in metres, model
   frame), then a random yaw, a random translation (up to 1 m per axis), the up axis (+y, or
   +z: Y-up rotated to Z-up by +90 degrees about X) and the unit (m, cm, mm).
   ``to_model @ [p, 1]`` maps the noise-free scan back to the model frame.

Frames: model frame = metres, Y up, facing +Z (before the root's yaw). Shapes: points (P, 3).
"""
from __future__ import annotations

import functools
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from service.model.garments import garment as G_
from service.model.body import lbs
from service.model.formats import mhclo
from tests.bench.common import shared_data_dir
from service.model.geometry.mesh import cluster_vertices, vertex_normals

UNIT_SCALE = {"m": 1.0, "cm": 100.0, "mm": 1000.0}  # file units per metre
UPS = ("+y", "+z")
ROOT_MAX_TILT_DEG = 10.0
HIDDEN_BEHIND_CLOTH_M = 0.04
CONTACT_M = 0.005  # skin this close to cloth is covered, whichever side (cloth pushed in by posing)
SHOES_P, HAT_P = 0.4, 0.1
# virtual scanner
SAMPLE_SPACING_M = 0.004
PIXEL_M = 0.008
DEPTH_TOL_M = 0.01
VIEW_ELEVATIONS_DEG = (-20.0, 10.0, 45.0)
VIEW_AZIMUTHS = 8


@dataclass
class SyntheticScan:
    """A synthetic scan and its truth (see the module docstring)."""

    points: np.ndarray  # (P, 3) float64, scan units and axes
    normals: np.ndarray | None  # (P, 3) unit, scan axes
    faces: np.ndarray | None  # (F, 3) int64; None for a point cloud
    unit: str  # 'm' | 'cm' | 'mm'
    up: str  # '+y' | '+z'
    to_model: np.ndarray  # (4, 4) similarity: scan -> model frame (metres, Y up)
    weights: np.ndarray  # (K,) true shape
    rotvecs: np.ndarray  # (17, 3) true pose (local axis-angle per bone)
    translation: np.ndarray  # (3,) metres, model frame
    true_posed: np.ndarray  # (V, 3) true posed body, model frame, all vertices
    true_joints: np.ndarray  # (17, 3) posed joints, model frame
    gender: str
    measurements: dict  # the 12 attributes measured on the rest-pose true body
    garments: list[str]
    clothed: bool
    point_is_body: np.ndarray = field(default=None)  # (P,) bool: the point lies on the skin
    true_rest: np.ndarray = field(default=None)  # (V, 3) the true rest-pose body, model frame

    @property
    def point_cloud(self) -> bool:
        return self.faces is None

    def points_in_model_frame(self) -> np.ndarray:
        """The scan's points mapped by ``to_model`` (metres, model frame)."""
        return self.points @ self.to_model[:3, :3].T + self.to_model[:3, 3]


# -- pose ------------------------------------------------------------------------------------
def _random_axes(rng: np.random.Generator, n: int) -> np.ndarray:
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def random_pose(rng: np.random.Generator, max_deg: float = 45.0, anatomical: bool = False) -> np.ndarray:
    """(17, 3) rotvecs: every non-root bone a uniformly random axis and an angle uniform in
    [0, max_deg] degrees; the root a yaw uniform in [-180, 180) degrees (about +Y) after a
    tilt of at most min(max_deg, 10) degrees about a random horizontal axis.

    ``anatomical``: a bone whose draw is outside the anatomical joint limits
    (``fitting.JOINT_LIMITS_DEG``: a knee bent 33 degrees sideways, a foot turned 50 degrees) is
    drawn again, from the same distribution, until it is inside: a person can stand in the pose.
    The redraws come from a child of ``rng`` (``Generator.spawn``), so ``rng``'s own stream, and
    with it every other bone, the root and whatever the caller draws next (frame, garments,
    noise), is the same as without."""
    from scipy.spatial.transform import Rotation

    from service.model.body.model import BONES

    n = len(BONES)
    axes = _random_axes(rng, n)
    angles = np.radians(rng.uniform(0.0, max_deg, size=n))
    rv = axes * angles[:, None]
    yaw = rng.uniform(-np.pi, np.pi)
    a = rng.uniform(0.0, 2 * np.pi)
    tilt = np.radians(rng.uniform(0.0, min(max_deg, ROOT_MAX_TILT_DEG)))
    root = Rotation.from_rotvec([0.0, yaw, 0.0]) * Rotation.from_rotvec(tilt * np.array([np.cos(a), 0.0, np.sin(a)]))
    rv[0] = root.as_rotvec()
    if anatomical:
        from service.model.fitting.rig import joint_limits

        lo, hi = joint_limits()
        redraw = rng.spawn(1)[0]
        for b in range(1, n):
            if not np.all((rv[b] >= lo[b]) & (rv[b] <= hi[b])):
                rv[b] = _draw_within_limits(redraw, lo[b], hi[b], max_deg)
    return rv


def _draw_within_limits(rng: np.random.Generator, lo: np.ndarray, hi: np.ndarray, max_deg: float) -> np.ndarray:
    """(3,) a rotation vector drawn as :func:`random_pose` draws a bone's (a uniformly random
    axis, an angle uniform in [0, max_deg] degrees) again and again until it lies in the box
    [lo, hi] (3,) radians."""
    for _ in range(10_000):
        rv = _random_axes(rng, 1)[0] * np.radians(rng.uniform(0.0, max_deg))
        if np.all((rv >= lo) & (rv <= hi)):
            return rv
    raise ValueError(f"no rotation within the limits and {max_deg} degrees")  # pragma: no cover


LEG_BONES = (11, 12, 14, 15)  # thigh_l, shin_l, thigh_r, shin_r (``BONES`` order)
# the centre lines of the two legs (hip -> knee -> ankle) closer than this pass through each
# other: two knees side by side are ~12 cm apart centre to centre
LEG_CLEARANCE_M = 0.08


def leg_gap(joints: np.ndarray, samples: int = 50) -> float:
    """The least distance (metres) between the left leg's centre line (hip -> knee -> ankle:
    joints 11 -> 12 -> 13) and the right leg's (14 -> 15 -> 16); joints (17, 3) posed."""
    t = np.linspace(0.0, 1.0, samples)[:, None]

    def line(a, b, c):
        return np.concatenate([joints[a] + t * (joints[b] - joints[a]), joints[b] + t * (joints[c] - joints[b])])

    return float(cKDTree(line(11, 12, 13)).query(line(14, 15, 16))[0].min())


def separate_legs(model, vertices: np.ndarray, rotvecs: np.ndarray, rng: np.random.Generator,
                  max_deg: float) -> np.ndarray:
    """(17, 3) rotvecs: ``rotvecs`` with the thighs and shins drawn again (as
    :func:`random_pose` draws them, within the joint limits) from ``rng`` while the legs of the
    rest body ``vertices`` (V, 3) posed so pass through each other (:func:`leg_gap` under
    ``LEG_CLEARANCE_M``): a random pose within each bone's limits can still cross the legs
    through one another, which nobody can stand in."""
    from service.model.fitting.rig import joint_limits

    lo, hi = joint_limits()
    rv = np.array(rotvecs, np.float64)
    for _ in range(10_000):
        if leg_gap(model.forward(pose=rv, vertices=vertices).joints) >= LEG_CLEARANCE_M:
            return rv
        for b in LEG_BONES:
            rv[b] = _draw_within_limits(rng, lo[b], hi[b], max_deg)
    raise ValueError("no pose with the legs apart")  # pragma: no cover


def _rot_x(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])


def _rot_y(rad: float) -> np.ndarray:
    c, s = np.cos(rad), np.sin(rad)
    return np.array([[c, 0, s], [0, 1.0, 0], [-s, 0, c]])


def up_rotation(up: str) -> np.ndarray:
    """Rotation from the model's Y-up axes to a file's axes with ``up`` up."""
    return np.eye(3) if up == "+y" else _rot_x(90.0)


# -- garments --------------------------------------------------------------------------------
def default_clothes_dir() -> Path:
    return shared_data_dir() / "makehuman_clothes"


def available_garments(clothes_dir: Path | None = None) -> list[str]:
    """The stems of the ``.mhclo`` files under ``clothes_dir`` (sorted)."""
    base = Path(clothes_dir or default_clothes_dir())
    return sorted(f.stem for f in base.glob("*/*.mhclo"))


@functools.lru_cache(maxsize=64)
def _load_garment(path: str, n_base: int) -> tuple[mhclo.Binding, np.ndarray]:
    p = Path(path)
    binding = mhclo.parse_mhclo(p.read_text(encoding="utf-8", errors="replace"), n_base)
    _, faces = mhclo.parse_obj_faces(p.with_suffix(".obj").read_text(encoding="utf-8", errors="replace"))
    return binding, faces


def _garment_path(clothes_dir: Path, stem: str) -> Path:
    hits = sorted(Path(clothes_dir).glob(f"*/{stem}.mhclo"))
    if not hits:
        raise FileNotFoundError(f"no garment {stem!r} under {clothes_dir}")
    return hits[0]


def _garment_source(clothes_dir: Path, name: str, n_base: int) -> tuple[mhclo.Binding, np.ndarray]:
    """(binding, faces) of a garment: a ``.mhclo`` stem under ``clothes_dir``, else an item id of
    the compiled catalogue (``service.model.garments.catalogue``: e.g. ``pencil-skirt``, the lower part
    of a MakeHuman suit, or ``hair-bob02``)."""
    hits = sorted(Path(clothes_dir).glob(f"*/{name}.mhclo")) if Path(clothes_dir).is_dir() else []
    if hits:
        return _load_garment(str(hits[0]), n_base)
    from service.model.garments.catalogue import load_catalogue

    items = load_catalogue().items
    if name not in items:
        raise FileNotFoundError(f"no garment {name!r} under {clothes_dir} nor in the catalogue")
    return items[name].binding, np.asarray(items[name].faces, np.int64)


def _choose_garments(rng: np.random.Generator, names: list[str], gender: str) -> list[str]:
    """One suit (the body's gender when available) and maybe shoes or a hat. Always draws the
    same number of random values."""
    u = rng.uniform(size=3)
    suits = [n for n in names if "suit" in n]
    own = [n for n in suits if n.startswith(f"{gender}_")] or suits
    shoes = [n for n in names if n.startswith("shoes")]
    hats = [n for n in names if n.startswith("fedora")]
    out = [own[int(u[0] * len(own))]] if own else []
    if u[1] < SHOES_P and shoes:
        out.append(shoes[int(u[2] * len(shoes))])
    elif SHOES_P <= u[1] < SHOES_P + HAT_P and hats:
        out.append(hats[int(u[2] * len(hats))])
    return out


# -- visibility ------------------------------------------------------------------------------
def _view_directions() -> np.ndarray:
    dirs = [[0.0, 1.0, 0.0]]
    for el in np.radians(VIEW_ELEVATIONS_DEG):
        for az in np.arange(VIEW_AZIMUTHS) * 2 * np.pi / VIEW_AZIMUTHS:
            dirs.append([np.cos(el) * np.sin(az), np.sin(el), np.cos(el) * np.cos(az)])
    return np.array(dirs)


def _seen(points: np.ndarray, n_body: int) -> tuple[np.ndarray, np.ndarray]:
    """Orthographic z-buffer visibility of surface samples (the first ``n_body`` on the skin,
    the others on garments) from every view direction: (seen with everything, seen with the
    body samples alone), each (N,) bool."""
    from scipy.ndimage import maximum_filter

    X, Y, Z = np.ascontiguousarray(np.asarray(points, np.float32).T)  # 1-D columns: fast
    seen_all = np.zeros(len(X), bool)
    seen_body = np.zeros(n_body, bool)
    inv_pix = np.float32(1.0 / PIXEL_M)
    for d in _view_directions():
        u = np.cross(d, [0.0, 0.0, 1.0] if abs(d[1]) > 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(d, u)
        a, b, z = ((np.float32(e[0]) * X + np.float32(e[1]) * Y + np.float32(e[2]) * Z) for e in (u, v, d))
        i = ((a - a.min()) * inv_pix).astype(np.int64) + 1
        j = ((b - b.min()) * inv_pix).astype(np.int64) + 1
        shape = (int(i.max()) + 2, int(j.max()) + 2)
        flat = i * shape[1] + j
        # z: larger = nearer the camera
        zb_body = np.full(shape[0] * shape[1], -np.inf, np.float32)
        np.maximum.at(zb_body, flat[:n_body], z[:n_body])
        zb_all = zb_body.copy()
        np.maximum.at(zb_all, flat[n_body:], z[n_body:])
        zb_all = maximum_filter(zb_all.reshape(shape), size=3).reshape(-1)
        zb_body = maximum_filter(zb_body.reshape(shape), size=3).reshape(-1)
        seen_all |= z >= zb_all[flat] - DEPTH_TOL_M
        seen_body |= z[:n_body] >= zb_body[flat[:n_body]] - DEPTH_TOL_M
    return seen_all, seen_body


def _surface_samples(vertices: np.ndarray, faces: np.ndarray, rng: np.random.Generator):
    """Face centroids plus area-weighted random samples (~SAMPLE_SPACING_M apart):
    (points (N, 3), face index (N,))."""
    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    n = int(area.sum() / SAMPLE_SPACING_M**2)
    fi = rng.choice(len(faces), size=n, p=area / area.sum())
    r = rng.uniform(size=(n, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    t = tri[fi]
    pts = t[:, 0] + r[:, :1] * (t[:, 1] - t[:, 0]) + r[:, 1:] * (t[:, 2] - t[:, 0])
    return np.concatenate([tri.mean(1), pts]), np.concatenate([np.arange(len(faces)), fi])


def _face_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    t = vertices[faces]
    n = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)


def _visible_faces(vertices: np.ndarray, faces: np.ndarray, face_label: np.ndarray,
                   rng: np.random.Generator) -> np.ndarray:
    """(F,) bool: the faces a scanner sees of the merged posed mesh (label 0 = body, > 0 =
    garments); see the module docstring (step 4)."""
    is_body_face = face_label == 0
    pts, fi = _surface_samples(vertices, faces, rng)
    order = np.argsort(~is_body_face[fi], kind="stable")  # skin samples first
    pts, fi = pts[order], fi[order]
    n_body = int(is_body_face[fi].sum())
    seen_all, seen_body = _seen(pts, n_body)
    face_seen = np.zeros(len(faces), bool)
    face_seen[fi[seen_all]] = True
    face_seen_naked = np.zeros(len(faces), bool)
    face_seen_naked[fi[:n_body][seen_body]] = True

    # skin just behind cloth: nearest garment sample in front of the skin
    g = np.arange(n_body, len(pts))
    gn = _face_normals(vertices, faces)[fi[g]]
    body_faces = faces[is_body_face]
    bv = np.unique(body_faces)
    dist, nn = cKDTree(pts[g]).query(vertices[bv], distance_upper_bound=HIDDEN_BEHIND_CLOTH_M)
    hit = np.isfinite(dist)
    hidden_v = np.zeros(len(vertices), bool)
    q = pts[g][nn[hit]]
    n = gn[nn[hit]]
    d = q - vertices[bv[hit]]  # skin -> cloth
    front = np.einsum("ij,ij->i", d, n)
    dn = np.linalg.norm(d, axis=1)
    hidden_v[bv[hit]] = (dn < CONTACT_M) | ((front >= 0) & (front >= 0.5 * dn))
    behind_cloth = hidden_v[faces].sum(1) >= 2

    keep = np.where(is_body_face, ~((face_seen_naked & ~face_seen) | behind_cloth), face_seen)
    return keep


# -- re-meshing ------------------------------------------------------------------------------
def remesh(vertices: np.ndarray, faces: np.ndarray, n_points: int, rng: np.random.Generator,
           face_labels: np.ndarray | None = None, iterations: int = 4):
    """Re-mesh by vertex clustering to about ``n_points`` vertices (module docstring, step 5):
    (vertices (C, 3), faces (F', 3), each vertex's label from ``face_labels`` (F,) or None)."""
    import trimesh

    tri = vertices[faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum()
    h = np.sqrt(1.5 * area / n_points)
    Vs, Fs, src = trimesh.remesh.subdivide_to_size(vertices, faces, max_edge=0.6 * h, max_iter=12,
                                                   return_index=True)
    offset = rng.uniform(0.0, 1.0, size=3)
    best = None
    for _ in range(iterations):
        rep, F = cluster_vertices(Vs, Fs, h, offset * h)
        if best is None or abs(len(rep) - n_points) < abs(len(best[0]) - n_points):
            best = (rep, F)
        h *= np.sqrt(len(rep) / n_points)
    rep, F = best
    perm = rng.permutation(len(rep))
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    labels = None
    if face_labels is not None:
        vl = np.empty(len(Vs), np.asarray(face_labels).dtype)
        vl[Fs] = np.asarray(face_labels)[src][:, None]
        labels = vl[rep[perm]]
    return Vs[rep[perm]], inv[F], labels


# -- clothes ---------------------------------------------------------------------------------
def dress(model, X: np.ndarray, transforms: np.ndarray, translation: np.ndarray, names: list[str],
          clothes_dir: Path | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """The garments ``names`` (mhclo stems) on the rest body X (V, 3): each fitted by its
    binding, pushed out of the body like a try-on (3 mm), then posed with the blend, by its
    binding weights, of its bound vertices' skinning transforms (``transforms`` (J, 4, 4) of
    ``model.forward``) and moved by ``translation``. Returns [(vertices (M, 3), faces)]."""
    nb = model.n_body_vertices
    if not names:
        return []
    clothes_dir = Path(clothes_dir or default_clothes_dir())
    A = lbs.blend_transforms(transforms, model.lbs_indices, model.lbs_weights)
    body_n = vertex_normals(X[:nb], model.body_faces)
    body_tree = cKDTree(X[:nb])
    out = []
    for name in names:
        binding, gfaces = _garment_source(clothes_dir, name, X.shape[0])
        g = binding.fit(X)
        g, _ = G_.push_out(g, X[:nb], body_n, body_tree.query(g)[1][:, None],
                           G_.laplacian_smoother(gfaces, len(g)))
        g = np.asarray(g, np.float64)
        w = binding.weights / binding.weights.sum(1, keepdims=True)
        Ag = np.einsum("mk,mkij->mij", w, A[binding.indices])
        out.append((np.einsum("mij,mj->mi", Ag[:, :3, :3], g) + Ag[:, :3, 3] + translation,
                    np.asarray(gfaces, np.int64)))
    return out


# -- the scan --------------------------------------------------------------------------------
DETAIL_BUMPS = 80  # bumps over the body surface (individual_detail)
DETAIL_RADIUS_M = (0.04, 0.12)  # their Gaussian radii, uniform in this range


DETAIL_RIGID_BONES = (4, 7, 10, 13, 16)  # head, hands, feet (``body.BONES``): no soft tissue to vary


def individual_detail(X: np.ndarray, body_faces: np.ndarray, n_body: int, rng: np.random.Generator,
                      rms_mm: float, mask: np.ndarray | None = None) -> np.ndarray:
    """The rest body X (V, 3) with a smooth displacement no body model spans: a real person's
    fat and muscle distribution. DETAIL_BUMPS Gaussian bumps centred on area-uniform points of
    the skin (faces over the first ``n_body`` vertices), each moving every vertex along the
    centre's normal by a(k) exp(-|x - c_k|^2 / 2 r_k^2), a zero-mean normal amplitude and r
    uniform in DETAIL_RADIUS_M, times ``mask`` (V,) in [0, 1] (1: soft tissue; the skull, the
    hands and the soles keep their shape); scaled so that the skin's displacement along its
    own normals has RMS ``rms_mm`` where the mask is over 1/2. Applied to every vertex (helper
    geometry too, so the clothes' bindings follow). Returns (V, 3) float64."""
    X = np.asarray(X, np.float64)
    F = np.asarray(body_faces, np.int64)
    tri = X[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    fi = rng.choice(len(F), size=DETAIL_BUMPS, p=area / area.sum())
    u = rng.dirichlet(np.ones(3), size=DETAIL_BUMPS)
    centres = np.einsum("kj,kjd->kd", u, tri[fi])
    fn = np.cross(tri[fi, 1] - tri[fi, 0], tri[fi, 2] - tri[fi, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    radii = rng.uniform(*DETAIL_RADIUS_M, size=DETAIL_BUMPS)
    amps = rng.normal(size=DETAIL_BUMPS)
    d2 = ((X[:, None, :] - centres[None]) ** 2).sum(-1)  # (V, K)
    D = (np.exp(-d2 / (2 * radii ** 2)) * amps) @ fn  # (V, 3)
    if mask is not None:
        D *= np.asarray(mask, np.float64)[:, None]
    soft = np.ones(n_body, bool) if mask is None else np.asarray(mask)[:n_body] > 0.5
    n = vertex_normals(X[:n_body], F)
    rms = np.sqrt(np.mean(np.einsum("ij,ij->i", D[:n_body], n)[soft] ** 2))
    return X + D * (rms_mm / 1000.0 / max(rms, 1e-12))


# relaxed hands (``curl_fingers``): the fingers beyond the knuckles (this share of the hand's
# length from the wrist, along the hand) turn towards the palm about the knuckles' line, by an
# angle growing linearly to the full curl at the fingertips
CURL_KNUCKLE_SHARE = 0.45


def curl_fingers(model, X: np.ndarray, degrees: float) -> np.ndarray:
    """A rest body's vertices X (V, 3), model frame, with relaxed hands: a scanned person's
    fingers are curled towards the palm (in an A-pose, the palms face the thighs), which the
    model's 17 bones cannot do. Per hand (the vertices its bone moves most): the hand's axis
    from its joint (the wrist) to its farthest vertices, the palm's normal its thinnest
    direction turned medially; a vertex further along the axis than CURL_KNUCKLE_SHARE of the
    hand's length turns about the knuckles' line (axis x palm) towards the palm by ``degrees``
    times its share of the way from the knuckles to the fingertips (the thumb's tip with them).
    The hand's axis and knuckles are found here, not taken from the fitting's ``finger_region``:
    the truth does not lean on the method it tests."""
    from service.model.body.model import BONES

    X = np.array(X, np.float64)
    W = np.zeros((len(X), len(BONES)))
    np.add.at(W, (np.repeat(np.arange(len(X)), 4), model.lbs_indices.ravel()), model.lbs_weights.ravel())
    bone = np.argmax(W, axis=1)
    J = model.forward(pose=np.zeros((len(BONES), 3)), vertices=X).joints
    for name in ("hand_l", "hand_r"):
        b = BONES.index(name)
        at = np.flatnonzero(bone == b)
        P = X[at] - J[b]
        reach = np.linalg.norm(P, axis=1)
        a = P[reach >= np.percentile(reach, 95)].mean(0)
        a /= np.linalg.norm(a)
        palm = np.linalg.svd(P - P.mean(0), full_matrices=False)[2][2]
        palm -= a * (palm @ a)
        palm /= np.linalg.norm(palm)
        if palm[0] * np.sign(J[b, 0] - J[0, 0]) > 0:  # the palm faces the body's midline
            palm = -palm
        k = np.cross(a, palm)  # turning about k takes a towards the palm
        along = P @ a
        knuckle = CURL_KNUCKLE_SHARE * along.max()
        f = along > knuckle
        theta = np.radians(degrees) * np.clip((along[f] - knuckle) / (along.max() - knuckle), 0.0, 1.0)
        Q = P[f] - a * knuckle
        c, sn = np.cos(theta)[:, None], np.sin(theta)[:, None]
        Q = Q * c + np.cross(k, Q) * sn + k * (Q @ k)[:, None] * (1.0 - c)  # Rodrigues
        X[at[f]] = J[b] + a * knuckle + Q
    return X


def make_scan(model, rng: np.random.Generator, weights: np.ndarray, gender: str, *, clothed: bool,
              point_cloud: bool, n_points: int = 12_500, noise_mm: float = 2.0, max_pose_deg: float = 45.0,
              garments: list[str] | None = None, clothes_dir: Path | None = None, unit: str | None = None,
              up: str | None = None, anatomical: bool = False, detail_mm: float = 0.0,
              detail_rng: np.random.Generator | None = None, finger_curl_deg: float = 0.0) -> SyntheticScan:
    """A synthetic scan of the body ``weights`` (see the module docstring). ``garments``
    (mhclo stems) overrides the random choice; ``unit``/``up`` override the random frame;
    ``anatomical``: the pose within the joint limits (:func:`random_pose`; everything else the
    same as without). ``detail_mm`` > 0: the person is not in the body model's space, the rest
    body gets :func:`individual_detail` of that RMS (drawn from ``detail_rng``; the truth,
    ``weights`` excepted, is the displaced body). ``finger_curl_deg`` > 0: relaxed hands,
    :func:`curl_fingers` by that angle (the truth too: its measurements do not change)."""
    weights = np.asarray(weights, np.float64)
    X = model.vertices(weights).astype(np.float64)
    nb = model.n_body_vertices
    if detail_mm > 0:
        rigid = np.isin(model.lbs_indices, DETAIL_RIGID_BONES)
        mask = 1.0 - np.where(rigid, model.lbs_weights, 0.0).sum(axis=1)
        X = individual_detail(X, model.body_faces, nb, detail_rng or np.random.default_rng(0), detail_mm,
                              np.clip(mask, 0.0, 1.0))
    measurements = model.measure(X, gender)
    if finger_curl_deg > 0:
        X = curl_fingers(model, X, finger_curl_deg)

    # random draws in a fixed order (same person/pose/frame/garments whether clothed or not)
    rotvecs = random_pose(rng, max_pose_deg, anatomical)
    if anatomical:  # nor the legs through each other (a child generator: the draws below stay)
        rotvecs = separate_legs(model, X, rotvecs, rng.spawn(1)[0], max_pose_deg)
    u_unit, u_up = rng.uniform(size=2)
    yaw = rng.uniform(-np.pi, np.pi)
    shift = rng.uniform(-1.0, 1.0, size=3)
    clothes_dir = Path(clothes_dir or default_clothes_dir())
    names = available_garments(clothes_dir) if clothes_dir.is_dir() else []
    chosen = _choose_garments(rng, names, gender)
    seed_vis, seed_mesh, seed_noise = rng.integers(0, 2**63 - 1, size=3)
    unit = unit or tuple(UNIT_SCALE)[int(u_unit * 3)]
    up = up or UPS[int(u_up * 2)]
    if unit not in UNIT_SCALE or up not in UPS:
        raise ValueError(f"unit must be one of {tuple(UNIT_SCALE)} and up one of {UPS}")
    if not clothed:
        chosen = []
    elif garments is not None:
        chosen = list(garments)
    if clothed and not chosen:
        raise FileNotFoundError(f"no MakeHuman garments under {clothes_dir}")

    # pose the body (lifted onto the floor) and the joints
    rest_posed = model.forward(pose=rotvecs, vertices=X)
    translation = np.array([0.0, -rest_posed.vertices[:nb, 1].min(), 0.0])
    posed = rest_posed.vertices + translation
    joints = rest_posed.joints + translation

    # dress in the rest pose (pushed out of the body like a try-on), pose with the bound
    # vertices' transforms
    parts_v, parts_f, labels = [posed[:nb]], [np.asarray(model.body_faces, np.int64)], [0]
    offset = nb
    for k, (gv, gf) in enumerate(dress(model, X, rest_posed.transforms, translation, chosen, clothes_dir), start=1):
        parts_v.append(gv)
        parts_f.append(gf + offset)
        labels.append(k)
        offset += len(gv)
    V = np.concatenate(parts_v)
    F = np.concatenate(parts_f)
    face_label = np.concatenate([np.full(len(f), lab) for f, lab in zip(parts_f, labels)])

    if chosen:
        keep = _visible_faces(V, F, face_label, np.random.default_rng(seed_vis))
        F, face_label = F[keep], face_label[keep]
    used = np.unique(F)
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    V, F = V[used], remap[F]

    mesh_rng = np.random.default_rng(seed_mesh)
    if point_cloud:
        import trimesh

        tm = trimesh.Trimesh(V, F, process=False)
        # ask for 15 % more (a smaller rejection radius), keep the first n_points
        pts, fi = trimesh.sample.sample_surface_even(tm, int(1.15 * n_points) + 1, seed=mesh_rng)
        if len(pts) < n_points:
            more, fi2 = trimesh.sample.sample_surface(tm, n_points - len(pts), seed=mesh_rng)
            pts, fi = np.concatenate([pts, more]), np.concatenate([fi, fi2])
        pts, fi = np.asarray(pts[:n_points], np.float64), fi[:n_points]
        normals = _face_normals(V, F)[fi]
        out_faces = None
        is_body = face_label[fi] == 0
    else:
        pts, out_faces, lab = remesh(V, F, n_points, mesh_rng, face_labels=face_label)
        is_body = lab == 0
        normals = None

    noisy = pts + np.random.default_rng(seed_noise).normal(scale=noise_mm / 1000.0, size=pts.shape)
    if out_faces is not None:
        normals = vertex_normals(noisy, out_faces).astype(np.float64)

    # model frame -> scan frame: p_s = s Rup (Ryaw p + t)
    s = UNIT_SCALE[unit]
    Rm = up_rotation(up) @ _rot_y(yaw)
    to_scan = np.eye(4)
    to_scan[:3, :3] = s * Rm
    to_scan[:3, 3] = s * (up_rotation(up) @ shift)
    to_model = np.linalg.inv(to_scan)
    points = noisy @ to_scan[:3, :3].T + to_scan[:3, 3]
    if normals is not None:
        normals = normals @ Rm.T
    return SyntheticScan(points=points, normals=normals, faces=out_faces, unit=unit, up=up, to_model=to_model,
                         weights=weights, rotvecs=rotvecs, translation=translation, true_posed=posed,
                         true_joints=joints, gender=gender, measurements=measurements, garments=chosen,
                         clothed=bool(clothed), point_is_body=is_body, true_rest=X)


# -- files -----------------------------------------------------------------------------------
FORMATS = ("obj", "ply", "stl", "glb", "xyz")
POINT_CLOUD_FORMATS = ("ply", "xyz", "obj")


def scan_file_bytes(scan: SyntheticScan, fmt: str) -> bytes:
    """The scan as a file: ``obj``, ``ply``, ``stl``, ``glb`` (meshes, trimesh's exporters;
    normals where the format carries them) or ``xyz`` (text ``x y z nx ny nz`` per line).
    Point clouds only as ``ply`` (binary, x y z nx ny nz), ``xyz`` or ``obj`` (``v``/``vn``)."""
    fmt = fmt.lower().lstrip(".")
    if fmt not in FORMATS:
        raise ValueError(f"unknown format {fmt!r}; expected one of {FORMATS}")
    P = np.asarray(scan.points, np.float64)
    N = scan.normals
    if fmt == "xyz":
        cols = P if N is None else np.hstack([P, N])
        buf = io.StringIO()
        np.savetxt(buf, cols, fmt="%.6f")
        return buf.getvalue().encode()
    if scan.faces is None:
        if fmt not in POINT_CLOUD_FORMATS:
            raise ValueError(f"a point cloud cannot be written as {fmt!r}; use one of {POINT_CLOUD_FORMATS}")
        if fmt == "obj":
            lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in P]
            if N is not None:
                lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in N]
            return ("\n".join(lines) + "\n").encode()
        props = ["x", "y", "z"] + ([] if N is None else ["nx", "ny", "nz"])
        head = ("ply\nformat binary_little_endian 1.0\n"
                f"element vertex {len(P)}\n" + "".join(f"property float {p}\n" for p in props)
                + "end_header\n").encode()
        data = (P if N is None else np.hstack([P, N])).astype("<f4")
        return head + data.tobytes()
    import trimesh

    kw = {} if N is None else {"vertex_normals": np.asarray(N, np.float64)}
    mesh = trimesh.Trimesh(P, scan.faces, process=False, **kw)
    if fmt == "obj":
        return mesh.export(file_type="obj", include_normals=N is not None, include_texture=False).encode()
    if fmt == "ply":
        return mesh.export(file_type="ply", encoding="binary", vertex_normal=N is not None)
    if fmt == "stl":
        return mesh.export(file_type="stl")
    return mesh.export(file_type="glb", include_normals=N is not None)


__all__ = ["SyntheticScan", "random_pose", "make_scan", "scan_file_bytes", "available_garments", "remesh",
           "up_rotation", "UNIT_SCALE", "FORMATS", "POINT_CLOUD_FORMATS"]


# -- shapes that are not a person (the person check) -------------------------------------------
NON_PERSON_KINDS = ("box", "ellipsoid", "chair", "two_people", "two_people_touching", "stick_figure")


def _capsule(a, b, radius: float):
    """A trimesh capsule of ``radius`` (metres) from point a (3,) to point b (3,)."""
    import trimesh

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    length = float(np.linalg.norm(b - a))
    m = trimesh.creation.capsule(height=length, radius=radius, count=[16, 16])
    m.apply_transform(trimesh.geometry.align_vectors([0.0, 0.0, 1.0], (b - a) / length))
    m.apply_translation((a + b) / 2)
    return m


def _non_person_mesh(model, kind: str, rng: np.random.Generator):
    """(vertices (V, 3), faces (F, 3)) of a person-sized shape that is not one person, in the
    model frame (metres, Y up, standing on y = 0)."""
    import trimesh

    if kind == "box":  # a dense person-sized box
        m = trimesh.creation.box(extents=(0.5, 1.8, 0.3))
        m.apply_translation((0, 0.9, 0))
        m = m.subdivide_to_size(0.02)
    elif kind == "ellipsoid":
        m = trimesh.creation.icosphere(subdivisions=5)
        m.apply_scale((0.25, 0.87, 0.16))
        m.apply_translation((0, 0.87, 0))
    elif kind == "chair":  # seat, four legs, a back: 1.1 m high
        parts = [trimesh.creation.box(extents=(0.5, 0.05, 0.5)).apply_translation((0, 0.45, 0)),
                 trimesh.creation.box(extents=(0.5, 0.6, 0.05)).apply_translation((0, 0.8, -0.225))]
        for x in (-0.22, 0.22):
            for z in (-0.22, 0.22):
                parts.append(trimesh.creation.box(extents=(0.04, 0.45, 0.04)).apply_translation((x, 0.225, z)))
        m = trimesh.util.concatenate(parts)
        m = m.subdivide_to_size(0.02)
    elif kind == "stick_figure":  # a mannequin-like figure: capsule trunk and limbs, a ball for a head
        parts = [_capsule((0, 0.95, 0), (0, 1.45, 0), 0.15),
                 trimesh.creation.icosphere(radius=0.11).apply_translation((0, 1.65, 0)),
                 _capsule((-0.1, 0.05, 0), (-0.1, 0.9, 0), 0.07), _capsule((0.1, 0.05, 0), (0.1, 0.9, 0), 0.07),
                 _capsule((-0.2, 1.4, 0), (-0.45, 0.95, 0), 0.05), _capsule((0.2, 1.4, 0), (0.45, 0.95, 0), 0.05)]
        m = trimesh.util.concatenate(parts)
    elif kind in ("two_people", "two_people_touching"):  # two people side by side (T-pose span 1.2 m)
        nb = model.n_body_vertices
        vs, fs = [], []
        gap = 0.8 if kind == "two_people" else 0.5  # 40 cm apart, or hands overlapping
        for k, dx in enumerate((-gap, gap)):
            w = np.zeros(model.n_components)
            w[:3] = rng.normal(scale=0.5, size=3) * np.sqrt(model.variances[:3])
            pose = random_pose(rng, 10.0)
            pose[0] = 0.0  # both facing +Z
            out = model.forward(w, pose, np.zeros(3))
            v = out.vertices[:nb] + [dx, -out.vertices[:nb, 1].min(), 0.0]
            vs.append(v)
            fs.append(np.asarray(model.body_faces, np.int64) + k * nb)
        return np.concatenate(vs), np.concatenate(fs)
    else:
        raise ValueError(f"unknown shape {kind!r}; expected one of {NON_PERSON_KINDS}")
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces, np.int64)


def non_person_scan(model, kind: str, rng: np.random.Generator, n_points: int = 12_500, noise_mm: float = 2.0,
                    unit: str | None = None, up: str | None = None):
    """A point cloud (points (P, 3) file units, normals (P, 3), unit, up) of a shape that is
    not one person (``NON_PERSON_KINDS``), in a random unit, up axis, yaw and placement."""
    import trimesh

    V, F = _non_person_mesh(model, kind, rng)
    unit = unit or tuple(UNIT_SCALE)[int(rng.integers(3))]
    up = up or UPS[int(rng.integers(2))]
    tm = trimesh.Trimesh(V, F, process=False)
    pts, fi = trimesh.sample.sample_surface(tm, n_points, seed=rng)
    normals = _face_normals(V, F)[fi]
    pts = np.asarray(pts, np.float64) + rng.normal(scale=noise_mm / 1000.0, size=(len(pts), 3))
    Rm = up_rotation(up) @ _rot_y(rng.uniform(-np.pi, np.pi))
    s = UNIT_SCALE[unit]
    points = s * (pts @ Rm.T + up_rotation(up) @ rng.uniform(-1.0, 1.0, size=3))
    return points, normals @ Rm.T, unit, up


def front_only(scan: SyntheticScan, min_cos: float = 0.1) -> SyntheticScan:
    """A single-view (front) scan from a point-cloud scan: only the points whose normal faces the
    camera in front of the person (the true root's facing), as a depth camera sees them
    (self-occlusion ignored). The truth is the scan's."""
    from dataclasses import replace

    from service.model.body.lbs import axis_angle_to_matrix

    if scan.faces is not None or scan.normals is None:
        raise ValueError("front_only needs a point cloud with normals")
    R = scan.to_model[:3, :3] / np.cbrt(np.linalg.det(scan.to_model[:3, :3]))
    facing = axis_angle_to_matrix(scan.rotvecs[:1])[0] @ np.array([0.0, 0.0, 1.0])
    keep = (scan.normals @ R.T) @ facing > min_cos
    return replace(scan, points=scan.points[keep], normals=scan.normals[keep],
                   point_is_body=None if scan.point_is_body is None else scan.point_is_body[keep])


# -- what real scanners add and lose (issue 12) ------------------------------------------------
DEGRADATIONS = ("holes", "cut_head", "capped_head", "floor_disc", "scanner_floor", "room_floor", "dark_hair",
                "no_head", "long_hair", "raw_artifacts", "cut_soles")
ROOM_FLOOR_HALF_M = 1.6  # the room floor's half width (metres)


def _model_points(scan: SyntheticScan) -> np.ndarray:
    return scan.points_in_model_frame()


def _from_model(scan: SyntheticScan, P: np.ndarray) -> np.ndarray:
    inv = np.linalg.inv(scan.to_model)
    return P @ inv[:3, :3].T + inv[:3, 3]


def _model_rotation(scan: SyntheticScan) -> np.ndarray:
    """The rotation part (3, 3) of ``to_model`` (scan axes -> model axes)."""
    A = scan.to_model[:3, :3]
    return A / np.cbrt(np.linalg.det(A))


def _with_points(scan: SyntheticScan, P: np.ndarray, normal: np.ndarray, tri: np.ndarray | None) -> SyntheticScan:
    """The scan with points P (N, 3) (model frame) added: not the body's, all with the model-frame
    ``normal`` (3,), and a mesh's triangles ``tri`` (T, 3) indexing P (added to its faces)."""
    from dataclasses import replace

    n0 = len(scan.points)
    normals = None if scan.normals is None else np.concatenate([scan.normals, np.tile(normal @ _model_rotation(scan),
                                                                                      (len(P), 1))])
    faces = None if scan.faces is None else np.concatenate([scan.faces, np.asarray(tri, np.int64) + n0])
    is_body = None if scan.point_is_body is None else np.concatenate([scan.point_is_body, np.zeros(len(P), bool)])
    return replace(scan, points=np.concatenate([scan.points, _from_model(scan, P)]), normals=normals, faces=faces,
                   point_is_body=is_body)


def keep_points(scan: SyntheticScan, keep: np.ndarray) -> SyntheticScan:
    """The scan with only the points ``keep`` (P,) bool; a mesh keeps the faces whose three
    vertices stay. The truth is the scan's."""
    from dataclasses import replace

    keep = np.asarray(keep, bool)
    faces = None
    if scan.faces is not None:
        remap = np.cumsum(keep) - 1
        F = scan.faces[keep[scan.faces].all(1)]
        faces = remap[F]
    return replace(scan, points=scan.points[keep], faces=faces,
                   normals=None if scan.normals is None else scan.normals[keep],
                   point_is_body=None if scan.point_is_body is None else scan.point_is_body[keep])


def with_holes(scan: SyntheticScan, rng: np.random.Generator, n_holes: int = 8,
               radius_m: tuple[float, float] = (0.04, 0.09)) -> SyntheticScan:
    """Surface patches missing (occlusions, dark or shiny cloth): ``n_holes`` balls of a radius
    uniform in ``radius_m`` around random scan points above knee height (0.45 m; the feet are
    left to the floor conditions); every point inside is dropped."""
    P = _model_points(scan)
    cand = np.flatnonzero(P[:, 1] > P[:, 1].min() + 0.45)
    centres = P[rng.choice(cand, size=n_holes, replace=False)]
    radii = rng.uniform(*radius_m, size=n_holes)
    d = np.linalg.norm(P[:, None, :] - centres[None], axis=2)
    return keep_points(scan, ~(d < radii).any(1))


def cut_head_top(scan: SyntheticScan, depth_m: float = 0.04) -> SyntheticScan:
    """The top of the head cut off, as by a scanner whose field of view ends below it: every
    point above the horizontal plane (model frame) ``depth_m`` below the true body's highest
    vertex is dropped."""
    top = float(scan.true_posed[:, 1].max())
    P = _model_points(scan)
    return keep_points(scan, P[:, 1] <= top - depth_m)


def capped_head(scan: SyntheticScan, depth_m: float = 0.04, noise_m: float = 0.001) -> SyntheticScan:
    """The head's top cut off ``depth_m`` below the true crown and the opening closed by a flat
    cap, as a scanner's software that makes the mesh watertight fills it: points as dense as the
    scan's (the median over its points of 8 neighbours per disc to the 8th), uniformly at random
    on the cut's plane inside the convex hull of the rim (the points within 1 cm below the cut,
    15 cm around the crown), with
    ``noise_m`` of noise, normals up; a mesh gets their Delaunay triangles (not joined to the
    rim). The cap is the scan's, not the body's (``point_is_body`` false)."""
    from scipy.spatial import ConvexHull, Delaunay, cKDTree

    scan = cut_head_top(scan, depth_m)
    crown = scan.true_posed[np.argmax(scan.true_posed[:, 1])]
    level = float(crown[1]) - depth_m
    P = _model_points(scan)
    rim = P[(P[:, 1] > level - 0.01) & (np.linalg.norm(P[:, [0, 2]] - crown[[0, 2]], axis=1) < 0.15)][:, [0, 2]]
    r8 = cKDTree(P).query(P, k=9)[0][:, -1]
    density = float(np.median(8 / (np.pi * r8**2)))  # points per square metre of the surface
    hull = ConvexHull(rim)
    rng = np.random.default_rng(len(P))
    lo, hi = rim.min(0), rim.max(0)
    xz = lo + rng.uniform(size=(int(density * np.prod(hi - lo)), 2)) * (hi - lo)
    xz = xz[Delaunay(rim[hull.vertices]).find_simplex(xz) >= 0]
    cap = np.column_stack([xz[:, 0], level + rng.normal(scale=noise_m, size=len(xz)), xz[:, 1]])
    return _with_points(scan, cap, np.array([0.0, 1.0, 0.0]), Delaunay(xz).simplices)


# dark hair (``without_hair_returns``): the head's vertices (by their largest skinning weight) on
# the crown, within DARK_HAIR_CROWN_M of the rest template head's top, or on the back of the head
# (behind the head's centroid and facing backwards: rest normal z < DARK_HAIR_BACK_NZ; not the
# nostrils'), and every scan point within DARK_HAIR_M of them posed
DARK_HAIR_CROWN_M = 0.07
DARK_HAIR_BACK_NZ = -0.2
DARK_HAIR_M = 0.015


def _head_vertices(model, n: int) -> np.ndarray:
    """(n,) bool: the model's first ``n`` vertices that the head bone moves most."""
    from service.model.body.model import BONES

    W = np.zeros((n, len(BONES)))
    np.add.at(W, (np.repeat(np.arange(n), 4), model.lbs_indices[:n].ravel()), model.lbs_weights[:n].ravel())
    return np.argmax(W, axis=1) == BONES.index("head")


def without_hair_returns(scan: SyntheticScan) -> SyntheticScan:
    """Dark hair, which many body scanners do not see: no points on the crown and the back of
    the head (the face, the ears below the crown and the neck stay). Drawn from the body model's
    rest template, not from the fitting's own scalp region: every point within DARK_HAIR_M of the
    crown's or the back of the head's vertices in the true posed body is dropped."""
    from scipy.spatial import cKDTree

    from service.model.body.model import load_body_model
    from service.model.geometry.mesh import vertex_normals

    model = load_body_model()
    n = model.n_body_vertices
    head = _head_vertices(model, n)
    rest = model.mean[:n].astype(np.float64)
    nz = vertex_normals(rest, np.asarray(model.body_faces, np.int64))[:, 2]
    back = (nz < DARK_HAIR_BACK_NZ) & (rest[:, 2] < rest[head, 2].mean())
    covered = head & ((rest[:, 1] > rest[head, 1].max() - DARK_HAIR_CROWN_M) | back)
    d, _ = cKDTree(scan.true_posed[:n][covered]).query(_model_points(scan))
    return keep_points(scan, d > DARK_HAIR_M)


NO_HEAD_M = 0.015  # without_head: scan points this near the true head's vertices are dropped


def without_head(scan: SyntheticScan) -> SyntheticScan:
    """No head at all: a scanner whose field of view ends at the neck, or a head hidden (dark
    hair and a face turned from the cameras). Every point within NO_HEAD_M of the true posed
    body's head vertices (those the head bone moves most, the body model's rest template) is
    dropped (the eyes' and eyebrows' too); the neck stays."""
    from scipy.spatial import cKDTree

    from service.model.body.model import load_body_model

    head = _head_vertices(load_body_model(), len(scan.true_posed))  # the body and its helpers (eyes, eyebrows)
    d, _ = cKDTree(scan.true_posed[head]).query(_model_points(scan))
    return keep_points(scan, d > NO_HEAD_M)


# long hair (``with_long_hair``): a curtain of hair hanging straight down from the back of the head
# to LONG_HAIR_BELOW_M under the skull base (the head joint; about the shoulder blades), across
# LONG_HAIR_HALF_WIDTH either side of the spine, LONG_HAIR_THICK_M out from the back-most skin over
# each point (hanging hair bridges the nape's hollow)
LONG_HAIR_BELOW_M = 0.25
LONG_HAIR_HALF_WIDTH = 0.09
LONG_HAIR_THICK_M = 0.012
LONG_HAIR_BIN_M = 0.015  # the heightfield's cells (the body's vertices are ~1 cm apart)
LONG_HAIR_HIDES_M = 0.03  # scan points this near the back-most skin under the hair are hidden by it


def with_long_hair(scan: SyntheticScan) -> SyntheticScan:
    """Long hair down the back, which a body scan of a bare person shows over the nape and the
    upper back: the skin under the curtain (within LONG_HAIR_HIDES_M of the back-most skin) is
    dropped and the hair's surface added, sampled at the spacing of the scan's body points with 1
    mm of noise from its own generator (the bench's random draws after it stay those of the same
    scan without hair; a mesh gets its grid's triangles). The curtain is a heightfield in the body's frame (the
    shoulders' line across, model +Y up, backwards): over each cell, the back-most skin at or
    above it, plus LONG_HAIR_THICK_M. Its points are not body points."""
    from scipy.spatial import cKDTree

    from service.model.body.model import BONES, load_body_model

    J = scan.true_joints
    up = np.array([0.0, 1.0, 0.0])
    u = J[BONES.index("upper_arm_l")] - J[BONES.index("upper_arm_r")]
    u = u - up * u[1]
    u /= np.linalg.norm(u)
    back = np.cross(up, u)  # the model faces +Z with its left arm at +X: back = -Z at rest
    h = J[BONES.index("head")]
    B = scan.true_posed[: load_body_model().n_body_vertices] - h
    a, y, d = B @ u, B[:, 1], B @ back
    top = float(y.max())
    lo = -LONG_HAIR_BELOW_M
    sel = (np.abs(a) <= LONG_HAIR_HALF_WIDTH) & (y >= lo) & (d > 0.0)
    na = int(np.ceil(2 * LONG_HAIR_HALF_WIDTH / LONG_HAIR_BIN_M))
    ny = int(np.ceil((top - lo) / LONG_HAIR_BIN_M))
    ia = np.clip(((a[sel] + LONG_HAIR_HALF_WIDTH) / LONG_HAIR_BIN_M).astype(int), 0, na - 1)
    iy = np.clip(((top - y[sel]) / LONG_HAIR_BIN_M).astype(int), 0, ny - 1)  # row 0 at the top
    skin = np.full((ny, na), -np.inf)
    np.maximum.at(skin, (iy, ia), d[sel])
    hang = np.maximum.accumulate(skin, axis=0)  # hanging straight down: the back-most skin above
    P = _model_points(scan) - h
    pa, py, pd = P @ u, P[:, 1], P @ back
    inside = (np.abs(pa) < LONG_HAIR_HALF_WIDTH) & (py >= lo) & (py <= top)
    ja = np.clip(((pa + LONG_HAIR_HALF_WIDTH) / LONG_HAIR_BIN_M).astype(int), 0, na - 1)
    jy = np.clip(((top - py) / LONG_HAIR_BIN_M).astype(int), 0, ny - 1)
    under = inside & np.isfinite(hang[jy, ja]) & (pd > hang[jy, ja] - LONG_HAIR_HIDES_M)
    # the hair's surface on a grid at the scan's spacing (its body points' median nearest-neighbour
    # distance)
    body = P if scan.point_is_body is None else P[scan.point_is_body]
    spacing = float(np.median(cKDTree(body).query(body, k=2)[0][:, 1]))
    rng = np.random.default_rng(len(scan.points))
    scan = keep_points(scan, ~under)
    ga = np.arange(-LONG_HAIR_HALF_WIDTH, LONG_HAIR_HALF_WIDTH + 1e-9, spacing)
    gy = np.arange(top, lo - 1e-9, -spacing)
    A, Y = np.meshgrid(ga, gy)
    ka = np.clip(((A + LONG_HAIR_HALF_WIDTH) / LONG_HAIR_BIN_M).astype(int), 0, na - 1)
    ky = np.clip(((top - Y) / LONG_HAIR_BIN_M).astype(int), 0, ny - 1)
    D = hang[ky, ka] + LONG_HAIR_THICK_M + rng.normal(scale=0.001, size=A.shape)
    ok = np.isfinite(D)
    H = h + A[..., None] * u + Y[..., None] * up + np.where(ok, D, 0.0)[..., None] * back
    ids = -np.ones(A.shape, np.int64)
    ids[ok] = np.arange(int(ok.sum()))
    c00, c01, c10, c11 = ids[:-1, :-1], ids[:-1, 1:], ids[1:, :-1], ids[1:, 1:]
    quads = (c00 >= 0) & (c01 >= 0) & (c10 >= 0) & (c11 >= 0)
    tri = np.concatenate([np.stack([c00[quads], c10[quads], c01[quads]], 1),
                          np.stack([c01[quads], c10[quads], c11[quads]], 1)])
    return _with_points(scan, H[ok], back, tri)


def _floor_grid(centre: np.ndarray, half: float, spacing: float, rng: np.random.Generator,
                disc: bool) -> tuple[np.ndarray, np.ndarray]:
    """Floor points (N, 3) on y = 0 around ``centre`` (x, z) jittered on a grid, and their
    Delaunay triangles (T, 3) in the xz plane."""
    from scipy.spatial import Delaunay

    g = np.arange(-half, half + 1e-9, spacing)
    x, z = np.meshgrid(g, g)
    xz = np.stack([x.ravel(), z.ravel()], 1) + rng.uniform(-0.3, 0.3, size=(x.size, 2)) * spacing
    if disc:
        xz = xz[np.linalg.norm(xz, axis=1) <= half]
    tri = Delaunay(xz).simplices.astype(np.int64)
    P = np.column_stack([xz[:, 0] + centre[0], np.zeros(len(xz)), xz[:, 1] + centre[1]])
    return P, tri


def with_floor(scan: SyntheticScan, rng: np.random.Generator, kind: str = "disc") -> SyntheticScan:
    """Floor points under the feet (on the true floor, y = 0 in the model frame): ``disc``, a
    dense disc (radius 0.45 m, 6 mm spacing: about as many points as the body) as a turntable
    scanner leaves it; ``scanner``, a 1.4 m square of the room's floor at 15 mm spacing with
    4 mm of noise across the floor, tilted by up to 1.5 degrees (a scanner's level) and up to
    1 cm below or above the soles; ``room``, a 3.2 m square of the room's floor at 25 mm spacing,
    4 mm of noise (wider than any person is tall: the scan's extent no longer tells its unit).
    Meshes get the floor's triangles (not joined to the feet);
    point clouds its points with normals +Y (model frame)."""
    feet = scan.true_posed[:, 1] < 0.1
    c = scan.true_posed[feet][:, [0, 2]].mean(0)
    if kind == "disc":
        P, tri = _floor_grid(c, 0.45, 0.006, rng, disc=True)
        P[:, 1] += rng.normal(scale=0.001, size=len(P))
    elif kind == "scanner":
        P, tri = _floor_grid(c, 0.7, 0.015, rng, disc=False)
        a = rng.uniform(0, 2 * np.pi)
        tilt = np.radians(rng.uniform(0.0, 1.5))
        slope = np.tan(tilt) * np.array([np.cos(a), np.sin(a)])
        P[:, 1] = (P[:, [0, 2]] - c) @ slope + rng.uniform(-0.01, 0.01) + rng.normal(scale=0.004, size=len(P))
    elif kind == "room":
        P, tri = _floor_grid(c, ROOM_FLOOR_HALF_M, 0.025, rng, disc=False)
        P[:, 1] = rng.uniform(-0.01, 0.01) + rng.normal(scale=0.004, size=len(P))
    else:
        raise ValueError(f"unknown floor {kind!r}; expected 'disc', 'scanner' or 'room'")
    return _with_points(scan, P, np.array([0.0, 1.0, 0.0]), tri)


# a raw multi-view scanner's own errors (``with_raw_artifacts``): each view's patch of surface off
# by its calibration error, and flying pixels where a view grazes the surface
RAW_MISREGISTRATION_M = 0.001  # per-axis RMS of each view's offset
RAW_GRAZING_COS = 0.15  # a view grazes the surface where |normal . view| is below this ...
RAW_FLYING_SHARE = 0.1  # ... and this share of those points fly off, away from the camera,
RAW_FLYING_MEAN_M = 0.015  # by an exponential distance of this mean,
RAW_FLYING_MAX_M = 0.06  # cut at this


def _model_normals(scan: SyntheticScan) -> np.ndarray:
    """The scan's normals (P, 3) in the model frame."""
    return scan.normals @ _model_rotation(scan)


def with_raw_artifacts(scan: SyntheticScan, rng: np.random.Generator) -> SyntheticScan:
    """What a raw multi-view scanner's merged output has beyond noise: each point belongs to
    the horizontal view (``VIEW_AZIMUTHS`` at the 10-degree elevation) that faces it most, and
    each view's points are off by that view's random offset (``RAW_MISREGISTRATION_M`` per
    axis: steps where the patches meet); then flying pixels: where a view grazes the surface
    (``RAW_GRAZING_COS``), ``RAW_FLYING_SHARE`` of the points are pushed away from that camera
    along its ray (mixed depths at the silhouette's edge; exponential, ``RAW_FLYING_MEAN_M``
    mean, at most ``RAW_FLYING_MAX_M``), spikes joined to the mesh. A mesh's normals are taken
    again from its faces; a cloud keeps the ones it had. The truth is the scan's."""
    from dataclasses import replace

    el = np.radians(10.0)
    az = np.arange(VIEW_AZIMUTHS) * 2 * np.pi / VIEW_AZIMUTHS
    views = np.stack([np.cos(el) * np.sin(az), np.full(len(az), np.sin(el)), np.cos(el) * np.cos(az)], 1)
    P = _model_points(scan)
    N = _model_normals(scan)
    facing = N @ views.T  # (P, views)
    owner = np.argmax(facing, axis=1)
    P = P + rng.normal(scale=RAW_MISREGISTRATION_M, size=(len(views), 3))[owner]
    flown = np.zeros(len(P), bool)
    for v, d in enumerate(views):
        graze = np.flatnonzero((np.abs(facing[:, v]) < RAW_GRAZING_COS) & ~flown)
        pick = graze[rng.random(len(graze)) < RAW_FLYING_SHARE]
        P[pick] -= d * np.minimum(rng.exponential(RAW_FLYING_MEAN_M, len(pick)), RAW_FLYING_MAX_M)[:, None]
        flown[pick] = True
    points = _from_model(scan, P)
    normals = scan.normals if scan.faces is None else vertex_normals(points, scan.faces).astype(np.float64)
    return replace(scan, points=points, normals=normals)


def cut_soles(scan: SyntheticScan, height_m: float = 0.01) -> SyntheticScan:
    """The floor taken off as processing software often does, by a horizontal plane
    ``height_m`` above it (the true body's lowest point, model frame): the soles go with it."""
    return keep_points(scan, _model_points(scan)[:, 1] > float(scan.true_posed[:, 1].min()) + height_m)


def degrade(scan: SyntheticScan, kinds: tuple[str, ...] | list[str], rng: np.random.Generator) -> SyntheticScan:
    """Apply the named degradations (``DEGRADATIONS``) in order."""
    for k in kinds:
        if k == "holes":
            scan = with_holes(scan, rng)
        elif k == "cut_head":
            scan = cut_head_top(scan)
        elif k == "capped_head":
            scan = capped_head(scan)
        elif k == "floor_disc":
            scan = with_floor(scan, rng, "disc")
        elif k == "scanner_floor":
            scan = with_floor(scan, rng, "scanner")
        elif k == "room_floor":
            scan = with_floor(scan, rng, "room")
        elif k == "dark_hair":
            scan = without_hair_returns(scan)
        elif k == "no_head":
            scan = without_head(scan)
        elif k == "long_hair":
            scan = with_long_hair(scan)
        elif k == "raw_artifacts":
            scan = with_raw_artifacts(scan, rng)
        elif k == "cut_soles":
            scan = cut_soles(scan)
        else:
            raise ValueError(f"unknown degradation {k!r}; expected one of {DEGRADATIONS}")
    return scan

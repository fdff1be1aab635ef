"""The page's pose presets as body-model poses, adapted per body so that arms stay outside the
torso and thighs. Pure numpy.

The presets live in one data file, ``web_client/poses.json``, read by the page and here: for
each preset, world directions (Y up, facing +Z, the character's left = +X) of the segments
bone -> child, applied bone by bone in a fixed order (each bone is turned by the smallest
rotation that takes its segment onto the target direction, its children following), exactly as
the page's ``applyPose`` does on the GLB skeleton (whose rest bone frames are the world frame,
as ``service.model.body.lbs``).

Adaptation (:func:`adapted_poses`): the shoulder abduction of each arm is increased, in steps of
``ABDUCTION_STEP_DEG``, until no arm vertex is inside the torso or thighs (checked on the posed
body: :func:`arm_vertices_inside`), so presets suit heavy bodies too.

Shapes: avatar vertices (V, 3) metres; joints (17, 3); poses (17, 3) axis-angle radians in
``BONES`` order.
"""
from __future__ import annotations

import functools
import json
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from service.model.body import lbs as _lbs
from service.model.body.model import BONES
from service.model.geometry.mesh import closest_points_on_mesh, mesh_edges, vertex_faces, winding_numbers

POSES_FILE = Path(__file__).resolve().parents[3] / "web_client" / "poses.json"
ABDUCTION_STEP_DEG = 6.0  # extra shoulder abduction per adaptation step (then one bisection)
MAX_EXTRA_ABDUCTION_DEG = 60.0
ARM_BONES = {"l": ("upper_arm_l", "forearm_l", "hand_l"), "r": ("upper_arm_r", "forearm_r", "hand_r")}
TORSO_BONES = ("pelvis", "spine", "chest", "thigh_l", "thigh_r", "shin_l", "shin_r")
ARM_POINT_MIN_WEIGHT = 0.95  # an arm vertex: at least this much weight on one arm's bones
TORSO_MAX_ARM_WEIGHT = 0.02  # a torso vertex: at most this much on either arm
UPPER_ARM_SKIP = 0.6  # upper-arm vertices this close to the shoulder (x upper-arm length) are not tested:
# the armpit presses on the chest when the arm comes down, on heavy bodies flesh on flesh
NEAR_TORSO_M = 0.04  # the fast check skips arm points farther than this from every torso vertex
# the adaptation's version: bump it when a change here alters the poses it returns (stored
# adapted poses are keyed by it, with the presets and the body, see service.application.poses)
ADAPTATION_VERSION = 1
CONFIRM_BATCH = 8  # candidates confirmed by winding number at a time (deepest first)


@functools.lru_cache(maxsize=2)
def _read(path: str) -> dict:
    return json.loads(Path(path).read_text())


def presets(path: str | Path | None = None) -> dict:
    """``web_client/poses.json``: {"order": [...], "child": {...}, "poses": {name: {...}}}."""
    for p in ([Path(path)] if path else [POSES_FILE, Path.cwd() / "web_client" / "poses.json"]):
        if p.exists():
            return _read(str(p))
    raise FileNotFoundError("web_client/poses.json not found")


def targets(preset: dict) -> dict[str, np.ndarray]:
    """A preset's bone -> unit target direction (3,), ``mirror`` expanded (x negated for _r)."""
    out = {k: np.asarray(v, np.float64) for k, v in preset.get("targets", {}).items()}
    if preset.get("mirror"):
        for k, v in list(out.items()):
            if k.endswith("_l"):
                out[k[:-2] + "_r"] = v * np.array([-1.0, 1.0, 1.0])
    return {k: v / np.linalg.norm(v) for k, v in out.items()}


def rotation_between(a: np.ndarray, b: np.ndarray, max_angle: float = np.pi) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction a (3,) onto b (3,) (three.js'
    ``Quaternion.setFromUnitVectors``), or towards it by at most ``max_angle`` radians."""
    a = a / max(float(np.linalg.norm(a)), 1e-12)
    b = b / max(float(np.linalg.norm(b)), 1e-12)
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        perp = np.cross(a, [1.0, 0, 0]) if abs(a[0]) < 0.9 else np.cross(a, [0, 0, 1.0])
        return _lbs.axis_angle_to_matrix(min(np.pi, max_angle) * perp / np.linalg.norm(perp))
    return _lbs.axis_angle_to_matrix(axis / s * min(float(np.arctan2(s, c)), max_angle))


def pose_from_directions(joints: np.ndarray, parents: np.ndarray, bone_targets: dict[str, np.ndarray],
                         order: list[str], child: dict[str, str]) -> np.ndarray:
    """Local rotations as axis-angle (17, 3) that point each segment bone -> child along its
    target direction, bones taken in ``order``: R_j = R_parent,world^T  Delta  R_j,world, with
    Delta the smallest rotation from the segment's current world direction to the target."""
    J = len(parents)
    R = np.tile(np.eye(3), (J, 1, 1))
    joints = np.asarray(joints, np.float64)
    for bone in order:
        if bone not in bone_targets:
            continue
        j, c = BONES.index(bone), BONES.index(child[bone])
        G = _lbs.global_transforms(joints, parents, R)
        posed = np.einsum("jab,jb->ja", G[:, :3, :3], joints) + G[:, :3, 3]
        delta = rotation_between(posed[c] - posed[j], bone_targets[bone])
        parent_world = G[parents[j], :3, :3] if parents[j] >= 0 else np.eye(3)
        R[j] = parent_world.T @ delta @ G[j, :3, :3]
    return _lbs.matrix_to_axis_angle(R)


def abducted(bone_targets: dict[str, np.ndarray], side: str, degrees: float) -> dict[str, np.ndarray]:
    """The targets with one arm ('l' or 'r') turned away from the body by ``degrees`` about the
    forward axis (+Z): the whole arm swings out in the frontal plane."""
    a = np.radians(degrees) * (1.0 if side == "l" else -1.0)
    Rz = _lbs.axis_angle_to_matrix(np.array([0.0, 0.0, a]))
    return {k: (Rz @ v if k in ARM_BONES[side] else v) for k, v in bone_targets.items()}


def preset_poses(model, vertices: np.ndarray, path: str | Path | None = None) -> dict[str, np.ndarray]:
    """The page's presets on one avatar (V, 3), unadapted: {name: (17, 3) axis-angle}."""
    spec = presets(path)
    joints = model.joints(vertices)
    return {name: pose_from_directions(joints, model.bone_parents, targets(p), spec["order"], spec["child"])
            for name, p in spec["poses"].items()}


def stride_poses(model, vertices: np.ndarray, amplitudes: tuple[float, ...],
                 path: str | Path | None = None) -> list[np.ndarray]:
    """The page's walking preset on one avatar (V, 3), and its mirror (the other leg forward),
    each at the ``amplitudes``: every target direction t taken to (1 - a) down + a t (a = 1: the
    preset; a < 1 a shorter stride, a > 1 a longer one). Returns [(17, 3) axis-angle], the
    preset's amplitudes first, then the mirror's."""
    spec = presets(path)
    joints = model.joints(np.asarray(vertices, np.float64))
    walk = targets(spec["poses"]["walking"])
    flip = np.array([-1.0, 1.0, 1.0])
    mirror = {(k[:-2] + ("_r" if k.endswith("_l") else "_l")): v * flip for k, v in walk.items()}
    down = np.array([0.0, -1.0, 0.0])
    out = []
    for tg in (walk, mirror):
        for a in amplitudes:
            t = {k: (1 - a) * down + a * v for k, v in tg.items()}
            out.append(pose_from_directions(joints, model.bone_parents, {k: v / np.linalg.norm(v) for k, v in t.items()},
                                            spec["order"], spec["child"]))
    return out


def preset_transforms(model, vertices: np.ndarray, path: str | Path | None = None) -> np.ndarray:
    """Bone transforms (P, 17, 4, 4) of the page's presets (not adapted) on the avatar
    ``vertices`` (V, 3), in ``presets()`` order: the test poses of garment skin weights
    (``service.model.garments.skin_weights.release_stretched``)."""
    X = np.asarray(vertices, np.float64)
    return np.stack([model.forward(pose=p, vertices=X).transforms for p in preset_poses(model, X, path).values()])


# -- collision check: arm vertices inside the torso or thighs -------------------------------------
@functools.lru_cache(maxsize=4)
def _labels(model) -> dict:
    """Which body vertices are tested as arm points, and the torso surface they are tested
    against (from the body's skin weights; computed once per model)."""
    nb = model.n_body_vertices
    idx, w = model.lbs_indices[:nb], model.lbs_weights[:nb].astype(np.float64)
    W = np.zeros((nb, len(BONES)))
    np.add.at(W, (np.repeat(np.arange(nb), idx.shape[1]), idx.reshape(-1)), w.reshape(-1))
    arm_w = {s: W[:, [BONES.index(b) for b in bones]].sum(1) for s, bones in ARM_BONES.items()}
    torso_w = W[:, [BONES.index(b) for b in TORSO_BONES]].sum(1)
    torso_v = (torso_w > 0.5) & (arm_w["l"] < TORSO_MAX_ARM_WEIGHT) & (arm_w["r"] < TORSO_MAX_ARM_WEIGHT)
    F = model.body_faces
    torso_faces = F[torso_v[F].all(axis=1)]
    used = np.unique(torso_faces)
    remap = np.full(nb, -1, np.int64)
    remap[used] = np.arange(len(used))
    main = _lbs.main_bone(idx, w)
    # the body surface without one arm: an arm point's winding number with respect to it is ~1
    # inside the torso and ~0 outside (the hole at the shoulder is far from the tested points),
    # whatever the arm does to itself (a bent elbow overlapping its own upper arm)
    without = {s: F[~(arm_w[s][F] > 0.5).all(axis=1)] for s in ARM_BONES}
    tf = remap[torso_faces]
    return {"arm_w": arm_w, "main": main, "torso_vertices": used, "torso_faces": tf,
            "torso_vertex_faces": vertex_faces(tf, len(used)), "without_arm": without}


def arm_points(model, vertices: np.ndarray, side: str) -> np.ndarray:
    """Indices of the body vertices tested for one arm: mostly skinned to that arm, the upper
    arm's shoulder end left out (the armpit touches the torso by design)."""
    lab = _labels(model)
    nb = model.n_body_vertices
    J = model.joints(vertices)
    up, fo = BONES.index(ARM_BONES[side][0]), BONES.index(ARM_BONES[side][1])
    X = np.asarray(vertices[:nb], np.float64)
    length = np.linalg.norm(J[fo] - J[up])
    along = (X - J[up]) @ ((J[fo] - J[up]) / length)
    ok = lab["arm_w"][side] >= ARM_POINT_MIN_WEIGHT
    ok &= (lab["main"] != up) | (along > UPPER_ARM_SKIP * length)
    return np.flatnonzero(ok)


def _inside_candidates(model, X: np.ndarray, probe: np.ndarray, near_m: float | None = NEAR_TORSO_M) -> np.ndarray:
    """Indices into ``probe`` (P, 3) of the points that may be inside the torso or thighs of the
    posed body X (>= n_body, 3), deepest first: within ``near_m`` of a torso vertex (None: any)
    and behind the closest torso triangle (face-normal sign). An arm entering the torso has
    points just behind its surface (the arm's own vertex spacing), so "any inside" is decided
    among the near ones; the far ones skip the closest-point search (most of its cost)."""
    lab = _labels(model)
    TV, TF = X[lab["torso_vertices"]], lab["torso_faces"]
    tree = cKDTree(TV)
    near = (np.arange(len(probe)) if near_m is None
            else np.flatnonzero(np.isfinite(tree.query(probe, distance_upper_bound=near_m)[0])))
    if not len(near):
        return np.zeros(0, np.int64)
    face, q, _ = closest_points_on_mesh(probe[near], TV, TF, tree=tree, vert_faces=lab["torso_vertex_faces"])
    tri = TV[TF[face]]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    off = probe[near] - q
    order = np.flatnonzero(np.einsum("ij,ij->i", off, fn) < 0)  # behind the closest triangle
    depth = np.linalg.norm(off, axis=1)
    return near[order[np.argsort(-depth[order])]]


def _confirmed(model, X: np.ndarray, probe: np.ndarray, side: str) -> np.ndarray:
    """(P,) bool: the generalised winding number of each probe point (P, 3) with respect to the
    posed body X without that arm's faces is > 1/2 (inside the torso or thighs)."""
    return winding_numbers(probe, X, _labels(model)["without_arm"][side]) > 0.5


def arm_vertices_inside(model, posed: np.ndarray, points: np.ndarray, side: str, *,
                        exhaustive: bool = False) -> np.ndarray:
    """The arm points (indices into the body) of a posed body (>= n_body, 3) that are inside the
    torso or thighs. Candidates (:func:`_inside_candidates`) are confirmed by their generalised
    winding number with respect to the posed body surface without that arm's faces. With
    ``exhaustive`` every arm point is checked by winding number (slow; the tests' reference);
    without, the search stops at the first confirmed batch (enough to decide "any")."""
    nb = model.n_body_vertices
    X = np.asarray(posed[:nb], np.float64)
    probe = X[points]
    cand = np.arange(len(points)) if exhaustive else _inside_candidates(model, X, probe)
    found = []
    for s in range(0, len(cand), CONFIRM_BATCH):  # stop at the first batch that confirms any
        c = cand[s:s + CONFIRM_BATCH]
        hit = c[_confirmed(model, X, probe[c], side)]
        found.append(points[hit])
        if len(hit) and not exhaustive:
            break
    return np.concatenate(found) if found else np.zeros(0, np.int64)


INSIDE_SHARE_STRIDE = 4  # arm_inside_share: every 4th arm point tested ...
INSIDE_SHARE_SAMPLE = 24  # ... and this many of its candidates confirmed by winding number


def arm_inside_share(model, posed: np.ndarray, points: np.ndarray, side: str) -> float:
    """An estimate of the share of an arm's points (indices into the body) of a posed body
    (>= n_body, 3) inside the torso or thighs, at a bounded cost (for scoring many poses):
    among every ``INSIDE_SHARE_STRIDE``-th point, those behind their closest torso triangle
    (:func:`_inside_candidates`, at any distance), times the confirmed fraction of
    ``INSIDE_SHARE_SAMPLE`` of them taken evenly over their depths. A forearm resting on a hip
    gives a few per cent, a hand hidden in a thigh or an arm through the chest tens."""
    points = np.asarray(points)[::INSIDE_SHARE_STRIDE]
    if not len(points):
        return 0.0
    nb = model.n_body_vertices
    X = np.asarray(posed[:nb], np.float64)
    probe = X[points]
    cand = _inside_candidates(model, X, probe, near_m=None)
    if not len(cand):
        return 0.0
    sample = cand[np.unique(np.linspace(0, len(cand) - 1, INSIDE_SHARE_SAMPLE).astype(np.int64))]
    return float(len(cand) * _confirmed(model, X, probe[sample], side).mean() / len(points))


def adapted_poses(model, vertices: np.ndarray, path: str | Path | None = None) -> dict[str, np.ndarray]:
    """The page's presets for one avatar (V, 3), each arm's abduction increased (steps of
    ``ABDUCTION_STEP_DEG``, then one bisection, at most ``MAX_EXTRA_ABDUCTION_DEG``) until none
    of its vertices is inside the torso or thighs. Returns {name: (17, 3) axis-angle}."""
    spec = presets(path)
    X = np.asarray(vertices, np.float64)
    joints = model.joints(X)
    pts = {s: arm_points(model, X, s) for s in ARM_BONES}
    out = {}
    for name, p in spec["poses"].items():
        tg = targets(p)
        extra = {"l": 0.0, "r": 0.0}

        def pose_with(extra):
            cur = tg
            for s, a in extra.items():
                cur = abducted(cur, s, a)
            return pose_from_directions(joints, model.bone_parents, cur, spec["order"], spec["child"])

        def collides(side, a):
            pose = pose_with({**extra, side: a})
            posed = model.forward(pose=pose, vertices=X).vertices
            return len(arm_vertices_inside(model, posed, pts[side], side)) > 0

        for side in ARM_BONES:  # the arms are independent: one side at a time
            if not any(b in tg for b in ARM_BONES[side]):
                continue
            lo, hi = None, 0.0  # lo: largest known colliding extra; hi: candidate
            while hi <= MAX_EXTRA_ABDUCTION_DEG and collides(side, hi):
                lo, hi = hi, hi + ABDUCTION_STEP_DEG
            if lo is not None and hi <= MAX_EXTRA_ABDUCTION_DEG:  # one bisection: half a step
                mid = 0.5 * (lo + hi)
                if not collides(side, mid):
                    hi = mid
            extra[side] = min(hi, MAX_EXTRA_ABDUCTION_DEG)
        out[name] = pose_with(extra)
    return out


# -- figures ----------------------------------------------------------------------------------------
def edge_stretch(rest: np.ndarray, posed: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Length ratio posed / rest (E,) of every mesh edge (rest (n, 3), posed (n, 3))."""
    e = mesh_edges(faces)
    r = np.linalg.norm(rest[e[:, 0]] - rest[e[:, 1]], axis=1)
    p = np.linalg.norm(posed[e[:, 0]] - posed[e[:, 1]], axis=1)
    ok = r > 1e-9
    return p[ok] / r[ok]

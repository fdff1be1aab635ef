"""Stage 1, the initialisation (no human in the loop): the coarse parametric ICP that frees the
skeleton from the pelvis outwards, the limb search at discrete turns, limbs aimed at the scan's
landmarks, the stature from the scan's extent and the headless hypothesis.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from service.model.body import poses as POSES
from service.model.body.model import BONES
from service.model.body.lbs import axis_angle_to_matrix, matrix_to_axis_angle
from service.model.body.poses import rotation_between
from service.model.fitting import landmarks as LM, scan_cleanup as SC
from service.model.formats.frames import up_candidates
from service.model.geometry.mesh import vertex_normals
from service.model.geometry.solvers import damped_step, point_to_plane_normal_equations, trimmed_mean
from service.model.fitting.params import DEFAULT_PARAMS, FitParams, TUNING
from service.model.fitting.prepare import (
    _make_scan,
    _posed_normals,
    _Scan,
    _yaw,
    seen_shares,
)
from service.model.fitting.regions import _clothing_weight, _hair, finger_weights, loose_region_weight
from service.model.fitting.rig import (
    _anchor_terms,
    _apply_pose,
    _bone_ids,
    _joint_limit_terms,
    _pose_jacobian,
    _pose_model,
    _Rig,
    _smoothness,
    _State,
    _Sub,
    _subset,
    ALL_BONES,
    BONE_LEVELS,
    limit_violation,
    ROOT_ONLY,
)


def _coarse(rig: _Rig, scan: _Scan, s: _State, sub: "_Sub", rest_normals: np.ndarray,
            schedule: list[tuple[np.ndarray, int]], clothed: bool, params: FitParams,
            omega: float | None = None, contact: float | None = None,
            landmarks: tuple | None = None, anchor: tuple | None = None,
            hole_spacing: float | None = None, fingers_from: int | None = None,
            shape_free: np.ndarray | None = None) -> tuple[_State, float]:
    """Parametric ICP on subsamples: per iteration, correspondences both ways (template
    subsample -> nearest scan point, scan subsample -> nearest template vertex) rejected by
    normals and distance, point-to-plane residuals weighted for clothing, then one damped
    Gauss-Newton step on (translation, the scheduled bones, the first shape components).
    ``schedule``: [(bones, n_shape_components)] per iteration; ``contact``: the clothing
    weight's contact depth (``_clothing_weight``; None: constant ``inside_weight``). Returns the state and the
    final trimmed mean distance (metres) both ways. ``landmarks``: (effector subset, targets
    (e, 3), weight, iterations): point-to-point pulls of the effectors to the scan's tips in the
    first ``iterations`` iterations (issue 12's landmark initialisation). ``fingers_from``: from
    this iteration on, the fingers' pairs weighted by their residuals (``FitParams.finger_scale``).
    ``hole_spacing``: the
    scan subsample's point spacing (metres); given, a template vertex whose nearest scan point
    is off to its side (a hole's or a cut head top's rim, ``scan_cleanup.over_hole``) is not
    pulled to it, as in Alg. 1. ``shape_free`` (n,) bool over the template's vertices: their
    pairs move the pose, not the shape (``FitParams.face_shape_min_seen``)."""
    cos_rej = np.cos(np.radians(params.coarse_normal_reject_deg))
    offsets = None  # (17,) metres: the clothes' stand-off per region (FitParams.cloth_offset_mean)
    if clothed and contact is not None and params.cloth_offset_mean is not None:
        # Exponential prior of the stand-offs, -log p = o / mean, in the data terms' units
        # (squared metres: 2 s^2 times a negative log-likelihood, s^2 the shape prior's
        # weight), with a small quadratic term so that the Newton step is bounded
        offsets = np.zeros(len(rig.parents))
        offset_prior_gradient = 2.0 * params.shape_prior / params.cloth_offset_mean
        offset_prior_hessian = np.eye(len(offsets)) * offset_prior_gradient / params.cloth_offset_mean
    Ps = scan.points[scan.sub]
    Ns = scan.normals[scan.sub]
    m = len(sub.idx)
    omega = params.coarse_bone_smoothness if omega is None else omega
    lam = params.shape_prior
    cost = np.inf
    for it, (bones, n_shape) in enumerate(schedule):
        p = _pose_model(rig, s, sub)
        nv = _posed_normals(rest_normals, p)
        # template -> scan
        d1, j1 = scan.sub_tree.query(p.v)
        ok1 = (d1 < params.coarse_max_dist) & (np.einsum("ij,ij->i", nv, Ns[j1]) > cos_rej)
        if hole_spacing is not None:
            ok1 &= ~SC.over_hole(p.v, Ps[j1], Ns[j1], hole_spacing, scan.sub_tree)
        if scan.sub_rim is not None:  # a hole's rim (FitParams.rim_reject)
            ok1 &= ~scan.sub_rim[j1]
        # scan -> template
        d2, i2 = cKDTree(p.v).query(Ps)
        if params.exclusive_hops is not None:
            ok1 &= rig.hops[sub.region, sub.region[i2[j1]]] <= params.exclusive_hops
        ok2 = (d2 < params.coarse_max_dist) & (np.einsum("ij,ij->i", nv[i2], Ns) > cos_rej)
        wv = sub.area if params.area_weighted else None
        if params.absent_bones:  # no pairs either way (FitParams.absent_bones)
            present = ~np.isin(sub.region, _bone_ids(params.absent_bones))
            ok1 &= present
            ok2 &= present[i2]
            cost = 0.5 * (trimmed_mean(d1[present], weights=None if wv is None else wv[present]) + trimmed_mean(d2))
        else:
            cost = 0.5 * (trimmed_mean(d1, weights=wv) + trimmed_mean(d2))
        if not (ok1.any() and ok2.any()):
            break
        a_i, a_n, a_c = np.nonzero(ok1)[0], Ns[j1[ok1]], Ps[j1[ok1]]
        b_i, b_n, b_c = i2[ok2], nv[i2[ok2]], Ps[ok2]
        vi = np.r_[a_i, b_i]
        nn = np.r_[a_n, b_n]
        cc = np.r_[a_c, b_c]
        r = np.einsum("ij,ij->i", nn, p.v[vi] - cc)
        if offsets is not None:  # the clothes moved in by their region's stand-off
            r = r + offsets[sub.region[vi]]
        wa = np.full(len(a_i), m / len(a_i)) if wv is None else m * wv[a_i] / wv[a_i].sum()
        hair = _hair(rig, params)[sub.idx[vi]] if params.hair_region and not clothed else None
        w = _clothing_weight(r, clothed, params, contact, hair) * np.r_[wa, np.full(len(b_i), m / len(b_i))]
        if clothed and contact is not None and params.loose_region_depth is not None:
            w = w * loose_region_weight(r, sub.region[vi], params.loose_region_depth)
        w = w / np.maximum(1.0, np.abs(r) / params.robust_scale)  # Huber-like: far pairs count less
        if fingers_from is not None and it >= fingers_from:  # bent fingers (FitParams.finger_scale)
            w = w * finger_weights(r, rig.fingers[sub.idx[vi]], params.finger_scale)
        comps = np.arange(n_shape)
        Jall = _pose_jacobian(rig, p, bones, comps if n_shape else None, params.compiled)
        if n_shape and shape_free is not None:  # those vertices' pairs leave the shape be
            Jall[shape_free[sub.idx], :, 3 + 3 * len(bones):] = 0.0
        if offsets is not None:
            H, g = point_to_plane_normal_equations(Jall, vi, nn, w, r, sub.region[vi], len(offsets),
                                                   compiled=params.compiled)
            H[-len(offsets):, -len(offsets):] += offset_prior_hessian
            g[-len(offsets):] += offset_prior_gradient
        else:
            H, g = point_to_plane_normal_equations(Jall, vi, nn, w, r, compiled=params.compiled)
        npz = 3 + 3 * len(bones)
        if landmarks is not None and it < landmarks[3]:
            eff, targets, w_lm, _ = landmarks
            pe = _pose_model(rig, s, eff)
            Je = _pose_jacobian(rig, pe, bones, comps if n_shape else None, params.compiled)
            Je = Je.reshape(-1, Je.shape[2])
            ne = Je.shape[1]
            H[:ne, :ne] += w_lm * Je.T @ Je
            g[:ne] += w_lm * Je.T @ (pe.v - targets).reshape(-1)
        Hs, gs = _smoothness(rig, s, p, bones, omega)
        if anchor is not None:
            Ha, ga = _anchor_terms(rig, s, p, bones, *anchor)
            Hs, gs = Hs + Ha, gs + ga
        Hl, gl = _joint_limit_terms(rig, s, p, bones, params.joint_limit_weight)
        H[:npz, :npz] += Hs + Hl
        g[:npz] += gs + gl
        if n_shape:
            sh = slice(npz, npz + n_shape)
            H[sh, sh] += lam * np.diag(rig.precision[comps])
            g[sh] += lam * rig.precision[comps] * s.beta[comps]
            if params.posture_weight > 0:  # shape and posture decoupled
                A = rig.posture[:, comps]
                H[sh, sh] += params.posture_weight * A.T @ A
                g[sh] += params.posture_weight * A.T @ (rig.posture @ s.beta)
        if offsets is None:
            delta = damped_step(H, g, damping=params.damping, levenberg=params.levenberg)
        else:
            delta = _offset_step(H, g, offsets, params)
        step = np.abs(delta[3:npz]).max(initial=0.0)
        if step > params.max_rotation_step:  # keep each rotation step small (linearisation)
            delta *= params.max_rotation_step / step
        _apply_pose(rig, s, p, bones, delta[:npz])
        if n_shape:
            s.beta[comps] += delta[npz:npz + n_shape]
        if offsets is not None:
            offsets = np.maximum(offsets + delta[len(delta) - len(offsets):], 0.0)
    return s, cost




def _offset_step(H: np.ndarray, g: np.ndarray, offsets: np.ndarray, params: FitParams) -> np.ndarray:
    """The damped Gauss-Newton step (P,) of ``_coarse`` whose last len(offsets) unknowns are the
    clothes' stand-offs o >= 0 (``FitParams.cloth_offset_mean``): min 1/2 d^T H d + g^T d subject
    to o + d_o >= 0, by active sets: an offset the step would take below 0 is held at exactly 0
    and the rest solved again given that; one held whose gradient points into o > 0 is freed."""
    base = len(g) - len(offsets)
    fixed = np.zeros(len(g), bool)
    delta = np.zeros(len(g))
    for _ in range(TUNING.offset_active_set_rounds):
        delta = np.zeros(len(g))
        delta[base:][fixed[base:]] = -offsets[fixed[base:]]
        fr = ~fixed
        delta[fr] = damped_step(H[np.ix_(fr, fr)], g[fr] + H[np.ix_(fr, fixed)] @ delta[fixed],
                                damping=params.damping, levenberg=params.levenberg)
        low = fr[base:] & (offsets + delta[base:] < 0)
        if low.any():
            fixed[base:] |= low
            continue
        free_up = fixed[base:] & ((H @ delta + g)[base:] < 0)  # the objective falls into o > 0
        if not free_up.any():
            break
        fixed[base:] &= ~free_up
    return delta


def _chamfer(rig: _Rig, scan: _Scan, s: _State, sub: _Sub, params: FitParams = DEFAULT_PARAMS) -> float:
    """Symmetric trimmed mean distance (m) between the template subsample and the scan's, the
    template's side weighted by vertex area (``FitParams.area_weighted``)."""
    v = _pose_model(rig, s, sub).v
    d1, _ = scan.sub_tree.query(v)
    d2, _ = cKDTree(v).query(scan.points[scan.sub])
    wv = sub.area if params.area_weighted else None
    if params.absent_bones:  # their vertices have no scan surface to be near (FitParams.absent_bones)
        present = ~np.isin(sub.region, _bone_ids(params.absent_bones))
        d1, wv = d1[present], None if wv is None else wv[present]
    return 0.5 * (trimmed_mean(d1, weights=wv) + trimmed_mean(d2))


# chains whose first bone is re-tried at discrete rotations (a limb caught in a local minimum)
SEARCH_BONES = tuple(BONES.index(b) for b in ("upper_arm_l", "upper_arm_r", "thigh_l", "thigh_r", "chest", "forearm_l",
                                              "forearm_r", "shin_l", "shin_r"))




def _limit_cost(s: _State, params: FitParams) -> float:
    if params.joint_limit_weight <= 0:
        return 0.0
    return TUNING.limit_cost_m_per_rad * float(np.abs(limit_violation(matrix_to_axis_angle(s.rot))).sum())


@dataclass(frozen=True)
class _Arms:
    """What the initialisation's arm-inside cost needs: the model (its torso surface) and the
    arm points tested per side (``poses.arm_points`` on the mean rest body)."""

    model: object
    points: dict


def _arms(model, params: FitParams) -> _Arms | None:
    if params.arm_inside_cost <= 0:
        return None
    rest = model.vertices(np.zeros(model.n_components))
    return _Arms(model, {side: POSES.arm_points(model, rest, side) for side in POSES.ARM_BONES})


def _init_cost(rig: _Rig, scan: _Scan, s: _State, sub: _Sub, params: FitParams, arms: _Arms | None,
               bound: float = np.inf) -> float:
    """The initialisation's cost of a state (metres): the symmetric distance (``_chamfer``),
    the joint limits' cost and, only where it can decide (that sum below ``bound``), the
    arms' share inside the torso or thighs times ``FitParams.arm_inside_cost`` (see there)."""
    cost = _chamfer(rig, scan, s, sub, params) + _limit_cost(s, params)
    if arms is None or cost >= bound:
        return cost
    posed = _pose_model(rig, s, _subset(rig, np.arange(len(rig.mean)))).v
    share = sum(POSES.arm_inside_share(arms.model, posed, pts, side) for side, pts in arms.points.items())
    return cost + params.arm_inside_cost * share


def _limb_search(rig: _Rig, scan: _Scan, s: _State, sub: _Sub, rest_normals: np.ndarray, clothed: bool,
                 params: FitParams, arms: _Arms | None = None) -> _State:
    """For each bone in SEARCH_BONES: try its local rotation turned by TUNING.search_angle_deg about
    each axis (both ways), let the bone's subtree settle for a few ICP iterations, keep the
    candidate of the lowest cost (``_init_cost``)."""
    best_cost = _init_cost(rig, scan, s, sub, params, arms)
    for b in SEARCH_BONES:
        bones = np.nonzero(rig.subtree[b])[0]
        for axis in np.vstack([np.eye(3), -np.eye(3)]):
            cand = s.copy()
            cand.rot[b] = axis_angle_to_matrix(axis * np.radians(TUNING.search_angle_deg)) @ cand.rot[b]
            cand, _ = _coarse(rig, scan, cand, sub, rest_normals, [(bones, 0)] * 3, clothed, params)
            cost = _init_cost(rig, scan, cand, sub, params, arms, bound=best_cost - 1e-4)
            if cost < best_cost - 1e-4:
                best_cost, s = cost, cand
    return s


# landmark initialisation (issue 12): the chain (upper, lower bone) aimed at each extremity,
# and the bone whose far end is the extremity's effector on the template
# per extremity: the chain of bones aimed at it, and (its bone, the bone its chain hangs from)
LANDMARK_CHAINS = {tip: tuple(BONES.index(b) for b in chain) for tip, chain in {
    "hand_l": ("upper_arm_l", "forearm_l"), "hand_r": ("upper_arm_r", "forearm_r"),
    "foot_l": ("thigh_l", "shin_l"), "foot_r": ("thigh_r", "shin_r")}.items()}
EFFECTOR_BONES = {tip: tuple(BONES.index(b) for b in pair) for tip, pair in {
    "head": ("head", "pelvis"), "hand_l": ("hand_l", "upper_arm_l"), "hand_r": ("hand_r", "upper_arm_r"),
    "foot_l": ("foot_l", "thigh_l"), "foot_r": ("foot_r", "thigh_r")}.items()}
LANDMARK_ANCHORS = (BONES.index("pelvis"), BONES.index("neck"))  # joints whose nearest scan points anchor the geodesics


def _effector_subset(rig: _Rig) -> _Sub:
    """The template vertex at the far end of each effector bone (``landmarks.LABELS`` order):
    among the vertices mostly skinned to the bone, the one farthest from its chain's root joint
    in the mean rest shape (the head top, fingertips, toe tips)."""
    idx = []
    for label in LM.LABELS:
        bone, anchor = EFFECTOR_BONES[label]
        cand = np.nonzero(rig.W[:, bone] > 0.5)[0]
        idx.append(cand[np.argmax(np.linalg.norm(rig.mean[cand] - rig.jmean[anchor], axis=1))])
    return _subset(rig, np.array(idx))


def _aim_limbs(rig: _Rig, s: _State, targets: dict, eff: _Sub) -> _State:
    """The state with each limb of ``targets`` ({label: (3,) scan tip}) turned, bone by bone
    from the limb's root (cyclic coordinate descent), so that its effector points at the tip."""
    s = s.copy()
    max_angle = np.radians(TUNING.aim_max_deg)
    for _ in range(TUNING.aim_rounds):
        for label, bones in LANDMARK_CHAINS.items():
            if label not in targets:
                continue
            k = LM.LABELS.index(label)
            for b in bones:
                p = _pose_model(rig, s, eff)
                q = p.G[b, :3, :3] @ p.joints[b] + p.G[b, :3, 3]  # the bone's posed joint
                Rw = rotation_between(p.v[k] - q, targets[label] - q, max_angle)
                Rp = p.G[rig.parents[b], :3, :3]
                s.rot[b] = Rp.T @ Rw @ Rp @ s.rot[b]
    return s


def _landmark_hypotheses(rig: _Rig, scan: _Scan, s0: _State, s_icp: _State, sub: _Sub,
                         rest_normals: np.ndarray, schedule: list, clothed: bool, params: FitParams,
                         arms: _Arms | None = None) -> _State:
    """Issue 12: the scan's extremities (``landmarks.find_extremities``) assigned to the
    template's effectors at the root-fitted state ``s0``; for the assignment and its left/right
    swaps the limbs are aimed at the tips and the coarse schedule run. The state of least
    cost (``_init_cost``) wins; ``s_icp`` (ICP alone) is one of the candidates, so a scan
    without usable landmarks (holes, a skirt, a hand on the hip) keeps it."""
    best_cost = _init_cost(rig, scan, s_icp, sub, params, arms)
    best = s_icp
    pts = scan.points[scan.sub]
    ext = LM.find_extremities(pts)
    eff = _effector_subset(rig)
    # the template's own geodesics from its anchors to its effectors, at the root-fitted pose
    p0 = _pose_model(rig, s0, sub)
    q0 = np.einsum("jab,jb->ja", p0.G[:, :3, :3], p0.joints) + p0.G[:, :3, 3]
    anchors = q0[list(LANDMARK_ANCHORS)]
    e0 = _pose_model(rig, s0, eff).v
    near = cKDTree(p0.v).query(e0)[1]  # the subsample's vertices nearest the effectors
    expected = LM.Extremities(p0.v[near], np.zeros(len(e0)), e0[0], near,
                              LM.knn_graph(p0.v, max_edge=TUNING.template_graph_max_edge_m)).anchor_geodesics(p0.v, anchors)
    tips = LM.assign(ext.points, ext.anchor_geodesics(pts, anchors), expected, e0)
    for h in LM.hypotheses(tips)[:params.landmark_hypotheses]:
        if not any(label in h for label in LANDMARK_CHAINS):
            continue
        cand = _aim_limbs(rig, s0, h, eff)
        keep = np.array([label in h for label in LM.LABELS])
        pull = (_subset(rig, eff.idx[keep]), np.array([h[label] for label in np.array(LM.LABELS)[keep]]),
                TUNING.landmark_weight * len(sub.idx), int(TUNING.landmark_pull_share * len(schedule)))
        cand, _ = _coarse(rig, scan, cand, sub, rest_normals, schedule, clothed, params, landmarks=pull)
        cost = _init_cost(rig, scan, cand, sub, params, arms, bound=best_cost - TUNING.landmark_margin_m)
        if cost < best_cost - TUNING.landmark_margin_m:
            best_cost, best = cost, cand
    return best




def _coarse_setup(rig: _Rig, params: FitParams, rng: np.random.Generator) -> tuple[_Sub, np.ndarray, list]:
    """The initialisation's template subsample (``coarse_points`` vertices), its rest normals
    (m, 3) and the coarse schedule: the bone levels in turn, then every bone with the first
    ``coarse_shape_components`` shape components."""
    n = len(rig.mean)
    idx = np.sort(rng.choice(n, size=min(params.coarse_points, n), replace=False))
    n_it = params.coarse_iterations
    per_level = max(1, n_it // (2 * len(BONE_LEVELS)))
    schedule = [(lv, 0) for lv in BONE_LEVELS for _ in range(per_level)]
    schedule += [(ALL_BONES, params.coarse_shape_components)] * max(1, n_it - len(schedule))
    return _subset(rig, idx), vertex_normals(rig.mean, rig.faces, rig.incidence)[idx], schedule


def _initialise(rig: _Rig, points_m: np.ndarray, normals: np.ndarray, clothed: bool,
                params: FitParams, rng: np.random.Generator, arms: _Arms | None = None):
    """Up axis, facing and a coarse pose and shape (see module docstring). Returns
    (up label, R0 (3, 3), t0 (3,), scan in the model frame, state)."""
    sub, rest_normals, schedule = _coarse_setup(rig, params, rng)
    model_centre = rig.mean.mean(0)
    candidates = []
    for up, Rup in up_candidates(points_m):
        for k in range(params.yaw_steps):
            R = _yaw(2 * np.pi * k / params.yaw_steps) @ Rup
            P = points_m @ R.T
            t = np.array([model_centre[0], 0.0, model_centre[2]]) - np.array([P[:, 0].mean(), P[:, 1].min(), P[:, 2].mean()])
            candidates.append((up, R, t))
    screened = []
    for up, R, t in candidates:
        scan = _make_scan(points_m, normals, R, t, params.coarse_points, rng)
        s = _State(np.zeros(len(rig.U)), np.tile(np.eye(3), (17, 1, 1)), np.zeros(3))
        s, cost = _coarse(rig, scan, s, sub, rest_normals, [(ROOT_ONLY, 0)] * 5, clothed, params)
        screened.append((cost, up, R, t, scan, s))
    screened.sort(key=lambda x: x[0])
    best = None
    coarse = []
    chosen = screened[:params.coarse_candidates]
    if params.coarse_each_up:  # both up-axis signs reach the coarse stage (FitParams.coarse_each_up)
        for label in dict.fromkeys(c[1] for c in screened):
            if not any(c[1] == label for c in chosen):
                chosen.append(next(c for c in screened if c[1] == label))
    for cost0, up, R, t, scan, s0 in chosen:
        s, cost = _coarse(rig, scan, s0.copy(), sub, rest_normals, schedule, clothed, params)
        coarse.append((cost, up, R, t, scan, s, s0))
    coarse.sort(key=lambda x: x[0])
    _, up, R, t, scan, s, s0 = coarse[0]
    if params.landmark_init:  # issue 12: limbs aimed at the scan's extremities, several hypotheses
        best = None
        for c_cost, up_c, R_c, t_c, scan_c, s_c, s0_c in coarse[:max(1, params.landmark_candidates)]:
            if c_cost > params.landmark_candidate_ratio * coarse[0][0]:
                break  # far behind the best: not a facing the landmarks could prefer
            s_c = _landmark_hypotheses(rig, scan_c, s0_c, s_c, sub, rest_normals, schedule, clothed, params, arms)
            cost = _init_cost(rig, scan_c, s_c, sub, params, arms, bound=np.inf if best is None else best[0])
            if best is None or cost < best[0]:
                best = (cost, up_c, R_c, t_c, scan_c, s_c)
        _, up, R, t, scan, s = best
    if params.limb_search:
        s = _limb_search(rig, scan, s, sub, rest_normals, clothed, params, arms)
        s, _ = _coarse(rig, scan, s, sub, rest_normals, schedule[-4:], clothed, params)
    if params.init_stature_max is not None and not clothed:  # shoes, hats: not the body's height
        s2 = _stature_from_extent(rig, scan, s, params)
        if s2 is not None:
            s, _ = _coarse(rig, scan, s2, sub, rest_normals, schedule[-4:], clothed, params)
    return up, R, t, s, [c[0] for c in screened]


def _stature_from_extent(rig: _Rig, scan: _Scan, s: _State, params: FitParams) -> _State | None:
    """The coarse state with its rest stature scaled by the scan's height over the posed
    body's (both along the model's up axis, in the same posture): the least-prior change of the
    shape that does it. None when the ratio is beyond ``init_stature_max``."""
    top, soles = rig.stature_ids
    V = _pose_model(rig, s, _subset(rig, np.arange(len(rig.mean)))).v
    ratio = float(np.ptp(scan.points[:, 1]) / max(np.ptp(V[:, 1]), 1e-6))
    if abs(ratio - 1.0) > params.init_stature_max:
        return None
    ends = np.concatenate([[top], soles])
    y = rig.mean[ends, 1] + s.beta @ rig.U[:, ends, 1]  # rest heights of the top and the soles
    sole = ends[1 + np.argmin(y[1:])]
    h = y[0] - y[1:].min()  # the rest stature, as ``measurements`` reads it
    g = rig.U[:, top, 1] - rig.U[:, sole, 1]  # (K,) d stature / d beta
    C = 1.0 / rig.precision
    out = s.copy()
    out.beta = s.beta + h * (ratio - 1.0) * C * g / float(g @ (C * g))
    return out


def _without_head(rig: _Rig, pts_m: np.ndarray, nrm: np.ndarray, clothed: bool, params: FitParams, seed: int,
                  rims: tuple | None, s: _State, R0: np.ndarray, t0: np.ndarray) -> tuple[tuple | None, dict]:
    """The initialisation's coarse stage again with the head absent (``FitParams.headless_check``),
    from its result (the limbs it found, in its frame R0 (3, 3), t0 (3,)) with the head and neck
    at rest and the mean shape: the scan pts_m (P, 3) metres with normals nrm (P, 3), ``s`` the
    first initialisation's state. Returns ((state, seen shares, params with the head absent) when
    the scan has no head, else None; the figures of the choice for the fit's stats)."""
    from service.model.body.model import BONES

    t0_s = time.perf_counter()
    head = BONES.index("head")
    p1 = replace(params, absent_bones=(*params.absent_bones, "head"), hair_region=False)
    rng = np.random.default_rng([seed, 1])
    sub, rest_normals, schedule = _coarse_setup(rig, p1, rng)
    s1 = s.copy()
    s1.rot[[head, BONES.index("neck")]] = np.eye(3)
    s1.beta[:] = 0.0
    s1, _ = _coarse(rig, _make_scan(pts_m, nrm, R0, t0, p1.coarse_points, rng), s1, sub, rest_normals, schedule,
                    clothed, p1)
    P1 = pts_m @ R0.T + t0
    seen0, seen1 = seen_shares(rig, s, P1, rims)[head], seen_shares(rig, s1, P1, rims)
    # the scan points the headless body's head is the nearest part to, above its skull base (a
    # collar or the nape below it is the neck's): a face, a head turned away from the body's,
    # a hat; a scan without a head has none there
    posed = _pose_model(rig, s1, _subset(rig, np.arange(len(rig.mean))))
    joints = np.einsum("jab,jb->ja", posed.G[:, :3, :3], posed.joints) + posed.G[:, :3, 3]
    up = joints[head] - joints[BONES.index("neck")]
    up /= max(float(np.linalg.norm(up)), 1e-9)
    d1, j1 = cKDTree(posed.v).query(P1)
    is_head = posed.sub.region == head
    owned = float(np.mean(is_head[j1] & (d1 < TUNING.headless_near_m) & ((P1 - joints[head]) @ up > TUNING.headless_above_m)))
    adopt = bool(seen1[head] < TUNING.unseen_share and owned <= TUNING.headless_head_share)
    figures = {"head_seen": [round(float(seen0), 3), round(float(seen1[head]), 3)],
               "head_points": round(owned, 4), "adopted": adopt, "seconds": round(time.perf_counter() - t0_s, 2)}
    return ((s1, seen1, replace(p1, hair_region=params.hair_region)) if adopt else None), figures

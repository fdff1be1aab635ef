"""Parametric body fitting of a clothed avatar, scan or point cloud (editing paper, Sec. 4.2,
Alg. 1), with an automatic initialisation and a clothing-aware data term.

Input: points (P, 3) float64 in the file's units and axes; normals (P, 3) unit or None
(estimated for point clouds); faces (F, 3) int or None (None: a point cloud). Output: the
body model's shape weights beta (K,), a pose theta (17 local bone rotations, axis-angle) and a
translation such that ``M(beta, theta)`` (the model's rest body, linear blend skinned) lies on
the scan, or just inside its clothes.

Our body model is the paper's revised SCAPE in its LBS form: rest shape ``mean + beta @ U``
(PCA, ``service.model.body.model``) and ``Q(theta)`` = LBS over 17 bones (``service.model.skinning``).

Stages:
1. Initialisation (the paper adjusts the pose by hand; here no human is in the loop): units
   from the size of the scan (m/cm/mm), the up axis from its principal axis (Y or Z up, either
   sign), the facing from a search over yaw angles scored by a rigid fit, then a coarse
   parametric ICP on subsamples with correspondences in both directions that frees the
   skeleton from the pelvis outwards (``BONE_LEVELS``) and then the main shape components, so
   limbs are pulled into the scan's pose; limbs caught in a local minimum are re-tried at
   discrete turns (``_limb_search``); on a bare scan the coarse rest stature is then scaled
   by the scan's height over the posed body's (``_stature_from_extent``, ``init_stature_max``:
   the coarse shape stays near the population's). The same ICP then refines pose and all shape components
   on more points, damped lightly (``refine_levenberg``) so that it follows the valley along
   which shape and posture trade (a longer bone bent more) to the scan's minimum: the rest-pose
   body does not absorb posture (issue 12). As in Alg. 1, the refinement does not pull the
   template into a scan's holes (``refine_hole_reject``; on a bare scan, in Alg. 1 too, no pair
   with a point on a hole's rim found on the scan, ``rim_reject``), and on a bare scan it pairs only
   surfaces whose normals are within 30 degrees (``refine_normal_reject_deg``). A clothed scan
   is first refined as if bare
   (``refine_bare_iterations``: the posture of the clothes' outer surface), then with the
   clothing weights (issue 12: limbs left in a wrong posture by the initialisation otherwise
   hide inside loose clothes), each bone held towards the posture of that first stage where the
   clothing weights leave it little data (``clothed_posture_anchor``; Alg. 1 likewise). The
   initialisation's distances of a clothed scan count the template's side per surface area,
   not per vertex (``area_weighted``): the template's hands and head hold over half its vertices.
   Hidden limbs (issue 12): the initialisation's cost adds the arms' share inside the torso or
   thighs (``arm_inside_cost``), and no ICP or Alg. 1 pair joins a template vertex to a scan
   point whose nearest template vertex lies on a bone more than ``exclusive_hops`` joints away
   (the scan point is another body part's: a hand over a hole is not pulled into the thigh).
   A scan without a head (``headless_check``): the initialisation's coarse stage runs again with
   the head taking no pairs (``absent_bones``), kept when no scan lies where that fit's head
   is; the head is then the prior's. A bare scan's poorly seen head (the face in a hole, the
   top cut, hair) is refined and fitted twice, the second time with the whole head and neck
   setting their pose only, and the body leaving less of the scan unexplained is kept
   (``head_hypothesis_seen``, ``scan_to_surface_mm``).
2. Alg. 1 (``_alg1``): repeat { correspondences template -> scan (nearest point, rejected when normals differ
   by more than 30 degrees); repeat { update T (Eq. 2), update theta (Eq. 3), update beta (Eq. 4) }
   until 20 iterations or T moves < 1 mm } until 3 iterations (``max_outer``) or T moves < 5 mm. On a bare
   scan Eqs. 3 and 4 fit the model to the template vertices matched to the scan only
   (``alg1_matched_only``): over a hole T is the model itself, extrapolated.
   Eq. 2's matrix (edge Laplacian + correspondence weights) depends only on the correspondences,
   so it is factored once per outer iteration (``EdgeSystem``) and re-solved in the inner loop.
3. Clothing: a template vertex outside the scan (the body would poke through the clothes) keeps
   the full correspondence weight; inside (the clothes stand off the body) it gets
   ``inside_weight`` in the ICP and is dropped in Alg. 1 beyond ``alg1_inside_tol`` (Alg. 1's
   alternation is blind to weights: T, then the body, would follow loose clothes outwards); the
   shape is held by a Gaussian prior. The body ends inside the clothes, touching them where
   they are tight.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.spatial import cKDTree

from service.model.body.lbs import matrix_to_axis_angle
from service.model.fitting import person_check as PC, scan_cleanup as SC
from service.model.formats.frames import orient_outward
from service.model.geometry.mesh import closest_points_on_mesh, estimate_normals, vertex_normals
from service.model.fitting.alg1 import _alg1, _posture_anchor, known_terms
from service.model.fitting.checks import (
    check_person_before,
    check_population,
    FitError,
    NOT_A_PERSON,
    NOT_FITTED,
)
from service.model.fitting.initialise import _arms, _coarse, _initialise, _without_head
from service.model.fitting.params import DEFAULT_PARAMS, FitParams, TUNING
from service.model.fitting.prepare import (
    _correspondences,
    _make_scan,
    _rims,
    detect_scan_unit,
    seen_shares,
    seen_vertices,
)
from service.model.fitting.rig import _bone_ids, _pose_model, _rig, _subset, ALL_BONES


@dataclass
class FitResult:
    weights: np.ndarray  # (K,) PCA weights of the rest-pose body
    rotvecs: np.ndarray  # (17, 3) local axis-angle rotation per bone, BONES order
    translation: np.ndarray  # (3,) metres, model frame
    unit: str  # 'm' | 'cm' | 'mm' detected in the file
    up: str  # the file's up axis, e.g. '+y', '+z'
    to_model: np.ndarray  # (4, 4) similarity: file coordinates -> model frame (metres, Y up, +Z facing)
    residual_mm: float  # mean distance from the fitted posed body to the scan (accepted correspondences)
    posed_vertices: np.ndarray  # (V, 3) fitted body in the model frame
    partial: bool = False  # a side of the body has no scan surface (single-view scan)
    coverage: dict = field(default_factory=dict)  # per side of the body: share with scan surface nearby
    unseen: list = field(default_factory=list)  # bones the scan hardly shows, left to the prior (unseen_prior)
    outer_iterations: int = 0
    inner_iterations: int = 0
    seconds: float = 0.0
    stats: dict = field(default_factory=dict)
    kept: np.ndarray | None = None  # (P,) bool: the input points the fit used (the floor and stray clusters dropped)


def fit_body(model, points: np.ndarray, normals: np.ndarray | None = None,
             faces: np.ndarray | None = None, *, clothed: bool = True,
             progress: Callable[[float, str], None] | None = None,
             params: FitParams = DEFAULT_PARAMS, seed: int = 0, known: dict[str, float] | None = None,
             gender: str | None = None) -> FitResult:
    """Fit the body model to a scan (see the module docstring), with ``params.blas_threads``
    BLAS threads.

    points: (P, 3) file units and axes; normals: (P, 3) or None; faces: (F, 3) or None;
    known: the person's own measurements, if any ({attribute: cm or kg}, see ``known_terms``),
    with ``gender`` ('female'/'male', else estimated from the fit) for the weight's density.
    Raises FitError when the scan cannot be fitted."""
    if params.blas_threads is None:
        return _fit_body(model, points, normals, faces, clothed, progress, params, seed, known, gender)
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=params.blas_threads, user_api="blas"):
        return _fit_body(model, points, normals, faces, clothed, progress, params, seed, known, gender)


def scan_to_surface_mm(points: np.ndarray, body: np.ndarray, faces: np.ndarray,
                       clip: float = TUNING.head_hypothesis_clip_m) -> float:
    """Mean distance (mm) of scan points (P, 3) to a posed body's surface (vertices (V, 3),
    faces (F, 3)), both in the model frame, each clipped at ``clip`` metres (a stray point or
    a floor counts no more than that): how much of the scan the body leaves unexplained."""
    _, q, _ = closest_points_on_mesh(points, body, faces)
    return 1000.0 * float(np.minimum(np.linalg.norm(points - q, axis=1), clip).mean())


def _fit_body(model, points: np.ndarray, normals: np.ndarray | None, faces: np.ndarray | None,
              clothed: bool, progress: Callable[[float, str], None] | None, params: FitParams,
              seed: int, known: dict[str, float] | None = None, gender: str | None = None) -> FitResult:
    t_start = time.perf_counter()
    report = progress or (lambda f, m: None)
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 100 or not np.all(np.isfinite(pts)):
        raise FitError("the scan needs at least 100 finite 3D points")
    wide = None
    try:
        unit, scale = detect_scan_unit(pts)
    except FitError:
        # wider than a person: a room's floor around them (issue 12), or several people
        wide = SC.clean_wide_scan(pts, normals, faces) if params.scan_cleanup else None
        if wide is None and params.person_check:  # perhaps several people, side by side
            for s_unit in (1.0, 0.01, 0.001):
                reason = PC.separate_bodies(pts * s_unit)
                if reason:
                    raise FitError(NOT_A_PERSON + reason) from None
        if wide is None:
            raise
    cleaning = None
    if wide is not None:
        unit, scale, pts_m, normals, faces, cleaning = wide
    else:
        pts_m = pts * scale
        if params.scan_cleanup:  # floor, stray clusters (issue 12)
            pts_m, normals, faces, cleaning = SC.clean_scan(pts_m, normals, faces)
    if params.person_check:
        check_person_before(pts_m)
    n_scan, pick = len(pts_m), None
    if params.max_points is not None and n_scan > params.max_points:  # a dense scan: a random share
        pick = np.sort(np.random.default_rng([seed, 7]).choice(n_scan, size=params.max_points, replace=False))
        if faces is None or not len(faces):  # a point cloud: its normals (if estimated) from the share
            pts_m, normals, pick = pts_m[pick], None if normals is None else np.asarray(normals)[pick], None
    if normals is None:
        if faces is not None and len(faces):
            nrm = vertex_normals(pts_m, np.asarray(faces, np.int64))
        else:
            nrm = estimate_normals(pts_m)
    else:
        nrm = np.asarray(normals, np.float64)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
    if pick is not None:  # a mesh: its normals from the whole mesh, then the share
        pts_m, nrm = pts_m[pick], nrm[pick]
    nrm = orient_outward(pts_m, nrm)
    rig = _rig(model)
    rng = np.random.default_rng(seed)
    if clothed:  # hair is then clothes like the rest (FitParams.hair_region: bare scans)
        params = replace(params, hair_region=False)
    if not clothed:  # the initialisation's distances per template vertex (see FitParams.area_weighted)
        params = replace(params, area_weighted=False)
    report(0.02, "initialising: units, up axis, facing, coarse pose")
    find_rims = params.scan_cleanup and params.rim_reject and not clothed  # holes' rims (FitParams.rim_reject)
    rims = _rims(pts_m, nrm) if find_rims else None
    rim = None
    # the initialisation pairs the scalp as skin: its template starts far from the scan, where
    # hair_region's down-weighted pairs changed one of 48 bare 45-degree fits' path to a wrong minimum
    arms = _arms(model, params)
    up, R0, t0, s, screen_costs = _initialise(rig, pts_m, nrm, clothed, replace(params, hair_region=False), rng, arms)
    capped = 0
    if params.scan_cleanup and params.flat_cap:  # a flat cap over the head: no data (FitParams.flat_cap)
        cap = SC.flat_cap(pts_m @ R0.T + t0)
        if cap.any() and len(pts_m) - cap.sum() >= 100:
            capped = int(cap.sum())
            pts_m, nrm = pts_m[~cap], nrm[~cap]
            rims = _rims(pts_m, nrm) if find_rims else None
    P = pts_m @ R0.T + t0
    n = len(rig.mean)
    from service.model.body.model import BONES

    seen_v = seen_vertices(rig, s, P, rims)
    seen = seen_shares(rig, s, P, rims, seen_v)
    face_seen = float(seen_v[rig.face].mean())
    headless: dict = {}
    if params.headless_check and "head" not in params.absent_bones:  # a scan without its head?
        alt, headless = _without_head(rig, pts_m, nrm, clothed, params, seed, rims, s, R0, t0)
        if alt is not None:
            s, seen, params = alt
    t_init = time.perf_counter() - t_start
    N = nrm @ R0.T
    unseen = None  # the unseen bones' pull to the rest posture (FitParams.unseen_prior)
    if params.unseen_prior > 0:
        w_unseen = np.where(seen < TUNING.unseen_share, params.unseen_prior, 0.0)
        w_unseen[_bone_ids(TUNING.unseen_free_bones)] = 0.0
        if clothed:  # only the hands (FitParams.clothed_unseen_bones): clothes are not holes;
            # an absent head keeps the clothed anchors' pull (FitParams.absent_bones)
            w_unseen[np.setdiff1d(np.arange(len(w_unseen)), _bone_ids(params.clothed_unseen_bones))] = 0.0
        else:
            w_unseen[_bone_ids(params.absent_bones)] = params.unseen_prior
        if not clothed or w_unseen.any():
            unseen = (np.broadcast_to(np.eye(3), s.rot.shape).copy(), w_unseen)
    shape_free = None  # a poorly seen head's face: pose, not shape (FitParams.face_shape_min_seen)
    if (not clothed and params.hair_region and params.face_shape_min_seen is not None
            and "head" not in params.absent_bones and seen[BONES.index("head")] < params.face_shape_min_seen):
        shape_free = rig.face
    head_hypotheses = [shape_free]  # a poorly seen head: a second, shaped by the body (FitParams.head_hypothesis_seen)
    if (not clothed and params.hair_region and params.head_hypothesis_seen is not None
            and "head" not in params.absent_bones and seen[BONES.index("head")] < params.head_hypothesis_seen):
        head_hypotheses.append(rig.face | rig.scalp)
    if params.refine_iterations:
        report(0.12, "refining pose and shape")
        scan = _make_scan(pts_m, nrm, R0, t0, params.refine_points, rng, rims)
        rim = scan.rim
        ridx = np.sort(rng.choice(n, size=min(params.refine_points, n), replace=False))
        rn = vertex_normals(rig.mean, rig.faces, rig.incidence)[ridx]
        rsub = _subset(rig, ridx)
        # the refinement's ICP stays per vertex (area_weighted off): area weights there took four
        # good held-out fits from 2.8-3.7 to 3.2-5.9 mm (the error is per vertex as well)
        rparams = replace(params, levenberg=params.refine_levenberg, area_weighted=False)
        if not clothed and params.refine_normal_reject_deg is not None:
            rparams = replace(rparams, coarse_normal_reject_deg=params.refine_normal_reject_deg)
        # no pull into holes here either (see ``FitParams.refine_hole_reject``)
        holes = (SC.point_spacing(scan.sub_tree, scan.points[scan.sub])
                 if params.scan_cleanup and params.refine_hole_reject else None)
        if clothed and params.refine_bare_iterations:
            # posture first, on the clothes' outer surface (issue 12, see FitParams)
            omega = params.bone_smoothness if params.bare_smoothness is None else params.bare_smoothness
            s, _ = _coarse(rig, scan, s, rsub, rn, [(ALL_BONES, len(rig.U))] * params.refine_bare_iterations,
                           False, rparams, omega=omega, hole_spacing=holes, anchor=unseen)
        anchor = (_posture_anchor(s.rot, params.clothed_posture_anchor, unseen)
                  if clothed and params.refine_bare_iterations else unseen)
        if clothed and params.clothed_shape_prior is not None:  # the body found; now inside the clothes
            params = replace(params, shape_prior=params.clothed_shape_prior)
            rparams = replace(rparams, shape_prior=params.clothed_shape_prior)
        tree = scan.tree
    else:
        tree = cKDTree(P)
        rim = None if rims is None else rims[0] <= TUNING.rim_spacings * rims[1]
    full_sub = _subset(rig, np.arange(n))
    tried = []
    t_refine = time.perf_counter() - t_start - t_init
    for k, free in enumerate(head_hypotheses):
        t_k = time.perf_counter()
        sk = s.copy()
        if params.refine_iterations:
            sk, _ = _coarse(rig, scan, sk, rsub, rn,
                            [(ALL_BONES, len(rig.U))] * params.refine_iterations, clothed,
                            rparams, omega=params.bone_smoothness,
                            contact=params.clothing_contact, anchor=anchor, hole_spacing=holes,
                            fingers_from=None if params.finger_scale is None or params.finger_refine_from is None
                            else int(params.finger_refine_from * params.refine_iterations), shape_free=free)
        t_refine += time.perf_counter() - t_k
        given = None
        if known and params.known_weight > 0:
            from service.model.body.shape import estimate_gender

            given = known_terms(model, known, gender or estimate_gender(model, sk.beta))
        share = (k / len(head_hypotheses), 1.0 / len(head_hypotheses))
        report(0.2 + 0.8 * share[0], "fitting the body (Alg. 1)")
        sk, outer, inner_total, backend = _alg1(
            rig, sk, tree, P, N, clothed, params, rim,
            _posture_anchor(sk.rot, params.alg1_posture_anchor, unseen) if clothed else unseen,
            given, free, lambda f, m: report(0.2 + 0.8 * (share[0] + share[1] * f), m))
        final = _pose_model(rig, sk, full_sub).v
        score = scan_to_surface_mm(P, final, rig.faces) if len(head_hypotheses) > 1 else 0.0
        tried.append((score, k, sk, outer, inner_total, backend, final))
    score, chosen, s, outer, inner_total, backend, final = min(tried, key=lambda x: (x[0], x[1]))
    shape_free = head_hypotheses[chosen]

    c, nc, w = _correspondences(final, rig, tree, P, N, False, params, rim)
    d = np.linalg.norm(final - c, axis=1)
    accepted = w > 0
    present = ~np.isin(full_sub.region, _bone_ids(params.absent_bones))  # an absent head matches nothing
    if accepted[present].mean() < params.min_accepted:
        raise FitError(NOT_A_PERSON + f"fewer than {100 * params.min_accepted:.0f} % of the body found "
                       "a matching surface on the scan")
    residual_mm = 1000 * float(d[accepted].mean())
    full = model.forward(s.beta, s.rot, s.trans).vertices
    checks: dict = {}
    if params.person_check:
        body_tree = cKDTree(final)
        near = PC.scan_to_body(P, final, body_tree)  # the checks' shared nearest body vertices
        reason, checks = PC.fit_evidence(P, final, near)
        if reason:
            raise FitError(NOT_A_PERSON + reason)
        if not clothed:
            reason, surface = PC.bare_surface(P, final, rig.faces, near, body_tree)
            checks.update(surface)
            if reason:
                raise FitError(NOT_A_PERSON + reason)
        reason, part = PC.unexplained_part(P, final, near)
        checks.update(part)
        if reason:
            raise FitError(NOT_FITTED + reason)
        checks.update(check_population(model, s.beta))
    # partial scans: the share of each side of the body with scan surface nearby
    facing = s.rot[0] @ np.array([0.0, 0.0, 1.0])  # the root's facing (model faces +Z at rest)
    coverage = PC.side_coverage(final, vertex_normals(final, rig.faces, rig.incidence), facing, tree, N)
    to_model = np.eye(4)
    to_model[:3, :3] = scale * R0
    to_model[:3, 3] = t0
    report(1.0, "done")
    return FitResult(
        weights=s.beta.copy(), rotvecs=matrix_to_axis_angle(s.rot), translation=s.trans.copy(), unit=unit, up=up,
        to_model=to_model, residual_mm=residual_mm, posed_vertices=full,
        partial=PC.is_partial(coverage), coverage=coverage,
        unseen=sorted({*params.absent_bones, *([] if unseen is None else [BONES[b] for b in np.flatnonzero(unseen[1] > 0)])},
                      key=BONES.index),
        outer_iterations=outer, inner_iterations=inner_total, seconds=time.perf_counter() - t_start,
        stats={"init_seconds": t_init, "refine_seconds": t_refine, "solver": backend, "accepted_fraction": float(accepted[present].mean()),
               "hair_region": bool(params.hair_region and not clothed),
               "seen": {b: round(float(x), 3) for b, x in zip(BONES, seen)}, "headless": headless,
               "face_shape_from_body": shape_free is not None, "face_seen": round(face_seen, 3),
               "head_shape_from_body": bool(chosen == 1),
               "head_hypotheses": [{"head_from_body": bool(k == 1), "scan_to_surface_mm": round(x[0], 3),
                                    "chosen": bool(k == chosen)} for k, x in enumerate(tried)] if len(tried) > 1 else [],
               "person_check": checks, "cleaning": cleaning.stats if cleaning is not None else None,
               "points": {"scan": n_scan, "fitted": len(pts_m), "flat_cap": capped},
               "screen_costs_mm": [round(1000 * x, 1) for x in sorted(screen_costs)[:4]]},
        kept=None if cleaning is None else cleaning.kept,
    )

"""Stage 2, the editing paper's Alg. 1 (Sec. 4.2, Eqs. 2-4): T, then pose theta, then shape beta,
alternated over re-matched correspondences; and the known-measurement terms of the shape step.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from service.model.geometry.solvers import EdgeSystem, damped_step
from service.model.fitting.params import FitParams, TUNING
from service.model.fitting.prepare import _correspondences
from service.model.fitting.regions import finger_weights
from service.model.fitting.rig import (
    _anchor_terms,
    _apply_pose,
    _joint_limit_terms,
    _pose_jacobian,
    _pose_model,
    _Rig,
    _shape_jacobian,
    _smoothness,
    _State,
    _subset,
    ALL_BONES,
)




def known_terms(model, known: dict[str, float], gender: str) -> Callable[[np.ndarray], tuple]:
    """The Gauss-Newton terms of measurements given for the rest body: ``known`` {attribute of
    ``M.ATTRIBUTES`` but gender: value in its unit (cm, kg)}. Returns f(beta (K,)) -> (H (K, K),
    g (K,), residuals (m,) in sigmas) of 1/2 sum_a ((m_a(beta) - known_a) / sigma_a)^2, the
    measurements m_a exact (``shape.WeightMeasures``) and linearised at beta."""
    from service.model.body import measurements as M
    from service.model.body.shape import weight_measures

    names = [n for n in M.ATTRIBUTES[1:] if n in known]
    unknown = set(known) - set(names)
    if unknown:
        raise ValueError(f"not a body measurement: {sorted(unknown)}")
    wm = weight_measures(model)
    rows = [M.RAW_NAMES.index(n) for n in names]
    scale = np.array([M.api_scale(n) for n in names])  # raw (m, kg) -> API units (cm, kg)
    target = np.array([float(known[n]) for n in names])
    sigma = np.array([TUNING.known_sigma.get(n, TUNING.known_sigma_cm) for n in names])

    def terms(beta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raw, J = wm.measure(beta, gender, jacobian=True, names=names)
        r = (raw[rows] * scale - target) / sigma
        Jr = J[rows] * (scale / sigma)[:, None]
        return Jr.T @ Jr, Jr.T @ r, r

    return terms


def _posture_anchor(rot: np.ndarray, weight: float, unseen: tuple | None) -> tuple[np.ndarray, np.ndarray | float]:
    """A clothed fit's pull towards the posture ``rot`` (17, 3, 3) at ``weight`` per bone
    (``FitParams.clothed_posture_anchor``, ``alg1_posture_anchor``), as ``_anchor_terms``'
    (rotations, weights), but each unseen bone of ``unseen`` ((17, 3, 3) rest rotations, (17,)
    weights, or None) pulled to its rest posture at its own weight instead
    (``FitParams.clothed_unseen_bones``)."""
    if unseen is None:
        return rot.copy(), weight
    rest, w = unseen
    out = np.where((w > 0)[:, None, None], rest, rot)
    return out, np.where(w > 0, w, weight)




def _alg1(rig: _Rig, s: _State, tree: cKDTree, P: np.ndarray, N: np.ndarray, clothed: bool, params: FitParams,
          rim: np.ndarray | None, anchor: tuple | None, given: Callable | None, shape_free: np.ndarray | None,
          report: Callable[[float, str], None]) -> tuple[_State, int, int, str | None]:
    """Alg. 1 of the fitting paper from the state ``s`` (changed in place): the template T
    (Eq. 2, ``EdgeSystem``), then the pose (Eq. 3, one Gauss-Newton step) and the shape (Eq. 4,
    linear least squares with the prior) alternated per inner iteration, correspondences per
    outer one. P, N (P, 3): the scan's points and normals in the model frame, ``tree`` a k-d
    tree over them; ``rim`` (P,) bool or None: a hole's rim; ``anchor``: (rotations (17, 3, 3),
    weights) pulling the posture (``_anchor_terms``) or None; ``given``: the customer's
    measurements' terms (``known_terms``) or None; ``shape_free`` (n,) bool or None: vertices
    whose pairs move the pose, not the shape. ``report(fraction, message)``: progress within
    it. Returns (state, outer iterations, inner iterations, the solver's backend)."""
    n = len(rig.mean)
    upd = np.arange(0, n, max(1, params.update_stride))
    sw = float(params.update_stride)  # the update terms stand for all vertices
    lam = params.shape_prior
    all_comps = np.arange(len(rig.U))
    full_sub, upd_sub = _subset(rig, np.arange(n)), _subset(rig, upd)
    AtA = rig.posture.T @ rig.posture
    T = _pose_model(rig, s, full_sub).v
    outer = inner_total = 0
    backend = None
    for outer in range(1, params.max_outer + 1 if params.run_alg1 else 1):
        T_outer = T.copy()
        c, nc, w = _correspondences(T, rig, tree, P, N, clothed, params, rim)
        system = EdgeSystem.precompute(rig.laplacian, w * (params.alpha_point + params.alpha_plane))
        # a bare scan's template vertices without a scan point (over a hole) are the model itself,
        # extrapolated by Eq. 2, not data: Eqs. 3 and 4 fit the model to the matched ones
        support = np.repeat(w[upd] > 0 if params.alg1_matched_only and not clothed
                            else np.ones(len(upd), bool), 3).astype(np.float64)
        fingers = rig.fingers[upd] if params.finger_scale is not None else None
        support_outer = support
        shape_support = None if shape_free is None else np.repeat(~shape_free[upd], 3).astype(np.float64)
        backend = system.backend
        for _ in range(params.max_inner):
            inner_total += 1
            T_prev = T
            # Eq. 2: update T with beta and theta fixed
            m = _pose_model(rig, s, full_sub).v
            pi = T - nc * np.einsum("ij,ij->i", T - c, nc)[:, None]
            rhs = rig.laplacian @ m + (w * params.alpha_point)[:, None] * c \
                + (w * params.alpha_plane)[:, None] * pi + system.eps * m
            T = system.solve(rhs)
            target = T[upd]
            # Eq. 3: update theta with T and beta fixed (one Gauss-Newton step)
            p = _pose_model(rig, s, upd_sub)
            if fingers is not None:  # Eqs. 3 and 4 hardly follow bent fingers (FitParams.finger_scale)
                support = support_outer * np.repeat(finger_weights(np.linalg.norm(p.v - target, axis=1), fingers,
                                                                   params.finger_scale), 3)
            Jp = _pose_jacobian(rig, p, ALL_BONES, compiled=params.compiled).reshape(-1, 3 + 3 * 17)
            r = (p.v - target).reshape(-1) * support
            H = sw * Jp.T @ (Jp * support[:, None])
            g = sw * Jp.T @ r
            Hs, gs = _smoothness(rig, s, p, ALL_BONES, params.bone_smoothness)
            Hl, gl = _joint_limit_terms(rig, s, p, ALL_BONES, params.joint_limit_weight)
            if anchor is not None:
                Ha, ga = _anchor_terms(rig, s, p, ALL_BONES, *anchor)
                Hs, gs = Hs + Ha, gs + ga
            delta = damped_step(H + Hs + Hl, g + gs + gl, damping=params.damping)
            _apply_pose(rig, s, p, ALL_BONES, delta)
            # Eq. 4: update beta with T and theta fixed (linear least squares with the prior)
            p = _pose_model(rig, s, upd_sub)
            Jb = _shape_jacobian(rig, p, all_comps).reshape(-1, len(all_comps))
            bsupport = support if shape_support is None else support * shape_support
            r = (p.v - target).reshape(-1) * bsupport
            Hb = sw * Jb.T @ (Jb * bsupport[:, None]) + lam * np.diag(rig.precision) + params.posture_weight * AtA
            gb = sw * Jb.T @ r + lam * rig.precision * s.beta + params.posture_weight * AtA @ s.beta
            if given is not None:  # the customer's own measurements (FitParams.known_weight)
                Hk, gk, _ = given(s.beta)
                Hb, gb = Hb + params.known_weight * Hk, gb + params.known_weight * gk
            s.beta = s.beta - np.linalg.solve(Hb, gb)
            if np.linalg.norm(T - T_prev, axis=1).max() <= params.inner_tol:
                break
        report(outer / params.max_outer, f"outer iteration {outer}")
        if np.linalg.norm(T - T_outer, axis=1).max() <= params.outer_tol:
            break
    return s, outer, inner_total, backend

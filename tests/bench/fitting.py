"""``tryon bench fitting [--limit N] [--json] [--no-kill]``: parametric body fitting of scans.

1. Accuracy and time of ``service.model.fitting.fit.fit_body`` on synthetic scans with a known body
   (``tests/bench/synthetic_scans.py``): N held-out avatars (default 12, alternately male and
   female; ``--limit`` sets N), each in a random pose (up to 45 degrees per bone, any yaw),
   scanned under three conditions -- clothed mesh, unclothed mesh, clothed point cloud -- with
   12,500 points, 2 mm noise, a random unit (m/cm/mm), up axis (+y/+z) and placement. The same
   seed per avatar gives the same pose and frame in all three conditions. Per condition:

   * body error: the fitted posed body is brought into the truth's model frame through the
     scan (``truth.to_model @ inv(fit.to_model)``: yaw and translation may be split
     differently between the frame and the root bone), then the true body vertices' mean
     distance to the fitted body surface (point-to-surface), and the mean distance between
     corresponding vertices (vertex-to-vertex, same topology: stricter); median and p90 over
     the scans, beside a baseline fitted in the same run: the population mean shape in the
     TRUE pose and translation (what shape recovery is worth);
   * the 12 attributes measured on the fitted rest-pose body (the true gender) against those
     of the true body: mean absolute error per attribute;
   * posed joint positions: mean error over the 17 joints (mm);
   * wall time per fit (median, p90), unit and up axis detected, failures (exceptions are
     counted, never raised), refusals by the person check (false rejections), whole scans
     flagged ``partial``;
   * the rest-pose stature error (median |error| and worst), and body error, stature and time
     again for the same scan fitted as before issue 12's shape/posture decoupling
     (``BEFORE_PARAMS``: the refinement damped like the coarse stage, Levenberg 1e-3): before.

   Issue 12 adds conditions of real scanner output and loose clothes (``Condition``; each with
   ``--conditions NAME,...``): ``tight_clothes`` (catalogue T-shirt with sports trousers or
   jeans), ``loose_clothes`` (a pencil skirt -- the legs under it inferred from the hips, the
   knees and feet below -- with a blouse, or a business suit; with hair), ``holes`` (8 missing
   surface patches of 4-9 cm radius), ``cut_head`` (everything above a plane 4 cm under the
   head top dropped), ``floor_disc`` (a dense disc of floor points under the feet, a point
   cloud), ``room_floor`` (a 3.2 m square of a room's floor around an unclothed point cloud:
   wider than a person, so the unit is told after the floor is found), ``scanner`` (a clothed mesh with holes, a cut head top and a scanner's noisy,
   tilted floor) and ``scanner_minimal`` (the same three on a bare mesh: a body scanner's output
   of a person in minimal clothing, fitted as unclothed); their "before" is the same scan fitted without the scan cleaning
   (``FitParams(scan_cleanup=False)``), same run. ``bare_hair``: a bare mesh with hair
   (MakeHuman's bob for women, short hair for men) fitted as unclothed; its "before" pairs the
   scalp as skin (``FitParams(hair_region=False)``); ``scanner_hair``: the same with the scanner
   condition's holes, cut head top and floor. ``off_model``, ``off_model_scanner`` and
   ``off_model_clothed``: the person is not in the body model's space (the held-out people
   are, to 0.02 mm; real people are not): 4 mm RMS of smooth soft-tissue detail on the skin
   (``synthetic_scans.individual_detail``; the skull, hands and soles keep their shape), bare,
   as the scanner condition's bare scan, and in a random MakeHuman suit (and
   ``off_model_scanner_hair``: the scanner's bare scan with hair, fitted as bare;
   ``off_model_scanner_dark_hair``: the scanner's bare scan without the crown and the back of the
   head, as many scanners return dark hair, ``synthetic_scans.without_hair_returns``; its
   "before" has no unseen bones' prior); ``headless`` and ``headless_clothed``: no head at
   all (``synthetic_scans.without_head``), bare scanner output (holes, the scanner's floor)
   and a person in a random MakeHuman suit; their "before" has no second coarse fit with
   the head absent (``FitParams.headless_check``); the truth is the displaced body, and each scan also reports the model's own best (``model_floor_mm``: the
   true rest body's distance to its least-squares projection on the model's space).
   ``scanner_raw``: a raw multi-view scanner's own errors on the bare scan with holes and a cut
   head top (each view's patch off by its calibration, flying pixels where a view grazes the
   surface, the floor cut off 1 cm above it: ``synthetic_scans.with_raw_artifacts``,
   ``cut_soles``); no "before" unless ``--before`` names one (``face_shape``: the face's pairs
   shaping the body however little of the head is seen).

   ``--via-file FMT`` (ply, obj, glb, stl, xyz): every scan is fitted as the service reads it back
   from an upload in that format (:func:`as_uploaded`), not from the generated arrays.

1b. The person check (:func:`bench_person_check`): non-person shapes (box, ellipsoid, chair,
   two people apart and touching) with the check off (before) and on; CesiumMan; single-view
   front scans flagged ``partial``.

2. Jobs lost under worker kills (skipped with ``--no-kill``): a real ``tryon serve`` on its own
   embedded Redis in a temporary directory (never a database it did not create) with
   ``TRYON_EMBEDDED_WORKER=0`` and 3 ``tryon worker`` processes on the same data directory; 50 small scans are uploaded
   (``POST /v1/customers``, 202 + job) while every few seconds a random worker's whole process
   group (worker and work-horse) is SIGKILLed and replaced; jobs are polled
   (``GET /v1/jobs/{id}``) until done/failed or a 15-minute deadline: done, failed, lost.
"""
from __future__ import annotations

import functools
import os
import random
import signal
import sys
import time
from dataclasses import dataclass

import httpx
import numpy as np
from scipy.spatial import cKDTree

from service.model.body import measurements as M
from service.model.body.model import BONES, load_body_model
from service.model.geometry.mesh import closest_point_on_triangles, vertex_faces
from tests.bench import synthetic_scans as SS
from tests.bench.common import heldout_people, shared_data_dir
from tests.harness import RETAILERS, run_server, start_worker, stop_process



@dataclass(frozen=True)
class Condition:
    """A scanning condition: ``clothed`` (the scan wears clothes; the fit is told so), ``cloud``
    (a point cloud, else a mesh), ``garments`` (gender -> garment ids: ``.mhclo`` stems or
    catalogue items; None: a random MakeHuman suit, maybe shoes or a hat), ``degrade``
    (``synthetic_scans.DEGRADATIONS`` applied in order), ``before`` (the same scan fitted again,
    same run, with ``BEFORE_PARAMS(before)``: ``"refine_damping"``, ``"pose_prior"``,
    ``"scan_cleanup"`` without the scan cleaning of issue 12 (``FitParams(scan_cleanup=False)``),
    ``"clothing_contact"`` (``FitParams(clothing_contact=None)``), None: not)."""

    name: str
    clothed: bool
    cloud: bool
    garments: dict | None = None
    degrade: tuple = ()
    before: str | None = "refine_damping"
    fit_clothed: bool | None = None  # the fit's ``clothed`` flag when not ``clothed`` (hair on a bare body)
    detail_mm: float = 0.0  # the person off the body model's space (synthetic_scans.individual_detail)
    finger_curl_deg: float = 0.0  # relaxed hands (synthetic_scans.curl_fingers)

    @property
    def fitted_clothed(self) -> bool:
        return self.clothed if self.fit_clothed is None else self.fit_clothed


CONDITIONS = (
    Condition("clothed_mesh", True, False),
    Condition("unclothed_mesh", False, False),
    Condition("clothed_cloud", True, True),
    # issue 12: real scanner output and loose clothes
    Condition("tight_clothes", True, False, {"female": ["womens-tshirt", "sports-trousers"],
                                             "male": ["mens-tshirt", "mens-jeans"]}, before="scan_cleanup"),
    Condition("loose_clothes", True, False, {"female": ["pinstripe-blouse", "pencil-skirt", "hair-bob02"],
                                             "male": ["business-suit", "hair-short02"]}, before="scan_cleanup"),
    Condition("holes", False, False, degrade=("holes",), before="scan_cleanup"),
    Condition("cut_head", False, False, degrade=("cut_head",), before="scan_cleanup"),
    Condition("floor_disc", False, True, degrade=("floor_disc",), before="scan_cleanup"),
    Condition("scanner", True, False, degrade=("holes", "cut_head", "scanner_floor"), before="scan_cleanup"),
    Condition("room_floor", False, True, degrade=("room_floor",), before="scan_cleanup"),
    # what a body scanner gives: the person in minimal clothing (bare here), the mesh with holes,
    # a cut head top and the scanner's floor; fitted as unclothed
    Condition("scanner_minimal", False, False, degrade=("holes", "cut_head", "scanner_floor"), before="scan_cleanup"),
    # the same with the cut head's opening closed by a flat cap, as a scanner's software that makes
    # the mesh watertight leaves it (synthetic_scans.capped_head)
    Condition("scanner_capped", False, False, degrade=("holes", "capped_head", "scanner_floor"), before="flat_cap"),
    # a bare person with hair (MakeHuman's bob or short hair), fitted as bare: a body scanner's
    # customer in minimal clothing
    Condition("bare_hair", True, False, {"female": ["hair-bob02"], "male": ["hair-short02"]},
              before="hair_region", fit_clothed=False),
    # the same scanner output with hair (MakeHuman's bob or short hair), fitted as bare
    Condition("scanner_hair", True, False, {"female": ["hair-bob02"], "male": ["hair-short02"]},
              degrade=("holes", "cut_head", "scanner_floor"), before="hair_region", fit_clothed=False),
    # a real person is not in the body model's space: smooth individual detail of 4 mm RMS on
    # the skin (the model spans the held-out people to 0.02 mm), bare, as a body scanner's
    # output, and clothed
    Condition("off_model", False, False, before=None, detail_mm=4.0),
    Condition("off_model_scanner", False, False, degrade=("holes", "cut_head", "scanner_floor"),
              before="scan_cleanup", detail_mm=4.0),
    Condition("off_model_clothed", True, False, before=None, detail_mm=4.0),
    # the nearest to a body scanner's real output here: off the model's space, bare with hair,
    # holes, the head top cut and the scanner's floor, fitted as bare
    Condition("off_model_scanner_hair", True, False, {"female": ["hair-bob02"], "male": ["hair-short02"]},
              degrade=("holes", "cut_head", "scanner_floor"), before="hair_region", fit_clothed=False, detail_mm=4.0),
    # dark hair, which many scanners do not see: a bare scanner scan without the crown and the back
    # of the head (no hair, and no scalp under it), off the model's space
    Condition("off_model_scanner_dark_hair", False, False, degrade=("dark_hair", "holes", "cut_head", "scanner_floor"),
              before="unseen_prior", detail_mm=4.0),
    # no head at all (a field of view ending at the neck, a head hidden): bare scanner output
    # (holes, the scanner's floor) and a person in a random MakeHuman suit, both without the head
    Condition("headless", False, False, degrade=("no_head", "holes", "scanner_floor"), before="headless"),
    Condition("headless_clothed", True, False, degrade=("no_head",), before="headless"),
    # long hair down the back to the shoulder blades (synthetic_scans.with_long_hair) on bare
    # scanner output (holes, a cut head top, the scanner's floor), fitted as bare: the same scans
    # as scanner_minimal but for the hair
    Condition("long_hair", False, False, degrade=("holes", "long_hair", "cut_head", "scanner_floor"),
              before="hair_back"),
    # relaxed hands: a scanned person's fingers curled 70 degrees towards the palm, which the model
    # cannot bend (synthetic_scans.curl_fingers), on bare scanner output (holes, a cut head top, the
    # scanner's floor) and on a person in a random MakeHuman suit; their body error is also given
    # without the hands, whose fingers no fit can match
    Condition("relaxed_hands", False, False, degrade=("holes", "cut_head", "scanner_floor"), before="finger_weight",
              finger_curl_deg=70.0),
    Condition("relaxed_hands_clothed", True, False, before="finger_weight", finger_curl_deg=70.0),
    # a raw multi-view scanner's own errors on bare scanner output (holes, a cut head top): each
    # view's patch off by its calibration (1 mm RMS per axis), flying pixels where a view grazes
    # the surface (synthetic_scans.with_raw_artifacts), and the floor taken off 1 cm above it, the
    # soles with it (synthetic_scans.cut_soles); compare scanner_minimal, the same people
    Condition("scanner_raw", False, False, degrade=("holes", "cut_head", "raw_artifacts", "cut_soles"), before=None),
)
DEFAULT_AVATARS = 12
N_POINTS = 12_500
NOISE_MM = 2.0
MAX_POSE_DEG = 45.0
SEED = 2024
GOALS = {"clothed_body_mm": 3.0, "unclothed_body_mm": 1.5, "body_p90_mm": 8.0, "seconds": 10.0}


# -- ground truth and errors ------------------------------------------------------------------
def BEFORE_PARAMS(kind: str = "refine_damping"):
    """The fit before one of issue 12's changes: ``refine_damping`` (the shape/posture
    decoupling: the refinement's Levenberg damping as the coarse stage's, 1e-3, which crawls
    along the shape-posture valley), ``pose_prior`` (no joint limits, bone smoothness 0.1) or
    ``scan_cleanup`` (no floor or stray-cluster removal, holes not rejected in the data term) or
    ``clothing_contact`` (the refinement's clothing weight a constant ``inside_weight`` for body
    points inside the clothes, not the depth-dependent contact weight) or ``landmark_init`` (the
    initialisation from ICP alone, no landmark hypotheses) or ``landmark_candidates`` (the
    landmark hypotheses tried on the best coarse candidate only, not on each of the best 3) or
    ``refine_bare`` (clothed scans refined with the clothing weights from the start, no
    posture-first refinement on the clothes' outer surface: ``FitParams(refine_bare_iterations=0)``)
    or ``wrong_fit`` (issue 12's wrong fits: the initialisation's distances per template vertex,
    not per area, and no pull of a clothed fit's posture towards the posture of the clothes'
    outer surface) or ``bone_smoothness`` (the refinement's and Eq. 3's pull of every bone towards
    its parent's rotation at 0.1, not 0.02) or ``clothed_prior`` (a clothed scan's clothing-aware refinement and Alg. 1
    with the bare scans' shape prior, not ``FitParams.clothed_shape_prior``) or ``refine_holes`` (the refinement's ICP pulling template vertices over a hole to its rim,
    a bare scan's normals rejected beyond the coarse stage's 60 degrees: no
    ``FitParams.refine_hole_reject``, no ``refine_normal_reject_deg``) or ``blas_threads`` (BLAS with the library's default threads, not 1: ``FitParams(blas_threads=None)``) or
    ``loose_regions`` (a clothed scan's inside pairs weighted by their own depth alone, neither
    by how deep their body region sits in the clothes nor with a stand-off per region:
    ``FitParams(loose_region_depth=None, cloth_offset_mean=None)``) or ``cloth_offsets`` (main
    before the clothes' stand-off per body region, 2026-11-25: the loose regions' weights
    instead and the clothed posture anchor at 1.0, ``FitParams(cloth_offset_mean=None,
    loose_region_depth=0.01, clothed_posture_anchor=1.0)``) or ``posture_anchor`` (the
    stand-offs with the clothed posture anchor at 1.0, not 0.1) or ``hidden_limbs`` (main before
    2026-11-25's second stop: no arm-inside cost in the initialisation, no exclusive pairs, Alg.
    1's pose and shape fitted to every template vertex; the upper arm's 75-degree adduction limit,
    module data, stays) or ``alg1_outer`` (Alg. 1 with up to 10 outer iterations, not 3:
    ``FitParams(max_outer=10)``) or ``rim_reject`` (no pairs dropped at the holes' rims found on
    the scan, ``FitParams(rim_reject=False)``) or ``hair_region`` (a bare scan's scalp paired as
    skin, ``FitParams(hair_region=False)``) or ``hair_back`` (the upper back paired as skin on a
    bare scan, ``FitParams(hair_back=False)``) or ``unseen_prior`` (bones in a hole not pulled to
    their rest posture, ``FitParams(unseen_prior=0)``) or ``headless`` (no second
    coarse fit with the head absent, ``FitParams(headless_check=False)``) or ``known`` (the same fit without the
    measurements given with ``--known``) or ``finger_weight`` (the fingers' pairs weighed as any
    other vertex's, ``FitParams(finger_scale=None)``) or ``head_hypothesis`` (a poorly seen head
    fitted once, without the second hypothesis whose head and neck follow the body,
    ``FitParams(head_hypothesis_seen=None)``) or ``clothed_hands`` (a clothed scan's hand in a
    hole held by the clothed anchors like any bone, not pulled to its rest posture,
    ``FitParams(clothed_unseen_bones=())``) or ``init_stature`` (the initialisation's rest
    stature left where the coarse stage put it, not scaled by the scan's height,
    ``FitParams(init_stature_max=None)``) or ``numpy_kernels`` (the pose Jacobian and the
    point-to-plane rows by the numpy reference, not the compiled kernels,
    ``FitParams(compiled=False)``) or ``coarse_each_up`` (only the screen's best facings through
    the initialisation's coarse stage, whatever their up-axis sign,
    ``FitParams(coarse_each_up=False)``)."""
    from service.model.fitting.params import FitParams

    kinds = _before_kinds()
    if kind not in kinds:
        raise ValueError(f"unknown 'before' kind {kind!r}")
    return FitParams(**kinds[kind])


def before_kinds() -> tuple[str, ...]:
    """The names ``BEFORE_PARAMS`` knows (``tryon bench fitting --before``)."""
    return tuple(_before_kinds())


def _before_kinds() -> dict[str, dict]:
    from service.model.fitting.params import FitParams

    return {
        "wrong_fit": {"area_weighted": False, "clothed_posture_anchor": 0.0, "alg1_posture_anchor": 0.0},
        "finger_weight": {"finger_scale": None},
        "bone_smoothness": {"bone_smoothness": 0.1},
        "refine_holes": {"refine_hole_reject": False, "refine_normal_reject_deg": None},
        "clothed_prior": {"clothed_shape_prior": None},
        "refine_bare": {"refine_bare_iterations": 0},
        "blas_threads": {"blas_threads": None},
        "cloth_offsets": {"cloth_offset_mean": None, "loose_region_depth": 0.01, "clothed_posture_anchor": 1.0},
        "posture_anchor": {"clothed_posture_anchor": 1.0},
        "hidden_limbs": {"arm_inside_cost": 0.0, "exclusive_hops": None, "alg1_matched_only": False},
        "alg1_outer": {"max_outer": 10},
        "rim_reject": {"rim_reject": False},
        "flat_cap": {"flat_cap": False},
        "hair_region": {"hair_region": False},
        "hair_back": {"hair_back": False},
        "face_shape": {"face_shape_min_seen": None, "head_hypothesis_seen": None},
        "head_hypothesis": {"head_hypothesis_seen": None},
        "clothed_hands": {"clothed_unseen_bones": ()},
        "init_stature": {"init_stature_max": None},
        "numpy_kernels": {"compiled": False},
        "coarse_each_up": {"coarse_each_up": False},
        "unseen_prior": {"unseen_prior": 0.0},
        "headless": {"headless_check": False},
        "known": {},
        "loose_regions": {"loose_region_depth": None, "cloth_offset_mean": None},
        "landmark_init": {"landmark_init": False},
        "landmark_candidates": {"landmark_candidates": 1},
        "scan_cleanup": {"scan_cleanup": False},
        "refine_damping": {"refine_levenberg": FitParams().levenberg},
        "clothing_contact": {"clothing_contact": None},
        "pose_prior": {"joint_limit_weight": 0.0, "bone_smoothness": 0.1, "coarse_bone_smoothness": 0.1},
    }


def posed(model, weights: np.ndarray, rotvecs: np.ndarray, translation: np.ndarray):
    """The posed body (V, 3) and joints (17, 3) of a shape and a pose (model frame)."""
    out = model.forward(weights, rotvecs, translation)
    return out.vertices, out.joints


class BodySurface:
    """Unsigned point-to-surface distances to a body mesh in the template topology (exact
    among the triangles around the k nearest vertices)."""

    def __init__(self, faces: np.ndarray, n_vertices: int, k: int = 8):
        self.faces = np.asarray(faces, np.int64)
        self.n = n_vertices
        self.k = k
        self.vert_faces = vertex_faces(self.faces, n_vertices)

    def distances(self, points: np.ndarray, vertices: np.ndarray) -> np.ndarray:
        V = np.asarray(vertices[: self.n], np.float64)
        _, nn = cKDTree(V).query(points, k=self.k)
        cand = self.vert_faces[nn].reshape(len(points), -1)
        valid = cand >= 0
        tri = V[self.faces[np.where(valid, cand, 0)]]  # (P, C, 3, 3)
        p = np.asarray(points, np.float64)[:, None, :]
        q = closest_point_on_triangles(p, tri[..., 0, :], tri[..., 1, :], tri[..., 2, :])
        return np.where(valid, np.linalg.norm(p - q, axis=-1), np.inf).min(axis=1)


def _apply(T: np.ndarray, P: np.ndarray) -> np.ndarray:
    return P @ T[:3, :3].T + T[:3, 3]


def v2v_mm(model, scan, fit) -> float:
    """Mean distance (mm) between the fitted and the true posed body, vertex to vertex, in the
    truth's model frame (through the scan: ``scan.to_model @ inv(fit.to_model)``)."""
    nb = model.n_body_vertices
    C = scan.to_model @ np.linalg.inv(np.asarray(fit.to_model, np.float64))
    return 1000 * float(np.linalg.norm(_apply(C, np.asarray(fit.posed_vertices[:nb], np.float64))
                                       - scan.true_posed[:nb], axis=1).mean())


@functools.lru_cache(maxsize=2)
def head_vertices(model) -> np.ndarray:
    """(n_body,) bool: the body vertices the head bone moves most."""
    from service.model.fitting.rig import _rig

    return np.argmax(_rig(model).W, axis=1) == BONES.index("head")


@functools.lru_cache(maxsize=2)
def hand_vertices(model) -> np.ndarray:
    """(n_body,) bool: the body vertices a hand bone moves most."""
    from service.model.fitting.rig import _rig

    return np.isin(np.argmax(_rig(model).W, axis=1), [BONES.index("hand_l"), BONES.index("hand_r")])


def evaluate(model, scan, fit, surface: BodySurface) -> dict:
    """Errors of a fit against the scan's truth (see the module docstring)."""
    nb = model.n_body_vertices
    C = scan.to_model @ np.linalg.inv(np.asarray(fit.to_model, np.float64))  # fit frame -> truth frame
    Pf = _apply(C, np.asarray(fit.posed_vertices, np.float64))
    truth = scan.true_posed[:nb]
    _, Jf = posed(model, fit.weights, fit.rotvecs, fit.translation)
    fitted_m = model.measure(model.vertices(fit.weights), scan.gender)
    jerr = np.linalg.norm(_apply(C, Jf) - scan.true_joints, axis=1)
    p2s = surface.distances(truth, Pf)
    return {
        "worst_joint": [BONES[int(np.argmax(jerr))], round(1000 * float(jerr.max()), 1)],
        "v2v_mm": 1000 * float(np.linalg.norm(Pf[:nb] - truth, axis=1).mean()),
        "p2s_mm": 1000 * float(p2s.mean()),
        # without the head's vertices: a scan with no head shows nothing of its posture
        "p2s_no_head_mm": 1000 * float(p2s[~head_vertices(model)].mean()),
        # without the hands: relaxed fingers (synthetic_scans.curl_fingers) no fit can follow
        "p2s_no_hands_mm": 1000 * float(p2s[~hand_vertices(model)].mean()),
        "joints_mm": 1000 * float(np.linalg.norm(_apply(C, Jf) - scan.true_joints, axis=1).mean()),
        "measurements": {n: float(fitted_m[n] - scan.measurements[n]) for n in M.ATTRIBUTES[1:]},
        "unit_ok": fit.unit == scan.unit, "up_ok": fit.up == scan.up,
        "residual_mm": float(fit.residual_mm), "partial": bool(fit.partial),
        "stature_err_cm": float(fitted_m["height_cm"] - scan.measurements["height_cm"]),
        "iterations": [int(fit.outer_iterations), int(fit.inner_iterations)],
        "unseen": list(fit.unseen), "head_shape_from_body": bool(fit.stats.get("head_shape_from_body", False)),
        "head_hypotheses": len(fit.stats.get("head_hypotheses", [])) or 1,
    }


def model_floor_mm(model, scan, surface: BodySurface) -> float:
    """How near the body model comes to the true rest body (a person off its space): the
    mean distance (mm) of the true rest-pose skin to the rest body of its least-squares
    weights (``model.project``), the error a perfect fit would still have."""
    nb = model.n_body_vertices
    X = np.asarray(scan.true_rest, np.float64)
    Y = model.vertices(model.project(X)).astype(np.float64)
    return 1000 * float(surface.distances(X[:nb], Y).mean())


def baseline(model, scan, surface: BodySurface) -> dict:
    """The population mean shape in the true pose and translation, against the truth."""
    nb = model.n_body_vertices
    V, _ = posed(model, np.zeros(model.n_components), scan.rotvecs, scan.translation)
    truth = scan.true_posed[:nb]
    return {"v2v_mm": 1000 * float(np.linalg.norm(V[:nb] - truth, axis=1).mean()),
            "p2s_mm": 1000 * float(surface.distances(truth, V).mean())}


def _stats(values: list[float]) -> dict:
    a = np.asarray(values, np.float64)
    if not len(a):
        return {"n": 0, "median": None, "p90": None, "mean": None}
    return {"n": int(len(a)), "median": float(np.median(a)), "p90": float(np.percentile(a, 90)),
            "mean": float(a.mean())}


# -- 1. accuracy ------------------------------------------------------------------------------
def select_conditions(names: str | None, before: str | None = None) -> tuple[Condition, ...]:
    """The conditions named in a comma-separated list (None or '': all); ``before`` overrides
    every condition's "before" refit ('refine_damping', 'pose_prior', 'scan_cleanup',
    'clothing_contact', 'landmark_init', 'refine_bare', 'none')."""
    from dataclasses import replace

    wanted = [n.strip() for n in (names or "").split(",") if n.strip()] or [c.name for c in CONDITIONS]
    known = {c.name: c for c in CONDITIONS}
    unknown = [n for n in wanted if n not in known]
    if unknown:
        raise ValueError(f"unknown conditions {unknown}; expected some of {list(known)}")
    out = tuple(known[n] for n in wanted)
    if before:
        out = tuple(replace(c, before=None if before == "none" else before) for c in out)
    return out


def parse_fit_params(text: str | None) -> dict:
    """'name=value,...' (values Python literals, e.g. ``None``, ``0.05``) -> {name: value},
    checked against the fields of ``FitParams``."""
    import ast
    from dataclasses import fields

    from service.model.fitting.params import FitParams

    known = {f.name for f in fields(FitParams)}
    out = {}
    for item in (text or "").split(","):
        if not item.strip():
            continue
        name, _, value = item.partition("=")
        name = name.strip()
        if name not in known:
            raise ValueError(f"unknown FitParams field {name!r}")
        out[name] = ast.literal_eval(value.strip())
    return out


def with_overrides(params, overrides: dict):
    """``params`` with ``overrides`` applied to every field it leaves at the default (a
    "before" kind's own change wins)."""
    from dataclasses import replace

    from service.model.fitting.params import FitParams

    default = FitParams()
    return replace(params, **{k: v for k, v in overrides.items() if getattr(params, k) == getattr(default, k)})


def as_uploaded(model, scan, fmt: str):
    """What the fitting job fits when ``scan`` is uploaded as a ``fmt`` file
    (``synthetic_scans.scan_file_bytes``): read by ``uploads.read_body_upload`` (vertices on no
    face dropped, a mesh's normals from its faces, a dense mesh simplified), stored and loaded
    as the queue does (``mesh_io.scan_to_npz_bytes``: float32 offsets). Returns the
    ``mesh_io.Scan``; raises ``ValueError`` when the upload is refused or read as an avatar."""
    from service.application.uploads import read_body_upload
    from service.model.formats.mesh_io import Scan, scan_from_npz_bytes, scan_to_npz_bytes

    up = read_body_upload(model, SS.scan_file_bytes(scan, fmt), f"scan.{fmt}")
    if not isinstance(up, Scan):
        raise ValueError(f"the {fmt} upload was read as a template avatar, not a scan")
    return scan_from_npz_bytes(scan_to_npz_bytes(up))


def bench_fitting_accuracy(limit: int = 0, progress=None, max_pose_deg: float = MAX_POSE_DEG,
                           conditions: tuple[Condition, ...] = CONDITIONS, anatomical: bool = True,
                           fit_params: dict | None = None, known: tuple[str, ...] = (),
                           via_file: str | None = None) -> dict:
    """``known``: attributes of the truth given to every fit (``fit_body(known=...)``, the
    person's own measurements given with the scan; the ``known`` "before" leaves them out).
    ``via_file``: each scan is fitted as the service reads it back from an upload in that format
    (:func:`as_uploaded`; 'ply', 'obj', 'glb', 'stl' or 'xyz'), not from the generated arrays;
    a refused upload counts as a failure."""
    from service.model.fitting.params import FitParams
    from service.model.fitting.fit import fit_body

    overrides = dict(fit_params or {})
    params = FitParams(**overrides)

    model = load_body_model()
    clothes = shared_data_dir() / "makehuman_clothes"
    n = limit or DEFAULT_AVATARS
    people = heldout_people(model, n)
    surface = BodySurface(model.body_faces, model.n_body_vertices)
    rows: dict[str, list] = {c.name: [] for c in conditions}
    failures: dict[str, list] = {c.name: [] for c in conditions}
    base: dict[str, list] = {c.name: [] for c in conditions}
    scan_seconds = []
    for k, person in enumerate(people):
        for cond in conditions:
            name, clothed, cloud = cond.name, cond.clothed, cond.cloud
            t0 = time.perf_counter()
            scan = SS.make_scan(model, np.random.default_rng([SEED, person["index"]]), person["weights"],
                                person["gender"], clothed=clothed, point_cloud=cloud, n_points=N_POINTS,
                                noise_mm=NOISE_MM, max_pose_deg=max_pose_deg, clothes_dir=clothes,
                                garments=None if cond.garments is None else cond.garments[person["gender"]],
                                anatomical=anatomical, detail_mm=cond.detail_mm,
                                detail_rng=np.random.default_rng([SEED, 13, person["index"]]),
                                finger_curl_deg=cond.finger_curl_deg)
            if cond.degrade:
                scan = SS.degrade(scan, cond.degrade, np.random.default_rng([SEED, 11, person["index"]]))
            scan_seconds.append(time.perf_counter() - t0)
            base[name].append(baseline(model, scan, surface))
            t0 = time.perf_counter()
            try:
                given = {a: scan.measurements[a] for a in known} or None
                data = scan if via_file is None else as_uploaded(model, scan, via_file)
                t0 = time.perf_counter()
                fit = fit_body(model, data.points, data.normals, data.faces, clothed=cond.fitted_clothed, params=params,
                               known=given, gender=scan.gender if given else None)
                seconds = time.perf_counter() - t0
                row = evaluate(model, scan, fit, surface)
            except Exception as exc:  # noqa: BLE001 - a benchmark counts failures, never crashes
                failures[name].append({"avatar": person["index"], "error": f"{type(exc).__name__}: {exc}"[:300]})
                continue
            try:  # the same scan without the pose prior or the scan cleaning: "before", same run
                if cond.before is None:
                    raise RuntimeError("not measured in this condition")
                t1 = time.perf_counter()
                prev = evaluate(model, scan, fit_body(model, data.points, data.normals, data.faces, clothed=cond.fitted_clothed,
                                                      params=with_overrides(BEFORE_PARAMS(cond.before), overrides)),
                                surface)
                row["before"] = {"p2s_mm": prev["p2s_mm"], "p2s_no_head_mm": prev["p2s_no_head_mm"],
                                 "p2s_no_hands_mm": prev["p2s_no_hands_mm"],
                                 "stature_err_cm": prev["stature_err_cm"],
                                 "measurements": prev["measurements"], "seconds": time.perf_counter() - t1}
            except Exception as exc:  # noqa: BLE001
                row["before"] = {"error": f"{type(exc).__name__}: {exc}"[:200]}
            row.update({"avatar": person["index"], "gender": person["gender"], "seconds": seconds,
                        "unit": scan.unit, "up": scan.up, "garments": scan.garments,
                        "points": int(len(data.points))})
            if cond.detail_mm:  # the model's own best: the true rest body's projection on its space
                row["floor_mm"] = model_floor_mm(model, scan, surface)
            rows[name].append(row)
            if progress:
                progress(f"[{k + 1}/{len(people)}] {name}: avatar {person['index']} {row['p2s_mm']:.2f} mm, "
                         f"{seconds:.1f} s, worst joint {row['worst_joint']}; before "
                         + (f"{row['before']['p2s_mm']:.2f} mm" if "p2s_mm" in row["before"] else "-"))
    out = {"avatars": len(people), "points": N_POINTS, "noise_mm": NOISE_MM, "max_pose_deg": max_pose_deg,
           "via_file": via_file,
           "poses": "anatomical" if anatomical else "free", "fit_params": {k: repr(v) for k, v in overrides.items()}, "known": list(known),
           "cpu_count": os.cpu_count(), "scan_generation_s_median": float(np.median(scan_seconds)),
           "goal": GOALS, "conditions": {}}
    for cond in conditions:
        name, clothed, cloud = cond.name, cond.clothed, cond.cloud
        r = rows[name]
        E = {a: [abs(x["measurements"][a]) for x in r] for a in M.ATTRIBUTES[1:]}
        goal_mm = GOALS["clothed_body_mm" if cond.fitted_clothed else "unclothed_body_mm"]
        p2s = _stats([x["p2s_mm"] for x in r])
        t = _stats([x["seconds"] for x in r])
        out["conditions"][name] = {
            "clothed": clothed, "fitted_clothed": cond.fitted_clothed, "point_cloud": cloud, "garments": cond.garments,
            "degrade": list(cond.degrade),
            "fits": len(r), "failures": len(failures[name]),
            "failure_examples": failures[name][:3],
            "body_p2s_mm": p2s, "body_v2v_mm": _stats([x["v2v_mm"] for x in r]),
            "body_p2s_no_head_mm": _stats([x["p2s_no_head_mm"] for x in r]),
            "body_p2s_no_hands_mm": _stats([x["p2s_no_hands_mm"] for x in r]),
            "detail_mm": cond.detail_mm, "finger_curl_deg": cond.finger_curl_deg,
            "model_floor_p2s_mm": _stats([x["floor_mm"] for x in r if "floor_mm" in x]),
            "baseline_mean_shape_true_pose": {
                "p2s_mm": _stats([b["p2s_mm"] for b in base[name]]),
                "v2v_mm": _stats([b["v2v_mm"] for b in base[name]])},
            "joints_mm": _stats([x["joints_mm"] for x in r]),
            "measurements_mae": {a: (float(np.mean(v)) if v else None) for a, v in E.items()},
            "seconds": t,
            "unit_detected": sum(x["unit_ok"] for x in r), "up_detected": sum(x["up_ok"] for x in r),
            "residual_mm": _stats([x["residual_mm"] for x in r]),
            "stature_abs_err_cm": _stats([abs(x["stature_err_cm"]) for x in r]),
            "stature_worst_cm": max((abs(x["stature_err_cm"]) for x in r), default=None),
            "flagged_partial": sum(x["partial"] for x in r),
            "before": {
                "kind": cond.before,
                "fits": sum("p2s_mm" in x["before"] for x in r),
                "failures": sum("error" in x["before"] for x in r),
                "seconds": _stats([x["before"]["seconds"] for x in r if "seconds" in x["before"]]),
                "body_p2s_mm": _stats([x["before"]["p2s_mm"] for x in r if "p2s_mm" in x["before"]]),
                "body_p2s_no_head_mm": _stats([x["before"]["p2s_no_head_mm"] for x in r if "p2s_mm" in x["before"]]),
                "body_p2s_no_hands_mm": _stats([x["before"]["p2s_no_hands_mm"] for x in r if "p2s_mm" in x["before"]]),
                "body_p2s_mm_all": _stats([x["before"]["p2s_mm"] if "p2s_mm" in x["before"] else np.inf
                                           for x in r if x["before"].get("error") != "RuntimeError: not measured in this condition"]),
                "stature_abs_err_cm": _stats([abs(x["before"]["stature_err_cm"]) for x in r if "p2s_mm" in x["before"]]),
                "stature_worst_cm": max((abs(x["before"]["stature_err_cm"]) for x in r if "p2s_mm" in x["before"]),
                                        default=None),
                "measurements_mae": {a: (float(np.mean([abs(x["before"]["measurements"][a]) for x in r
                                                        if "measurements" in x["before"]]))
                                         if any("measurements" in x["before"] for x in r) else None)
                                     for a in M.ATTRIBUTES[1:]}},
            "refused_as_not_person": sum(("not a person" in f["error"]) or ("outside the population" in f["error"])
                                         for f in failures[name]),
            "refused_as_not_fitted": sum("could not be fitted to the whole scan" in f["error"] for f in failures[name]),
            "goal": {"body_p2s_median_mm": goal_mm, "body_p2s_p90_mm": GOALS["body_p90_mm"],
                     "seconds_median": GOALS["seconds"]},
            "meets_goal": bool(r) and not failures[name] and p2s["median"] <= goal_mm
            and p2s["p90"] <= GOALS["body_p90_mm"] and t["median"] <= GOALS["seconds"],
            "per_scan": r,
        }
    return out


# -- 1b. the person check and partial scans --------------------------------------------------
CESIUM_STATURE_M = 1.51  # CesiumMan (glTF sample): a 1.51 m clothed game character in T-pose
N_PARTIAL = 4


def bench_person_check(progress=None) -> dict:
    """Non-person shapes (``synthetic_scans.NON_PERSON_KINDS``, point clouds of 12,500 points)
    fitted as clothed with the person check off (before) and on (after), and as bare with it on
    (after_bare): rejected or not, with the reason; CesiumMan (fitted stature or the refusal); single-view front scans of bare
    held-out people (flagged ``partial`` or refused)."""
    from service.model.fitting.checks import FitError
    from service.model.fitting.params import FitParams
    from service.model.fitting.fit import fit_body
    from service.model.formats.mesh_io import read_scan

    model = load_body_model()
    rng = np.random.default_rng([SEED, 99])
    shapes = []
    for kind in SS.NON_PERSON_KINDS:
        pts, nrm, unit, up = SS.non_person_scan(model, kind, rng, n_points=N_POINTS)
        row = {"shape": kind}
        for label, params, clothed in (("before", FitParams(person_check=False), True), ("after", FitParams(), True),
                                       ("after_bare", FitParams(), False)):
            try:
                fit = fit_body(model, pts, nrm, None, clothed=clothed, params=params)
                m = model.measure(model.vertices(fit.weights), "female")
                row[label] = {"rejected": False, "height_cm": round(m["height_cm"], 1),
                              "weight_kg": round(m["weight_kg"], 1)}
            except FitError as exc:
                row[label] = {"rejected": True, "reason": str(exc)}
        shapes.append(row)
        if progress:
            progress(f"non-person {kind}: {row}")
    out: dict = {"shapes": shapes,
                 "rejected_before": sum(r["before"]["rejected"] for r in shapes),
                 "rejected_after": sum(r["after"]["rejected"] for r in shapes),
                 "rejected_after_bare": sum(r["after_bare"]["rejected"] for r in shapes)}
    path = shared_data_dir() / "gltf_samples" / "CesiumMan.glb"
    if path.is_file():
        sc = read_scan(path.read_bytes(), path.name)
        try:
            fit = fit_body(model, sc.points, sc.normals, sc.faces, clothed=True)
            h = model.measure(model.vertices(fit.weights), "male")["height_cm"]
            out["cesium_man"] = {"outcome": "fitted", "height_cm": round(h, 1),
                                 "stature_err_cm": round(h - 100 * CESIUM_STATURE_M, 1)}
        except FitError as exc:
            out["cesium_man"] = {"outcome": "refused", "reason": str(exc)}
    partial = []
    clothes = shared_data_dir() / "makehuman_clothes"
    for person in heldout_people(model, N_PARTIAL):
        scan = SS.make_scan(model, np.random.default_rng([SEED, 5, person["index"]]), person["weights"],
                            person["gender"], clothed=False, point_cloud=True, n_points=N_POINTS,
                            noise_mm=NOISE_MM, max_pose_deg=20.0, clothes_dir=clothes)
        front = SS.front_only(scan)
        try:
            fit = fit_body(model, front.points, front.normals, None, clothed=False)
            partial.append({"avatar": person["index"], "outcome": "partial" if fit.partial else "whole",
                            "coverage": fit.coverage})
        except FitError as exc:
            partial.append({"avatar": person["index"], "outcome": "refused", "reason": str(exc)})
    out["front_only"] = partial
    out["front_only_flagged_or_refused"] = sum(p["outcome"] != "whole" for p in partial)
    return out


# -- 2. jobs under worker kills ---------------------------------------------------------------
def bench_job_kills(n_jobs: int = 50, n_workers: int = 3, kill_every_s: float = 5.0,
                    deadline_s: float = 900.0, progress=None) -> dict:
    """Jobs done/failed/lost while workers are SIGKILLed (module docstring, part 2)."""
    # a few distinct small unclothed scans (PLY), cycled over the jobs
    model = load_body_model()
    people = heldout_people(model, 5)
    files = []
    for p in people:
        scan = SS.make_scan(model, np.random.default_rng([SEED, 7, p["index"]]), p["weights"], p["gender"],
                            clothed=False, point_cloud=False, n_points=3000, noise_mm=NOISE_MM,
                            max_pose_deg=MAX_POSE_DEG)
        files.append(SS.scan_file_bytes(scan, "ply"))
    worker_args = ("--worker-ttl", "10", "--job-monitoring-interval", "2", "--maintenance-interval", "5")
    rng = random.Random(SEED)
    result: dict = {"redis": "embedded (temporary data directory)", "jobs": n_jobs, "workers": n_workers,
                    "kill_every_s": kill_every_s, "deadline_s": deadline_s}
    try:
        with run_server(None, "embedded", log_level="warning", check_log=False, TRYON_EMBEDDED_WORKER="0") as server:
            server.client.headers["X-API-Key"] = RETAILERS["acme"]  # its customers' jobs open with its key
            workers = [start_worker(server.env, *worker_args) for _ in range(n_workers)]
            try:
                _run_kills(server.client, files, workers, lambda: start_worker(server.env, *worker_args),
                           n_jobs, kill_every_s, deadline_s, rng, result, progress)
            finally:
                for w in workers:
                    stop_process(w, signal.SIGKILL, wait=30)
    except Exception as exc:  # noqa: BLE001 - reported, never raised
        result["error"] = f"{type(exc).__name__}: {exc}"
    return result


def _run_kills(client, files, workers, start, n_jobs, kill_every_s, deadline_s, rng, result, progress) -> None:
    t0 = time.monotonic()
    jobs: dict[str, dict] = {}
    rejected: list[str] = []
    for i in range(n_jobs):
        r = client.post("/v1/customers", files={"mesh": (f"scan{i}.ply", files[i % len(files)],
                                                         "application/octet-stream")},
                        data={"clothed": "false"})
        body = r.json() if r.headers.get("content-type", "").startswith("application/json") else {}
        if r.status_code == 202 and isinstance(body.get("job"), dict) and body["job"].get("id"):
            jobs[body["job"]["id"]] = {"status": body["job"].get("status", "queued"), "customer_id": body.get("id")}
        else:
            rejected.append(f"{r.status_code}: {str(body or r.text)[:200]}")
    result.update(submitted=len(jobs), rejected=len(rejected), rejected_examples=rejected[:3])
    kills, last_kill = 0, time.monotonic()
    errors: dict[str, int] = {}
    while jobs and time.monotonic() - t0 < deadline_s:
        pending = [j for j, s in jobs.items() if s["status"] not in ("done", "failed")]
        if not pending:
            break
        for j in pending:
            try:
                r = client.get(f"/v1/jobs/{j}")
            except httpx.HTTPError:
                continue
            if r.status_code == 200:
                s = r.json()
                jobs[j]["status"] = s.get("status", "queued")
                if s.get("status") == "failed":
                    err = str(s.get("error"))[:120]
                    errors[err] = errors.get(err, 0) + 1
        if time.monotonic() - last_kill >= kill_every_s and any(
                s["status"] not in ("done", "failed") for s in jobs.values()):
            k = rng.randrange(len(workers))
            stop_process(workers[k], signal.SIGKILL, wait=30)  # the worker and its work-horse
            workers[k] = start()
            kills += 1
            last_kill = time.monotonic()
            if progress:
                done = sum(s["status"] == "done" for s in jobs.values())
                progress(f"kill {kills}: {done}/{len(jobs)} done after {time.monotonic() - t0:.0f} s")
        time.sleep(1.0)
    states = [s["status"] for s in jobs.values()]
    result.update({
        "done": states.count("done"), "failed": states.count("failed"),
        "lost": sum(s not in ("done", "failed") for s in states), "kills": kills,
        "wall_s": time.monotonic() - t0, "failure_errors": errors, "goal": {"lost": 0},
    })


# -- the suite --------------------------------------------------------------------------------
def run(limit: int = 0, repeats: int = 0, kill: bool = True, max_pose_deg: float = MAX_POSE_DEG,
        conditions: str | None = None, person_check: bool = True, before: str | None = None,
        poses: str = "anatomical", fit_params: str | None = None, known: str | None = None,
        via_file: str | None = None) -> dict:
    """The ``fitting`` suite (``repeats`` is unused: each fit is timed once); ``conditions``: a
    comma-separated subset of ``CONDITIONS`` (default all); ``person_check``: run part 1b;
    ``poses``: "anatomical" (every bone within the joint limits, :func:`SS.random_pose`) or
    "free" (any axis, as before 2026-11-24: a knee may bend 45 degrees sideways); ``fit_params``:
    'name=value,...' FitParams overrides in every fit (:func:`parse_fit_params`); ``known``:
    comma-separated measurements of the truth given to every fit (e.g. 'height_cm,weight_kg');
    ``via_file``: fit each scan as read back from an upload in that format (:func:`as_uploaded`)."""
    say = (lambda msg: print(msg, file=sys.stderr, flush=True)) \
        if sys.stderr.isatty() or os.environ.get("TRYON_BENCH_PROGRESS") else None
    res: dict = {"suite": "fitting",
                 "accuracy": bench_fitting_accuracy(limit, progress=say, max_pose_deg=max_pose_deg,
                                                    conditions=select_conditions(conditions, before),
                                                    anatomical=poses == "anatomical",
                                                    fit_params=parse_fit_params(fit_params),
                                                    known=tuple(a for a in (known or "").split(",") if a),
                                                    via_file=via_file)}
    if person_check:
        res["person_check"] = bench_person_check(progress=say)
    res["job_kills"] = bench_job_kills(progress=say) if kill else {"skipped": "--no-kill"}
    return res


def _f(x, fmt="{:.2f}") -> str:
    return "-" if x is None else fmt.format(x)


def format_result(r: dict) -> str:
    a = r["accuracy"]
    conds = a["conditions"]
    names = list(conds)
    L = [f"body fitting: {a['avatars']} held-out avatars x {len(names)} conditions; scans of {a['points']} points, "
         f"{a['noise_mm']:g} mm noise, {a.get('poses', 'free')} poses up to {a['max_pose_deg']:g} deg per bone, random unit/up/yaw/placement; "
         f"{a['cpu_count']} CPU cores"]
    if a.get("fit_params"):
        L.append("  FitParams overridden: " + ", ".join(f"{k}={v}" for k, v in a["fit_params"].items()))
    head = f"  {'':<40}" + "".join(f"{n.replace('_', ' '):>17}" for n in names)
    L.append(head)

    def row(label, values, goal=""):
        L.append(f"  {label:<40}" + "".join(f"{v:>17}" for v in values) + (f"   {goal}" if goal else ""))

    row("fits (failures)", [f"{c['fits']} ({c['failures']})" for c in conds.values()])
    goals = "goal: " + " / ".join(f"<= {c['goal']['body_p2s_median_mm']:g}" for c in conds.values())
    row("body error, point-to-surface median mm", [_f(c["body_p2s_mm"]["median"]) for c in conds.values()], goals)
    row("  p90 mm", [_f(c["body_p2s_mm"]["p90"]) for c in conds.values()], f"goal: <= {a['goal']['body_p90_mm']:g}")
    row("  without the head, median mm", [_f(c.get("body_p2s_no_head_mm", {}).get("median")) for c in conds.values()])
    row("  without the hands, median mm", [_f(c.get("body_p2s_no_hands_mm", {}).get("median")) for c in conds.values()])
    row("body error, vertex-to-vertex median mm", [_f(c["body_v2v_mm"]["median"]) for c in conds.values()])
    row("  p90 mm", [_f(c["body_v2v_mm"]["p90"]) for c in conds.values()])
    row("baseline: mean shape, true pose, p2s mm", [_f(c["baseline_mean_shape_true_pose"]["p2s_mm"]["median"])
                                                   for c in conds.values()])
    row("  v2v mm", [_f(c["baseline_mean_shape_true_pose"]["v2v_mm"]["median"]) for c in conds.values()])
    if any(c.get("detail_mm") for c in conds.values()):
        row("off the model: detail RMS mm", [f"{c.get('detail_mm', 0):g}" for c in conds.values()])
        row("  the model's own best, p2s median mm", [_f(c["model_floor_p2s_mm"]["median"]) if c.get("detail_mm")
                                                      else "-" for c in conds.values()])
    row("joints, mean over 17, median mm", [_f(c["joints_mm"]["median"]) for c in conds.values()])
    row("  p90 mm", [_f(c["joints_mm"]["p90"]) for c in conds.values()])
    row("unit / up axis detected", [f"{c['unit_detected']}/{c['up_detected']} of {c['fits']}" for c in conds.values()])
    row("time per fit, median s", [_f(c["seconds"]["median"]) for c in conds.values()],
        f"goal: <= {a['goal']['seconds']:g} s")
    row("  p90 s", [_f(c["seconds"]["p90"]) for c in conds.values()])
    row("rest-pose stature |error| median cm", [_f(c["stature_abs_err_cm"]["median"]) for c in conds.values()],
        "goal: <= 0.5")
    row("  worst cm", [_f(c["stature_worst_cm"]) for c in conds.values()], "goal: <= 1")
    row("before, same scans: what", [str(c["before"].get("kind") or "-").replace("_", " ")
                                      for c in conds.values()], "(no pose prior / no scan cleanup)")
    row("  fits (failures)", [f"{c['before']['fits']} ({c['before'].get('failures', 0)})"
                              for c in conds.values()])
    row("  p2s median mm", [_f(c["before"]["body_p2s_mm"]["median"]) for c in conds.values()])
    row("  p90 mm", [_f(c["before"]["body_p2s_mm"]["p90"]) for c in conds.values()])
    row("  without the head, median mm", [_f(c["before"].get("body_p2s_no_head_mm", {}).get("median"))
                                          for c in conds.values()])
    row("  without the hands, median mm", [_f(c["before"].get("body_p2s_no_hands_mm", {}).get("median"))
                                           for c in conds.values()])
    row("  stature |error| median cm", [_f(c["before"]["stature_abs_err_cm"]["median"])
                                        for c in conds.values()])
    row("  worst cm", [_f(c["before"]["stature_worst_cm"]) for c in conds.values()])
    for attr in ("waist_cm", "weight_kg", "arm_length_cm"):
        row(f"  {attr} mean |error|", [_f(c["before"].get("measurements_mae", {}).get(attr)) for c in conds.values()])
    row("  time per fit, median s", [_f(c["before"]["seconds"]["median"]) for c in conds.values()])
    row("    p90 s", [_f(c["before"]["seconds"]["p90"]) for c in conds.values()])
    row("refused (not a person / outside population)", [str(c["refused_as_not_person"]) for c in conds.values()],
        "goal: 0 (false rejections)")
    row("refused (part of the scan not explained)", [str(c.get("refused_as_not_fitted", 0)) for c in conds.values()],
        "a wrong fit refused, not returned")
    row("flagged partial (whole scans)", [str(c["flagged_partial"]) for c in conds.values()], "goal: 0")
    row("meets goals", ["yes" if c["meets_goal"] else "no" for c in conds.values()])
    L.append("  measurements on the fitted rest body, mean |error| (cm, kg)")
    for attr in M.ATTRIBUTES[1:]:
        row(f"    {attr}", [_f(c["measurements_mae"][attr]) for c in conds.values()])
    for n, c in conds.items():
        for f in c["failure_examples"]:
            L.append(f"  failure ({n}, avatar {f['avatar']}): {f['error']}")
    L.append(f"  (scan generation, median {a['scan_generation_s_median']:.2f} s per scan, not counted)")

    pc = r.get("person_check")
    if pc:
        L.append("")
        L.append(f"non-person shapes rejected: {pc['rejected_after']} of {len(pc['shapes'])} fitted as clothed, "
                 f"{pc.get('rejected_after_bare', '-')} of {len(pc['shapes'])} as bare "
                 f"(before, person check off, same run: {pc['rejected_before']} of {len(pc['shapes'])}); goal: all")
        for row_ in pc["shapes"]:
            b, a = row_["before"], row_["after"]
            ab = row_.get("after_bare", {"rejected": True})
            L.append(f"  {row_['shape']:<22} before: " + ("rejected" if b["rejected"] else
                     f"accepted ({b['height_cm']} cm, {b['weight_kg']} kg)") + "; after: "
                     + (a.get("reason", "rejected") if a["rejected"] else f"ACCEPTED ({a['height_cm']} cm)")
                     + "; fitted as bare: " + (ab.get("reason", "rejected") if ab["rejected"]
                                               else f"ACCEPTED ({ab['height_cm']} cm)"))
        cm = pc.get("cesium_man")
        if cm:
            L.append("  CesiumMan (1.51 m, T-pose, clothed): " + (
                f"fitted at {cm['height_cm']} cm ({cm['stature_err_cm']:+.1f} cm)" if cm["outcome"] == "fitted"
                else f"refused: {cm['reason']}"))
        L.append(f"single-view front scans (bare, <= 20 deg): {pc['front_only_flagged_or_refused']} of "
                 f"{len(pc['front_only'])} flagged partial or refused; goal: all")
        for p_ in pc["front_only"]:
            L.append(f"  avatar {p_['avatar']}: {p_['outcome']} {p_.get('coverage', p_.get('reason', ''))}")

    k = r.get("job_kills", {})
    L.append("")
    if "skipped" in k:
        L.append(f"jobs under worker kills: skipped ({k['skipped']})")
    elif "error" in k:
        L.append(f"jobs under worker kills: error: {k['error']}")
    else:
        L.append(f"jobs under worker kills: {k['jobs']} scans uploaded, {k['workers']} workers, one SIGKILLed "
                 f"(process group) every {k['kill_every_s']:g} s and replaced ({k['kills']} kills), "
                 f"Redis {k['redis']}")
        L.append(f"  done {k['done']}, failed {k['failed']}, lost {k['lost']} (goal 0; deadline "
                 f"{k['deadline_s']:g} s), rejected uploads {k['rejected']}, wall time {k['wall_s']:.1f} s")
        for err, count in k.get("failure_errors", {}).items():
            L.append(f"  failed x{count}: {err}")
        for ex in k.get("rejected_examples", []):
            L.append(f"  rejected: {ex}")
    return "\n".join(L)

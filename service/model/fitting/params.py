"""The fit's parameters: :class:`FitParams` (weights, iteration limits, switches) with their units.
"""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class FitParams:
    """Weights, iteration limits and switches of the fit (names follow the editing paper).

    Weights are relative to the data terms, which are sums of squared metres over template
    vertices (or over the subsample in the initialisation). ``None`` or 0 switches a term off
    where so noted. Why each value is what it is: CHANGELOG.md, "Scan fitting: the measurements
    behind `FitParams`' values".
    """

    # -- Alg. 1 (Sec. 4.2) loop limits
    max_outer: int = 3  # outer iterations (re-matched correspondences)
    max_inner: int = 20  # inner iterations (Eqs. 2, 3, 4) per outer iteration
    inner_tol: float = 0.001  # m: the inner loop stops when T moves less
    outer_tol: float = 0.005  # m: the outer loop stops when T moves less
    # -- correspondences
    normal_reject_deg: float = 30.0  # degrees: pairs whose normals differ more are rejected (Sec. 4.2)
    max_corr_dist: float = 0.10  # m: farther nearest points are not the same surface
    # -- Eq. 2 weights
    alpha_point: float = 0.1  # point-to-point term
    alpha_plane: float = 1.0  # point-to-plane term
    # -- Eq. 3: neighbouring-bone smoothness omega sum ||theta_b - theta_parent(b)||^2 over the
    # local rotations (also a pull towards the rest pose), per squared radian
    bone_smoothness: float = 0.02
    bare_smoothness: float | None = 0.1  # ... in a clothed scan's posture-first (bare) stage; None: bone_smoothness
    # -- clothing (a template vertex inside the scan: the clothes stand off the body)
    inside_weight: float = 0.1  # weight of such a pair in the ICP
    alg1_inside_tol: float = 0.003  # m: deeper pairs are dropped in Alg. 1
    # m: cloth thickness plus scanner noise; a pair d inside weighs 1 / (1 + (d / contact)^2)
    # (Cauchy) in the refinement. None: the constant inside_weight
    clothing_contact: float | None = 0.004
    # shape prior of a clothed scan's refinement and Alg. 1, as shape_prior (s^2, s in m: the
    # cloth's stand-off, not scanner noise). None: shape_prior throughout
    clothed_shape_prior: float | None = 0.02 ** 2
    # m: per body region, inside pairs also count 1 / (1 + (median depth / depth)^2) (loose
    # regions say only "the body is inside"). None: off (replaced by cloth_offset_mean)
    loose_region_depth: float | None = None
    # m: mean of the exponential prior on each body region's cloth stand-off o_R >= 0, one unknown
    # per region (the clothes moved in by o_R along their normals). None: off
    cloth_offset_mean: float | None = 0.05
    # -- shape
    shape_prior: float = 0.005 ** 2  # s^2 (s in m): Gaussian prior sum_k beta_k^2 / var_k as the posterior under noise s
    update_stride: int = 2  # the pose and shape updates use every n-th template vertex
    # -- initialisation (coarse parametric ICP on a subsample)
    coarse_points: int = 2000  # template and scan points in the coarse stage
    coarse_iterations: int = 24
    coarse_shape_components: int = 12  # shape components freed after the skeleton
    coarse_normal_reject_deg: float = 60.0  # degrees
    coarse_max_dist: float = 0.25  # m
    yaw_steps: int = 8  # facings tried around the up axis
    robust_scale: float = 0.05  # m: residuals beyond it are down-weighted (Huber-like)
    levenberg: float = 1e-3  # damping, relative to the mean diagonal of the normal equations
    max_rotation_step: float = 0.3  # radians per Gauss-Newton step
    min_accepted: float = 0.2  # share: fewer template vertices matching the scan is not a person
    coarse_candidates: int = 3  # best screened (up axis, facing) candidates taken through the coarse stage
    coarse_each_up: bool = True  # ... plus the best of each up-axis sign
    area_weighted: bool = True  # clothed scans: the template's side weighted by surface area per vertex
    # a pair is dropped when the template vertex nearest to its scan point lies on a bone more
    # than this many joints away (the point is another body part's). None: off
    exclusive_hops: int | None = 2
    # m per share: the initialisation's cost adds this times the share of the arms' points inside
    # the torso or thighs (poses.arm_inside_share). 0: off
    arm_inside_cost: float = 0.01
    limb_search: bool = True  # limbs caught in a local minimum re-tried at discrete turns
    landmark_init: bool = True  # limbs aimed at the scan's extremities (landmarks) before the coarse schedule
    landmark_hypotheses: int = 4  # left/right assignments scored beside ICP alone
    landmark_candidates: int = 3  # ... on this many best coarse candidates
    landmark_candidate_ratio: float = 1.5  # ... whose coarse cost is within this factor of the best
    # bare scans: the coarse rest stature scaled by the scan's height over the posed body's when
    # the ratio is within 1 +- this. None: off
    init_stature_max: float | None = 0.1
    coarse_bone_smoothness: float = 0.1  # per squared radian, against residuals normalised to the subsample
    # -- refinement before Alg. 1 (the same ICP on more points, every component)
    refine_points: int = 8000
    max_points: int | None = 100_000  # a denser scan is fitted on this many random points. None: all
    refine_normal_reject_deg: float | None = 30.0  # degrees, bare scans. None: coarse_normal_reject_deg
    refine_iterations: int = 24
    # clothed scans: iterations with symmetric weights first (the clothes' outer surface fitted as
    # skin gives the posture), then the clothing-aware ones. 0: off
    refine_bare_iterations: int = 12
    # per squared radian: the clothed refinement pulls each bone's local rotation towards the
    # posture of the bare stage (_anchor_terms). 0: off
    clothed_posture_anchor: float = 0.1
    alg1_posture_anchor: float = 1.0  # ... and Alg. 1's Eq. 3 of a clothed scan towards its start. 0: off
    refine_levenberg: float = 1e-6  # the refinement's damping (as levenberg): follows the shape/posture valley
    run_alg1: bool = True
    alg1_matched_only: bool = True  # bare scans: Eqs. 3 and 4 fit only template vertices matched to the scan
    person_check: bool = True  # person_check before and after the fit
    scan_cleanup: bool = True  # floor and stray clusters dropped, no pull into holes (scan_cleanup)
    refine_hole_reject: bool = True  # the refinement pairs no vertex whose nearest point is on a hole's rim
    rim_reject: bool = True  # bare scans, Alg. 1 too: no pair with a point on a rim found on the scan
    flat_cap: bool = True  # a scanner's flat cap over an open head top found and dropped
    hair_region: bool = True  # bare scans: the head but the face, and the neck, weighted as clothed
    hair_back: bool = True  # ... and the upper back (long hair)
    # bare scans whose head's seen share after the initialisation is below this: the face's pairs
    # move the pose but not the shape. None: off
    face_shape_min_seen: float | None = 0.65
    # ... below this: the refinement and Alg. 1 also run with the whole head and neck pose-only,
    # and the body leaving less of the scan unexplained is kept (scan_to_surface_mm). None: off
    head_hypothesis_seen: float | None = 0.75
    # per squared radian: bare scans, a bone hardly seen (seen share < TUNING.unseen_share) is pulled to
    # its rest posture (refinement and Eq. 3). 0: off
    unseen_prior: float = 0.03
    clothed_unseen_bones: tuple = ("hand_l", "hand_r")  # clothed scans: the bones unseen_prior applies to
    # bones the scan does not show (no pairs, not in the costs, pulled to rest; the body there is
    # the model's, extrapolated)
    absent_bones: tuple = ()
    headless_check: bool = True  # a scan without its head: the coarse stage re-run with the head absent, kept if so
    known_weight: float = 1.0  # measurements given with the scan (fit_body(known=...)): soft targets in Eq. 4
    # m: a finger's pair weighs 1 / (1 + (r / finger_scale)^2) (Cauchy; the model has no finger
    # bones). None: as any other vertex
    finger_scale: float | None = 0.005
    finger_refine_from: float | None = 0.5  # share of the refinement's iterations before finger_scale applies. None: Alg. 1 only
    joint_limit_weight: float = 10.0  # per squared radian outside JOINT_LIMITS_DEG (coarse ICP, Eq. 3). 0: none
    posture_weight: float = 0.0  # ||A beta||^2, the shape's change of the rest bone directions (_posture_matrix). 0: off
    damping: float = 1e-6  # Tikhonov damping of the Gauss-Newton steps
    blas_threads: int | None = 1  # BLAS threads while fitting. None: the library's default
    compiled: bool = True  # the pose Jacobian and point-to-plane rows by the compiled kernels where numba is there

DEFAULT_PARAMS = FitParams()


@dataclass(frozen=True)
class FitTuning:
    """Fixed tuning of the fit's stages (thresholds, shares, distances in metres, angles in
    degrees), next to :class:`FitParams`, whose fields a caller or the bench may change. One
    instance, :data:`TUNING`."""

    # -- regions (regions.py; rest template, metres, Y up, facing +Z)
    # where hair may stand off the skin: the vertices of hair_bones but the face (normal z >
    # scalp_face_normal_z, below the hairline scalp_hairline_m under the head's top)
    hair_bones: tuple = ('head', 'neck')
    scalp_hairline_m: float = 0.06
    scalp_face_normal_z: float = 0.8
    # where long hair may hang: the back (normal z < hair_back_normal_z) of hair_back_bones, between
    # the shoulder joints, down to hair_back_below_m under the skull base
    hair_back_below_m: float = 0.35
    hair_back_normal_z: float = -0.3
    hair_back_bones: tuple = ('spine', 'chest')
    # the fingers: a hand bone's vertices further from the wrist, along the hand, than this share
    # of the hand's length (the knuckles)
    finger_knuckle_share: float = 0.45
    # -- prepare (prepare.py)
    # a template vertex is seen (``seen_shares``) when a scan point within seen_m (or seen_spacings
    # of the scan's point spacings) of it, posed as initialised, is not on a hole's rim; a bone
    # with fewer than unseen_share of its vertices seen gets ``FitParams.unseen_prior``
    seen_m: float = 0.02
    seen_spacings: float = 2.0
    unseen_share: float = 0.3
    # ... but not the root (the scan's frame) nor the feet (a scanner's floor takes their soles)
    unseen_free_bones: tuple = ('pelvis', 'foot_l', 'foot_r')
    # a scan without its head (``FitParams.headless_check``): the headless coarse fit is kept when
    # no more than headless_head_share of the scan has the head as its nearest body part (within
    # headless_near_m) more than headless_above_m above the skull base
    headless_near_m: float = 0.1
    headless_above_m: float = 0.03
    headless_head_share: float = 0.002
    rim_spacings: float = 1.0  # a point this many point spacings from a hole's rim counts as on it (_make_scan)
    # -- initialise (initialise.py)
    offset_active_set_rounds: int = 40  # _offset_step's limit: each round fixes or frees at least one of 17
    search_angle_deg: float = 50.0  # the limb search's discrete turn of each searched bone
    limit_cost_m_per_rad: float = 0.05  # limb search: a pose 1 rad outside the limits costs as much as 5 cm of distance
    template_graph_max_edge_m: float = 0.15  # the template subsample is sparse on the legs (vertex density)
    # the coarse ICP of a hypothesis pulls the effectors to their tips (point to point, weight per
    # effector relative to the template subsample's size, i.e. a share of the data term) in this
    # share of its iterations; the rest fit the scan alone
    landmark_weight: float = 0.05
    landmark_pull_share: float = 0.75
    aim_rounds: int = 2  # cyclic-coordinate-descent sweeps over each chain's bones
    aim_max_deg: float = 120.0  # larger turns of one bone are clipped (a wrong tip must not fold a limb)
    landmark_margin_m: float = 0.0001  # a hypothesis must beat ICP alone by this much (symmetric distance, m)
    # -- Alg. 1 (alg1.py)
    # the tolerance of a measurement the customer gives (attribute units: cm, kg): one sigma of
    # ``FitParams.known_weight``'s term; the others (girths, lengths) known_sigma_cm
    known_sigma: dict = field(default_factory=lambda: {'height_cm': 0.5, 'weight_kg': 1.0})
    known_sigma_cm: float = 1.0
    # the head hypotheses' score (``FitParams.head_hypothesis_seen``): a scan point counts no more
    # than this far from the body (a flying pixel, a stray cluster left by the cleaning)
    head_hypothesis_clip_m: float = 0.05


TUNING = FitTuning()

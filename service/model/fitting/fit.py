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

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from service.model.geometry import kernels
from service.model.fitting import landmarks as LM
from service.model.fitting import person_check as PC
from service.model.fitting import scan_cleanup as SC
from service.model.formats.frames import UnitError, detect_unit, orient_outward, up_candidates
from service.model.geometry.mesh import closest_points_on_mesh, estimate_normals, face_incidence, vertex_normals
from service.model.body.lbs import axis_angle_to_matrix, global_transforms, matrix_to_axis_angle
from service.model.body import poses as POSES
from service.model.body.poses import rotation_between
from service.model.geometry.solvers import (
    EdgeSystem,
    damped_step,
    edge_incidence,
    nearest_correspondences,
    point_to_plane_normal_equations,
    trimmed_mean,
)


class FitError(ValueError):
    """A scan that cannot be fitted (not a standing person, degenerate, ...); the message is
    meant for the customer."""


NOT_A_PERSON = "not a person: "  # the prefix of every FitError of the person check
OUTSIDE_POPULATION = "the fitted body is outside the population: "
NOT_FITTED = "the body could not be fitted to the whole scan: "  # a wrong minimum (issue 12)


def check_person_before(points_m: np.ndarray) -> None:
    """The person check before the fit (``person_check``: convex solids, separate bodies);
    points (P, 3) metres. Raises :class:`FitError` ``not a person: <reason>``."""
    for check in (PC.convex_solid, PC.separate_bodies):
        reason = check(points_m)
        if reason:
            raise FitError(NOT_A_PERSON + reason)


def check_population(model, weights: np.ndarray) -> dict:
    """The fitted shape (K,) inside the population (shape prior, accepted measurement ranges);
    raises :class:`FitError` saying why not. Returns the figures."""
    measured = model.measure(model.vertices(weights), "female")  # gender only labels, geometry alike
    reason, figures = PC.population_check(weights, model.variances, measured, model.attributes)
    if reason:
        raise FitError(OUTSIDE_POPULATION + reason)
    return figures


@dataclass(frozen=True)
class FitParams:
    """Weights and iteration limits of the fit (names follow the editing paper)."""

    # Alg. 1 loop limits and tolerances (metres). Outer iterations: issue 12, scans with holes
    # drift in Alg. 1's later outer iterations, each re-matching moving the fit further from the
    # truth (held-out avatar 3 in a casual suit, scanner, 20 degrees: 10 -> 7.34 mm, 5 -> 6.82, 3
    # -> 5.92). Fitting bench, 12 avatars, 20 and 45 degrees, scanner, minimal-clothing scanner,
    # holes, clothed and bare meshes, same run (2026-11-25, ``--before alg1_outer``): 10 -> 3
    # made 17 of 120 scans better by more than 0.05 mm (avatar 41's holes scan at 45 degrees
    # 2.19 -> 1.20 mm), none worse, 0.7-1.2 s faster; the others had converged by the third
    max_outer: int = 3
    max_inner: int = 20
    inner_tol: float = 0.001
    outer_tol: float = 0.005
    # correspondences
    normal_reject_deg: float = 30.0  # Sec. 4.2: rejected when normals differ by more
    max_corr_dist: float = 0.10  # metres; farther nearest points are not the same surface
    # Eq. 2
    alpha_point: float = 0.1
    alpha_plane: float = 1.0
    # Eq. 3: neighbouring-bone smoothness omega sum ||theta_b - theta_parent(b)||^2 with theta the
    # local (relative) rotations, i.e. also a pull towards the rest pose (in the refinement too).
    # Issue 12: raising it to 3 tripled the body error (1.0 -> 2.8 mm bare, 3.1 -> 8.2 mm
    # clothed). Lowering it from 0.1 to 0.02 (fitting bench, 12 avatars at 45 degrees, same run,
    # ``bare_smoothness`` 0.1): the pull had straightened bent knees and spines and the rest body
    # came out short (43 of 48 clothed scans); body error unclothed 1.16 -> 0.71 mm, clothed mesh
    # 2.97 -> 2.57, clothed cloud 2.82 -> 2.49, scanner 3.54 -> 3.30, loose clothes 3.51 -> 3.29
    # mm (57 of 60 scans better), the rest-pose stature median 0.49 -> 0.22, 0.72 -> 0.51,
    # 0.61 -> 0.41, 1.01 -> 0.81, 0.72 -> 0.55 cm; the weight under clothes 0.4-1.1 kg further
    # off. The joint limits and, for clothed scans, the posture anchors hold the pose instead
    bone_smoothness: float = 0.02
    # ... but 0.1 in a clothed scan's posture-first stage (the clothes' outer surface fitted as
    # skin, ``refine_bare_iterations``), which finds the posture the later stages are anchored
    # to: at 0.02 there too, held-out avatar 1 (bent forward, an arm up, a casual suit, clothed
    # point cloud, 45 degrees) folded into a wrong minimum, 6.6 -> 28.4 mm, the head 13 cm off and
    # the rest body 17.7 cm short; 0.1 in this stage: 6.2 mm. None: ``bone_smoothness``
    bare_smoothness: float | None = 0.1
    # clothing: weight of a correspondence whose template vertex is inside the scan
    inside_weight: float = 0.1
    # clothing in Alg. 1: correspondences more than this inside the scan are dropped there
    alg1_inside_tol: float = 0.003
    # clothing in the refinement (issue 12, loose clothes): a body point this far (metres) inside
    # the clothes may still touch them -- cloth thickness (~1-2 mm) plus the scanner's noise
    # (~2 mm) -- so it keeps nearly the full weight; deeper inside, the clothes stand off the
    # body (free space under a jacket or skirt) and the pair says only "the body is inside":
    # its weight falls as 1 / (1 + (depth / contact)^2) (Cauchy, redescending), so a loose
    # jacket 3 cm out pulls ~100x less than a tight shirt instead of inside_weight's constant
    # 10 %, which inflated the body under suits. None: the constant inside_weight
    clothing_contact: float | None = 0.004
    # ... and the shape prior of the clothing-aware refinement and Alg. 1 of a clothed scan
    # (as ``shape_prior``: s^2 for a per-coordinate residual s). Under clothes the residuals
    # are not the scanner's noise but the cloth's stand-off, ~1-3 cm under a suit, and with 5 mm
    # the body grew into it: held-out men at 45 degrees came out 15-26 kg heavier in loose suits
    # (waist +9-21 cm). 2 cm (fitting bench, 12 avatars, 45 degrees, against 5 mm in the same
    # run, bone smoothness 0.1): body error clothed mesh 3.08 -> 2.97 mm, scanner 3.75 -> 3.54
    # mm, better on 36 of the 45 scans both fitted (worse by <= 0.13 mm on 7), waist mean
    # |error| 7.3 -> 6.1 cm; two loose-clothes scans refused before (a calf outside the
    # population) are fitted. With smoothness 0.02 (6 clothed scans rechecked): 0.05-0.20 mm
    # better on 4 of 5 (0.02 worse), waists 0.3-2.2 cm smaller on 3 men, a refusal now fitted. Only
    # after the posture is found: a 5 cm prior from the initialisation on turned held-out
    # avatar 1's bent torso wrong (6.6 -> 14.6 mm); 5 cm here made women 0.1-0.2 mm worse.
    # None: ``shape_prior`` throughout
    clothed_shape_prior: float | None = 0.02 ** 2
    # ... and per body region (the template vertices' dominant bone): where the body sits deep
    # inside the clothes all over (the median depth of the region's pairs inside, the rest
    # counted as 0), the clothes hang loose there and say only that the body is inside them,
    # so every inside pair of the region counts 1 / (1 + (median / depth)^2) as much again. A
    # single pair's contact weight cannot tell a loose suit from a snug one: under a loose
    # jacket the pairs 1-2 cm deep still pulled the body out to fill it (held-out men in suits
    # 14-26 kg heavier, waists +10-23 cm). Snug regions (median a few mm) keep ~ their weight.
    # Fitting bench, 12 avatars at 45 degrees (anatomical poses), same run without -> with:
    # weight mean |error| clothed mesh 8.3 -> 5.2 kg, loose clothes 11.2 -> 9.2, scanner 7.7 ->
    # 5.7, point cloud 7.9 -> 6.0, tight 7.6 -> 7.0; body error p90 3.38 -> 2.99, 3.78 -> 3.49,
    # 4.18 -> 3.25 mm (medians within -0.12 / +0.08 mm; avatar 3 in a loose casual suit 4.78 ->
    # 2.66 mm, +26.1 -> +4.0 kg); the stature median 0.04-0.18 cm further off. 5 mm: men nearer
    # still, women 0.1-0.2 mm worse; 2 cm: next to no change. Off since the stand-offs below
    # replaced it (2026-11-25): with both, a region deep in the clothes has almost no data left,
    # and the trousers' stand-off let a 115 kg man's whole body shrink to -29 kg. None: off
    loose_region_depth: float | None = None
    # ... and a cloth stand-off per body region (issue 12: clothed men too heavy, the body
    # filling a hanging T-shirt): the clothing-aware refinement fits the body to the clothes
    # moved in by o_R >= 0 along their normals in each region R (the template vertices'
    # dominant bone), o_R one unknown per region with an exponential prior of this mean
    # (metres). The stand-off of the clothes over a region is correlated over all its pairs,
    # not independent noise per pair: without o_R thousands of pairs inside the clothes each
    # pull the body out a little against a shape prior that counts once, and the body fills
    # the clothes. With o_R the data fix the body only up to a uniform stand-off per region,
    # and the shape prior (the body's bare and snug parts predicting the loose ones) against
    # the offset prior decides how far inside it sits. Fitting bench, 12 avatars at 45 degrees
    # (anatomical poses), against the loose regions above, same run: body error median / p90
    # clothed mesh 2.33 / 2.99 -> 1.80 / 2.76 mm, loose clothes 3.14 / 3.49 -> 2.46 / 2.90, tight
    # 1.85 / 2.75 -> 1.52 / 2.04, point cloud 2.10 / 2.99 -> 1.71 / 2.24, scanner 2.64 / 3.02 ->
    # 2.25 / 2.68; weight mean |error| 5.7 -> 1.9, 9.2 -> 4.1, 7.0 -> 2.3, 6.2 -> 1.7, 5.8 -> 1.6
    # kg. A mean of 3 or 10 cm gives the same within 0.05 mm and 1.3 kg;
    # 1-2 cm is too dear an offset, and the body fills the clothes as before. None: off
    cloth_offset_mean: float | None = 0.05
    # Gaussian shape prior sum_k beta_k^2 / var_k, weighted against the data terms (sums of
    # squared metres over template vertices): s^2 makes it the posterior under per-coordinate
    # noise s
    shape_prior: float = 0.005 ** 2
    # the pose and shape updates use every n-th template vertex
    update_stride: int = 2
    # initialisation
    coarse_points: int = 2000
    coarse_iterations: int = 24
    coarse_shape_components: int = 12
    coarse_normal_reject_deg: float = 60.0
    coarse_max_dist: float = 0.25
    yaw_steps: int = 8
    robust_scale: float = 0.05  # metres: residuals beyond it are down-weighted (Huber-like)
    levenberg: float = 1e-3  # damping, relative to the mean diagonal of the normal equations
    max_rotation_step: float = 0.3  # radians per Gauss-Newton step
    min_accepted: float = 0.2  # fewer template vertices matching the scan: not a person
    coarse_candidates: int = 3
    # the best screened facing of each up-axis sign also goes through the coarse stage when the
    # screen's best ``coarse_candidates`` are all of the other sign: the screen (the root alone,
    # 5 iterations) can rank a body upside down first, on a scan without a head (held-out avatar
    # 4, 45 degrees: screened -y 93 mm / +y 109 mm, after the coarse stage +y 23 / -y 40 mm)
    coarse_each_up: bool = True
    # issue 12: the template's side of the initialisation's distances (ICP pairs, the symmetric
    # distance that scores hypotheses) weighted by the surface area each vertex stands for. The
    # template's vertices are far from uniform on the surface: the hands hold 12 % of them each
    # (2 % of the area), the head 31 % (8 %), a thigh 2.5 % (11 %); counted per vertex, a hand
    # off the scan (in a hole) cost as much as a thigh, and the limb search folded a forearm
    # onto the hip, the scan's own hand left out (held-out avatar 39, scanner, 20 degrees: 28 mm)
    # Clothed scans only: on bare held-out scans at 45 degrees (6 avatars) it bent one leg short
    # (1.1 -> 17.6 mm, the stature 15 cm short, not refused) and moved the other five by <=
    # 0.12 mm; per area the feet count less, and there the skin's feet and hands are sharp
    # features worth their vertices. Scoring per area but ICP per vertex: avatar 1 23 mm
    area_weighted: bool = True
    # issue 12: a template vertex's pair with its nearest scan point is dropped when the template
    # vertex nearest to that scan point lies on a bone more than this many joints away (the scan
    # point is another body part's): a hand over a hole in the scan is not pulled into the thigh
    # beside it (held-out avatar 40, raw scanner scan, 45 degrees); None: off
    exclusive_hops: int | None = 2
    # issue 12: the initialisation's cost of a pose adds this many metres times the share of the
    # arms' points inside the torso or thighs (``poses.arm_inside_share``; 0: off). The symmetric
    # distance is a trimmed mean: a limb hidden inside the body costs little there, and a raw
    # scanner scan with a hole at the hand (held-out avatar 40, 45 degrees) was fitted with the
    # hand inside the thigh, or with the arms crossed through the chest (an arm 78 cm long). At
    # 2 cm the coarse states of a clothed man bent forward 70 degrees (arms still inside the
    # torso there, 30-56 %) lost to a wrong facing (81 mm, refused); at 1 cm 2.16 mm, without 4.23
    arm_inside_cost: float = 0.01
    limb_search: bool = True
    # issue 12: limbs aimed at the scan's extremities (service.model.fitting.landmarks) before the
    # coarse schedule, the assignment and up to this many left/right swaps scored beside ICP alone
    landmark_init: bool = True
    landmark_hypotheses: int = 4
    # ... on each of this many best coarse candidates (up axis and facing): a turned, bent torso
    # can leave the right facing a hair behind a wrong one after ICP alone, and only the
    # landmarks tell them apart (held-out avatar 1 turned 178 degrees: coarse cost 0.0325 vs
    # 0.0323 for a body facing 45 degrees off; aimed at the tips, 17 vs 23 mm)
    landmark_candidates: int = 3
    # ... of those, only the ones whose coarse cost is within this factor of the best: held-out
    # scans at 45 degrees whose second or third candidate won came within 1.34x (most within
    # 1.02x); skipping those beyond 1.5x (9 of 22 tries on 16 scans) saves ~1.5 s each
    landmark_candidate_ratio: float = 1.5
    # issue 12: the coarse state's rest stature scaled by the scan's height over the posed
    # body's (``_stature_from_extent``), then a few coarse iterations. The coarse stage's 12
    # components left the stature near the population's: on 12 held-out bare scans at 20
    # degrees -16.0 to +11.7 cm off (median |error| 5.3 cm), after it -11.0 to +3.5 (1.85 cm),
    # and the refinement had less to find with the head unseen (long hair, a cut top). Bare
    # scans only: a clothed scan's height is its shoes' and hat's too (read from PLY files at 20
    # degrees the clothed scanner scan of held-out avatar 37, its top also cut, came out 2.53 cm
    # short after it and 2.32 -> 5.06 mm). None: off; a ratio beyond 1 +- this (half a body, a
    # missing head) leaves the state alone
    init_stature_max: float | None = 0.1
    # neighbouring-bone smoothness while the pose is found (against per-point residuals
    # normalised to the subsample size): a prior that prefers the smaller of two rotations
    # that explain the scan equally well
    coarse_bone_smoothness: float = 0.1
    # refinement before Alg. 1: the same parametric ICP on more points with every component
    refine_points: int = 8000
    # a dense scan (a body scanner's mesh: 100k-1M vertices) is fitted on this many of its points,
    # drawn at random once its floor and strays are gone (a mesh's normals from the whole mesh, a
    # point cloud's estimated on the share: 4.5 s for 450k points) (None: all). The
    # bench's scans have 12.5k; a 450k-point scanner mesh took 14.4 s (10.7 s initialising, 2.9 s
    # of it finding holes' rims), a 192k one 8.1 s
    max_points: int | None = 100_000
    # the refinement's pairs on a bare scan are rejected when normals differ by more than this
    # (the paper's Sec. 4.2 value, as in Alg. 1), not the coarse stage's 60 degrees. Issue 12, a
    # body scanner's mesh (bare, 8 holes, the head top cut 4 cm down, 20 degrees): held-out
    # avatar 41's face is in a hole; even started at the truth, the refinement tipped her head
    # back 27 degrees and grew it (stature +3.2 cm); from the initialisation +3.8 cm and 5.5 mm,
    # with 30 degrees (and ``refine_hole_reject``) +0.96 cm and 3.6 mm. Clothed scans keep 60
    # degrees: the clothes' normals are not the body's, and at 30 held-out avatar 1 in a loose
    # suit (45 degrees) went 4.9 -> 11.5 mm. None: ``coarse_normal_reject_deg``
    refine_normal_reject_deg: float | None = 30.0
    refine_iterations: int = 24
    # issue 12, clothed scans in poses up to 45 degrees: the initialisation can leave limbs 15-50
    # degrees off under loose clothes (and the rest body short), and the clothing-aware
    # refinement cannot pull them out -- body points deep inside the clothes hardly count, so a
    # wrong limb hides in a trouser leg. Clothed scans first get this many refinement iterations
    # with symmetric weights (the clothes' outer surface fitted as if it were skin: the posture
    # of the clothed silhouette is the body's), then the clothing-aware ones shrink the body
    # into the clothes. Resetting the shape after this stage instead was worse (7 -> 20 mm on
    # a work suit). 0: off
    refine_bare_iterations: int = 12
    # issue 12: with the clothing weights a limb inside the clothes has almost no data left (a
    # body point 5 cm inside counts 0.6 %, a scan point 5 cm outside the body as little) and the
    # priors alone move it: the clothing-aware refinement turned held-out avatar 1's forearm
    # (scanner, 45 degrees) 10 cm away from its sleeve (6.3 -> 18.6 mm). The clothed refinement
    # pulls each bone's local rotation towards the posture the bare stage found on the clothes'
    # outer surface (``_anchor_terms``, weight per squared radian against the data terms' sums
    # over the subsample, like ``bone_smoothness``): 6.9 mm (Alg. 1 not anchored; weight 0.3:
    # 15.0 mm, 3.0: 6.6 mm). Since the clothes' stand-offs (``cloth_offset_mean``) the body
    # under the clothes has its data back, and at 1.0 the anchor held the bare stage's posture
    # where it was wrong: a knee bent too little inside wide trousers, the legs short to match
    # (held-out avatar 2 in a work suit, 45 degrees: stature -1.75 cm). Fitting bench, 12
    # avatars at 45 degrees, the 5 clothed conditions, with the stand-offs, 1.0 -> 0.1 -> 0
    # (``--fit-params``, 2026-11-25): body error median 1.52-2.46 -> 1.34-2.01 -> 1.27-1.88 mm,
    # stature worst 0.94-2.04 -> 0.69-1.00 -> 0.47-1.05 cm. 0.1 keeps every stature worst
    # within 1 cm at 45 degrees and some of the anchor's hold; 0.3 was between the two at 45
    # degrees and a little better at 20 (stature worst 0.51-1.02 against 0.45-1.17 cm); at 20
    # degrees held-out avatar 3's spine under a casual suit goes 29-32 mm off (scanner 5.16 ->
    # 7.29 mm; 0.3: 5.15 mm). 0: off
    clothed_posture_anchor: float = 0.1
    # ... and Alg. 1's Eq. 3 of a clothed scan towards the posture it starts from: with the
    # refinement anchored, Alg. 1 alone turned held-out avatar 39's hand (scanner, 20 degrees,
    # part of the hand in a hole) 4 cm off (4.7 -> 11.6 mm); anchored, 4.9 mm (weight 10: 5.0 mm;
    # avatar 1: 7.3 mm either way). 0: off
    alg1_posture_anchor: float = 1.0
    # Levenberg damping of the refinement (relative to the mean diagonal, as ``levenberg``).
    # Issue 12: shape and posture trade along a shallow valley (a longer bone bent more
    # explains the scan almost as well); with the coarse stage's 1e-3 every step along it is
    # damped to a crawl and the fit stops with the rest-pose stature 2-4 cm off while the
    # posed body matches to 2 mm. 1e-6 follows the valley to the scan's minimum in ~10 steps
    refine_levenberg: float = 1e-6
    run_alg1: bool = True
    # issue 12: on bare scans Eqs. 3 and 4 fit the model to the template vertices matched to the
    # scan only. A hand over a hole in a raw scanner scan (no scan point within reach) spun
    # away in Alg. 1, 131 mm mean error on the hand after 10 outer iterations (held-out avatar
    # 40, 45 degrees), refined to 4 mm before it
    alg1_matched_only: bool = True
    person_check: bool = True  # service.model.fitting.person_check before and after the fit
    scan_cleanup: bool = True  # issue 12: floor and stray clusters dropped, no pull into holes (scan_cleanup)
    # no pull into holes in the refinement either (with ``scan_cleanup``), as in Alg. 1: a
    # template vertex whose nearest scan point is on a hole's rim (``scan_cleanup.over_hole``)
    # is not paired. Alone it moved avatar 41 above only from +3.8 to +3.4 cm
    refine_hole_reject: bool = True
    # ... and in Alg. 1 too, with ``scan_cleanup``: a template vertex
    # whose nearest scan point lies on a hole's rim, found on the scan itself
    # (``scan_cleanup.rim_points``: its neighbours on one side only), is not paired. ``over_hole``
    # tests the offset's direction and misses a rim the template juts out over: with the face in a
    # hole (held-out avatar 40, bare, 8 holes, 10 degrees) the nose and chin paired with the
    # neck below and the cheeks beside, 1,629 of the true body's head vertices more than 6 mm
    # from their pair's plane, and the fit nodded the head 45 degrees (6.2 mm body error). Not in
    # the initialisation, whose template starts far from the scan: there it cost held-out avatar
    # 40's arms (bare scanner output, 45 degrees: both raised, refused as outside the population).
    # Bare scans only: a clothed scan's hems and cuffs are rims too, and a clothed point cloud's
    # uneven sampling makes false ones (same run, 12 held-out avatars at 45 degrees, clothed
    # cloud 1.46 -> 1.67 mm median, one scan 1.32 -> 2.17; clothed mesh 3 worse, none better)
    rim_reject: bool = True
    # issue 12, a processed scan whose open head top a scanner's software closed with a flat cap
    # of new points (``scan_cleanup.flat_cap``, with ``scan_cleanup``): found after the
    # initialisation (the up axis known) and dropped, so the head's top is the model's, as under
    # a cut. A cap 4 cm below the crown pulled the head down to it (see README, **A flat cap**)
    flat_cap: bool = True
    # issue 12, hair on a bare scan (a scanner's customer in minimal clothing): the pairs of the
    # head but the face, and of the neck (``scalp_region``), weighted as a clothed scan's (the body
    # may lie inside the scan there), the rest as skin; in the refinement and Alg. 1, not the
    # initialisation. Clothed scans already weight every pair so. Without it the head and neck
    # grew into the hair: same run, 12 held-out people with MakeHuman's bob or short hair, 20
    # degrees, fitted bare: 1.43 -> 0.84 mm median, stature worst 1.22 -> 0.59 cm; bare scans
    # without hair +0.01-0.03 mm. It used to be off when the face was in a hole (nothing firm
    # would hold the head: held-out avatar 40, bald, 10 degrees, 4.1 mm with the head nodded);
    # since the rims' rejection (``rim_reject``) and the unseen parts' prior (``unseen_prior``)
    # that scan is 0.71 mm with it on, and off it turned held-out avatar 1's head 51 degrees
    # inside his short hair (scanner output, 20 degrees: 4.07 mm; on: 0.97 mm)
    hair_region: bool = True
    # ... and long hair down the back: the upper back (``hair_back_region``) weighted so too.
    # Without it the upper back grew into the hair (bench condition long_hair, 12 held-out people,
    # 20 degrees: 0.84 -> 0.56 mm median, every scan better or the same; 45: 0.96 -> 0.74 mm);
    # bare scans without long hair +0.00-0.02 mm
    hair_back: bool = True
    # issue 12, a bare scan whose head is poorly seen (its seen share after the initialisation,
    # ``seen_shares``, below this: the face in a hole, the top cut or under hair): the face's
    # pairs (the head's and neck's vertices outside ``scalp_region``) move the pose but not the
    # shape (the refinement's shape columns, Eq. 4 of Alg. 1). With the face in a hole its few
    # pairs are the hole's edges, and the scalp around it lets the body lie inside the scan (hair),
    # so a head grown up into the cut top fitted as well as the true one: the face's pairs grew the
    # neck. Held-out avatar 40, bare, the face in a hole, the head cut, a raw scanner's misregistered
    # views and flying pixels (bench ``scanner_raw``), 20 degrees: +2.74 cm, 3.18 mm -> +0.16 cm,
    # 1.09 mm; avatar 41 with long hair down the back (``long_hair``), 20 degrees: +4.77 cm, 5.19
    # mm -> +0.05 cm, 0.57 mm (in process; read from a PLY file +9.8 -> +7.5 cm: this head's fit
    # turns on small differences, see README, **A poorly seen face**; +1.96 cm with the second
    # hypothesis below).
    # The whole head and neck left out of the shape instead took a capped head's shape from the
    # body (avatar 41, ``scanner_capped``: -0.07 -> +2.41 cm). None: off
    face_shape_min_seen: float | None = 0.65
    # issue 12, ... and a second hypothesis for such a head: on a bare scan whose head's seen
    # share after the initialisation is below this, the refinement and Alg. 1 run twice from
    # the initialisation, once as above and once with the whole head and neck moving the pose
    # but not the shape (the head's height and size then follow the body, through the shape
    # prior), and the fit whose body leaves less of the scan unexplained is kept (the mean
    # distance of the scan's points to the body's surface, ``scan_to_surface_mm``). A head
    # grown up into a cut top leaves the jaw's points beside the neck; the one-sided pairs of
    # a possibly haired scalp and neck do not see them, the scan's distance to the body does.
    # Read from PLY files (bench ``--via-file ply``, 20 degrees): avatar 41 with long hair +7.45
    # -> +1.96 cm, avatar 40 with long hair +3.85 -> +0.36 cm, her capped head +1.91 -> -0.05
    # cm; the bench's own arrays: 190 of 192 bare fits identical at 20 and 45 degrees, two
    # worse by 0.06-0.07 mm (README, **A poorly seen head fitted twice**). None: off
    head_hypothesis_seen: float | None = 0.75
    # issue 12, the unseen side left to the prior: on a bare scan, a bone fewer than
    # UNSEEN_SHARE of whose template vertices have a scan point near them after the
    # initialisation (``seen_shares``: a hand or the neck in a hole) is pulled towards its rest
    # posture (the A-pose a scanner's customer stands in), this weight per squared radian as
    # ``bone_smoothness``, in the refinement and Alg. 1 (Eq. 3). Without it such a bone follows
    # whatever stray pairs it has: held-out avatar 39's left hand in a hole (17 % seen) turned
    # over, 83 mm mean error on the hand (scanner output with hair, 20 degrees: 7.41 -> 2.12 mm);
    # her neck in a hole (18 %), the head nodded and grew 3.2 cm into her bob (off the model's
    # space: 4.46 -> 2.53 mm, stature +3.24 -> +0.43 cm). A hand whose remaining pairs were right
    # pays for it: held-out avatar 41's, turned 45 degrees (scanner output, minimal clothing),
    # 1.35 -> 1.83 mm. 0.1: 2.42 / 2.58 / 2.40 mm; 0.01 lets the neck nod again (3.80 mm,
    # +2.76 cm). 0: off
    unseen_prior: float = 0.03
    # ... and on a clothed scan, for these bones only: clothes stand off the body, so elsewhere
    # a low seen share is the clothes, not a hole, but nothing covers the hands. A clothed
    # scan's hand in a hole (``seen_shares`` under UNSEEN_SHARE) is pulled to its rest posture
    # (``unseen_prior``) in place of the clothed anchors' pull (``clothed_posture_anchor``,
    # ``alg1_posture_anchor``) towards the posture the scan's surface gave it. Without it,
    # held-out avatar 2 in a work suit (bench ``scanner``, 20 degrees, read from a PLY file), his
    # left hand 8 % seen, turned it over: 51 mm mean error on the hand, 8.24 mm on the body
    # (3.60 mm with it; the bench's other clothed scans within 0.13 mm, most identical). A hand
    # missing altogether stays a guess either way (README, **A clothed scan's hand in a hole**).
    # Empty: off
    clothed_unseen_bones: tuple = ("hand_l", "hand_r")
    # bones the scan does not show at all (a scan without its head): their template vertices
    # take no pair either way in the initialisation, the refinement and Alg. 1, nor count in the
    # initialisation's costs, and their posture is pulled to rest (``unseen_prior``, or a
    # clothed fit's posture anchor); the body there is the model's, extrapolated (Eq. 2)
    absent_bones: tuple = ()
    # issue 12, a scan without its head (a field of view ending at the neck; dark hair and a
    # face in a hole): the template's head, ~a quarter of its vertices, was paired with the neck
    # and shoulders, bent and shrank into them. Bench condition ``headless`` (bare scanner
    # output without the head), 12 held-out people at 20 degrees: 9 of 12 came back 12-23 cm
    # short (15-47 mm off), "ready"; in a random MakeHuman suit (``headless_clothed``) -1.5 to
    # -18 cm. With this on, the initialisation's coarse stage is run again from its result with
    # the head absent (``absent_bones``; the head and neck at rest, the mean shape; ~0.2 s), and
    # that is kept when its head then has almost no scan near it (``seen_shares`` under
    # UNSEEN_SHARE) and almost no scan point has the head as its nearest part above the skull
    # base (HEADLESS_HEAD_SHARE): the scan has no head, which is left to the prior and said in
    # ``unseen``. False: off
    headless_check: bool = True
    # issue 12, measurements the customer gives with the scan (``fit_body(known=...)``: the
    # surface of a man in a loose suit is that of a heavier man in a tighter one): soft targets
    # on the rest body in Eq. 4, each residual in units of KNOWN_SIGMA, weighted against the data
    # term (sum over the template's vertices of squared metres)
    known_weight: float = 1.0
    # issue 12, real hands: a scanned person's fingers are relaxed (curled towards the palm) or
    # spread, and the model has no finger bones, while the hands hold 24 % of the template's
    # vertices. A finger's pair (``finger_region``) weighs 1 / (1 + (r / finger_scale)^2) as much
    # as another (Cauchy, redescending; r its residual, metres: the point-to-plane one in the
    # refinement, in Eqs. 3 and 4 of Alg. 1 the model's distance to Eq. 2's template, which
    # carries the template's fingers to the scan's): fingers the model can match keep nearly
    # their weight, bent ones hardly count. Bench condition relaxed_hands (bare scanner output,
    # fingers curled 70 degrees), 12 held-out people at 45 degrees: body error without the hands
    # 1.12 -> 0.76 mm median, arm length mean |error| 0.91 -> 0.21 cm; in a suit 2.78 -> 2.40 mm.
    # None: as any other vertex
    finger_scale: float | None = 0.005
    # ... in the refinement from this share of its iterations on (the hands first aligned by
    # every vertex): from its start, held-out avatar 5's hand drifted (bare scanner output with
    # flat hands, 45 degrees: refused as a wrong fit, 9.4 mm), and clothed fits with flat hands
    # lost 0.2-0.4 mm, the wrists turned; in Alg. 1 alone, 1.12 -> 0.97 mm. None: Alg. 1 only
    finger_refine_from: float | None = 0.5
    # the pose prior: weight of the joint-limit penalty (JOINT_LIMITS_DEG) in the coarse ICP and
    # in Eq. 3, per squared radian outside a limit (0: no limits)
    joint_limit_weight: float = 10.0
    # shape and posture decoupled: weight of ||A beta||^2, the shape's change of the rest bone
    # directions (``_posture_matrix``; squared metres, against the data terms' sums of squared
    # metres over template vertices); 0: off
    posture_weight: float = 0.0
    damping: float = 1e-6
    # BLAS threads while fitting (None: the library's default, one per core). The fit's dense
    # products are small to medium (the refinement's normal equations: ~16,000 x 130); OpenBLAS
    # threads on 2 cores shared with other processes spin and wait: one clothed scan took 72-76 s
    # with the default and 15.7-15.8 s with 1 thread on the loaded machine (same result)
    blas_threads: int | None = 1
    # the pose Jacobian and the point-to-plane rows by the compiled kernels (``kernels``
    # ``pose_jacobian_into``, ``pair_rows``) where numba is there; False: the numpy reference
    # (the same numbers to ~1e-15 relative; the bench's ``--before numpy_kernels``)
    compiled: bool = True


DEFAULT_PARAMS = FitParams()
MAX_HEIGHT_M, MIN_HEIGHT_M = 2.6, 0.9  # a standing, sitting or crouching adult


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


# -- the model as data for fitting ------------------------------------------------------------
@dataclass
class _Rig:
    """Body-surface data of the model in float64: mean (n, 3), U (K, n, 3), joint mean (17, 3)
    and joint directions (K, 17, 3), dense LBS weights W (n, 17), faces, edges, subtree
    indicator S (17, 17) with S[b, j] = 1 when j is in b's subtree, prior precisions (K,)."""

    mean: np.ndarray
    U: np.ndarray
    jmean: np.ndarray
    jdirs: np.ndarray
    W: np.ndarray
    faces: np.ndarray
    edges: np.ndarray
    incidence: sp.csr_matrix
    laplacian: sp.csc_matrix
    parents: np.ndarray
    subtree: np.ndarray
    precision: np.ndarray
    posture: np.ndarray  # (3 * 16, K): the shape's change of each bone's direction (see _posture_matrix)
    area: np.ndarray  # (n,) the mean rest body's surface area per vertex (a third of each incident face's), m^2
    hops: np.ndarray  # (17, 17) int: bones between two bones in the skeleton (bone_hops)
    scalp: np.ndarray  # (n,) bool: where hair may stand off the skin (scalp_region)
    face: np.ndarray  # (n,) bool: the head's vertices but the scalp (FitParams.face_shape_min_seen)
    hair_back: np.ndarray  # (n,) bool: where long hair may cover the back (hair_back_region)
    fingers: np.ndarray  # (n,) bool: the fingers, beyond the knuckles (finger_region)
    stature_ids: tuple  # (top vertex, sole vertices (m,)): the stature's ends (measurements)
    subsets: dict = field(default_factory=dict)


@functools.lru_cache(maxsize=4)
def _rig(model) -> _Rig:
    n = model.n_body_vertices
    K = model.n_components
    full_mean = model.mean.astype(np.float64)
    comps = model.components.astype(np.float64)
    jreg = model.joint_regressor
    jmean = np.asarray(jreg @ full_mean)
    jdirs = np.stack([np.asarray(jreg @ comps[k]) for k in range(K)])
    W = np.zeros((n, len(model.bone_parents)))
    np.add.at(W, (np.repeat(np.arange(n), 4), model.lbs_indices[:n].ravel()),
              model.lbs_weights[:n].astype(np.float64).ravel())
    faces = np.asarray(model.body_faces, np.int64)
    edges, B = edge_incidence(faces, n)
    parents = np.asarray(model.bone_parents)
    J = len(parents)
    subtree = np.eye(J)
    for j in range(J - 1, 0, -1):  # children follow parents: accumulate bottom-up
        subtree[parents[j]] += subtree[j]
    return _Rig(mean=full_mean[:n], U=comps[:, :n], jmean=jmean, jdirs=jdirs, W=W, faces=faces,
                edges=edges, incidence=face_incidence(faces, n), laplacian=(B.T @ B).tocsc(),
                parents=parents, subtree=(subtree > 0).astype(np.float64),
                precision=1.0 / np.maximum(model.variances.astype(np.float64), 1e-12),
                posture=_posture_matrix(jmean, jdirs, parents), area=vertex_areas(full_mean[:n], faces),
                hops=bone_hops(parents), scalp=scalp_region(full_mean[:n], faces, W),
                face=face_region(full_mean[:n], faces, W),
                hair_back=hair_back_region(full_mean[:n], faces, W, jmean),
                fingers=finger_region(full_mean[:n], W, jmean),
                stature_ids=(int(model.measurement_spec.top), np.asarray(model.measurement_spec.soles, np.int64)))


# where hair may stand off the skin on the rest template (metres, Y up, facing +Z): the vertices
# of HAIR_BONES but the face (facing forward, normal z > SCALP_FACE_NORMAL_Z, below the hairline
# SCALP_HAIRLINE_M under the head's top). A bob hangs to the jaw and over the nape (MakeHuman's
# bob02 on the mean body: 67 % of the neck within 3 cm of it), long hair further. Held-out avatar
# 38 with the bob, 20 degrees, fitted bare: the head's top 15 cm only +0.87 cm of stature, 1.84 mm;
# the head and neck +0.65 cm, 1.53 mm (neck 3.5 -> 0.0 mm outward on average). The face is its
# front only (normal z > 0.8): with 0.3, locks beside the cheeks widened the face (+2.9 mm outward
# on average, avatar 38 at 10 degrees); same seeds, 12 bare people with hair, 10 degrees:
# 0.89 -> 0.79 mm median, stature worst 0.74 -> 0.58 cm; bald scans unchanged (+-0.02 mm)
HAIR_BONES = ("head", "neck")
SCALP_HAIRLINE_M = 0.06
SCALP_FACE_NORMAL_Z = 0.8


def scalp_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) bool: where a scan of a bare person may show hair, not skin, on a rest body
    (vertices (n, 3), faces (F, 3), dense skinning weights W (n, 17)): the head but the face,
    and the neck."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    head = bone == BONES.index("head")
    if not head.any():
        return head
    y = vertices[:, 1]
    top = float(y[head].max())
    nz = vertex_normals(vertices, faces)[:, 2]
    face = head & (nz > SCALP_FACE_NORMAL_Z) & (y < top - SCALP_HAIRLINE_M)
    return np.isin(bone, [BONES.index(b) for b in HAIR_BONES]) & ~face


def face_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n,) bool: the face on a rest body (vertices (n, 3), faces (F, 3), dense skinning weights
    W (n, 17)): the vertices of HAIR_BONES outside ``scalp_region``."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    return np.isin(bone, [BONES.index(b) for b in HAIR_BONES]) & ~scalp_region(vertices, faces, W)


# where long hair may hang on the rest template: the back (normal z < HAIR_BACK_NORMAL_Z) of the
# spine and chest bones, between the shoulder joints, down to HAIR_BACK_BELOW_M under the skull base
# (the head joint; about the middle of the back)
HAIR_BACK_BELOW_M = 0.35
HAIR_BACK_NORMAL_Z = -0.3
HAIR_BACK_BONES = ("spine", "chest")


def hair_back_region(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(n,) bool: where long hair may cover the back of a bare person on a rest body (vertices
    (n, 3), faces (F, 3), dense skinning weights W (n, 17), joints (17, 3))."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    nz = vertex_normals(vertices, faces)[:, 2]
    head = joints[BONES.index("head")]
    half = 0.5 * abs(joints[BONES.index("upper_arm_l"), 0] - joints[BONES.index("upper_arm_r"), 0])
    return (np.isin(bone, [BONES.index(b) for b in HAIR_BACK_BONES]) & (nz < HAIR_BACK_NORMAL_Z)
            & (vertices[:, 1] > head[1] - HAIR_BACK_BELOW_M) & (np.abs(vertices[:, 0] - head[0]) < half))


# the fingers on the rest template: the vertices a hand bone moves most that lie further from its
# joint (the wrist), along the hand (towards its farthest vertices), than FINGER_KNUCKLE_SHARE of
# the hand's length (the knuckles)
FINGER_KNUCKLE_SHARE = 0.45


def finger_region(vertices: np.ndarray, W: np.ndarray, joints: np.ndarray) -> np.ndarray:
    """(n,) bool: the fingers of a rest body (vertices (n, 3), dense skinning weights W (n, 17),
    joints (17, 3)), which the 17 bones cannot bend (``FitParams.finger_scale``)."""
    from service.model.body.model import BONES

    bone = np.argmax(W, axis=1)
    out = np.zeros(len(vertices), bool)
    for name in ("hand_l", "hand_r"):
        b = BONES.index(name)
        at = np.flatnonzero(bone == b)
        if not len(at):
            continue
        P = vertices[at] - joints[b]
        reach = np.linalg.norm(P, axis=1)
        axis = P[reach >= np.percentile(reach, 95)].mean(0)  # towards the fingertips
        axis /= np.linalg.norm(axis)
        along = P @ axis
        out[at] = along > FINGER_KNUCKLE_SHARE * along.max()
    return out


def finger_weights(residuals: np.ndarray, fingers: np.ndarray, scale: float) -> np.ndarray:
    """(n,) multipliers of n pairs' weights: 1 / (1 + (r / scale)^2) where ``fingers`` (n,) bool
    (residuals r (n,) metres), else 1 (``FitParams.finger_scale``)."""
    return np.where(fingers, 1.0 / (1.0 + (np.asarray(residuals, np.float64) / scale) ** 2), 1.0)


def _hair(rig: _Rig, params: FitParams) -> np.ndarray:
    """(n,) bool: the template vertices a bare scan may show hair over (``FitParams.hair_region``,
    ``hair_back``)."""
    return rig.scalp | rig.hair_back if params.hair_back else rig.scalp


# a template vertex counts as seen (``seen_shares``) when a scan point within SEEN_M (or
# SEEN_SPACINGS of the scan's point spacings, on a sparse scan) of it, posed as initialised, is
# not on a hole's rim; a bone with fewer than UNSEEN_SHARE of its vertices seen gets
# ``FitParams.unseen_prior``. Bare scans of 12 held-out people with holes, 20 degrees: a hand or
# neck in a hole 8-26 %, seen ones 41-100 % (the neck under a bob: 43-100 %)
SEEN_M = 0.02
SEEN_SPACINGS = 2.0
UNSEEN_SHARE = 0.3
# ... but not the root (the scan's frame, not a posture) nor the feet: a scanner's floor takes
# their soles (``scan_cleanup``), 9-21 % seen on good fits, and their tops still hold them; the
# rest pulled one 45-degree foot 10 -> 17 degrees off
UNSEEN_FREE_BONES = ("pelvis", "foot_l", "foot_r")
# a scan without its head (``FitParams.headless_check``): the headless coarse fit is kept when no
# more than HEADLESS_HEAD_SHARE of the scan has its head as the nearest body part (within
# HEADLESS_NEAR_M) more than HEADLESS_ABOVE_M above its skull base (the head joint, along the
# neck). Measured with the second fit forced, 12 held-out people each: 0-0.05 % on scans without
# a head (bare and clothed, 20 and 45 degrees; a suit's collar is the neck's), 0.8 % for one with
# a hat left floating; scans whose head is only a face (dark hair) 0-0.8 %. Whole heads: never
# kept on 120 bench scans (bare, cut head top, hair, two suits; 20 and 45 degrees)
HEADLESS_NEAR_M = 0.10
HEADLESS_ABOVE_M = 0.03
HEADLESS_HEAD_SHARE = 0.002


def seen_vertices(rig: "_Rig", s: "_State", P: np.ndarray, rims: tuple | None) -> np.ndarray:
    """(n,) bool: the template vertices, posed by the state ``s``, with a scan point of P (P, 3;
    model frame) near them (SEEN_M, SEEN_SPACINGS) that is not on a hole's rim (``rims``: (rim
    distance (P,), point spacing) or None)."""
    V = _pose_model(rig, s, _subset(rig, np.arange(len(rig.mean)))).v
    tree = cKDTree(P)
    radius = max(SEEN_M, SEEN_SPACINGS * SC.point_spacing(tree, P))
    d, j = tree.query(V, distance_upper_bound=radius)
    seen = np.isfinite(d)
    if rims is not None:
        seen &= ~(rims[0][np.minimum(j, len(P) - 1)] <= RIM_SPACINGS * rims[1])
    return seen


def seen_shares(rig: "_Rig", s: "_State", P: np.ndarray, rims: tuple | None,
                seen: np.ndarray | None = None) -> np.ndarray:
    """(17,) per bone (BONES order): the share of the template vertices it moves most that are
    seen (``seen_vertices``, or ``seen`` (n,) bool when given)."""
    bone = np.argmax(rig.W, axis=1)
    seen = seen_vertices(rig, s, P, rims) if seen is None else seen
    count = np.bincount(bone, minlength=len(rig.parents))
    return np.bincount(bone, weights=seen, minlength=len(rig.parents)) / np.maximum(count, 1) + (count == 0)


def bone_hops(parents: np.ndarray) -> np.ndarray:
    """(J, J) int: the number of joints between bones a and b in the skeleton tree (0 on the
    diagonal, 1 for a bone and its parent); parents (J,) int, -1 at the root."""
    J = len(parents)
    hops = np.full((J, J), J, np.int64)
    np.fill_diagonal(hops, 0)
    for j, p in enumerate(parents):
        if p >= 0:
            hops[j, p] = hops[p, j] = 1
    for k in range(J):  # Floyd-Warshall on 17 nodes
        hops = np.minimum(hops, hops[:, k:k + 1] + hops[k:k + 1, :])
    return hops


def vertex_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(n,) a third of the area of each face incident to each vertex; vertices (n, 3), faces (F, 3)."""
    v = vertices[faces]
    a = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1)
    out = np.zeros(len(vertices))
    np.add.at(out, faces.ravel(), np.repeat(a / 3.0, 3))
    return out


def _posture_matrix(jmean: np.ndarray, jdirs: np.ndarray, parents: np.ndarray) -> np.ndarray:
    """(3 (J - 1), K): A beta stacks, for every bone j with a parent p, the part of the rest bone
    vector's change (joint j - joint p, linear in beta: jdirs) perpendicular to the mean bone
    direction. Shape weights with A beta = 0 change bone lengths, not posture: ||A beta||^2 is
    the penalty that keeps posture in the bone rotations (shape and posture decoupled)."""
    rows = []
    for j, p in enumerate(parents):
        if p < 0:
            continue
        u = jmean[j] - jmean[p]
        u = u / max(np.linalg.norm(u), 1e-12)
        rows.append((np.eye(3) - np.outer(u, u)) @ (jdirs[:, j] - jdirs[:, p]).T)
    return np.concatenate(rows)


# -- state and its Jacobians -------------------------------------------------------------------
@dataclass
class _State:
    beta: np.ndarray  # (K,)
    rot: np.ndarray  # (17, 3, 3) local rotations
    trans: np.ndarray  # (3,)

    def copy(self) -> "_State":
        return _State(self.beta.copy(), self.rot.copy(), self.trans.copy())


@dataclass
class _Sub:
    """A subset of the template's vertices with its data laid out for the updates: idx (m,),
    mean (m, 3), Ut (m, 3, K) shape directions, W (m, 17) LBS weights."""

    idx: np.ndarray
    mean: np.ndarray
    Ut: np.ndarray
    W: np.ndarray
    area: np.ndarray  # (m,) surface area per vertex over its mean (1 on average)
    region: np.ndarray  # (m,) int: the body region, the vertex's dominant bone


def _subset(rig: _Rig, idx: np.ndarray) -> _Sub:
    idx = np.asarray(idx)
    key = idx.tobytes()
    if key in rig.subsets:
        return rig.subsets[key]
    W = rig.W[idx]
    area = rig.area[idx]
    sub = _Sub(idx=idx, mean=rig.mean[idx], Ut=np.ascontiguousarray(rig.U[:, idx].transpose(1, 2, 0)),
               W=W, area=area / max(float(area.mean()), 1e-12), region=np.argmax(W, axis=1))
    if len(rig.subsets) < 8:  # the fit's fixed subsets, kept with the model
        rig.subsets[key] = sub
    return sub


@dataclass
class _Posed:
    v: np.ndarray  # (m, 3) posed vertices
    rest: np.ndarray  # (m, 3) rest vertices
    joints: np.ndarray  # (17, 3) rest joints
    G: np.ndarray  # (17, 4, 4) global transforms
    M: np.ndarray  # (m, 3, 3) blended rotations sum_j w_ij R_j
    sub: _Sub


def _flat(G: np.ndarray) -> np.ndarray:
    """(J, 4, 4) transforms -> (J, 12) rows [R.ravel(), t]."""
    return np.concatenate([G[:, :3, :3].reshape(len(G), 9), G[:, :3, 3]], axis=1)


def _pose_model(rig: _Rig, s: _State, sub: _Sub) -> _Posed:
    """M(beta, theta) on the template vertices of ``sub`` (the editing paper's Eq. 1, LBS form)."""
    rest = sub.mean + sub.Ut @ s.beta
    joints = rig.jmean + np.tensordot(s.beta, rig.jdirs, axes=1)
    G = global_transforms(joints, rig.parents, s.rot, s.trans)
    A = sub.W @ _flat(G)  # blended transforms (m, 12)
    M = A[:, :9].reshape(-1, 3, 3)
    v = (M @ rest[:, :, None])[:, :, 0] + A[:, 9:]
    return _Posed(v=v, rest=rest, joints=joints, G=G, M=M, sub=sub)


def _pose_jacobian(rig: _Rig, p: _Posed, bones: np.ndarray, comps: np.ndarray | None = None,
                   compiled: bool = True) -> np.ndarray:
    """(m, 3, 3 + 3 len(bones)): d v_i / d(translation, dw_b for b in bones), where dw_b rotates
    bone b's subtree in the world frame about its posed joint q_b, moving v_i by
    dw_b x (S_b(i) - W_b(i) q_b) with S_b(i) = sum_{j in subtree(b)} w_ij G_j(x_i).
    With ``comps``: (m, 3, 3 + 3 len(bones) + len(comps)), the shape Jacobian
    (``_shape_jacobian``) in the last columns, written in place (no concatenated copy).
    ``compiled`` (and numba there): the pose columns by ``kernels.pose_jacobian_into`` (each
    vertex visits only its non-zero weights), else the numpy reference below."""
    m = len(p.v)
    nb = len(bones)
    npz = 3 + 3 * nb
    q = np.einsum("jab,jb->ja", p.G[:, :3, :3], p.joints) + p.G[:, :3, 3]  # posed joints (17, 3)
    J = np.empty((m, 3, npz + (0 if comps is None else len(comps))))
    if compiled and kernels.AVAILABLE:
        kernels.pose_jacobian_into(np.ascontiguousarray(p.rest), np.ascontiguousarray(p.G),
                                   np.ascontiguousarray(p.sub.W), rig.subtree[bones], q[bones], J)
    else:
        per_bone = p.rest @ p.G[:, :3, :3].transpose(0, 2, 1) + p.G[:, None, :3, 3]  # (17, m, 3)
        contrib = p.sub.W.T[:, :, None] * per_bone  # w_ij G_j(x_i)
        sub = rig.subtree[bones]  # (nb, 17)
        S = np.tensordot(sub, contrib, axes=1)  # (nb, m, 3)
        arm = (S - (sub @ p.sub.W.T)[:, :, None] * q[bones][:, None, :]).transpose(1, 2, 0)  # (m, 3, nb)
        J[:, :, :3] = np.eye(3)
        J4 = J[:, :, 3:npz].reshape(m, 3, nb, 3)  # a view: (vertex, coordinate, bone, rotation axis)
        # -[arm]x, the cross-product matrix of dw x arm
        J4[:, 0, :, 0], J4[:, 0, :, 1], J4[:, 0, :, 2] = 0.0, arm[:, 2], -arm[:, 1]
        J4[:, 1, :, 0], J4[:, 1, :, 1], J4[:, 1, :, 2] = -arm[:, 2], 0.0, arm[:, 0]
        J4[:, 2, :, 0], J4[:, 2, :, 1], J4[:, 2, :, 2] = arm[:, 1], -arm[:, 0], 0.0
    if comps is not None:
        _shape_jacobian(rig, p, comps, out=J[:, :, npz:])
    return J


def _shape_jacobian(rig: _Rig, p: _Posed, comps: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """(m, 3, len(comps)): d v_i / d beta_k with the rotations fixed. The rest vertex moves by
    U_k and every joint by its regressed direction, which moves each bone's translation
    t_j = R_parent p_j - R_j p_j + t_parent (forward kinematics, linear in the joints).
    ``out``: an (m, 3, len(comps)) array (a view) to write it into."""
    Rg = p.G[:, :3, :3]
    k = len(comps)  # the fits' components are a prefix: a view, not a copy (76 of them: 10 ms)
    Ut = p.sub.Ut[:, :, :k] if np.array_equal(comps, np.arange(k)) else p.sub.Ut[:, :, comps]
    dp = rig.jdirs[comps]  # (C, 17, 3)
    dt = np.zeros_like(dp)
    for j, par in enumerate(rig.parents):
        own = dp[:, j] - dp[:, j] @ Rg[j].T
        dt[:, j] = own if par < 0 else dp[:, j] @ Rg[par].T - dp[:, j] @ Rg[j].T + dt[:, par]
    out = np.matmul(p.M, Ut, out=out)  # (m, 3, C)
    out += (p.sub.W @ dt.transpose(1, 0, 2).reshape(17, -1)).reshape(-1, k, 3).transpose(0, 2, 1)
    return out


def _apply_pose(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, delta: np.ndarray) -> None:
    """Apply world-frame subtree rotations dw_b about the posed joints (first order: each local
    rotation becomes R_pg^T exp(dw_b) R_pg R_local, R_pg the parent's global rotation)."""
    s.trans = s.trans + delta[:3]
    E = axis_angle_to_matrix(delta[3:].reshape(-1, 3))
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0:
            s.rot[b] = E[c] @ s.rot[b]
        else:
            Rp = p.G[par, :3, :3]
            s.rot[b] = Rp.T @ E[c] @ Rp @ s.rot[b]


def _smoothness(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, omega: float):
    """Eq. 3's neighbouring-bone term omega sum ||theta_b - theta_parent(b)||^2 as the squared
    relative rotation r_b = rotvec(R_local_b); d r_b / d w_b = R_pg^T. Returns (H, g) over
    the pose parameters (3 + 3 len(bones))."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    a = matrix_to_axis_angle(s.rot)
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0:
            continue
        Rp = p.G[par, :3, :3]
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += omega * np.eye(3)
        g[sl] += omega * Rp @ a[b]
    return H, g


def _anchor_terms(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, rot: np.ndarray,
                  weight: float | np.ndarray):
    """A pull of each bone's local rotation towards a posture ``rot`` (17, 3, 3), the root's
    too: 1/2 sum_b weight_b ||r_b||^2 with r_b = rotvec(rot_b^T R_local_b), as Gauss-Newton
    terms with d r_b / d w_b = rot_b^T R_pg^T to first order (as ``_smoothness``; the root:
    R_pg = I); ``weight`` one for all bones or (17,) per bone. Returns (H, g) over the pose
    parameters (3 + 3 len(bones))."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    if np.all(np.asarray(weight) <= 0):
        return H, g
    r = matrix_to_axis_angle(np.einsum("bji,bjk->bik", rot, s.rot))  # rot_b^T R_b
    wb = np.broadcast_to(np.asarray(weight, np.float64), (len(rig.parents),))
    for c, b in enumerate(bones):
        if wb[b] <= 0:
            continue
        par = rig.parents[b]
        Rp = np.eye(3) if par < 0 else p.G[par, :3, :3]
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += wb[b] * np.eye(3)
        g[sl] += wb[b] * Rp @ rot[b] @ r[b]
    return H, g


# -- joint limits (issue 12): anatomical ranges per bone, hand-set ------------------------------
# Box limits (degrees) on each bone's local rotation vector (x, y, z), relative to the rest
# pose (A-pose, elbows a little bent, facing +Z, Y up, x to the body's left): for the legs x
# is flexion (thigh: negative = the leg forward; shin: positive = the knee bends), y the twist
# about the bone, z the sideways swing. The pelvis (the whole body's orientation) is free.
# Generous on purpose: they keep a fit out of impossible postures (a knee bent sideways, a
# forearm through the hip), not out of unusual ones.
JOINT_LIMITS_DEG: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "spine": ((-40, -30, -30), (40, 30, 30)),
    "chest": ((-35, -30, -30), (35, 30, 30)),
    "neck": ((-45, -60, -40), (45, 60, 40)),
    "head": ((-45, -60, -40), (45, 60, 40)),
    "upper_arm_l": ((-120, -120, -75), (120, 120, 120)),
    "upper_arm_r": ((-120, -120, -120), (120, 120, 75)),
    "forearm_l": ((-150, -150, -150), (150, 150, 150)),
    "forearm_r": ((-150, -150, -150), (150, 150, 150)),
    "hand_l": ((-80, -90, -60), (80, 90, 60)),
    "hand_r": ((-80, -90, -60), (80, 90, 60)),
    "thigh_l": ((-125, -50, -60), (40, 50, 60)),
    "thigh_r": ((-125, -50, -60), (40, 50, 60)),
    "shin_l": ((-20, -35, -20), (150, 35, 20)),
    "shin_r": ((-20, -35, -20), (150, 35, 20)),
    "foot_l": ((-50, -35, -35), (50, 35, 35)),
    "foot_r": ((-50, -35, -35), (50, 35, 35)),
}


@functools.lru_cache(maxsize=1)
def joint_limits() -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (17, 3) radians in BONES order from JOINT_LIMITS_DEG (-inf/inf: free)."""
    from service.model.body.model import BONES

    lo, hi = np.full((len(BONES), 3), -np.inf), np.full((len(BONES), 3), np.inf)
    for b, (l, h) in JOINT_LIMITS_DEG.items():
        lo[BONES.index(b)], hi[BONES.index(b)] = np.radians(l), np.radians(h)
    return lo, hi


def limit_violation(rotvecs: np.ndarray) -> np.ndarray:
    """(17, 3) radians by which each local rotation vector (17, 3) is outside its box (0 inside)."""
    lo, hi = joint_limits()
    return np.minimum(rotvecs - lo, 0.0) + np.maximum(rotvecs - hi, 0.0)


def _joint_limit_terms(rig: _Rig, s: _State, p: _Posed, bones: np.ndarray, weight: float):
    """The joint-limit penalty weight/2 sum_b ||v_b||^2 (v_b = ``limit_violation`` of the local
    rotation vector a_b) as Gauss-Newton terms (H, g) over the pose parameters (3 + 3 len(bones)),
    with d a_b / d w_b = J_l^-1(a_b) R_pg^T (the pose prior in Eq. 3)."""
    n = 3 + 3 * len(bones)
    H, g = np.zeros((n, n)), np.zeros(n)
    if weight <= 0:
        return H, g
    a = matrix_to_axis_angle(s.rot)
    v = limit_violation(a)
    for c, b in enumerate(bones):
        par = rig.parents[b]
        if par < 0 or not v[b].any():
            continue
        Jw = _left_jacobian_inv(a[b]) @ p.G[par, :3, :3].T  # d a_b / d w_b
        sl = slice(3 + 3 * c, 6 + 3 * c)
        H[sl, sl] += weight * Jw.T @ np.diag((v[b] != 0).astype(float)) @ Jw
        g[sl] += weight * Jw.T @ v[b]
    return H, g


def _left_jacobian_inv(phi: np.ndarray) -> np.ndarray:
    """(3, 3) d log(exp(d) R) / d d at d = 0 for R = exp(phi): the inverse left Jacobian of SO(3)."""
    t = float(np.linalg.norm(phi))
    K = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    if t < 1e-6:
        return np.eye(3) - 0.5 * K
    t = min(t, np.pi - 1e-3)
    return np.eye(3) - 0.5 * K + (1 / t ** 2 - (1 + np.cos(t)) / (2 * t * np.sin(t))) * K @ K


ALL_BONES = np.arange(17)
ROOT_ONLY = np.array([0])
# the coarse stage frees the skeleton from the root outwards (BONES order; see body.py)
BONE_LEVELS = (
    np.array([0]),  # pelvis
    np.array([0, 1, 11, 14]),  # + spine, thighs
    np.array([0, 1, 2, 11, 12, 14, 15]),  # + chest, shins
    np.array([0, 1, 2, 3, 5, 8, 11, 12, 13, 14, 15, 16]),  # + neck, upper arms, feet
    ALL_BONES,
)


# -- scan preparation and initialisation ------------------------------------------------------
def detect_scan_unit(points: np.ndarray) -> tuple[str, float]:
    """(unit, metres per unit) of a scan (``frames.detect_unit``); :class:`FitError` if none fits."""
    try:
        return detect_unit(points)
    except UnitError as exc:
        raise FitError(str(exc)) from exc


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


RIM_SPACINGS = 1.0  # a point this many point spacings from a hole's rim counts as on it (_make_scan)


@dataclass
class _Scan:
    points: np.ndarray  # (P, 3) model frame, metres
    normals: np.ndarray  # (P, 3)
    sub: np.ndarray  # indices of a subsample for the coarse stage
    sub_tree: cKDTree
    # (P,) bool: points at a hole's rim (within a point spacing of one); None: not checked
    rim: np.ndarray | None = None
    # (len(sub),) bool: subsample points within the subsample's spacing of a rim; None: not checked
    sub_rim: np.ndarray | None = None

    @functools.cached_property
    def tree(self) -> cKDTree:
        """All points (built only for the candidate that goes on to Alg. 1)."""
        return cKDTree(self.points)


def _make_scan(points: np.ndarray, normals: np.ndarray, R: np.ndarray, t: np.ndarray,
               n_sub: int, rng: np.random.Generator, rims: tuple[np.ndarray, float] | None = None) -> _Scan:
    """The scan (P, 3) moved by R, t, with a random subsample of ``n_sub`` points. With
    ``rims`` (rim distance (P,): metres from each point to the nearest rim point,
    ``scan_cleanup.rim_distance``; the scan's point spacing, metres), the points near a hole's
    rim are marked: the full scan's within ``RIM_SPACINGS`` spacings, the subsample's within as
    many of the subsample's spacings (the nearest subsample point to a spot inside a hole lies
    about that close to the rim)."""
    P = points @ R.T + t
    N = normals @ R.T
    sub = rng.choice(len(P), size=min(n_sub, len(P)), replace=False)
    sub_tree = cKDTree(P[sub])
    if rims is None:
        return _Scan(P, N, sub, sub_tree)
    rim_distance, spacing = rims
    sub_spacing = SC.point_spacing(sub_tree, P[sub])
    return _Scan(P, N, sub, sub_tree, rim=rim_distance <= RIM_SPACINGS * spacing,
                 sub_rim=rim_distance[sub] <= RIM_SPACINGS * sub_spacing)


def _posed_normals(rest_normals: np.ndarray, p: _Posed) -> np.ndarray:
    """Normals of posed vertices from rest normals rotated by the blended bone rotations."""
    n = (p.M @ rest_normals[:, :, None])[:, :, 0]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


def _clothing_weight(signed: np.ndarray, clothed: bool, params: FitParams,
                     contact: float | None = None, hair: np.ndarray | None = None) -> np.ndarray:
    """Weight (n,) of correspondences by the side of the scan the body is on: ``signed`` (n,)
    metres > 0 is a body point outside the scan (through the clothes: full weight), < 0 inside:
    ``inside_weight``, or with ``contact`` (metres) the asymmetric Cauchy weight
    1 / (1 + (depth / contact)^2) (see ``FitParams.clothing_contact``)."""
    if not clothed:  # a bare scan: as clothed on the scalp (``hair`` (n,) bool per pair), else 1
        if hair is None or not hair.any():
            return np.ones_like(signed)
        return np.where(hair, _clothing_weight(signed, True, params, contact), 1.0)
    if contact is None:
        return np.where(signed >= 0, 1.0, params.inside_weight)
    return np.where(signed >= 0, 1.0, 1.0 / (1.0 + (signed / contact) ** 2))


def loose_region_weight(signed: np.ndarray, region: np.ndarray, depth: float) -> np.ndarray:
    """(n,) multipliers of the clothing weights of n body-scan pairs (``FitParams.loose_region_depth``):
    ``signed`` (n,) metres, < 0 a body point inside the clothes; ``region`` (n,) int, the pair's
    body region. A pair inside in region R gets 1 / (1 + (m_R / depth)^2), with m_R the
    median over R's pairs of max(-signed, 0); pairs outside get 1."""
    inside = np.maximum(-np.asarray(signed, np.float64), 0.0)
    out = np.ones(len(inside))
    for b in np.unique(region):
        at = region == b
        out[at & (inside > 0)] = 1.0 / (1.0 + (float(np.median(inside[at])) / depth) ** 2)
    return out


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


OFFSET_ACTIVE_SET_ROUNDS = 40  # _offset_step's limit: each round fixes or frees at least one of 17


def _offset_step(H: np.ndarray, g: np.ndarray, offsets: np.ndarray, params: FitParams) -> np.ndarray:
    """The damped Gauss-Newton step (P,) of ``_coarse`` whose last len(offsets) unknowns are the
    clothes' stand-offs o >= 0 (``FitParams.cloth_offset_mean``): min 1/2 d^T H d + g^T d subject
    to o + d_o >= 0, by active sets: an offset the step would take below 0 is held at exactly 0
    and the rest solved again given that; one held whose gradient points into o > 0 is freed."""
    base = len(g) - len(offsets)
    fixed = np.zeros(len(g), bool)
    delta = np.zeros(len(g))
    for _ in range(OFFSET_ACTIVE_SET_ROUNDS):
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
SEARCH_BONES = (5, 8, 11, 14, 2, 6, 9, 12, 15)  # upper arms, thighs, chest, forearms, shins
SEARCH_ANGLE_DEG = 50.0


LIMIT_COST_M_PER_RAD = 0.05  # limb search: a pose 1 rad outside the limits costs as much as 5 cm of distance


def _limit_cost(s: _State, params: FitParams) -> float:
    if params.joint_limit_weight <= 0:
        return 0.0
    return LIMIT_COST_M_PER_RAD * float(np.abs(limit_violation(matrix_to_axis_angle(s.rot))).sum())


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
    """For each bone in SEARCH_BONES: try its local rotation turned by SEARCH_ANGLE_DEG about
    each axis (both ways), let the bone's subtree settle for a few ICP iterations, keep the
    candidate of the lowest cost (``_init_cost``)."""
    best_cost = _init_cost(rig, scan, s, sub, params, arms)
    for b in SEARCH_BONES:
        bones = np.nonzero(rig.subtree[b])[0]
        for axis in np.vstack([np.eye(3), -np.eye(3)]):
            cand = s.copy()
            cand.rot[b] = axis_angle_to_matrix(axis * np.radians(SEARCH_ANGLE_DEG)) @ cand.rot[b]
            cand, _ = _coarse(rig, scan, cand, sub, rest_normals, [(bones, 0)] * 3, clothed, params)
            cost = _init_cost(rig, scan, cand, sub, params, arms, bound=best_cost - 1e-4)
            if cost < best_cost - 1e-4:
                best_cost, s = cost, cand
    return s


# landmark initialisation (issue 12): the chain (upper, lower bone) aimed at each extremity,
# and the bone whose far end is the extremity's effector on the template
LANDMARK_CHAINS = {"hand_l": (5, 6), "hand_r": (8, 9), "foot_l": (11, 12), "foot_r": (14, 15)}
EFFECTOR_BONES = {"head": (4, 0), "hand_l": (7, 5), "hand_r": (10, 8), "foot_l": (13, 11), "foot_r": (16, 14)}
LANDMARK_ANCHORS = (0, 3)  # the joints (pelvis, neck) whose nearest scan points anchor the geodesics
TEMPLATE_GRAPH_MAX_EDGE_M = 0.15  # the template subsample is sparse on the legs (vertex density)
# the coarse ICP of a hypothesis pulls the effectors to their tips (point to point, weight per
# effector relative to the template subsample's size, i.e. a share of the data term) in this
# share of its iterations; the rest fit the scan alone
LANDMARK_WEIGHT = 0.05
LANDMARK_PULL_SHARE = 0.75
AIM_ROUNDS = 2  # cyclic-coordinate-descent sweeps over each chain's bones
AIM_MAX_DEG = 120.0  # larger turns of one bone are clipped (a wrong tip must not fold a limb)


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
    max_angle = np.radians(AIM_MAX_DEG)
    for _ in range(AIM_ROUNDS):
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
                              LM.knn_graph(p0.v, max_edge=TEMPLATE_GRAPH_MAX_EDGE_M)).anchor_geodesics(p0.v, anchors)
    tips = LM.assign(ext.points, ext.anchor_geodesics(pts, anchors), expected, e0)
    for h in LM.hypotheses(tips)[:params.landmark_hypotheses]:
        if not any(label in h for label in LANDMARK_CHAINS):
            continue
        cand = _aim_limbs(rig, s0, h, eff)
        keep = np.array([label in h for label in LM.LABELS])
        pull = (_subset(rig, eff.idx[keep]), np.array([h[label] for label in np.array(LM.LABELS)[keep]]),
                LANDMARK_WEIGHT * len(sub.idx), int(LANDMARK_PULL_SHARE * len(schedule)))
        cand, _ = _coarse(rig, scan, cand, sub, rest_normals, schedule, clothed, params, landmarks=pull)
        cost = _init_cost(rig, scan, cand, sub, params, arms, bound=best_cost - LANDMARK_MARGIN_M)
        if cost < best_cost - LANDMARK_MARGIN_M:
            best_cost, best = cost, cand
    return best


LANDMARK_MARGIN_M = 1e-4  # a hypothesis must beat ICP alone by this much (symmetric distance, m)


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


def _rims(pts_m: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, float]:
    """The scan's holes' rims for ``FitParams.rim_reject``: (distance (P,) metres from each point
    to the nearest rim point, the scan's point spacing). pts_m, nrm (P, 3)."""
    tree = cKDTree(pts_m)
    return SC.rim_distance(pts_m, SC.rim_points(pts_m, nrm, tree)), SC.point_spacing(tree, pts_m)


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
    owned = float(np.mean(is_head[j1] & (d1 < HEADLESS_NEAR_M) & ((P1 - joints[head]) @ up > HEADLESS_ABOVE_M)))
    adopt = bool(seen1[head] < UNSEEN_SHARE and owned <= HEADLESS_HEAD_SHARE)
    figures = {"head_seen": [round(float(seen0), 3), round(float(seen1[head]), 3)],
               "head_points": round(owned, 4), "adopted": adopt, "seconds": round(time.perf_counter() - t0_s, 2)}
    return ((s1, seen1, replace(p1, hair_region=params.hair_region)) if adopt else None), figures


# -- Alg. 1 -----------------------------------------------------------------------------------
def _correspondences(T: np.ndarray, rig: _Rig, tree: cKDTree, points: np.ndarray, normals: np.ndarray,
                     clothed: bool, params: FitParams, rim: np.ndarray | None = None):
    """Nearest scan point of each template vertex, rejected when normals differ by more than
    the threshold or it is too far (Alg. 1, line 4). Returns (c, nc, weight (0 = rejected))."""
    nT = vertex_normals(T, rig.faces, rig.incidence)
    j, _, ok = nearest_correspondences(T, nT, tree, normals, max_dist=params.max_corr_dist,
                                       normal_reject_deg=params.normal_reject_deg)
    c, nc = points[j], normals[j]
    signed = np.einsum("ij,ij->i", T - c, nc)
    if clothed:  # Alg. 1's alternation would carry T, then the body, out to loose clothes
        ok &= signed >= -params.alg1_inside_tol
    elif params.hair_region:  # ... and on a bare scan the scalp out to the hair
        ok &= ~_hair(rig, params) | (signed >= -params.alg1_inside_tol)
    if params.scan_cleanup:  # holes, a cut head top (issue 12)
        ok &= ~SC.over_hole(T, c, nc, SC.point_spacing(tree, points), tree)
    if rim is not None:  # (P,) bool: a hole's rim (FitParams.rim_reject)
        ok &= ~rim[j]
    if params.exclusive_hops is not None:  # the scan point is another body part's (FitParams)
        region = _subset(rig, np.arange(len(T))).region
        owner = cKDTree(T).query(c[ok])[1]
        ok[ok] = rig.hops[region[ok], region[owner]] <= params.exclusive_hops
    if params.absent_bones:
        ok &= ~np.isin(_subset(rig, np.arange(len(T))).region, _bone_ids(params.absent_bones))
    return c, nc, ok.astype(np.float64)


def _bone_ids(names) -> np.ndarray:
    from service.model.body.model import BONES

    return np.array([BONES.index(b) for b in names], np.int64)


# the tolerance of a measurement the customer gives (attribute units: cm, kg): one sigma of
# ``FitParams.known_weight``'s term; the others (girths, lengths) KNOWN_SIGMA_CM
KNOWN_SIGMA = {"height_cm": 0.5, "weight_kg": 1.0}
KNOWN_SIGMA_CM = 1.0


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
    sigma = np.array([KNOWN_SIGMA.get(n, KNOWN_SIGMA_CM) for n in names])

    def terms(beta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        raw, J = wm.measure(beta, gender, jacobian=True, names=names)
        r = (raw[rows] * scale - target) / sigma
        Jr = J[rows] * (scale / sigma)[:, None]
        return Jr.T @ Jr, Jr.T @ r, r

    return terms


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


# the head hypotheses' score (``FitParams.head_hypothesis_seen``): a scan point counts no more
# than this far from the body (a flying pixel, a stray cluster left by the cleaning)
HEAD_HYPOTHESIS_CLIP_M = 0.05


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


def scan_to_surface_mm(points: np.ndarray, body: np.ndarray, faces: np.ndarray,
                       clip: float = HEAD_HYPOTHESIS_CLIP_M) -> float:
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
        w_unseen = np.where(seen < UNSEEN_SHARE, params.unseen_prior, 0.0)
        w_unseen[_bone_ids(UNSEEN_FREE_BONES)] = 0.0
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
        rim = None if rims is None else rims[0] <= RIM_SPACINGS * rims[1]
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

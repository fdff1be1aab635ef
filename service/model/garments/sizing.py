"""Sizes and fit: size charts, grading, and how each size of a garment sits on a body.

Pure numpy/scipy (no web, queue or storage imports).

- A **size chart** is an ordered mapping label -> body measurements (the service's attribute
  names, API units: ``chest_cm``, ``waist_cm``, ...): the body each size is made for
  (:func:`validate_chart`).
- **Grading** (:func:`grade`): each size's rest shape is the base garment carried from the base
  size's body to that size's body by the warp the service already has (``autofit.autofit``,
  warping graph alone, no edge-length restoration: the garment takes the new size).
  The garment sits on the body it was uploaded on (``source``); size s is carried to
  ``source + (body_s - body_base)`` (same topology), so the base size is left as uploaded.
- **Fit** (:func:`fit_report`): at each region a tape goes around the body (the convex hull of
  a plane section, as ``measurements`` takes girths) and around the garment (the cloth's own
  length along the section of its rest shape that encloses the body there, as a tailor
  measures a garment laid flat). ``ease = garment girth - body girth``; the strain the body
  imposes on a garment tighter than it is ``max(0, body / garment - 1)`` (a closed loop on a
  convex section at static equilibrium stretches to the body's girth). The garment girths per
  size are constants of the garment (measured once at build, :func:`garment_girths`); a
  customer's body girths are measured once per body (:func:`body_girths`): the report is a
  few array operations (microseconds).
- **Lengths** (``lengths``): where the sleeve, trouser leg and hem end on each size's body
  against the body's own sleeve outseam, inseam and rise (:data:`LENGTH_REGIONS`), measured
  with the girths at the build; too short is ``tight``, too long ``loose``
  (:data:`LENGTH_THRESHOLDS`, on the difference from the design's length).
- **Verdicts** from thresholds per fabric (:data:`FIT_THRESHOLDS`, ease in % of the body's
  girth, so one table serves the hip and the upper arm) and the **recommendation**
  (:func:`recommend`): of the sizes with no region ``tight`` or ``too_tight``, the one whose
  ease is closest to the design ease (the base size on its own body); if every size is tight
  somewhere, the loosest.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from service.model.body import measurements as M
from service.model.body.model import BONES
from service.model.garments.lengths import LENGTH_REGIONS, LengthFrame, body_lengths, garment_lengths
from service.model.geometry.mesh import closest_points_on_mesh, mesh_edges, neighbour_mean, row_dot, vertex_normals
from service.model.body.lbs import main_bone

FABRICS = ("woven", "knit", "stretch")
DEFAULT_FABRIC = "woven"
VERDICTS = ("too_tight", "tight", "fit", "loose", "too_loose")
# the chart's measurements: the service's numeric attributes (API units)
CHART_MEASUREMENTS = tuple(a for a in M.ATTRIBUTES if a != "gender")
# a label of a garment without a size chart
ONE_SIZE = "one size"
MAX_SIZES = 12
MAX_LABEL_CHARS = 24

# regions in report order: girths (a tape around body and garment), then lengths (where the
# garment ends on the body, ``lengths``)
GIRTH_REGIONS = ("chest", "waist", "hip", "thigh", "upper_arm", "shoulders")
REGIONS = GIRTH_REGIONS + LENGTH_REGIONS
# upper arm: plane perpendicular to the shoulder -> elbow axis, this far down it (biceps level;
# ANSUR II "bicepscircumferenceflexed" is taken at the biceps' fullest point, ~40 % down)
UPPER_ARM_FRACTION = 0.4
# shoulders: horizontal tape this far below the acromion (ANSUR II "shouldercircumference",
# over the deltoids)
SHOULDER_DROP_M = 0.04
# thigh: the ``thigh_cm`` plane (perpendicular to the hip -> knee axis at crotch height) moved
# this far down the axis, below the crotch seam of trousers (at the crotch itself their
# section is one loop around both legs)
THIGH_DROP_M = 0.04
# the chart measurement that sizes each region (a chart giving some of these: the
# recommendation's design-ease distance is taken at those regions, as a tailor reads a chart)
REGION_MEASUREMENT = {"chest": "chest_cm", "waist": "waist_cm", "hip": "hip_cm", "thigh": "thigh_cm",
                      "sleeve": "arm_length_cm", "inseam": "inseam_cm"}
# an open garment section around a region must cover every one of these angular sectors around
# the body section's centre (the garment goes all around there), else it has no such region (a
# closed loop around the centre goes all around it, however few its points)
COVER_SECTORS = 12
# metres: a section's open ends this close to one another are the two sides of a seam (the loop
# goes on); farther apart, the section leaves the cloth there (a hem, a cuff) and is not a girth
SECTION_SEAM_GAP_M = 0.005


@dataclass(frozen=True)
class FitThresholds:
    """Verdict limits of one fabric, ease in % of the body's girth at the region.

    tight_pct: below it a size is ``tight`` (and ``too_tight`` below too_tight_pct);
    loose_pct / too_loose_pct: above them ``loose`` / ``too_loose``. A design's own ease on its
    base body, give or take ``design_margin_pct``, is ``fit``: where the fabric's limits would
    not leave that margin, the tight limits move down (the loose ones up) to it, the bands
    keeping their widths. strain_limit_pct: the fabric's usable stretch (the fit map's red)."""

    too_tight_pct: float
    tight_pct: float
    loose_pct: float
    too_loose_pct: float
    strain_limit_pct: float
    design_margin_pct: float = 4.0


# Woven cloth (shirting, denim, suiting) barely stretches (1-3 % in the warp and weft; ASTM
# D5035 strip tests): it needs positive ease to be worn (tailoring tables give 4-8 % at the chest
# for a fitted shirt). Single jersey knits take ~15-20 % before they bag; elastane blends
# (5-20 % spandex) 30-50 % (ASTM D2594 "stretch properties of knitted fabrics having low
# power"). Ease limits after Aldrich, "Metric Pattern Cutting" (ease tables: close fitting
# 0-4 %, fitted 4-10 %, loose 10-20 % of the girth) and Armstrong, "Patternmaking for Fashion
# Design" (negative ease of knits and stretch wovens).
FIT_THRESHOLDS: dict[str, FitThresholds] = {
    "woven": FitThresholds(too_tight_pct=0.0, tight_pct=3.0, loose_pct=20.0, too_loose_pct=32.0, strain_limit_pct=3.0),
    "knit": FitThresholds(too_tight_pct=-8.0, tight_pct=-2.0, loose_pct=16.0, too_loose_pct=28.0, strain_limit_pct=15.0),
    "stretch": FitThresholds(too_tight_pct=-20.0, tight_pct=-10.0, loose_pct=10.0, too_loose_pct=20.0,
                             strain_limit_pct=35.0),
}


@dataclass(frozen=True)
class LengthThresholds:
    """Verdict limits of one length region (cm), on how far a size ends from where the design
    ends: ``ease - design ease`` (the base size's length ease on its own body). Below short_cm
    it is ``tight`` (too short; ``too_tight`` below too_short_cm), above long_cm / too_long_cm
    ``loose`` / ``too_loose`` (too long). Fabric does not change a length."""

    too_short_cm: float
    short_cm: float
    long_cm: float
    too_long_cm: float


# Sleeves: ready-to-wear shirts come in sleeve lengths 1 inch (2.5 cm) apart (US dress-shirt
# sizing 32/33, 34/35, ...; EN 13402-1 gives the arm length in 5 cm steps): one step short
# shows the shirt cuff above the wrist bone, two is a different size. A longer sleeve bunches
# at the wrist before it covers the hand: a little more room on the long side.
# Inseams: trousers are sold in inseams 2 inches (5 cm) apart (US W/L 30, 32, 34): half a step
# short the hem clears the shoe (no break), a full step is a "high-water" trouser; too long
# breaks on the shoe and drags at two steps (alterations shorten: more room on the long side).
# Hems: a top's or dress's length is a style more than a fit; 5 cm is about a hand's width
# (a shirt that untucks, a skirt above the knee where it was meant at it), 10 cm another
# silhouette (Aldrich: body lengths in 5 cm grade steps between "hip", "thigh", "knee").
# the lengths whose "too short" rules a size out of the recommendation as a tight girth does (a
# tailor would not pick a short sleeve or trouser leg), when the chart sizes that length (gives
# one of the measurements below): a chart of girths alone (EN 13402-3's letter codes by chest)
# promises no sleeve length, and sizing up for a long arm there buys a chest too loose; the
# report still says the sleeve is short. Not the hem: a top's or skirt's length is a style,
# graded sizes barely differ in it (and not always in size order: a chart of girths leaves the
# size bodies' heights to the population), so it would choose by noise
CHOOSING_LENGTHS = ("sleeve", "inseam")
LENGTH_MEASUREMENTS = {"sleeve": ("arm_length_cm", "height_cm"), "inseam": ("inseam_cm", "height_cm")}
LENGTH_THRESHOLDS: dict[str, LengthThresholds] = {
    "sleeve": LengthThresholds(too_short_cm=-5.0, short_cm=-2.5, long_cm=4.0, too_long_cm=8.0),
    "inseam": LengthThresholds(too_short_cm=-5.0, short_cm=-2.5, long_cm=5.0, too_long_cm=10.0),
    "hem": LengthThresholds(too_short_cm=-10.0, short_cm=-5.0, long_cm=5.0, too_long_cm=10.0),
}


class ChartError(ValueError):
    """An invalid size chart or size choice: ``field`` (where) and ``message`` (why)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


def validate_chart(chart, base_size: str | None, ranges: dict[str, tuple[float, float]] | None = None
                   ) -> tuple[list[dict], str]:
    """A size chart as given (a mapping label -> {measurement: value}, in chart order) checked:
    labels non-empty and unique, measurements known numeric attributes (``ranges``: name ->
    (min, max) accepted, API units), every size giving the same measurements, sizes strictly
    increasing in every one of them, ``base_size`` one of the labels (default: the middle
    size). A value is a number or, as retailers' charts print them, an interval ``[low, high]``
    (low <= high): the size is made for its middle, and the interval is kept beside it.
    Returns ([{label, measurements[, intervals]}] in chart order, base label) or raises
    :class:`ChartError`."""
    if not isinstance(chart, dict) or not chart:
        raise ChartError("size_chart", "must be a JSON object of size label -> {measurement: value}, "
                                       'e.g. {"S": {"chest_cm": 88}, "M": {"chest_cm": 96}}')
    if len(chart) > MAX_SIZES:
        raise ChartError("size_chart", f"at most {MAX_SIZES} sizes; got {len(chart)}")
    sizes: list[dict] = []
    names: tuple | None = None
    for label, ms in chart.items():
        if not isinstance(label, str) or not label.strip() or len(label) > MAX_LABEL_CHARS \
                or not label.isprintable() or "," in label:
            raise ChartError("size_chart", f"size label {label!r}: 1-{MAX_LABEL_CHARS} printable characters, no comma")
        if not isinstance(ms, dict) or not ms:
            raise ChartError(f"size_chart.{label}", "must be an object of measurement name -> value (cm)")
        out: dict[str, float] = {}
        intervals: dict[str, list[float]] = {}
        for name, value in ms.items():
            field = f"size_chart.{label}.{name}"
            if name not in CHART_MEASUREMENTS:
                raise ChartError(field, "unknown measurement; known: " + ", ".join(CHART_MEASUREMENTS))
            ends = value if isinstance(value, list) else [value]
            if len(ends) != (2 if isinstance(value, list) else 1) or not all(_finite_number(v) for v in ends):
                raise ChartError(field, "must be a finite number or an interval [low, high] of two")
            if ends[0] > ends[-1]:
                raise ChartError(field, f"interval [{ends[0]:g}, {ends[-1]:g}]: low must not be above high")
            lo, hi = (ranges or {}).get(name, (-math.inf, math.inf))
            for v in ends:
                if not lo <= v <= hi:
                    raise ChartError(field, f"{v:g} is outside the accepted range {lo:g}-{hi:g}")
            out[name] = 0.5 * (float(ends[0]) + float(ends[-1]))
            if isinstance(value, list):
                intervals[name] = [float(ends[0]), float(ends[-1])]
        if names is None:
            names = tuple(sorted(out))
        elif tuple(sorted(out)) != names:
            raise ChartError(f"size_chart.{label}", f"gives {sorted(out)}, but the first size gives {list(names)}: "
                                                    "every size must give the same measurements")
        sizes.append({"label": label, "measurements": out, **({"intervals": intervals} if intervals else {})})
    labels = [s["label"] for s in sizes]
    folded = [lb.strip().casefold() for lb in labels]
    if len(set(folded)) != len(folded):
        raise ChartError("size_chart", f"size labels repeated: {labels}")
    for prev, cur in zip(sizes[:-1], sizes[1:]):
        for name in names or ():
            if not cur["measurements"][name] > prev["measurements"][name]:
                raise ChartError(f"size_chart.{cur['label']}.{name}",
                                 f"sizes must increase in every measurement in chart order: {cur['label']} "
                                 f"{cur['measurements'][name]:g} after {prev['label']} {prev['measurements'][name]:g}")
    if base_size is None:
        base_size = labels[(len(labels) - 1) // 2]
    if base_size not in labels:
        raise ChartError("base_size", f"'{base_size}' is not a size of the chart ({', '.join(labels)})")
    return sizes, base_size


def _finite_number(v) -> bool:
    return not isinstance(v, bool) and isinstance(v, (int, float)) and math.isfinite(v)


def check_fabric(fabric: str | None) -> str:
    """The fabric name, default ``woven``; :class:`ChartError` for an unknown one."""
    fabric = DEFAULT_FABRIC if fabric is None else fabric
    if fabric not in FIT_THRESHOLDS:
        raise ChartError("fabric", f"unknown fabric '{fabric}'; one of {', '.join(FABRICS)}")
    return fabric


def size_index(labels: list[str], size: str | None, default: int) -> int:
    """The index of ``size`` among ``labels`` (None: ``default``); :class:`ChartError` listing
    the labels when unknown."""
    if size is None:
        return default
    if size not in labels:
        raise ChartError("size", f"unknown size '{size}'; this garment's sizes: {', '.join(labels)}")
    return labels.index(size)


# -- grading ---------------------------------------------------------------------------------
def grade(model, garment: np.ndarray, faces: np.ndarray, source: np.ndarray, bodies: np.ndarray,
          base: int) -> np.ndarray:
    """Each size's rest shape (S, M, 3) float32: the garment (M, 3) on the body ``source``
    (V, 3) carried to ``source + bodies[s] - bodies[base]`` for every size s (bodies (S, V, 3)
    in the template topology, made from the chart) by the service's warp (the warping graph of
    ``autofit.autofit``, without restoring edge lengths: the cloth takes the new size; no
    push-out either, which would add girth to every size but the base one). The base
    size is the garment as given."""
    from dataclasses import replace

    from service.model.garments import autofit as AF

    S = len(bodies)
    out = np.empty((S, len(garment), 3), np.float32)
    out[base] = garment
    others = [s for s in range(S) if s != base]
    if not others:
        return out
    src = np.asarray(source, np.float64)
    T = np.stack([src + (np.asarray(bodies[s], np.float64) - np.asarray(bodies[base], np.float64)) for s in others])
    # the warp alone: no edge-length restoration (the cloth takes the new size) and no
    # collision push-out (it would add girth to the other sizes but not to the base size)
    params = replace(AF.DEFAULT_PARAMS, edge_iterations=0, collision_passes=0)
    helpers = np.arange(*AF.HELPER_TIGHTS) if params.follow_helper_tights and len(model.mean) >= AF.HELPER_TIGHTS[1] \
        else None
    res = AF.autofit(garment, faces, src, T, model.body_faces, params, body_points=helpers,
                     body_labels=main_bone(model.lbs_indices, model.lbs_weights),
                     label_hops=AF.bone_hops(model.bone_parents))
    out[others] = [keep_offsets(garment, f, src, t, model.body_faces, faces) for f, t in zip(res.fits, T)]
    return out


# grading keeps the garment's distance from the body (its ease) where it lies near the body:
# fully up to KEEP_NEAR_M off the surface, fading to the warp's own (scaled with the body) at
# KEEP_FAR_M, where cloth hangs (a skirt's hem) rather than follows the body
KEEP_NEAR_M = 0.04
KEEP_FAR_M = 0.10
# the correction is smoothed over the garment's edges (neighbour means) so that the body's
# normals turning in creases (armpits, crotch) do not crumple short edges
KEEP_SMOOTHING = 3


def keep_offsets(garment: np.ndarray, warped: np.ndarray, source: np.ndarray, target: np.ndarray,
                 body_faces: np.ndarray, garment_faces: np.ndarray | None = None) -> np.ndarray:
    """The warped garment (M, 3) with each vertex's offset along the body's normal set back to
    the garment's (M, 3) offset on ``source`` (V, 3), measured at the same body point (face and
    barycentrics of the vertex's closest point on ``source``) of ``target`` (V, 3): the warp
    places the cloth along the body and scales its gap with the body; a size's ease is the
    gap kept (girth = body girth + 2 pi gap on a convex section). Weighted by
    ``KEEP_NEAR_M``/``KEEP_FAR_M``, smoothed over ``garment_faces`` (K, 3) when given.
    Returns (M, 3) float64."""
    g = np.asarray(garment, np.float64)
    W = np.asarray(warped, np.float64)
    F = np.asarray(body_faces, np.int64)
    src, tgt = np.asarray(source, np.float64), np.asarray(target, np.float64)
    face, _, bary = closest_points_on_mesh(g, src, F)
    tri = F[face]

    def point_and_normal(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        N = vertex_normals(X, F)
        c = np.einsum("mk,mkd->md", bary, X[tri])
        n = np.einsum("mk,mkd->md", bary, N[tri])
        return c, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)

    c0, n0 = point_and_normal(src)
    ct, nt = point_and_normal(tgt)
    d0 = row_dot(g - c0, n0)
    dw = row_dot(W - ct, nt)
    w = np.clip((KEEP_FAR_M - d0) / (KEEP_FAR_M - KEEP_NEAR_M), 0.0, 1.0)
    shift = w * (d0 - dw)
    if garment_faces is not None:
        A = neighbour_mean(garment_faces, len(g))
        for _ in range(KEEP_SMOOTHING):
            shift = 0.5 * (shift + A @ shift)
    return W + shift[:, None] * nt


def bound_size_fits(fit, examples: np.ndarray, rests: np.ndarray, bodies_on: np.ndarray) -> list[np.ndarray]:
    """Every size's example fits of a garment bound to the body (a MakeHuman binding: ``fit``
    maps an avatar (V, 3) to the garment (M, 3)): size s on example e is the binding's fit to
    e plus that size's grading displacement where it was graded, ``rests[s] -
    fit(bodies_on[s])``: the graded garment carried with each body as the binding carries the
    garment (made to measure, as the warp's per-size fits; the base size's are exactly the
    binding's fits). examples (E, V, 3), rests (S, M, 3), bodies_on (S, V, 3) -> S arrays
    (E, M, 3) float64."""
    on_examples = np.stack([np.asarray(fit(X), np.float64) for X in examples])
    return [on_examples + (np.asarray(rests[s], np.float64) - np.asarray(fit(bodies_on[s]), np.float64))[None]
            for s in range(len(rests))]


def size_bodies_on(source: np.ndarray, bodies: np.ndarray, base: int) -> np.ndarray:
    """(S, V, 3) the body each size's rest shape sits on: ``source + bodies[s] - bodies[base]``."""
    src = np.asarray(source, np.float64)
    return np.stack([src + (np.asarray(b, np.float64) - np.asarray(bodies[base], np.float64)) for b in bodies])


# -- regions ---------------------------------------------------------------------------------
@dataclass
class Region:
    """One tape on a body: plane ``normal . x = offset``, the body section's centre (3,), and
    points (K, 3) the garment's section must NOT enclose: for the thigh the other thigh (a
    skirt has no thigh girth), for the chest the upper arms where they cross its plane (a
    long sleeve cut where it meets the body is not a chest girth)."""

    normal: np.ndarray
    offset: float
    centre: np.ndarray
    exclude: np.ndarray | None = None  # (K, 3); one point (3,) is read as (1, 3)
    body_girth: float = 0.0  # metres

    def __post_init__(self):
        if self.exclude is not None:
            self.exclude = np.atleast_2d(np.asarray(self.exclude, np.float64))


class RegionSpec:
    """The body edges each region's tape may cross (template topology), once per body model."""

    def __init__(self, model):
        self.spec = model.measurement_spec
        nb = model.n_body_vertices
        edges = mesh_edges(np.asarray(model.body_faces))
        edges = edges[(edges < nb).all(axis=1)]
        bone = main_bone(model.lbs_indices[:nb], model.lbs_weights[:nb])
        both = lambda ids: edges[np.isin(bone[edges[:, 0]], ids) & np.isin(bone[edges[:, 1]], ids)]  # noqa: E731
        b = {n: i for i, n in enumerate(BONES)}
        self.arm_edges = both([b["upper_arm_l"]])
        self.shoulder_edges = both([b[n] for n in ("spine", "chest", "upper_arm_l", "upper_arm_r", "neck")])
        self.joint = b
        self.model = model

    def regions(self, X: np.ndarray) -> dict[str, Region]:
        """The regions' planes and body girths on a body X (V, 3) (metres)."""
        X = np.asarray(X, np.float64)
        spec = self.spec
        out: dict[str, Region] = {}

        def put(name, edges, normal, offset, exclude=None):
            sec = M._hull_section(X, edges, normal, float(offset), grad=False)
            centre = sec.pts.mean(axis=0) if len(sec.pts) else np.zeros(3)
            out[name] = Region(normal, float(offset), centre, exclude, sec.perimeter)

        J = self.model.joints(X)
        b = self.joint
        chest_y = X[spec.nipples, 1].mean()
        arms = []
        for side in ("l", "r"):
            sh, el = J[b["upper_arm_" + side]], J[b["forearm_" + side]]
            if (sh[1] - chest_y) * (el[1] - chest_y) < 0:  # the arm's axis crosses the chest plane
                arms.append(sh + (chest_y - sh[1]) / (el[1] - sh[1]) * (el - sh))
        put("chest", spec.chest_edges, M.Y, chest_y, exclude=np.array(arms) if arms else None)
        put("waist", spec.waist_edges, M.Y, X[spec.navel, 1])
        f = M.HIP_LEVEL_FRACTION
        put("hip", spec.hip_edges, M.Y, (1 - f) * X[spec.crotch, 1] + f * X[spec.navel, 1])
        jr = spec.joint_ids
        hip, knee = J[jr["hip"]], J[jr["knee"]]
        u = hip - knee
        n = u / np.linalg.norm(u)
        s = (X[spec.crotch, 1] - knee[1]) / (hip[1] - knee[1])
        origin = knee + s * u - THIGH_DROP_M * n
        hr, kr = J[b["thigh_r"]], J[b["shin_r"]]
        other = kr + s * (hr - kr) - THIGH_DROP_M * n
        put("thigh", spec.thigh_edges, n, n @ origin, exclude=other)
        sh, el = J[b["upper_arm_l"]], J[b["forearm_l"]]
        a = (el - sh) / np.linalg.norm(el - sh)
        put("upper_arm", self.arm_edges, a, a @ (sh + UPPER_ARM_FRACTION * (el - sh)),
            exclude=J[b["chest"]])
        put("shoulders", self.shoulder_edges, M.Y, X[spec.acromion, 1].mean() - SHOULDER_DROP_M)
        return out


def body_girths(regions: dict[str, Region]) -> np.ndarray:
    """(R,) the body's girths (cm) at ``GIRTH_REGIONS``."""
    return np.array([100.0 * regions[r].body_girth for r in GIRTH_REGIONS])


class GarmentSections:
    """A garment's mesh cut by planes: the loops of cloth around a body region (topology once
    per garment: faces (F, 3))."""

    def __init__(self, faces: np.ndarray, n_vertices: int):
        F = np.asarray(faces, np.int64)
        self.edges = mesh_edges(F)
        key = self.edges[:, 0] * n_vertices + self.edges[:, 1]
        order = np.argsort(key)
        fe = np.stack([np.sort(F[:, [0, 1]], 1), np.sort(F[:, [1, 2]], 1), np.sort(F[:, [2, 0]], 1)], 1)
        fkey = fe[..., 0] * n_vertices + fe[..., 1]
        self.face_edges = order[np.searchsorted(key, fkey, sorter=order)]  # (F, 3) edge ids

    def girth(self, V: np.ndarray, region: Region, closed: bool = False, tape: bool = False,
              body_girth: float = 0.0) -> float | None:
        """The cloth's length (metres) along the plane section of the garment V (M, 3) that
        encloses the region's centre (the innermost such loop), or None when no section of
        the garment goes all around it there (or one also encloses a point of ``region.exclude``).
        An open chain counts (the two fronts of a buttoned shirt or an open jacket overlap
        without meeting) unless ``closed`` (a garment closed all around: see :func:`_closed`).
        ``tape``: instead of the cloth's length along that loop, the perimeter of its convex
        hull, as a tape laid around the garment on a body reads it (a draped garment's folds
        and wrinkles add cloth length along the section, not girth). ``body_girth`` (metres,
        the body's girth there): an open chain that leaves a share of the body bare (it turns
        about the centre by that much less than a full turn, :func:`_turn`) adds that share of
        the body's girth, the bare arc counted at no ease, so that an open garment's ease is its
        cloth against the part of the body it covers (its cloth length alone read an open-backed
        top 11 cm tight on the body it was made for)."""
        V = np.asarray(V, np.float64)
        e = self.edges
        s = V @ region.normal - region.offset
        sa, sb = s[e[:, 0]], s[e[:, 1]]
        cross = ((sa * sb) <= 0) & ((sa != 0) | (sb != 0))
        if cross.sum() < 3:
            return None
        t = np.where(cross, sa / np.where(sa - sb == 0, 1, sa - sb), 0.0)
        P = V[e[:, 0]] + t[:, None] * (V[e[:, 1]] - V[e[:, 0]])
        fc = cross[self.face_edges]
        segf = fc.sum(1) == 2
        if not segf.any():
            return None
        fe = self.face_edges[segf]
        pick = np.argsort(~fc[segf], axis=1, kind="stable")[:, :2]
        seg = np.take_along_axis(fe, pick, 1)  # (S, 2) crossing edge ids
        ids, inv = np.unique(seg, return_inverse=True)
        inv = inv.reshape(-1, 2)
        n = len(ids)
        adj = sp.coo_matrix((np.ones(len(inv)), (inv[:, 0], inv[:, 1])), shape=(n, n))
        ncomp, lab = connected_components(adj, directed=False)
        e1, e2 = M._plane_basis(region.normal)
        p2 = np.stack([P[ids] @ e1, P[ids] @ e2], 1)
        seglen = np.linalg.norm(P[seg[:, 0]] - P[seg[:, 1]], axis=1)
        slab = lab[inv[:, 0]]
        c2 = np.array([region.centre @ e1, region.centre @ e2])
        x2 = None if region.exclude is None else np.stack([region.exclude @ e1, region.exclude @ e2], 1)
        best = None
        deg = np.bincount(inv.ravel(), minlength=n)  # chain ends: degree 1
        for c in range(ncomp):
            m = slab == c
            a, b = p2[inv[m, 0]], p2[inv[m, 1]]
            if closed and not _closed(P[ids[(lab == c) & (deg == 1)]]):
                continue
            # an open chain (a shirt's fronts, an open back) goes around a point when it turns
            # about it by half a turn or more, walked end to end; a loop (or a chain that
            # branches) by the even-odd rule, which for an open chain would depend on where
            # its ray leaves it (through an opening: outside; through overlapping fronts: twice)
            opened = bool((deg[lab == c] == 1).any())
            order = _chain_order(inv[m]) if opened else None
            around = (lambda x: _encloses(a, b, x)) if order is None else \
                (lambda x: _turn(p2[order], x) >= np.pi)  # noqa: E731
            turn = 2.0 * np.pi if order is None else _turn(p2[order], c2)
            # a loop around the centre goes all around it; an open chain must also leave no
            # sector of it bare (a coarse trouser hem's loop, a few points around a leg that
            # stands off its centre, left sectors empty and was read as no loop)
            if turn < np.pi or (order is None and not around(c2)) or (opened and not _covers(p2[lab == c], c2)):
                continue
            if x2 is not None and any(around(x) for x in x2):
                continue
            length = float(seglen[m].sum())
            if body_girth:  # the bare share at no ease (none for a loop)
                length += body_girth * max(0.0, 1.0 - turn / (2.0 * np.pi))
            if best is None or length < best[0]:
                best = (length, c)
        if best is None:
            return None
        return M.hull_perimeter(p2[lab == best[1]], grad=False)[0] if tape else best[0]


def _closed(ends: np.ndarray) -> bool:
    """Whether a chain of section segments whose open ends are ``ends`` (K, 3) is a loop: no
    open end, or each one within ``SECTION_SEAM_GAP_M`` of another (a seam whose two sides are
    separate vertices). A chain that leaves the cloth through a hem or cuff is not a girth, even
    where the even-odd rule finds the region's centre inside it (the section through an armpit
    running into a sleeve)."""
    if not len(ends):
        return True
    if len(ends) % 2:
        return False
    d = np.linalg.norm(ends[:, None] - ends[None], axis=2)
    np.fill_diagonal(d, np.inf)
    return bool((d.min(axis=1) <= SECTION_SEAM_GAP_M).all())


def _chain_order(segments: np.ndarray) -> np.ndarray | None:
    """The nodes of an open chain of section ``segments`` (S, 2) in order from one open end to
    the other; None for a chain that branches (a non-manifold seam)."""
    nbr: dict[int, list[int]] = {}
    for i, j in segments.tolist():
        nbr.setdefault(i, []).append(j)
        nbr.setdefault(j, []).append(i)
    if any(len(v) > 2 for v in nbr.values()):
        return None
    node = next(k for k, v in nbr.items() if len(v) == 1)
    order, prev = [node], -1
    while len(order) <= len(nbr):
        nxt = [k for k in nbr[node] if k != prev]
        if not nxt:
            break
        prev, node = node, nxt[0]
        order.append(node)
    return np.array(order)


def _turn(points: np.ndarray, p: np.ndarray) -> float:
    """How far (radians, >= 0) a polyline of points (K, 2), walked in order, turns about p (2,):
    a full turn (2 pi) around it, more where its ends overlap (a buttoned shirt's fronts), less
    by the share of the way around that it leaves open (an open jacket's front, a V-neck at the
    shoulders, a cropped back): that share of the body is bare."""
    ang = np.arctan2(points[:, 1] - p[1], points[:, 0] - p[0])
    return abs(float(np.angle(np.exp(1j * np.diff(ang))).sum()))  # each step's angle wrapped to (-pi, pi]


def _encloses(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> bool:
    """Even-odd rule: segments a -> b (S, 2) around the point p (2,) (a ray along +x)."""
    ya, yb = a[:, 1] - p[1], b[:, 1] - p[1]
    hit = (ya > 0) != (yb > 0)
    if not hit.any():
        return False
    t = ya[hit] / (ya[hit] - yb[hit])
    x = a[hit, 0] + t * (b[hit, 0] - a[hit, 0])
    return bool(((x > p[0]).sum()) % 2 == 1)


def _covers(points: np.ndarray, p: np.ndarray) -> bool:
    ang = np.arctan2(points[:, 1] - p[1], points[:, 0] - p[0])
    sec = np.floor((ang + np.pi) / (2 * np.pi) * COVER_SECTORS).astype(int) % COVER_SECTORS
    return len(np.unique(sec)) == COVER_SECTORS


def garment_girths(sections: GarmentSections, rest: np.ndarray, regions: dict[str, Region],
                   closed: bool = False, tape: bool = False) -> np.ndarray:
    """(R,) the garment's girths (cm) at ``GIRTH_REGIONS`` on the body it sits on (its rest
    shape (M, 3) and that body's ``regions``); NaN where it has no such region (``closed``,
    ``tape``: :meth:`GarmentSections.girth`)."""
    out = np.full(len(GIRTH_REGIONS), np.nan)
    for i, r in enumerate(GIRTH_REGIONS):
        g = sections.girth(rest, regions[r], closed, tape, 0.0 if tape else regions[r].body_girth)
        if g is not None:
            out[i] = 100.0 * g
    return out


# -- the fit ---------------------------------------------------------------------------------
@dataclass
class SizeFit:
    """What a garment's fit report needs, fixed at its build: garment girths and lengths (S, R)
    cm per size and region of ``REGIONS`` (NaN: the garment has no such region), the design
    ease (R,) cm (the base size's ease on its own body), the fabric. Stored records made before
    a region existed read it as NaN (:meth:`from_meta` maps regions by name)."""

    labels: list[str]
    garment_cm: np.ndarray
    design_cm: np.ndarray
    design_body_cm: np.ndarray
    fabric: str
    key: np.ndarray | None = None  # (R,) bool: the regions the chart sizes (None: all)
    # (S, R) cm: the chart's own measurement of each size at each girth region it gives (NaN
    # elsewhere; :func:`chart_girths`), from the garment's record (not stored in ``to_meta``)
    chart_cm: np.ndarray | None = None

    def to_meta(self) -> dict:
        nan = lambda a: [None if not np.isfinite(x) else round(float(x), 3) for x in a]  # noqa: E731
        return {"labels": list(self.labels), "regions": list(REGIONS), "fabric": self.fabric,
                "garment_cm": [nan(r) for r in self.garment_cm], "design_cm": nan(self.design_cm),
                "design_body_cm": nan(self.design_body_cm),
                "key": None if self.key is None else [bool(k) for k in self.key]}

    @classmethod
    def from_meta(cls, d: dict) -> "SizeFit":
        arr = lambda a: np.array([np.nan if x is None else x for x in a], np.float64)  # noqa: E731
        if list(d["regions"]) != list(REGIONS):  # older builds (no lengths): their regions, mapped by name
            idx = {r: i for i, r in enumerate(d["regions"])}
            pick = lambda a: np.array([a[idx[r]] if r in idx else np.nan for r in REGIONS])  # noqa: E731
        else:
            pick = lambda a: a  # noqa: E731
        key = None if d.get("key") is None else np.nan_to_num(pick(np.array(d["key"], float))).astype(bool)
        return cls(list(d["labels"]), np.stack([pick(arr(r)) for r in d["garment_cm"]]), pick(arr(d["design_cm"])),
                   pick(arr(d["design_body_cm"])), d["fabric"], key)


def size_fit(labels: list[str], garment_cm: np.ndarray, base: int, base_body_cm: np.ndarray,
             fabric: str, measurements: list[str] | None = None) -> SizeFit:
    """A garment's :class:`SizeFit`: girths and lengths (S, R) cm per size, the base size's index
    and the girths and lengths (R,) cm of the base size's own body (from the chart; the body it was uploaded on
    without a chart); ``measurements``: the names the chart gives (its key regions). Regions
    not present in every size are dropped (NaN)."""
    G = np.asarray(garment_cm, np.float64)
    G[:, ~np.isfinite(G).all(axis=0)] = np.nan
    given = set(measurements or ())
    key = np.array([REGION_MEASUREMENT.get(r) in given or bool(given & set(LENGTH_MEASUREMENTS.get(r, ())))
                    for r in REGIONS])
    return SizeFit(list(labels), G, G[base] - base_body_cm, np.asarray(base_body_cm, np.float64), fabric,
                   key if key.any() else None)


def chart_girths(measurements: list[dict[str, float]]) -> np.ndarray:
    """(S, R) cm: each size's chart measurements (``measurements``, one dict per size in chart
    order, API names) at the girth regions of ``REGIONS`` (:data:`REGION_MEASUREMENT`); NaN where
    the chart gives none."""
    out = np.full((len(measurements), len(REGIONS)), np.nan)
    for i, r in enumerate(REGIONS):
        name = REGION_MEASUREMENT.get(r)
        if r in GIRTH_REGIONS and name is not None:
            for s, m in enumerate(measurements):
                if m.get(name) is not None:
                    out[s, i] = float(m[name])
    return out


def verdicts(ease_cm: np.ndarray, body_cm: np.ndarray, design_cm: np.ndarray, fabric: str) -> np.ndarray:
    """Verdict index (into ``VERDICTS``) of each ease (..., R) cm on girths body_cm (R,) for a
    design ease design_cm (R,) of ``fabric`` (:class:`FitThresholds`)."""
    th = FIT_THRESHOLDS[fabric]
    pct = 100.0 * ease_cm / body_cm
    dpct = 100.0 * design_cm / body_cm
    # a design's own ease, give or take the margin, is a fit: the limits move below (above) it
    # where the fabric's would not leave that margin, keeping the width of the tight (loose) band
    tight = np.minimum(th.tight_pct, dpct - th.design_margin_pct)
    too_tight = np.minimum(th.too_tight_pct, tight - (th.tight_pct - th.too_tight_pct))
    loose = np.maximum(th.loose_pct, dpct + th.design_margin_pct)
    too_loose = np.maximum(th.too_loose_pct, loose + (th.too_loose_pct - th.loose_pct))
    v = np.full(pct.shape, 2, np.int64)
    v[pct < tight] = 1
    v[pct < too_tight] = 0
    v[pct > loose] = 3
    v[pct > too_loose] = 4
    return v


def length_verdicts(ease_cm: np.ndarray, design_cm: np.ndarray, regions) -> np.ndarray:
    """Verdict index (into ``VERDICTS``) of each length ease (..., L) cm at the length
    ``regions`` (L names of ``LENGTH_REGIONS``) for the design's length ease design_cm (L,):
    too short -> ``tight`` / ``too_tight``, too long -> ``loose`` / ``too_loose``
    (:data:`LENGTH_THRESHOLDS`, on ``ease - design ease``)."""
    th = [LENGTH_THRESHOLDS[r] for r in regions]
    d = np.asarray(ease_cm, np.float64) - design_cm
    v = np.full(d.shape, 2, np.int64)
    v[d < np.array([t.short_cm for t in th])] = 1
    v[d < np.array([t.too_short_cm for t in th])] = 0
    v[d > np.array([t.long_cm for t in th])] = 3
    v[d > np.array([t.too_long_cm for t in th])] = 4
    return v


@dataclass
class FitReport:
    """The fit of every size on one body at ``REGIONS``: ease (S, R) cm, strain (S, R) % (0
    where the garment is looser than the body, and at lengths), verdicts (S, R) and per size (S,) (indices into ``VERDICTS``),
    present (R,) bool (regions the garment has), recommended size index."""

    labels: list[str]
    ease_cm: np.ndarray
    strain_pct: np.ndarray
    verdict: np.ndarray
    size_verdict: np.ndarray
    present: np.ndarray
    recommended: int

    def to_dict(self) -> dict:
        regions = [r for r, p in zip(REGIONS, self.present) if p]
        idx = np.flatnonzero(self.present)
        return {"recommended": self.labels[self.recommended],
                "sizes": [{"label": lb, "verdict": VERDICTS[int(self.size_verdict[s])],
                           "regions": [{"region": r, "ease_cm": round(float(self.ease_cm[s, i]), 1),
                                        "strain_pct": round(float(self.strain_pct[s, i]), 1),
                                        "verdict": VERDICTS[int(self.verdict[s, i])]}
                                       for r, i in zip(regions, idx)]}
                          for s, lb in enumerate(self.labels)]}


def fit_report(fit: SizeFit, body_cm: np.ndarray) -> FitReport:
    """Every size of a garment (``fit``) on a body with girths and lengths body_cm (R,)
    (:func:`girths_of_body`). A length's strain is 0 (a length is not stretched)."""
    present = np.isfinite(fit.design_cm) & np.isfinite(body_cm) & (body_cm > 0)
    ease = np.full(fit.garment_cm.shape, np.nan)
    strain = np.full(fit.garment_cm.shape, np.nan)
    v = np.full(fit.garment_cm.shape, 2, np.int64)
    girth = present & _IS_GIRTH
    G, B = fit.garment_cm[:, girth], body_cm[girth]
    ease[:, girth] = G - B
    strain[:, girth] = 100.0 * np.maximum(0.0, B / G - 1.0)
    v[:, girth] = verdicts(G - B, B, fit.design_cm[girth], fit.fabric)
    length = present & ~_IS_GIRTH
    ease[:, length] = fit.garment_cm[:, length] - body_cm[length]
    strain[:, length] = 0.0
    v[:, length] = length_verdicts(ease[:, length], fit.design_cm[length],
                                   [r for r, p in zip(REGIONS, length) if p])
    size_v = np.array([_size_verdict(row[present]) for row in v], np.int64)
    # a sleeve or inseam chooses only where the chart sizes it (:data:`LENGTH_MEASUREMENTS`)
    charted = np.zeros(len(REGIONS), bool) if fit.key is None else np.asarray(fit.key, bool)
    chooses = _CHOOSES & charted
    votes = present & (_IS_GIRTH | chooses)  # the hem neither rules out nor ranks sizes
    key = votes if fit.key is None else votes & fit.key
    # a girth the chart sizes but the garment has no section at (a waist chart for low-rise
    # trousers, a chest chart for dungarees whose bib does not go around): there the chart
    # itself ranks the sizes, by how far each size's chart measurement is from the body's
    by_chart = None
    if fit.key is not None and fit.chart_cm is not None:
        absent = np.asarray(fit.key, bool) & _IS_GIRTH & ~present & np.isfinite(body_cm) & \
            np.isfinite(fit.chart_cm).all(axis=0)
        if absent.any():
            by_chart = np.abs(fit.chart_cm[:, absent] - body_cm[absent]).sum(axis=1)
    if not key.any() and by_chart is None:
        key = votes
    # the recommendation's verdicts: a short sleeve or inseam rules a size out like a tight
    # girth, unless it is short in every size (no size mends it: the report says so, the
    # choice goes by the other regions); a hem's length does not choose (:data:`CHOOSING_LENGTHS`)
    choose = v.copy()
    choose[:, length & ((v < 2).all(axis=0) | ~chooses)] = 2
    return FitReport(fit.labels, ease, strain, v, size_v, present,
                     recommend(ease[:, present], fit.design_cm[present], choose[:, present], key[present], by_chart))


_IS_GIRTH = np.array([r in GIRTH_REGIONS for r in REGIONS])
_CHOOSES = np.array([r in CHOOSING_LENGTHS for r in REGIONS])


def _size_verdict(v: np.ndarray) -> int:
    """One size's verdict: its tightest region when any is tight, else its loosest."""
    if not len(v):
        return 2
    return int(v.min()) if v.min() < 2 else int(v.max())


def recommend(ease_cm: np.ndarray, design_cm: np.ndarray, verdict: np.ndarray, key: np.ndarray | None = None,
              by_chart: np.ndarray | None = None) -> int:
    """The size a tailor would pick: of the sizes with no region ``tight`` or ``too_tight``
    (verdict (S, R)), the one whose ease (S, R) is closest to the design ease (R,) (summed
    absolute difference over the ``key`` regions (R,) bool, those the chart sizes; None: all;
    plus ``by_chart`` (S,) cm, how far each size's chart is from the body where the garment has
    no section at a region the chart sizes); if every size is tight somewhere, the loosest
    (largest total ease)."""
    if ease_cm.shape[1] == 0 and by_chart is None:
        return 0
    ok = (verdict >= 2).all(axis=1)
    if not ok.any():
        return int(np.argmax(ease_cm.sum(axis=1)))
    k = np.ones(ease_cm.shape[1], bool) if key is None else np.asarray(key, bool)
    dist = np.abs(ease_cm - design_cm)[:, k].sum(axis=1)
    if by_chart is not None:
        dist = dist + by_chart
    dist[~ok] = np.inf
    return int(np.argmin(dist))


_REGION_SPECS: dict[int, tuple[object, RegionSpec]] = {}


def region_spec(model) -> RegionSpec:
    """The :class:`RegionSpec` of a body model (made once per model)."""
    hit = _REGION_SPECS.get(id(model))
    if hit is None or hit[0] is not model:
        hit = (model, RegionSpec(model))
        _REGION_SPECS[id(model)] = hit
    return hit[1]  # type: ignore[return-value]


def girths_of_body(model, X: np.ndarray) -> np.ndarray:
    """(R,) a body's girths and lengths (cm) at ``REGIONS`` (X (V, 3) metres): the tapes of
    :class:`RegionSpec`, then ``lengths.body_lengths``."""
    return np.concatenate([body_girths(region_spec(model).regions(X)), body_lengths(model.measurement_spec, X)])


def sized_garment_fit(model, rests: np.ndarray, faces: np.ndarray, bodies_on: np.ndarray, labels: list[str],
                      base: int, base_body: np.ndarray, fabric: str, measurements: list[str] | None = None) -> SizeFit:
    """The :class:`SizeFit` of a garment in sizes: rest shapes (S, M, 3) each on its body
    ``bodies_on`` (S, V, 3) (or one body (V, 3) for all), the base size's own body (V, 3)."""
    rs = region_spec(model)
    sections = GarmentSections(faces, rests.shape[1])
    bodies_on = np.asarray(bodies_on)
    thigh = GIRTH_REGIONS.index("thigh")
    rows = []
    for s in range(len(rests)):
        X = bodies_on[s] if bodies_on.ndim == 3 else bodies_on
        regions = rs.regions(X)
        g = garment_girths(sections, rests[s], regions)
        frame = LengthFrame.of(model, X, np.stack([regions[r].centre for r in ("chest", "waist", "hip")]))
        V = np.asarray(rests[s], np.float64)
        around = lambda n, o, c, x: sections.girth(V, Region(n, float(o), c, x)) is not None  # noqa: E731
        rows.append(np.concatenate([g, garment_lengths(around, frame, legs=bool(np.isfinite(g[thigh])))]))
    return size_fit(labels, np.stack(rows), base, girths_of_body(model, base_body), fabric, measurements)


# EN 13402-3:2013 "Size designation of clothes - Part 3: Size designation of clothes for
# body measurements" (CEN/TC 248), letter codes XS to XL: the body-dimension intervals a letter
# size is made for; a size made for an interval is made for its middle. Tops and whole-body
# garments by chest girth (men) or bust girth (women), 8 cm intervals; bottoms by waist girth,
# 6 cm intervals. The demo catalogue (``service.model.garments.demo_sizes``) and `tryon bench
# sizes` use these middles as size charts.
EN13402_3_LETTER_CHEST_CM: dict[str, tuple[float, float]] = {
    "XS": (78.0, 86.0), "S": (86.0, 94.0), "M": (94.0, 102.0), "L": (102.0, 110.0), "XL": (110.0, 118.0),
}
EN13402_3_LETTER_WAIST_CM: dict[str, tuple[float, float]] = {
    "XS": (64.0, 70.0), "S": (70.0, 76.0), "M": (76.0, 82.0), "L": (82.0, 88.0), "XL": (88.0, 94.0),
}


def en13402_chart(measurement: str = "chest_cm") -> dict[str, dict[str, float]]:
    """The EN 13402-3 letter sizes XS-XL as a size chart of ``measurement`` (the chest or bust
    intervals' middles, cm; ``waist_cm``: the waist intervals')."""
    table = EN13402_3_LETTER_WAIST_CM if measurement == "waist_cm" else EN13402_3_LETTER_CHEST_CM
    return {k: {measurement: (lo + hi) / 2} for k, (lo, hi) in table.items()}


def nearest_size(chart: dict[str, dict[str, float]], body: dict[str, float]) -> str:
    """The label of the size of ``chart`` (label -> measurements, cm) whose measurements are
    nearest those of ``body`` (name -> value, cm; Euclidean over the chart's measurements):
    the size of a garment made on that body."""
    def dist(ms: dict[str, float]) -> float:
        return math.sqrt(sum((v - float(body[k])) ** 2 for k, v in ms.items()))
    return min(chart, key=lambda label: dist(chart[label]))


# -- the fit map -----------------------------------------------------------------------------
# ease map: the gap (metres) between cloth and body where a fabric sits as designed (green),
# from the fit thresholds' middle of "fit" on a 95 cm girth (gap = ease / 2 pi), and where it
# hangs (blue). Red at contact (the try-on's clearance, 3 mm, or less).
EASE_MAP_CONTACT_M = 0.003
EASE_MAP_HANG_M = 0.06
FITMAP_KINDS = ("strain", "ease")
_RED, _GREEN, _BLUE = np.array([1.0, 0.0, 0.0]), np.array([0.0, 0.8, 0.1]), np.array([0.05, 0.2, 1.0])


def fit_gap_m(fabric: str, girth_cm: float = 95.0) -> float:
    """The cloth-to-body gap (metres) of a fabric's designed fit: the middle of its ``fit``
    ease band on a girth of ``girth_cm`` spread around it (ease / 2 pi), at least the contact
    gap."""
    th = FIT_THRESHOLDS[fabric]
    mid_pct = (th.tight_pct + th.loose_pct) / 2
    return max(EASE_MAP_CONTACT_M * 2, girth_cm / 100 * mid_pct / 100 / (2 * np.pi))


def _rgba(rgb: np.ndarray) -> np.ndarray:
    out = np.full((len(rgb), 4), 255, np.uint8)
    out[:, :3] = np.clip(np.round(rgb * 255), 0, 255).astype(np.uint8)
    return out


def strain_colors(strain: np.ndarray, fabric: str) -> np.ndarray:
    """COLOR_0 (M, 4) uint8 of a strain map (as CLO's): blue at rest to red at the fabric's
    stretch limit (``FitThresholds.strain_limit_pct``), through green."""
    t = np.clip(np.asarray(strain, np.float64) / (FIT_THRESHOLDS[fabric].strain_limit_pct / 100), 0.0, 1.0)[:, None]
    lo = _BLUE + (_GREEN - _BLUE) * np.clip(2 * t, 0, 1)
    hi = _GREEN + (_RED - _GREEN) * np.clip(2 * t - 1, 0, 1)
    return _rgba(np.where(t < 0.5, lo, hi))


def ease_colors(gap_m: np.ndarray, fabric: str) -> np.ndarray:
    """COLOR_0 (M, 4) uint8 of an ease map: red where the cloth presses the body (gap <=
    ``EASE_MAP_CONTACT_M``), green at the fabric's designed gap (:func:`fit_gap_m`), blue where
    it hangs (>= ``EASE_MAP_HANG_M``)."""
    g = np.asarray(gap_m, np.float64)[:, None]
    mid = fit_gap_m(fabric)
    a = np.clip((g - EASE_MAP_CONTACT_M) / (mid - EASE_MAP_CONTACT_M), 0, 1)
    b = np.clip((g - mid) / (EASE_MAP_HANG_M - mid), 0, 1)
    return _rgba(np.where(g < mid, _RED + (_GREEN - _RED) * a, _GREEN + (_BLUE - _GREEN) * b))


def body_gap(vertices: np.ndarray, body_vertices: np.ndarray, body_normals: np.ndarray,
             nearest: np.ndarray) -> np.ndarray:
    """(M,) signed gap (metres) of garment vertices (M, 3) over the body: along the normal of
    each one's nearest body vertex (``nearest`` (M,) ids)."""
    d = np.asarray(vertices, np.float64) - np.asarray(body_vertices, np.float64)[nearest]
    return np.einsum("ij,ij->i", d, np.asarray(body_normals, np.float64)[nearest])

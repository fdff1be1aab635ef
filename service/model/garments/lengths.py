"""Lengths of a garment and of a body: sleeve, inseam, hem (the length regions of the fit report).

Pure numpy (no web, queue or storage imports). Each length is where a part of the garment ends
on the body it sits on, measured the way the body's own length is measured
(``service.model.body.measurements``), so that ``garment length - body length`` is how far the
garment ends past (positive) or short of (negative) the body landmark:

- **sleeve**: the left sleeve's end along the arm from the shoulder tip, as the sleeve outseam
  ``arm_length_cm`` (acromion -> radiale -> stylion): the radiale -> stylion stretch is
  followed by planes across the forearm (perpendicular to the elbow -> wrist joint axis); the
  sleeve ends at the last plane where the cloth still goes all around the arm. Body: the
  customer's ``arm_length_cm`` (ends at the wrist bone).
- **inseam**: the left trouser leg's inside length from the crotch down: crotch height minus
  the height of the last horizontal plane where the leg still goes all around the left leg and
  not the right one. Body: ``inseam_cm`` (crotch to floor).
- **hem**: the garment's drop from the waist (navel level, as ``waist_height_cm``) to the last
  horizontal plane where it still goes all around the body (tops, dresses, skirts; not
  trousers). Body: the rise, waist to crotch (``waist_height_cm - inseam_cm``): the ease is
  how far below the crotch the hem sits (negative: above it, as every top's).

A garment has a length region only where it reaches far enough for the length to be a fit
question (:data:`SLEEVE_MIN_FOREARM`, :data:`INSEAM_MIN_SHIN`): a T-shirt's sleeve or a pair of
shorts is not "too short". The garment lengths of each size are measured once at the build
(a few dozen plane sections per size), the body lengths once per customer body.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from service.model.body import measurements as M
from service.model.body.model import BONES

# the length regions, in report order (after the girths of ``sizing``)
LENGTH_REGIONS = ("sleeve", "inseam", "hem")
# around(normal (3,), offset, centre (3,), exclude (3,) | None) -> whether the garment's plane
# section ``normal . x = offset`` has a loop all around ``centre`` and not ``exclude``
# (``sizing.GarmentSections.girth`` of a garment's rest shape)
Around = Callable[[np.ndarray, float, np.ndarray, "np.ndarray | None"], bool]

# a sleeve is a fit question when it goes all around the forearm at least this far from the
# elbow (radiale, 0) to the wrist (stylion, 1): long sleeves reach ~1; three-quarter sleeves
# end around the middle of the forearm and are meant to (Aldrich, "Metric Pattern Cutting for
# Menswear": 3/4 sleeve = elbow to mid-forearm), T-shirt sleeves above the elbow
SLEEVE_MIN_FOREARM = 0.7
# how far past the wrist the sleeve scan goes (m): a sleeve longer than that is too long anyway
SLEEVE_PAST_WRIST_M = 0.15
# trousers' inseam is a fit question when the leg goes all around the shin at least this far
# from the knee (0) to the ankle joint (1): full-length trousers reach ~1, capris (mid-calf,
# ~0.5) and shorts do not
INSEAM_MIN_SHIN = 0.75
# plane scan step (m) and bisection steps after it: 2 cm / 2**4 = 1.25 mm resolution
SCAN_STEP_M = 0.02
REFINE_STEPS = 4
# a section may miss a loop at an odd plane (one through a vertex, an open chain whose few
# crossing points leave a sector of ``sizing.COVER_SECTORS`` empty): the scan goes on over
# misses up to this long (m) before it calls the garment ended
MAX_GAP_M = 0.07
# the body lengths, read by the body's own measurement function (``measurements.measure``)
BODY_LENGTH_NAMES = ("arm_length_cm", "inseam_cm", "waist_height_cm")
_BONE = {n: i for i, n in enumerate(BONES)}


def body_lengths(spec: M.MeasurementSpec, X: np.ndarray) -> np.ndarray:
    """(3,) the body lengths (cm) at ``LENGTH_REGIONS`` of a body X (V, 3) metres: sleeve
    outseam, inseam (crotch height) and rise (waist height - crotch height), by
    ``measurements.measure``."""
    # gender only picks the density of the weight, which is not measured here
    raw = M.measure(spec, np.asarray(X, np.float64), "female", names=BODY_LENGTH_NAMES, extras=False)
    row = {n: i for i, n in enumerate(M.RAW_NAMES)}
    arm, inseam, waist = (100.0 * raw[row[n]] for n in BODY_LENGTH_NAMES)
    return np.array([arm, inseam, waist - inseam])


@dataclass
class LengthFrame:
    """A body's landmarks and joints that the length scans follow (metres)."""

    arm_to_elbow: float  # acromion -> radiale
    forearm: float  # radiale -> stylion
    elbow: np.ndarray  # (3,) elbow joint (left)
    wrist: np.ndarray  # (3,) wrist joint (left)
    axis: np.ndarray  # (3,) unit elbow -> wrist joint axis
    radiale: float  # the landmarks' positions along ``axis``
    stylion: float
    chest: np.ndarray  # (3,) chest joint: a sleeve's loop must not go around it
    legs: np.ndarray  # (2, 3, 3) hip, knee, ankle joints of the left and right leg
    crotch_y: float
    navel_y: float
    floor_y: float
    centres: np.ndarray  # (3, 3) the chest, waist and hip sections' centres: hem loops go around them

    @classmethod
    def of(cls, model, X: np.ndarray, centres: np.ndarray) -> "LengthFrame":
        """The frame of a body X (V, 3) whose chest, waist and hip sections' centres are
        ``centres`` (3, 3) (``sizing.RegionSpec.regions``), top to bottom."""
        X = np.asarray(X, np.float64)
        spec = model.measurement_spec
        J = model.joints(X)
        b = _BONE
        acr, rad, sty = X[int(spec.acromion[0])], X[spec.elbow], X[spec.wrist]
        elbow, wrist = J[b["forearm_l"]], J[b["hand_l"]]
        axis = (wrist - elbow) / np.linalg.norm(wrist - elbow)
        legs = np.stack([J[[b["thigh_l"], b["shin_l"], b["foot_l"]]], J[[b["thigh_r"], b["shin_r"], b["foot_r"]]]])
        return cls(float(np.linalg.norm(rad - acr)), float(np.linalg.norm(sty - rad)), elbow, wrist, axis,
                   float(rad @ axis), float(sty @ axis), J[b["chest"]], legs, float(X[spec.crotch, 1]),
                   float(X[spec.navel, 1]), float(X[spec.soles, 1].min()), np.asarray(centres, np.float64))

    def hem_centre(self, y: float) -> np.ndarray:
        """(3,) the point at height y that a hem loop goes around: the chest, waist and hip
        sections' centres interpolated in height (the hip's below it, between the legs)."""
        c = self.centres[::-1]  # bottom to top: increasing heights for np.interp
        return np.array([np.interp(y, c[:, 1], c[:, 0]), y, np.interp(y, c[:, 1], c[:, 2])])


def _leg_point(leg: np.ndarray, y: float) -> np.ndarray:
    """(3,) the point of a leg's hip -> knee -> ankle joint chain (3, 3) at height y (the
    ankle's below it)."""
    hip, knee, ankle = leg
    a, b = (hip, knee) if y >= knee[1] else (knee, ankle)
    t = np.clip((a[1] - y) / (a[1] - b[1]), 0.0, 1.0)
    return a + t * (b - a)


def _last(loop: Callable[[float], bool], lo: float, hi: float) -> float | None:
    """The largest s in [lo, hi] where ``loop(s)`` holds, scanning up from lo by
    ``SCAN_STEP_M`` over misses of at most ``MAX_GAP_M`` (None when it does not hold within
    that of lo), then bisecting between the last hit and the miss after it."""
    ok: float | None = None
    s = lo
    while s <= hi + 1e-9 and s - (lo if ok is None else ok) <= MAX_GAP_M + 1e-9:
        if loop(s):
            ok = s
        s += SCAN_STEP_M
    if ok is None:
        return None
    bad = ok + SCAN_STEP_M
    if bad > hi:
        return ok
    for _ in range(REFINE_STEPS):
        mid = (ok + bad) / 2
        ok, bad = (mid, bad) if loop(mid) else (ok, mid)
    return ok


def garment_lengths(around: Around, frame: LengthFrame, legs: bool) -> np.ndarray:
    """(3,) a garment's lengths (cm) at ``LENGTH_REGIONS`` on the body of ``frame``, its plane
    sections given by ``around`` (:data:`Around`); ``legs``: the garment goes around one thigh
    (trousers: no hem). NaN where it has no such length (see the module's rules)."""
    out = np.full(len(LENGTH_REGIONS), np.nan)
    fr = frame

    # sleeve: planes across the forearm at s metres along the elbow -> wrist axis
    def sleeve(s: float) -> bool:
        c = fr.elbow + (s - fr.elbow @ fr.axis) * fr.axis
        return around(fr.axis, s, c, fr.chest)

    span = fr.stylion - fr.radiale
    end = _last(sleeve, fr.radiale, fr.stylion + SLEEVE_PAST_WRIST_M)
    if end is not None and (end - fr.radiale) / span >= SLEEVE_MIN_FOREARM:
        out[0] = 100.0 * (fr.arm_to_elbow + fr.forearm * (end - fr.radiale) / span)

    # inseam: horizontal planes d metres below the left knee, around the left leg, not the right
    knee_y = fr.legs[0, 1, 1]

    def leg(d: float) -> bool:
        y = knee_y - d
        return around(M.Y, y, _leg_point(fr.legs[0], y), _leg_point(fr.legs[1], y))

    shin = knee_y - fr.legs[0, 2, 1]
    end = _last(leg, 0.0, knee_y - fr.floor_y)
    if end is not None and end / shin >= INSEAM_MIN_SHIN:
        out[1] = 100.0 * (fr.crotch_y - (knee_y - end))

    # hem: horizontal planes d metres below the highest of chest, waist, hip the garment goes
    # around, around the body (between the legs below the crotch)
    if not legs:
        for top in fr.centres[:, 1]:
            def hem(d: float, top: float = top) -> bool:
                return around(M.Y, top - d, fr.hem_centre(top - d), None)

            end = _last(hem, 0.0, top - fr.floor_y)
            if end is not None:
                out[2] = 100.0 * (fr.navel_y - (top - end))
                break
    return out

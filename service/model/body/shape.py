"""Tailor measurements -> PCA weights (once per customer).

1. Validate: known names, numbers, finite, inside the accepted range (``MeasurementError``).
2. Condition the population's joint Gaussian of (attributes, PCA weights) on whatever subset
   was given (gender as 0 = female, 1 = male); the Gaussian is that of the avatars fitted to
   ANSUR II training subjects (see ``_prior``). With all 12 given this is the editing paper's
   linear regression from biometric attributes to shape (Sec. 4.1); with none, the population
   mean.
3. Refine by Gauss-Newton so the avatar re-measures what was entered:
   min_w  sum_i ((m_i(w) - t_i) / tol_i)^2 + prior_weight * |L^-1 (w - w_c)|^2
   with tol_i the ISO 20685-1 allowable error and L L^T the conditional covariance.
4. The attributes not given are estimated by measuring the final avatar.

``refine`` takes the same Gauss-Newton steps as the slow, obvious ``refine_reference`` (kept
with ``avatar_from_measurements_reference`` for tests and benchmarks), computed cheaply: the
Jacobians come from the measurements as functions of the weights (``WeightMeasures``,
precomputed once per body model: the ~3,500 vertices the measurements read, and the weight
from the volume as a polynomial of w), and each iterate is measured exactly on the whole avatar
without a Jacobian. That exact measurement is what the customer gets.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from service.model.body import measurements as M
from service.model.geometry.solvers import prior_gauss_newton_step


@dataclass(frozen=True)
class RefineParams:
    """Weights and limits of the refinement (step 3 of the module docstring)."""

    iterations: int = 8  # Gauss-Newton steps at most
    tol_fraction: float = 0.2  # done when every entered attribute is within this share of its ISO tolerance
    prior_weight: float = 0.02  # weight of the conditional prior |L^-1 (w - w_c)|^2
    cov_jitter: float = 1e-8  # added to the conditional covariance's diagonal before inverting it


REFINE = RefineParams()
VOLUME_CUBIC_COMPONENTS = 20  # WeightMeasures' volume polynomial: cubic terms of this many components
GENDER_CODE = {"female": 0.0, "male": 1.0}


class MeasurementError(ValueError):
    """Bad measurement input: ``field`` names the attribute, ``message`` says why."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


@dataclass
class AvatarFit:
    """Result of ``avatar_from_measurements``.

    weights: (K,) float64; measurements: the 12 attributes re-measured (API units);
    estimated: names not given; vertices: (V, 3) float32; gender: "female" / "male"."""

    weights: np.ndarray
    measurements: dict
    estimated: list[str]
    vertices: np.ndarray
    gender: str


def validate_measurements(model, raw) -> dict:
    """Checked copy of the customer's measurements (API units), or ``MeasurementError``."""
    if raw is None:
        return {}
    if not isinstance(raw, dict):
        raise MeasurementError("measurements", "must be an object of attribute: value")
    specs = {a.name: a for a in model.attributes}
    out: dict = {}
    for name, value in raw.items():
        if name not in specs:
            raise MeasurementError(name, f"unknown attribute; known: {', '.join(M.ATTRIBUTES)}")
        if name == "gender":
            if value not in GENDER_CODE:
                raise MeasurementError(name, 'must be "female" or "male"')
            out[name] = value
            continue
        spec = specs[name]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise MeasurementError(name, f"must be a number in {spec.unit}")
        v = float(value)
        if not math.isfinite(v):
            raise MeasurementError(name, "must be a finite number")
        if not spec.min <= v <= spec.max:
            raise MeasurementError(
                name, f"{v:g} {spec.unit} is outside the allowed range {spec.min:g}-{spec.max:g} {spec.unit}"
            )
        out[name] = v
    return out


@dataclass
class JointGaussian:
    """Population Gaussian over x = (gender code, 11 attributes in API units, K weights)."""

    mean: np.ndarray  # (12 + K,)
    cov: np.ndarray  # (12 + K, 12 + K)
    n_attr: int = len(M.ATTRIBUTES)

    @classmethod
    def from_population(cls, attributes: np.ndarray, weights: np.ndarray) -> "JointGaussian":
        """attributes: (N, 12) with column 0 the gender code; weights: (N, K)."""
        X = np.hstack([attributes, weights]).astype(np.float64)
        return cls(X.mean(0), np.cov(X, rowvar=False))

    def condition(self, given: dict[int, float], noise: dict[int, float]) -> tuple[np.ndarray, np.ndarray]:
        """Mean (12 + K,) and covariance of x given x_S = values (index -> value), with
        observation noise variances ``noise`` (index -> variance)."""
        if not given:
            return self.mean.copy(), self.cov.copy()
        S = np.array(sorted(given))
        xs = np.array([given[i] for i in S])
        Sss = self.cov[np.ix_(S, S)] + np.diag([noise.get(i, 0.0) for i in S])
        Sxs = self.cov[:, S]
        gain = np.linalg.solve(Sss, Sxs.T).T  # (D, |S|)
        mean = self.mean + gain @ (xs - self.mean[S])
        cov = self.cov - gain @ Sxs.T
        return mean, cov


@functools.lru_cache(maxsize=4)
def _prior(model) -> JointGaussian:
    """The Gaussian of the avatars fitted to ANSUR II training subjects (the population's first
    rows). The heavy civilians that follow extend the shape space, but only 4 of their 12
    attributes were measured (the rest are the body model's defaults), so they stay out of
    the attribute regression."""
    n = int(model.meta["population"]["ansur_training"])
    return JointGaussian.from_population(model.population["attributes"][:n], model.population["weights"][:n])


def _gender_code(attrs: dict) -> float:
    return GENDER_CODE[attrs["gender"]]


# -- the measurements as functions of the weights -----------------------------------------------
WEIGHT_ROW = M.RAW_NAMES.index("weight_kg")


class WeightMeasures:
    """The raw measurements (``M.RAW_NAMES``) as functions of the PCA weights w (K,), for the
    refinement's Jacobian: the restricted measurement spec (``MeasurementSpec.restrict``) on
    ``mean + w . components`` of only the vertices it reads, and the weight from the volume
    polynomial (``M.VolumePolynomial``). Exact but for the weight (the polynomial's dropped
    cubic terms: grams) and float32 rounding. Built once per body model (``weight_measures``).

    Arrays: mean (3R,) float32, basis (K, 3R) float32 (the components at the R vertices),
    basis_T (3R, K) float64 (d vertices / d w, for Jacobians)."""

    def __init__(self, model, n_cubic: int = VOLUME_CUBIC_COMPONENTS):
        self.spec, self.ids = model.measurement_spec.restrict()
        K = model.n_components
        self.mean = np.ascontiguousarray(model.mean[self.ids].reshape(-1))
        self.basis = np.ascontiguousarray(model.components[:, self.ids].reshape(K, -1))
        self.basis_T = np.ascontiguousarray(self.basis.T, dtype=np.float64)
        nb = model.n_body_vertices
        self.volume = M.VolumePolynomial.fit(model.mean[:nb], model.components[:, :nb], model.body_faces, n_cubic)

    def measure(self, w: np.ndarray, gender: str, jacobian: bool = False, names=None):
        """Raw measurements (len(RAW_NAMES),) at weights w (K,); with ``jacobian`` also
        d measurements / d w (len(RAW_NAMES), K). Only ``names`` (default: the 11 attributes)
        are measured, the others left 0."""
        x = (self.mean + np.asarray(w, np.float32) @ self.basis).reshape(-1, 3)
        res = M.measure(self.spec, x, gender, jacobian, basis=self.basis_T, extras=False, names=names)
        raw, J = res if jacobian else (res, None)
        vol, dvol = self.volume(w)
        raw[WEIGHT_ROW] = M.DENSITY[gender] * vol
        if jacobian:
            J[WEIGHT_ROW] = M.DENSITY[gender] * dvol
            return raw, J
        return raw


@functools.lru_cache(maxsize=4)
def weight_measures(model) -> WeightMeasures:
    """The body model's ``WeightMeasures`` (built once per process and model, ~0.5 s)."""
    return WeightMeasures(model)


def precompute(model) -> None:
    """Build what ``avatar_from_measurements`` needs once per body model (the population
    prior, ``WeightMeasures``): call where the model is loaded, before forking workers, so that
    no request pays for it."""
    _prior(model)
    weight_measures(model)


# -- refinement ----------------------------------------------------------------------------------
@dataclass
class Refined:
    """Result of ``refine``: weights (K,) float64, the avatar's vertices (V, 3) float32, its
    raw measurements (``M.measure`` of those vertices, breadths/depths 0), Gauss-Newton steps
    taken and Jacobians evaluated."""

    weights: np.ndarray
    vertices: np.ndarray
    raw: np.ndarray
    steps: int = 0
    jacobians: int = 0


def _targets(targets: dict[str, float]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows of the entered attributes in the raw vector, their values and ISO tolerances
    (raw units: m, kg)."""
    names = [n for n in M.RAW_NAMES[:11] if n in targets]
    idx = np.array([M.RAW_NAMES.index(n) for n in names], np.int64)
    t = np.array([targets[n] / M.api_scale(n) for n in names])
    tol = np.array([M.ISO_TOLERANCE[n] for n in names])
    return idx, t, tol


def _exact(model, w: np.ndarray, gender: str) -> tuple[np.ndarray, np.ndarray]:
    """The avatar of weights w (V, 3) float32 and its raw measurements, measured exactly."""
    X = model.vertices(w)
    return X, M.measure(model.measurement_spec, X, gender, extras=False)


def refine(model, w0: np.ndarray, cov_w: np.ndarray, targets: dict[str, float], gender: str,
           params: RefineParams = REFINE) -> Refined:
    """Gauss-Newton refinement of PCA weights so the avatar measures ``targets`` (API units).

    w0: (K,) start and prior mean; cov_w: (K, K) prior covariance. The steps of
    ``refine_reference``, computed cheaply: each step's Jacobian comes from ``WeightMeasures``
    (a few thousand vertices, weights as the unknowns, the volume as a polynomial) and each
    iterate is measured exactly on the whole avatar, without a Jacobian. Stops when all entered
    attributes are within ``tol_fraction`` of their ISO tolerance (on the exact measurement),
    or after ``iterations`` steps."""
    w = np.asarray(w0, np.float64).copy()
    idx, t, tol = _targets(targets)
    if not len(idx):
        return Refined(w, *_exact(model, w, gender))
    space = weight_measures(model)
    C = cov_w + params.cov_jitter * np.eye(len(w))
    names = [M.RAW_NAMES[i] for i in idx]
    raw, J = space.measure(w, gender, jacobian=True, names=names)  # at w0: exact but for the weight (grams)
    X, steps, jacobians = None, 0, 1  # X: the avatar at w once raw is its exact measurement
    while True:
        r = (raw[idx] - t) / tol
        if np.all(np.abs(r) <= params.tol_fraction):
            if X is not None:
                break
            X, raw = _exact(model, w, gender)  # converged at w0: confirm on the exact measurement
            continue
        if steps >= params.iterations:
            break
        if J is None:
            _, J = space.measure(w, gender, jacobian=True, names=names)
            jacobians += 1
        w = prior_gauss_newton_step(w, w0, r, J[idx] / tol[:, None], C, params.prior_weight)
        J = None
        X, raw = _exact(model, w, gender)
        steps += 1
    if X is None:  # iterations == 0
        X, raw = _exact(model, w, gender)
    return Refined(w, X, raw, steps, jacobians)


def refine_reference(model, w0: np.ndarray, cov_w: np.ndarray, targets: dict[str, float], gender: str,
                     iterations: int | None = None, params: RefineParams = REFINE) -> np.ndarray:
    """The slow, obvious refinement (tests and benchmarks): a Jacobian of the whole mesh at
    every step. w0: (K,) start and prior mean; cov_w: (K, K) prior covariance. Returns weights (K,)."""
    idx, t, tol = _targets(targets)
    if not len(idx):
        return w0
    K = len(w0)
    evals, evecs = np.linalg.eigh(cov_w + params.cov_jitter * np.eye(K))
    Linv = (evecs / np.sqrt(np.maximum(evals, params.cov_jitter))).T  # whitening
    P = params.prior_weight * Linv.T @ Linv
    UT = model.components_T  # (3V, K)
    w = w0.astype(np.float64).copy()
    for _ in range(iterations or params.iterations):
        X = model.vertices(w)
        m, JX = M.measure(model.measurement_spec, X, gender, jacobian=True)
        r = (m[idx] - t) / tol
        if np.all(np.abs(r) <= params.tol_fraction):
            break
        Jw = np.asarray(JX[idx] @ UT) / tol[:, None]
        A = Jw.T @ Jw + P
        g = Jw.T @ r + P @ (w - w0)
        w -= np.linalg.solve(A, g)
    return w


# -- measurements -> avatar ----------------------------------------------------------------------
def _condition(model, given: dict) -> tuple[str, np.ndarray, np.ndarray]:
    """Step 2: (gender, conditional mean of the weights w_c (K,), their covariance (K, K))."""
    prior = _prior(model)
    nA = len(M.ATTRIBUTES)
    cond: dict[int, float] = {}
    noise: dict[int, float] = {}
    for i, name in enumerate(M.ATTRIBUTES):
        if name in given:
            cond[i] = _gender_code(given) if name == "gender" else given[name]
            if name != "gender":
                noise[i] = (M.ISO_TOLERANCE[name] * M.api_scale(name)) ** 2
    mean, cov = prior.condition(cond, noise)
    gender = given.get("gender") or ("male" if mean[0] >= 0.5 else "female")
    if "gender" not in given and cond:
        # condition on the estimated gender too, so the shape is consistent with it (with
        # nothing given at all the answer stays the population mean)
        cond[0] = GENDER_CODE[gender]
        mean, cov = prior.condition(cond, noise)
    return gender, mean[nA:], cov[nA:, nA:]


def avatar_from_measurements(model, measurements, params: RefineParams = REFINE) -> AvatarFit:
    """Any subset of the 12 attributes -> avatar (see module docstring)."""
    given = validate_measurements(model, measurements)
    gender, w0, cov_w = _condition(model, given)
    numeric = {k: v for k, v in given.items() if k != "gender"}
    fit = refine(model, w0, cov_w, numeric, gender, params)
    estimated = [n for n in M.ATTRIBUTES if n not in given]
    return AvatarFit(weights=fit.weights, measurements=M.to_api_units(fit.raw, gender), estimated=estimated,
                     vertices=fit.vertices, gender=gender)


def avatar_from_measurements_reference(model, measurements) -> AvatarFit:
    """``avatar_from_measurements`` with ``refine_reference`` (the slow path before the fast
    one): the baseline of tests and benchmarks."""
    given = validate_measurements(model, measurements)
    gender, w0, cov_w = _condition(model, given)
    numeric = {k: v for k, v in given.items() if k != "gender"}
    w = refine_reference(model, w0, cov_w, numeric, gender)
    X = model.vertices(w)
    measured = model.measure(X, gender)
    estimated = [n for n in M.ATTRIBUTES if n not in given]
    return AvatarFit(weights=w, measurements=measured, estimated=estimated, vertices=X, gender=gender)


def estimate_gender(model, weights: np.ndarray) -> str:
    """The population's more likely gender for a shape (the joint Gaussian conditioned on the
    weights): 'female' or 'male'."""
    prior = _prior(model)
    n_attr = len(M.ATTRIBUTES)
    w = np.asarray(weights, np.float64)
    cond = {n_attr + k: float(w[k]) for k in range(len(w))}
    mean, _ = prior.condition(cond, {i: 1e-6 for i in cond})
    return "male" if mean[0] >= 0.5 else "female"

"""Tailor measurements -> PCA weights (once per customer).

1. Validate: known names, numbers, finite, inside the accepted range (``MeasurementError``).
2. Condition the population's joint Gaussian of (attributes, PCA weights) on whatever subset
   was given (gender as 0 = female, 1 = male); the Gaussian is that of the avatars fitted to
   ANSUR II training subjects (see ``_prior``). With all 12 given this is the editing paper's
   linear regression from biometric attributes to shape (Sec. 4.1); with none, the population
   mean.
3. Refine by Gauss-Newton so the avatar re-measures what was entered:
   min_w  sum_i ((m_i(w) - t_i) / tol_i)^2 + PRIOR_WEIGHT * |L^-1 (w - w_c)|^2
   with tol_i the ISO 20685-1 allowable error and L L^T the conditional covariance.
4. The attributes not given are estimated by measuring the final avatar.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from service.model import measurements as M

PRIOR_WEIGHT = 0.02
REFINE = {"iterations": 8, "tol_fraction": 0.2, "cov_jitter": 1e-8}
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


def refine(model, w0: np.ndarray, cov_w: np.ndarray, targets: dict[str, float], gender: str,
           iterations: int | None = None) -> np.ndarray:
    """Gauss-Newton refinement of PCA weights so the avatar measures ``targets`` (API units).

    w0: (K,) start and prior mean; cov_w: (K, K) prior covariance. Returns weights (K,)."""
    names = [n for n in M.RAW_NAMES[:11] if n in targets]
    if not names:
        return w0
    idx = np.array([M.RAW_NAMES.index(n) for n in names])
    t = np.array([targets[n] / M.api_scale(n) for n in names])
    tol = np.array([M.ISO_TOLERANCE[n] for n in names])
    K = len(w0)
    evals, evecs = np.linalg.eigh(cov_w + REFINE["cov_jitter"] * np.eye(K))
    Linv = (evecs / np.sqrt(np.maximum(evals, REFINE["cov_jitter"]))).T  # whitening
    P = PRIOR_WEIGHT * Linv.T @ Linv
    UT = model.components_T  # (3V, K)
    w = w0.astype(np.float64).copy()
    for _ in range(iterations or REFINE["iterations"]):
        X = model.vertices(w)
        m, JX = M.measure(model.measurement_spec, X, gender, jacobian=True)
        r = (m[idx] - t) / tol
        if np.all(np.abs(r) <= REFINE["tol_fraction"]):
            break
        Jw = np.asarray(JX[idx] @ UT) / tol[:, None]
        A = Jw.T @ Jw + P
        g = Jw.T @ r + P @ (w - w0)
        w -= np.linalg.solve(A, g)
    return w


def avatar_from_measurements(model, measurements) -> AvatarFit:
    """Any subset of the 12 attributes -> avatar (see module docstring)."""
    given = validate_measurements(model, measurements)
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
    w0 = mean[nA:]
    cov_w = cov[nA:, nA:]
    numeric = {k: v for k, v in given.items() if k != "gender"}
    w = refine(model, w0, cov_w, numeric, gender)
    X = model.vertices(w)
    measured = model.measure(X, gender)
    estimated = [n for n in M.ATTRIBUTES if n not in given]
    return AvatarFit(weights=w, measurements=measured, estimated=estimated, vertices=X, gender=gender)

"""Measurements -> shape: validation, Gaussian conditioning (against the precision-matrix
formula), refinement to ISO tolerances, estimates of what was not given."""
from __future__ import annotations

import math

import numpy as np
import pytest

from service.bench import read_ansur
from service.model import measurements as M
from service.model import shape as S





@pytest.mark.parametrize("bad, field, words", [
    ({"shoe_size": 42}, "shoe_size", "unknown"),
    ({"height_cm": "tall"}, "height_cm", "number"),
    ({"height_cm": True}, "height_cm", "number"),
    ({"height_cm": math.nan}, "height_cm", "finite"),
    ({"weight_kg": math.inf}, "weight_kg", "finite"),
    ({"height_cm": 20}, "height_cm", "allowed range"),
    ({"waist_cm": 1e9}, "waist_cm", "allowed range"),
    ({"gender": "other"}, "gender", "female"),
    ([1, 2], "measurements", "object"),
])
def test_bad_measurements_name_the_field(model, bad, field, words):
    with pytest.raises(S.MeasurementError) as e:
        S.avatar_from_measurements(model, bad)
    assert e.value.field == field
    assert words in e.value.message
    if "range" in words:
        spec = {a.name: a for a in model.attributes}[field]
        assert f"{spec.min:g}" in e.value.message and f"{spec.max:g}" in e.value.message


def test_nothing_given_is_the_population_mean(model):
    fit = S.avatar_from_measurements(model, {})
    n = model.meta["population"]["ansur_training"]
    surveyed_mean = model.population["weights"][:n].mean(axis=0)  # the ANSUR II people
    np.testing.assert_allclose(fit.weights, surveyed_mean, atol=1e-6)
    # and near the shape space's origin (which also averages in the heavy civilians)
    assert np.all(np.abs(fit.weights) < 0.5 * np.sqrt(model.variances))
    assert fit.estimated == list(M.ATTRIBUTES)
    assert set(fit.measurements) == set(M.ATTRIBUTES)


def test_conditioning_matches_precision_formula(model):
    g = S._prior(model)
    rng = np.random.default_rng(2)
    D = len(g.mean)
    S_idx = [0, 1, 2, 5]
    x_s = g.mean[S_idx] + rng.normal(size=4) * np.sqrt(np.diag(g.cov)[S_idx])
    mean, cov = g.condition(dict(zip(S_idx, x_s)), {})
    # reference: conditional of a Gaussian via its precision matrix (ridge for conditioning)
    cov_r = g.cov + 1e-9 * np.eye(D)
    Lam = np.linalg.inv(cov_r)
    R = [i for i in range(D) if i not in S_idx]
    ref = g.mean[R] - np.linalg.solve(Lam[np.ix_(R, R)], Lam[np.ix_(R, S_idx)] @ (x_s - g.mean[S_idx]))
    np.testing.assert_allclose(mean[R], ref, rtol=1e-4, atol=1e-4 * np.abs(ref).max())
    np.testing.assert_allclose(mean[S_idx], x_s, atol=1e-6)


def test_some_given_are_reproduced_and_the_rest_estimated(model):
    q = {"gender": "female", "height_cm": 163.0, "weight_kg": 61.0, "waist_cm": 79.0}
    fit = S.avatar_from_measurements(model, q)
    for k, v in q.items():
        if k != "gender":
            assert abs(fit.measurements[k] - v) <= M.ISO_TOLERANCE[k] * M.api_scale(k), k
    assert fit.measurements["gender"] == "female"
    assert set(fit.estimated) == set(M.ATTRIBUTES) - set(q)
    # estimates are plausible for such a woman
    assert 80 < fit.measurements["hip_cm"] < 115
    assert 65 < fit.measurements["inseam_cm"] < 85


def test_gender_is_estimated_when_not_given(model):
    tall_heavy = S.avatar_from_measurements(model, {"height_cm": 190.0, "weight_kg": 95.0, "shoulder_width_cm": 44})
    small = S.avatar_from_measurements(model, {"height_cm": 155.0, "weight_kg": 50.0, "shoulder_width_cm": 34})
    assert tall_heavy.gender == "male" and small.gender == "female"
    assert "gender" in tall_heavy.estimated


def test_held_out_ansur_subjects_all_twelve_within_iso(model):
    held = read_ansur(heldout=True)[::97]  # a spread of held-out subjects, both files
    ok = 0
    for s in held:
        m = s["measurements"]
        fit = S.avatar_from_measurements(model, m)
        errs = [abs(fit.measurements[n] - m[n]) / (M.ISO_TOLERANCE[n] * M.api_scale(n)) for n in M.ATTRIBUTES[1:]]
        ok += max(errs) <= 1.0
    assert ok >= 0.85 * len(held)

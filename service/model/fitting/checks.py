"""The fit's errors and the person checks around it (``person_check``): :class:`FitError`, whose
message is meant for the customer, and the checks before and after Alg. 1.
"""
from __future__ import annotations

import numpy as np

from service.model.fitting import person_check as PC


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

"""A garment's example fits from the cloth drape engine: the garment at its own size settled on
every example avatar and on population bodies, and the clothing basis through those drapes
(``garment.regress_basis``) returned as example fits (``garment.example_equivalent``), so that it
is stored and tried on like any other basis.

Shapes: rest (M, 3) m, faces (F, 3) int, warp fits (E, M, 3) on the E = 1 + 2N example avatars
(listing order), example avatars (E, V, 3)."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.model.drape import Config, drape_examples

from . import garment as G
from .tryon import population_sample, strain_maps


# cloth this far off the skin in every drape a shopper sees (a basis's example drapes, a customer's
# exact drape). Contact is per garment vertex, so body details smaller than the garment's
# triangles (nipples, shoulder blades, the armpit's fold) show through a cloth lying at the
# try-on's 3 mm (``garment.CLEARANCE``), or through a basis blended from drapes at the solver's
# 0.5 mm; twice the try-on's hides them
DRAPE_CLEARANCE_M = 2 * G.CLEARANCE


@dataclass
class DrapedFits:
    """fits (E, M, 3) float32: the basis's example fits; strain_fits (E, M) float32: those of
    its strain channel (``tryon.build_garment_basis``), fitted to the drapes' own strain maps;
    drapes (E + P, M, 3): every drape the basis is fitted through (examples first, then the
    population bodies of ``weights`` (P, N)); stats: one per body tried (a population body that
    failed, left out of the fit: ``{"failed": reason}``)."""
    fits: np.ndarray
    drapes: np.ndarray
    weights: np.ndarray
    stats: list[dict]
    strain_fits: np.ndarray


def fitted_drapes(drapes: np.ndarray, n_examples: int) -> np.ndarray:
    """(E + P,) bool: the drapes (E + P, M, 3) a basis is fitted through. The example avatars'
    (the first ``n_examples``) always; a population body's only if its drape settled outside it
    (not NaN). ``drape_examples`` solves those bodies without the drape's fallback, so a body
    the garment goes on only with friction at every stiffness level (a size too small for it)
    fails and is left out too: such a drape rests where its start put it, and on the largest
    bodies, at the edge of the fit, it tilts the line for everyone (the women's T-shirt XS, 9 of
    192: 4.8 -> 6.2 mm mean off held-out direct drapes)."""
    ok = np.isfinite(drapes).all(axis=(1, 2))
    ok[:n_examples] = True
    return ok


def draped_example_fits(model, examples: G.ExampleSet, example_avatars: np.ndarray, rest: np.ndarray,
                        faces: np.ndarray, warp_fits: np.ndarray, fabric: str, population: int,
                        progress: Callable[[float, str], None] | None = None,
                        clearance_m: float = DRAPE_CLEARANCE_M, workers: int = 1,
                        gender: str | None = None, max_vertices: int | None = Config.proxy_max_vertices) -> DrapedFits:
    """The garment (its rest shape: its own size) draped on every example avatar, each solve
    started from its warp fit there, and on ``population`` people of the body model's training
    population (``tryon.population_sample``; ``gender``: the garment's, ``female``, ``male`` or
    None for unisex), started from the warp fits' basis there. With
    population bodies the fits are those of the least-squares basis through all the drapes: a
    drape is not linear in the body (tight on large bodies, hanging on small ones), and the
    central difference of two examples half a std from the mean extrapolates it badly. Raises
    ``DrapeError`` naming the example avatar that failed; a population body that fails is left
    out (its stats say ``failed``). The cloth rests ``clearance_m`` off the skin. A garment of
    more than ``max_vertices`` vertices is draped as a simulation mesh of about that many
    (``drape.proxy``; None: as it is)."""
    warp_fits = np.asarray(warp_fits, np.float64)
    people = population_sample(model, population, gender)  # (P, K): whole bodies
    W = people[:, : examples.n]  # the components the basis has
    shapes, inits = np.asarray(example_avatars), warp_fits
    if len(W):
        g0, B0 = G.build_basis(warp_fits, examples)
        shapes = np.concatenate([shapes, model.vertices(people)])
        inits = np.concatenate([warp_fits, [G.synthesize(g0, B0, w) for w in W]])
    bodies = np.stack([model.body_vertices(X) for X in shapes]).astype(np.float64)
    drapes, stats = drape_examples(np.asarray(rest, np.float64), np.asarray(faces, np.int64),
                                   np.asarray(inits, np.float64), bodies, model.body_faces, fabric,
                                   config=Config(clearance_m=clearance_m, proxy_max_vertices=max_vertices), progress=progress,
                                   required=len(warp_fits), workers=workers)
    fits = drapes[: len(warp_fits)]
    if len(W):
        ok = fitted_drapes(drapes, len(warp_fits))
        drapes, W = drapes[ok], W[ok[len(warp_fits):]]
        weights = np.vstack([examples.weights(), W])
        g, B = G.regress_basis(drapes, weights, examples.sigma)
        fits = G.example_equivalent(g, B, examples)
        # the strain map regressed over the same drapes as its own channel: a tight garment's
        # strain is not the strain of the regressed positions (their errors along short edges)
        gs, Bs = G.regress_basis(strain_maps(rest, faces, drapes)[:, :, None], weights, examples.sigma)
        strains = G.example_equivalent(gs, Bs, examples)[:, :, 0]
    else:
        strains = strain_maps(rest, faces, fits)
    return DrapedFits(fits=fits, drapes=drapes, weights=W, stats=stats, strain_fits=strains)

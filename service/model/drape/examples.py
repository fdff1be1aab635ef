"""One garment draped on every example avatar: the example fits of a clothing basis from a
garment at its own size (the rest shape), started from the warp fits. The solves are
independent: with ``workers`` > 1 they run in that many forked processes, which inherit the
factored system (factor once, solve many, on every core)."""
from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Callable

import numpy as np

from service.model.geometry import kernels

from .proxy import ProxyDraper, precompute
from .solver import Config, Draper, DrapeError

MIN_SOLVES_PER_WORKER = 4  # fewer solves than this per process: not worth forking for

# what a forked process solves: (draper, inits, bodies, body faces, required), set just before the fork
_FORKED: tuple[Draper | ProxyDraper, np.ndarray, np.ndarray, np.ndarray, int] | None = None


def _child_signals() -> None:
    """A forked process's signals as the system's: it must not run the handlers it inherits (a
    worker's graceful shutdown, a test session's teardown), and the pool's terminate (SIGTERM)
    must end it at once, whatever it is doing; Ctrl-C is the parent's to handle."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _solve(draper: Draper | ProxyDraper, body: np.ndarray, body_faces: np.ndarray, init: np.ndarray,
           fallbacks: bool) -> tuple[np.ndarray | None, dict]:
    """One drape (``Draper.solve``'s ``fallbacks``): (vertices (N, 3) float32 or None, stats or
    {"failed": why})."""
    try:
        r = draper.solve(body, body_faces, init, fallbacks)
    except DrapeError as exc:
        return None, {"failed": str(exc), "seconds": 0.0, "settled": False}
    return r.vertices, r.stats


def _solve_one(i: int) -> tuple[int, np.ndarray | None, dict]:
    """Solve i of the forked set: (i, vertices or None, stats)."""
    assert _FORKED is not None
    draper, inits, bodies, body_faces, required = _FORKED
    return (i, *_solve(draper, bodies[i], body_faces, inits[i], i < required))


def _solves(draper: Draper | ProxyDraper, inits: np.ndarray, bodies: np.ndarray, body_faces: np.ndarray, workers: int,
            required: int):
    """(i, vertices or None, stats) of every body, in the order they finish; the bodies from
    ``required`` on solved without the drape's fallbacks."""
    global _FORKED
    n = len(bodies)
    if workers <= 1 or n < 2 * MIN_SOLVES_PER_WORKER or "fork" not in multiprocessing.get_all_start_methods():
        for i in range(n):
            yield (i, *_solve(draper, bodies[i], body_faces, inits[i], i < required))
        return
    if kernels.AVAILABLE:
        kernels.warm()  # compiled (or loaded) before the fork, not once per process behind a lock
    _FORKED = (draper, inits, bodies, body_faces, required)
    try:
        with multiprocessing.get_context("fork").Pool(min(workers, n // MIN_SOLVES_PER_WORKER),
                                                      initializer=_child_signals) as pool:
            yield from pool.imap_unordered(_solve_one, range(n))
    finally:
        _FORKED = None


def drape_examples(rest: np.ndarray, faces: np.ndarray, inits: np.ndarray, bodies: np.ndarray,
                   body_faces: np.ndarray, fabric: str = "woven", config: Config | None = None,
                   progress: Callable[[float, str], None] | None = None,
                   required: int | None = None, workers: int = 1) -> tuple[np.ndarray, list[dict]]:
    """The garment (rest shape (N, 3), faces (F, 3)) settled on each example body (bodies
    (E, B, 3) with ``body_faces`` (G, 3)) from its warp fit there (inits (E, N, 3)): factored
    once, solved per body, in ``workers`` processes (a garment denser than
    ``config.proxy_max_vertices`` through its simulation mesh: ``proxy``). Returns the draped fits (E, N, 3) float32
    and each solve's stats (the same whatever ``workers``). Raises :class:`DrapeError` naming
    the example that failed, among the first ``required`` bodies (default all); a later body
    that fails gets NaN fits and ``{"failed": reason}``. The later bodies are solved without the
    drape's fallbacks (``Draper.solve``): a build leaves out of its basis's fit the population
    drapes that would need one (``garments.draped.fitted_drapes``), so it does not spend a second
    solve on them."""
    inits = np.asarray(inits)
    if inits.ndim != 3 or inits.shape[1:] != np.shape(rest) or len(inits) != len(bodies):
        raise DrapeError(f"expected one start shape per example body; got {inits.shape} for {len(bodies)} bodies")
    draper = precompute(rest, faces, fabric, config)
    how = (f" (as a simulation mesh of {len(draper.simulation.keep)} of its {draper.n} vertices)"
           if isinstance(draper, ProxyDraper) else "")
    out = np.empty(inits.shape, np.float32)
    stats: list[dict] = [{} for _ in range(len(bodies))]
    solves = _solves(draper, inits, bodies, body_faces, workers, len(bodies) if required is None else required)
    try:
        for done, (i, verts, st) in enumerate(solves, start=1):
            if verts is None:
                if required is None or i < required:
                    raise DrapeError(f"example avatar {i}: {st['failed']}")
                out[i] = np.nan
            else:
                out[i] = verts
            stats[i] = st
            if progress is not None:
                progress(done / len(bodies), f"draped on {done} of {len(bodies)} example avatars{how}")
    finally:
        solves.close()  # a failure stops the other processes now
    return out, stats

"""One garment draped on every example avatar: the example fits of a clothing basis from a
garment at its own size (the rest shape), started from the warp fits."""
from __future__ import annotations

from collections.abc import Callable

import numpy as np

from .solver import Config, DrapeError, precompute


def drape_examples(rest: np.ndarray, faces: np.ndarray, inits: np.ndarray, bodies: np.ndarray,
                   body_faces: np.ndarray, fabric: str = "woven", config: Config | None = None,
                   progress: Callable[[float, str], None] | None = None,
                   required: int | None = None) -> tuple[np.ndarray, list[dict]]:
    """The garment (rest shape (N, 3), faces (F, 3)) settled on each example body (bodies
    (E, B, 3) with ``body_faces`` (G, 3)) from its warp fit there (inits (E, N, 3)): factored
    once, solved per body. Returns the draped fits (E, N, 3) float32 and each solve's stats.
    Raises :class:`DrapeError` naming the example that failed, among the first ``required``
    bodies (default all); a later body that fails gets NaN fits and ``{"failed": reason}``."""
    inits = np.asarray(inits)
    if inits.ndim != 3 or inits.shape[1:] != np.shape(rest) or len(inits) != len(bodies):
        raise DrapeError(f"expected one start shape per example body; got {inits.shape} for {len(bodies)} bodies")
    draper = precompute(rest, faces, fabric, config)
    out = np.empty(inits.shape, np.float32)
    stats = []
    for i, (init, body) in enumerate(zip(inits, bodies)):
        try:
            r = draper.solve(body, body_faces, init)
        except DrapeError as exc:
            if required is None or i < required:
                raise DrapeError(f"example avatar {i}: {exc}") from None
            out[i] = np.nan
            stats.append({"failed": str(exc), "seconds": 0.0, "settled": False})
            continue
        out[i] = r.vertices
        stats.append(r.stats)
        if progress is not None:
            progress((i + 1) / len(bodies), f"draped on {i + 1} of {len(bodies)} example avatars")
    return out, stats

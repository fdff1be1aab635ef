"""``tryon bench kernels``: the compiled geometry kernels (``service.model.geometry.kernels``, numba)
against the numpy paths they replace, interleaved in one run (``geometry.COMPILED`` switched per
call, the order alternating), on held-out customers:

- ``closest_points``: 5,000 points within ~1 cm of a customer's skin, closest points on the body
  mesh (25k faces), the kd-tree query included;
- ``winding_numbers``: 64 such points against the whole body surface;
- ``adapt_poses``: the page's four poses adapted to a body (``poses.adapted_poses``);
- ``first_outfit``: what ``outfit.glb?pose_correctives=1`` computes for a new customer, in
  process: the T-shirt and jeans on the avatar with its default look, layered, with the
  correctives of the page poses (every cache cold: a new body, the layering, the correctives);
- ``second_outfit``: the striped shirt under the casual jacket on the same body (its posed
  bodies cached, as for a customer's second outfit).

Each row: median ms with the kernels and without, their ratio, and whether every output (the
closest points, the adapted poses, the GLB bytes) came out identical (winding numbers: their
largest difference)."""
from __future__ import annotations

import time

import numpy as np

CUSTOMERS = 8
POINTS = 5000
WINDING_POINTS = 64
GARMENTS = {"female": ("womens-tshirt", "womens-jeans"), "male": ("mens-tshirt", "mens-jeans")}
SECOND = ("striped-shirt", "casual-jacket")


def _timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def run(limit: int = 0, repeats: int = 0) -> dict:
    """``limit``: customers (default 8)."""
    from service.application import look as looks
    from service.application import scenes
    from service.model.geometry import mesh as G
    from service.model.geometry import kernels
    from service.model.body import poses as P
    from service.model.garments import tryon as T
    from service.model.body.model import load_body_model
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment
    from service.storage.cache import VersionedLRU
    from tests.bench.tryon import customers

    if not kernels.AVAILABLE:
        raise RuntimeError("numba is not installed: nothing to compare")
    kernels.warm()
    model = load_body_model()
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    cat = load_catalogue()
    bases = {}
    for gid in {*SECOND, *[g for o in GARMENTS.values() for g in o]}:
        it = cat.items[gid]
        basis = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex,
                                      layout=it.render_layout(), material=it.material)
        bases[gid] = (Garment(id=gid, body_model=model.version, owner="bench", name=gid, source="demo",
                              color=[0.5, 0.5, 0.5, 1.0], layer=it.layer), basis)
    n = limit or CUSTOMERS
    bodies = customers(model, n)
    nb = model.n_body_vertices
    faces = np.asarray(model.body_faces, np.int64)
    rng = np.random.default_rng(11)
    rows = ("closest_points", "winding_numbers", "adapt_poses", "first_outfit", "second_outfit")
    ts: dict = {r: {True: [], False: []} for r in rows}
    same = {r: True for r in rows if r != "winding_numbers"}
    winding_diff = 0.0

    def outfit(body, gids, gender, poses):
        items = sorted((bases[g] for g in gids), key=lambda x: x[0].layer)
        return scenes.outfit_glb(model, body, items, None, look=looks.resolve(gender), poses=poses)

    # warm both paths (the catalogue's bindings, templates) on a body that is not measured
    outfit(T.customer_body(model, bodies[0].weights), GARMENTS["female"], "female", None)
    for i, b in enumerate(bodies):
        X = np.asarray(b.vertices[:nb], np.float64)
        pts = X[rng.integers(0, nb, POINTS)] + rng.normal(0, 0.01, (POINTS, 3))
        gender = "female" if i % 2 == 0 else "male"
        out: dict = {r: {} for r in rows}
        for compiled in ((True, False) if i % 2 == 0 else (False, True)):
            G.COMPILED = compiled
            try:
                t, out["closest_points"][compiled] = _timed(lambda: G.closest_points_on_mesh(pts, X, faces))
                ts["closest_points"][compiled].append(t)
                t, out["winding_numbers"][compiled] = _timed(lambda: G.winding_numbers(pts[:WINDING_POINTS], X, faces))
                ts["winding_numbers"][compiled].append(t)
                t, poses = _timed(lambda: P.adapted_poses(model, b.vertices))
                ts["adapt_poses"][compiled].append(t)
                out["adapt_poses"][compiled] = poses
                # a new customer: a fresh body (no posed bodies), no layering or correctives cached
                scenes._layered = VersionedLRU(scenes.LAYERED_CACHE_SIZE)
                scenes._correctives = VersionedLRU(scenes.CORRECTIVES_CACHE_SIZE)
                looks._fitted = VersionedLRU(looks.FITTED_CACHE_SIZE)
                body = T.customer_body(model, b.weights)
                t, out["first_outfit"][compiled] = _timed(lambda: outfit(body, GARMENTS[gender], gender, poses))
                ts["first_outfit"][compiled].append(t)
                t, out["second_outfit"][compiled] = _timed(lambda: outfit(body, SECOND, gender, poses))
                ts["second_outfit"][compiled].append(t)
            finally:
                G.COMPILED = True
        same["closest_points"] &= all(np.array_equal(a, c) for a, c in zip(out["closest_points"][True],
                                                                           out["closest_points"][False]))
        winding_diff = max(winding_diff, float(np.abs(out["winding_numbers"][True] - out["winding_numbers"][False]).max()))
        same["adapt_poses"] &= all(np.array_equal(out["adapt_poses"][True][k], out["adapt_poses"][False][k])
                                   for k in out["adapt_poses"][True])
        for r in ("first_outfit", "second_outfit"):
            same[r] &= out[r][True] == out[r][False]
    res: dict = {"customers": n, "rows": {}}
    for r in rows:
        on, off = 1000 * float(np.median(ts[r][True])), 1000 * float(np.median(ts[r][False]))
        res["rows"][r] = {"compiled_ms": on, "numpy_ms": off, "speedup": off / on,
                          "identical": same.get(r), **({"max_abs_diff": winding_diff} if r == "winding_numbers" else {})}
    return res


def format_result(r: dict) -> str:
    lines = [f"compiled geometry kernels vs numpy, interleaved, {r['customers']} held-out customers (median ms)",
             f"  {'step':<17}{'compiled':>10}{'numpy':>10}{'speedup':>9}  outputs"]
    for k, v in r["rows"].items():
        same = f"max diff {v['max_abs_diff']:.1e}" if "max_abs_diff" in v else ("identical" if v["identical"] else "DIFFER")
        lines.append(f"  {k:<17}{v['compiled_ms']:>10.1f}{v['numpy_ms']:>10.1f}{v['speedup']:>8.2f}x  {same}")
    return "\n".join(lines)

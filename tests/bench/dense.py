"""``tryon bench dense``: garments as dense as pattern tools export them (CLO, Marvelous Designer:
5-10 mm triangles, 10,000-100,000 vertices), draped through their simulation mesh
(``service.model.drape.proxy``: above ``TRYON_DRAPE_MAX_VERTICES``, default 8,000) beside the
direct drape of the same garment, body, fabric and start: the baseline, same run.

The garments: the demo white T-shirt (knit, 2,822 vertices) subdivided once (11,102 vertices) and
twice (44,030: ~5 mm edges), its size as bound to the example avatar ``mean``, started from its
binding's fit on each body (the warp's place, made to measure). The bodies: ``--limit`` held-out
people (ANSUR II avatars the body model never saw; default 3), at the build's clearance (6 mm).

Rows, per garment (``t10k``, ``t44k``):
- ``direct_s`` / ``proxy_s``: median seconds of one drape, and their ratio (``speed_ratio``);
- ``vs_direct_mean_mm`` / ``_p99_mm`` / ``_max_mm``: the proxy drape's vertices from the direct
  drape's, over all the people (how far "the" drape is defined: the drape bench's
  ``basis_start_mean_mm``, the same drape from two reasonable starts, 6.1 mm);
- ``direct_crossings`` / ``proxy_crossings``: self-intersecting face pairs left, summed;
- ``proxy_inside_vertices``: vertices > 1 mm inside the body (winding numbers);
- ``strain_p99_direct`` / ``strain_p99_proxy``: the 99th percentile of edge stretch;
- ``simulation_vertices``, ``precompute_s`` (simplification and factorisation).
And ``build_44k_s``: the whole one-size build of the 44k garment as the service builds it (65
example avatars and ``TRYON_DRAPE_POPULATION`` population bodies in ``TRYON_DRAPE_WORKERS``
processes, the least-squares basis), through its simulation mesh (``--no-build``: skipped).
"""
from __future__ import annotations

import time

import numpy as np

HELDOUT_PEOPLE = 3


def _garments(m, E):
    """[(name, rest (N, 3), faces (F, 3), binding fit function X -> (N, 3))] of the subdivided T-shirt."""
    from service.model.garments.catalogue import load_catalogue
    from tests.drape_cases import subdivide

    item = next(i for i in load_catalogue().garments() if i.id == "white-tshirt")
    V, F = item.binding.fit(np.asarray(m.mean, np.float64)).astype(np.float64), item.faces.astype(np.int64)
    parents = []
    out = []
    for name in ("t10k", "t44k"):
        V, F, par = subdivide(V, F)
        parents.append(par)

        def fit(X, levels=tuple(parents)):
            x = item.binding.fit(X).astype(np.float64)
            for par in levels:
                x = np.vstack([x, 0.5 * (x[par[:, 0]] + x[par[:, 1]])])
            return x

        out.append((name, V, F, fit))
    return out


def run(limit: int = 0, repeats: int = 0, build: bool = True) -> dict:
    from service.model.body.model import load_body_model
    from service.model.drape import Config, precompute
    from service.model.drape.solver import edge_strain
    from service.model.garments.draped import DRAPE_CLEARANCE_M, draped_example_fits
    from service.model.garments.tryon import example_set, example_vertices
    from service.model.geometry import mesh as geometry
    from service.settings import Settings
    from tests.bench.common import heldout_avatars

    m = load_body_model()
    ex = example_set(m)
    E = example_vertices(m, ex)
    H = heldout_avatars(m)[: (limit or HELDOUT_PEOPLE)]
    cap = Settings.model_fields["drape_max_vertices"].default
    rows: dict = {}
    for name, V, F, fit in _garments(m, E):
        t0 = time.perf_counter()
        direct = precompute(V, F, "knit", Config(clearance_m=DRAPE_CLEARANCE_M, proxy_max_vertices=None))
        t_pre_direct = time.perf_counter() - t0
        t0 = time.perf_counter()
        proxy = precompute(V, F, "knit", Config(clearance_m=DRAPE_CLEARANCE_M, proxy_max_vertices=cap))
        t_pre_proxy = time.perf_counter() - t0
        td, tp, dist, xd, xp, inside, sd, sp = [], [], [], 0, 0, 0, [], []
        for X in H:
            BV = m.body_vertices(X).astype(np.float64)
            init = fit(X)
            t0 = time.perf_counter()
            rd = direct.solve(BV, m.body_faces, init)
            td.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            rp = proxy.solve(BV, m.body_faces, init)
            tp.append(time.perf_counter() - t0)
            a, b = rd.vertices.astype(np.float64), rp.vertices.astype(np.float64)
            dist.append(1000 * np.linalg.norm(a - b, axis=1))
            xd += len(geometry.intersecting_face_pairs(a, F))
            xp += len(geometry.intersecting_face_pairs(b, F))
            w = geometry.winding_numbers(b, BV, m.body_faces)
            cand = np.flatnonzero(w > 0.5)
            if len(cand):
                _, q, _ = geometry.closest_points_on_mesh(b[cand], BV, m.body_faces)
                inside += int((np.linalg.norm(b[cand] - q, axis=1) > 1e-3).sum())
            sd.append(np.percentile(edge_strain(V, F, a), 99))
            sp.append(np.percentile(edge_strain(V, F, b), 99))
        d = np.concatenate(dist)
        rows[name] = {"n_vertices": len(V), "simulation_vertices": len(proxy.simulation.keep),
                      "direct_s": float(np.median(td)), "proxy_s": float(np.median(tp)),
                      "speed_ratio": float(np.median(tp) / np.median(td)),
                      "vs_direct_mean_mm": float(d.mean()), "vs_direct_p99_mm": float(np.percentile(d, 99)),
                      "vs_direct_max_mm": float(d.max()), "direct_crossings": xd, "proxy_crossings": xp,
                      "proxy_inside_vertices": inside, "strain_p99_direct": float(np.median(sd)),
                      "strain_p99_proxy": float(np.median(sp)), "precompute_direct_s": t_pre_direct,
                      "precompute_proxy_s": t_pre_proxy, "people": len(H)}
        if build and name == "t44k":
            population = Settings.model_fields["drape_population"].default
            workers = Settings.model_fields["drape_workers"].default
            t0 = time.perf_counter()
            dfits = draped_example_fits(m, ex, E, V, F, np.stack([fit(X) for X in E]), "knit", population,
                                        workers=workers, gender=None, max_vertices=cap)
            rows["build_44k_s"] = {"value": time.perf_counter() - t0, "drapes": len(dfits.stats),
                                   "failed": sum("failed" in s for s in dfits.stats), "population": population,
                                   "workers": workers, "n_vertices": len(V),
                                   "median_drape_s": float(np.median([s["seconds"] for s in dfits.stats
                                                                      if "failed" not in s])),
                                   "crossings": int(sum(s.get("self_intersections", 0) for s in dfits.stats
                                                        if "failed" not in s))}
    return {"rows": rows, "max_vertices": cap}


def format_result(res: dict) -> str:
    rows = res["rows"]
    lines = [f"dense garments through a simulation mesh of <= {res['max_vertices']} vertices vs the direct drape "
             f"(same garment, body, start; median over {next(iter(rows.values()))['people']} held-out people)", ""]
    for name in ("t10k", "t44k"):
        r = rows.get(name)
        if r is None:
            continue
        lines += [f"{name}: {r['n_vertices']} vertices -> {r['simulation_vertices']}",
                  f"  one drape: {r['proxy_s']:.2f} s, direct {r['direct_s']:.2f} s (ratio {r['speed_ratio']:.2f})",
                  f"  from the direct drape: mean {r['vs_direct_mean_mm']:.2f} mm, p99 {r['vs_direct_p99_mm']:.2f} mm, "
                  f"max {r['vs_direct_max_mm']:.1f} mm",
                  f"  crossing face pairs: {r['proxy_crossings']} (direct {r['direct_crossings']}); vertices inside: "
                  f"{r['proxy_inside_vertices']}",
                  f"  edge stretch p99: {r['strain_p99_proxy']:.3f} (direct {r['strain_p99_direct']:.3f}); precompute "
                  f"{r['precompute_proxy_s']:.1f} s (direct {r['precompute_direct_s']:.1f} s)"]
    b = rows.get("build_44k_s")
    if b:
        lines.append(f"whole one-size build of the 44k garment ({b['drapes']} drapes, {b['workers']} processes): "
                     f"{b['value']:.0f} s (median drape {b['median_drape_s']:.2f} s, {b['failed']} failed, "
                     f"{b['crossings']} crossing pairs kept)")
    return "\n".join(lines)

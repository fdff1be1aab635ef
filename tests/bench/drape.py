"""``tryon bench drape``: the cloth drape engine (``service.model.drape``) against its analytic
cases, a dense reference solve of the same energy, NVIDIA Newton's VBD solver (when installed:
``pip install -e '.[bench-cloth]'``; its first run compiles Warp kernels for ~3 minutes), one
garment on two bodies of different waists, contact and self-intersection counts, and the time
of one ~10k-vertex garment on one body.

Rows (goals from issue 43):
- ``hoop_strain_pts``: a tube of rest girth Cg on a cylinder of girth Cb > Cg: |hoop strain -
  (Cb / Cg - 1)| in percentage points (goal <= 0.5);
- ``own_girth_pct``: the same tube hung from a wider band over a thinner cylinder: its girth
  below the band vs Cg, % (goal <= 1);
- ``sag_vs_dense_mm`` per fabric: a 20 cm square pinned at two corners, sag vs the L-BFGS
  minimiser of the same energy (goal <= 5 mm);
- ``sag_vs_newton_mm``: the same square (knit) vs Newton VBD on CPU (goal <= 5 mm);
- ``two_bodies_girth_cm``: one garment (a skirt of girth 90 cm hung from the hips) on two bodies
  whose waists are 70 and 80 cm: its girth at the waist on each, and their difference (goal <= 2);
- ``inside_vertices`` / ``self_intersections``: garment vertices > 1 mm inside the body (winding
  numbers), self-intersecting face pairs, over every drape of the run (goal 0 / 0);
- ``garment_10k_s``: a catalogue T-shirt subdivided to ~10k vertices, draped from its warp fit on
  an example avatar (goal <= 4 s on 2 cores); beside it, the same drape with the body contact's
  closest points refreshed more often (every vertex every 10 iterations, in between
  those that moved 0.5 mm), its time and its mean distance to the drape (the baseline of the same run);
- ``basis_vs_drape_mean_mm`` / ``_p99_mm``: the demo men's T-shirt (knit, 810 vertices, its size as
  bound to the mean avatar) built as the service builds it with ``TRYON_DRAPE`` on (draped on the
  65 example avatars and ``TRYON_DRAPE_POPULATION`` (default 192) people of the body model's
  training population, three quarters of them men: the garment's gender; the least-squares
  basis: ``garments.draped.draped_example_fits``), its try-on as served (``tryon.try_on``: the
  basis synthesis, then the push-out of the body) on held-out avatars (ANSUR
  II people the body model never saw, of both genders; 50, or ``--limit``) vs the garment draped
  directly on each from its warp fit there (goal mean <= 3 mm, p99 <= 12 mm; a held-out drape
  that fails, the shirt too small to go on, is counted and left out), and per gender; beside it
  the central-difference basis of the 65 example drapes alone (the paper's);
- ``whole_build_s``: that build (257 drapes + the basis), 2 cores (goal <= 5 min); beside it the
  crossing face pairs its drapes kept, the example avatars' solves that fell back to friction at
  every level and the population bodies left out (``build_*``);
- ``ease_vs_newton_mm`` / ``hem_vs_newton_cm``: that T-shirt draped from its warp fit on 5 held-out
  people here and by Newton VBD on CPU (2 simulated seconds, damped), both keeping the cloth 3 mm
  off the skin (Newton's particle radius, our clearance), Newton's material matched to ours
  (``drape_newton._cloth_builder``) and started where ours starts (``drape.start_outside``), its
  own vertices > 1 mm inside the body counted beside (``newton_inside_vertices``): the largest difference of
  ease at any girth region it has (chest, waist, shoulders), and of the hem height (goals 5 mm,
  1 cm); the same for the catalogue garments of ``NEWTON_GARMENTS`` (the sports trousers,
  stretch: hip and thigh; the long-sleeve tee, knit: chest, waist, upper arm, shoulders) on
  the first 5 held-out people of their gender (``<garment>_*`` keys; the rows' values are the
  largest over the garments). A draped garment's girth is read as a
  tape reads it, around the convex hull of its section (``GarmentSections.girth(tape=True)``):
  the cloth's length along the section also counts its wrinkles, which Newton's cloth forms
  where ours compresses (``cloth_length_max_mm``: that measure, beside); beside it each body's signed differences (``bodies_mm``, ours minus Newton's) and the
  same largest difference with our drape under Newton's contact model (``vertex_contact_max_mm``:
  vertices kept off the body, no body-vertex / cloth-face pass, which lifts our cloth by the
  body's details between its vertices);
- ``ease_vs_newton_full_contact_mm`` (with ``--newton-full-contact N``; 4-7 minutes a person on
  CPU): our drapes of the N of those 5 people with the largest chests against Newton VBD with the
  contacts ours has (no goal; ``drape_newton.garment_on_body(full_contact=True)``): its
  self-contact on and the body's faces near the shirt a fixed cloth in it, so that body vertices
  stay out of the cloth's faces and the cloth out of itself; the largest ease difference, each
  person's, the girths ours has that the reference's section cannot measure (``unmeasured``) and
  the hem height difference (``hem_cm``); the same for ``NEWTON_GARMENTS`` on the N (at most
  their cap) of their 5 people with the largest girth each names (``<garment>_*`` keys; the
  row's value is the largest over the garments): without self-contact Newton's loose cloth
  passes through itself, so its plain drape's hips read smaller;
- ``membrane_energy_vs_newton``: those drapes under our energy (``Draper.energy_terms``): the
  median over the 5 people of our drape's membrane energy (in-plane stretch and shear against the
  rest shape) over Newton's, each person's ratio (and against the full-contact reference where it
  ran), the total energies, and the shares of triangles compressed past the fabric's
  ``compress_limit_pct`` or stretched past its ``stretch_limit_pct`` (``Draper.principal_stretches``;
  medians; no goal: the two drapes' resting states compared under one energy: where ours is
  higher, it did not reach the state Newton found);
- ``basis_vs_drape_surface_mm``: the same pairs measured shape to shape, not vertex to vertex:
  each vertex's distance to the other mesh's surface, both ways (mean, p99; no goal): the
  vertex distance also counts the cloth sliding along the body, which the shape does not show;
- ``drape_repeatability_mm``: the direct drape of that T-shirt on 5 held-out people repeated from
  its start moved by 2 mm noise: mean (and p99) distance between the two (no goal: the floor
  under the basis-vs-drape figure, since friction and folds give cloth many resting shapes);
- ``drape_start_dependence_mm``: the same 5 drapes repeated from another reasonable start, the
  basis try-on there instead of the warp fit: mean (and p99) distance between the two (no goal:
  how far "the" direct drape is defined at all);
- ``basis_vs_exact_drape_mm``: on those 5 people, the basis try-on against the drape the
  service's exact-drape job gives (started where the job starts: the basis's start channel, the
  warp fits' basis, where the build's population drapes started; ``tryon.drape_start``): how far
  the shopper's try-on moves when the exact drape arrives (mean, p99; no goal);
- ``layered_slide_cm``: the demo dungarees (a T-shirt whose front MakeHuman cut away under the
  bib, and the dungarees over it: two pieces of cloth and 4 small parts, woven) draped on 3
  example avatars with its layers tied where they lie together (``Config.tie_m``): how far the
  two pieces slid apart (the difference of their median height changes, worst body; no goal);
  beside it the same drapes untied (the baseline of the same run), the face pairs crossing
  between the pieces of cloth and the solves' seconds;
- ``walking_step_stretch``: the catalogue's bottoms (skirts, trousers) as plain GLBs posed by
  their skin weights alone in the page's four poses on five bodies (``tryon bench tryon``'s
  pose-stretch measure): the 99.9th-percentile edge stretch of the worst garment, body and pose
  (the walking step for all of them; goal <= 1.5); beside it the avatar's own skin in the same
  poses and bodies (``avatar_skin``, the body model's skinning) and the worst garment's stretch
  relative to the body under it (``relative_to_body``).
"""
from __future__ import annotations

import time

import numpy as np

NEWTON_BODIES = 5  # held-out people the reference drapes the catalogue garment on
NEWTON_SECONDS = 2.0  # simulated seconds of the reference's damped settle
# catalogue garments compared with Newton beside the T-shirt, in their demo fabric
# (``demo.DEMO_FABRICS``), on held-out people of their gender, at the girth regions each has
# (the T-shirt has no hip or thigh): garment -> (the body girth by which the
# ``--newton-full-contact`` people are picked, the largest first; the most people it takes
# there: the long-sleeve tee's full-contact drapes take 5-15 minutes a person on 2 cores). The
# long-sleeve tee is the catalogue's garment with the upper arm, which neither other has.
NEWTON_GARMENTS = {"sports-trousers": ("hip", NEWTON_BODIES), "longsleeve-tee": ("chest", 2)}
NEWTON_RADIUS_M = 0.003  # Newton's cloth particle radius (its contact thickness), our clearance in that comparison
REPEAT_BODIES = 5  # held-out people the direct drape is repeated on from a perturbed start
HELDOUT_PEOPLE = 50  # held-out people the basis try-on is checked on against direct drapes (the figure)
REPEAT_START_NOISE_M = 0.002  # the perturbation: normal noise of this standard deviation per coordinate
LAYERED_GARMENT = "dungarees"  # the catalogue's garment of layered pieces (a T-shirt under a bib, 2,497 + 1,115 v)
LAYERED_BODIES = 3  # the example avatars it is draped on (the mean and the first two)


def self_intersections(V: np.ndarray, F: np.ndarray) -> int:
    """Pairs of faces (sharing no vertex) that intersect (``geometry.intersecting_face_pairs``)."""
    from service.model.geometry import mesh as geometry

    return len(geometry.intersecting_face_pairs(V, F))


def _inside(x: np.ndarray, BV: np.ndarray, BF: np.ndarray, depth_m: float = 0.001) -> int:
    """Garment vertices more than ``depth_m`` inside the closed body (winding number > 0.5 and
    farther than ``depth_m`` from the surface)."""
    from service.model.geometry import mesh as geometry

    w = geometry.winding_numbers(x, BV, BF)
    cand = np.flatnonzero(w > 0.5)
    if not len(cand):
        return 0
    _, q, _ = geometry.closest_points_on_mesh(x[cand], BV, BF)
    return int((np.linalg.norm(x[cand] - q, axis=1) > depth_m).sum())


def run(limit: int = 0, repeats: int = 0, newton: bool = True, newton_full: int = 0) -> dict:
    from service.model.drape import FABRICS, precompute
    from tests.drape_cases import cylinder, revolved_body, ring_girth, square_sag, subdivide, tube

    out: dict = {"rows": {}, "drapes": []}
    rows = out["rows"]
    inside = selfx = 0

    def record(name, V, F, BV, BF, r):
        nonlocal inside, selfx
        x = r.vertices.astype(np.float64)
        n_in = _inside(x, BV, BF) if BV is not None else 0
        n_sx = self_intersections(x, F)
        inside += n_in
        selfx += n_sx
        out["drapes"].append({"case": name, "n_vertices": len(V), "seconds": r.stats["seconds"],
                              "iterations": r.stats["iterations"], "settled": r.stats["settled"],
                              "inside": n_in, "self_intersections": n_sx})

    # 1. tube on a wider cylinder: hoop strain
    na, nh, Rg, Rb = 64, 12, 0.15, 0.156
    V, F = tube(Rg, 0.3, na, nh)
    BV, BF = cylinder(Rb, -0.3, 0.6)
    init = V.copy()
    init[:, [0, 2]] *= (Rb + 0.002) / Rg
    r = precompute(V, F, "knit").solve(BV, BF, init)
    x = r.vertices.astype(np.float64)
    hoop = ring_girth(x, nh // 2, na) / ring_girth(V, nh // 2, na) - 1
    rows["hoop_strain_pts"] = {"value": 100 * abs(hoop - (Rb / Rg - 1)), "goal": 0.5, "hoop_pct": 100 * hoop,
                               "expected_pct": 100 * (Rb / Rg - 1)}
    record("tube_on_wider", V, F, BV, BF, r)

    # 2. hung from a wider band over a thinner cylinder: own girth
    na2, nh2 = 32, 10
    V2, F2 = tube(Rg, 0.5, na2, nh2, y0=0.05)
    ys = np.linspace(-0.2, 0.7, 31)
    BV2, BF2 = revolved_body(ys, np.interp(ys, [-0.2, 0.25, 0.35, 0.7], [0.10, 0.10, 0.16, 0.16]), 64)
    r = precompute(V2, F2, "knit").solve(BV2, BF2, V2)
    g = ring_girth(r.vertices.astype(np.float64), 1, na2) / ring_girth(V2, 1, na2) - 1
    rows["own_girth_pct"] = {"value": 100 * abs(g), "goal": 1.0, "settled": r.stats["settled"]}
    record("tube_on_thinner", V2, F2, BV2, BF2, r)

    # 3. pinned square vs the dense reference, each fabric
    for fab in ("woven", "knit", "stretch"):
        sag, ref, r, _ = square_sag(7, 0.2, fab)
        rows[f"sag_vs_dense_mm_{fab}"] = {"value": 1000 * abs(sag - ref), "goal": 5.0, "sag_mm": 1000 * sag,
                                          "reference_mm": 1000 * ref, "settled": r.stats["settled"],
                                          "iterations": r.stats["iterations"]}
        if fab == "knit":
            knit_sag = sag

    # 4. vs Newton VBD (CPU)
    from tests.bench import drape_newton

    why = drape_newton.available() if newton else "skipped (--no-newton)"
    if why is None:
        from tests.drape_cases import square
        n = 7
        Vs, Fs = square(0.2, n, y=1.0)
        f = FABRICS["knit"]
        nr = drape_newton.square_sag(Vs, Fs, [0, n - 1], f.density_kg_per_m2, f.stretch_stiffness_n_per_m,
                                     f.bending_stiffness_nm)
        rows["sag_vs_newton_mm"] = {"value": 1000 * abs(knit_sag - nr["sag_m"]), "goal": 5.0,
                                    "newton_sag_mm": 1000 * nr["sag_m"], "newton_max_speed_m_s": nr["max_speed_m_s"],
                                    "newton_s": nr["seconds"]}
    else:
        rows["sag_vs_newton_mm"] = {"value": None, "goal": 5.0, "skipped": why}

    # 5. one garment on two bodies with waists 10 cm apart
    girths = []
    Rs = 0.90 / (2 * np.pi)
    V3, F3 = tube(Rs, 0.45, 48, 12, y0=0.10)
    d3 = precompute(V3, F3, "woven")
    for waist in (0.70, 0.80):
        Rw = waist / (2 * np.pi)
        ys = np.linspace(-0.2, 0.7, 37)
        BV3, BF3 = revolved_body(ys, np.interp(ys, [-0.2, 0.3, 0.45, 0.7], [Rw, Rw, 0.165, 0.165]), 96)
        r = d3.solve(BV3, BF3, V3)
        girths.append(ring_girth(r.vertices.astype(np.float64), 2, 48))
        record(f"skirt_waist_{int(100 * waist)}", V3, F3, BV3, BF3, r)
    rows["two_bodies_girth_cm"] = {"value": 100 * abs(girths[1] - girths[0]), "goal": 2.0,
                                   "girths_cm": [100 * g for g in girths], "body_waists_cm": [70, 80],
                                   "garment_girth_cm": 90.0}

    # 6. a ~10k-vertex garment from its warp fit on an example avatar
    from service.model.body.model import load_body_model
    from service.model.garments.catalogue import load_catalogue
    from service.model.garments.tryon import example_set, example_vertices

    m = load_body_model()
    E = example_vertices(m, example_set(m))
    item = next(i for i in load_catalogue().garments() if i.id == "white-tshirt")
    rest0, init0 = item.binding.fit(E[0]).astype(np.float64), item.binding.fit(E[1]).astype(np.float64)
    Vg, Fg, par = subdivide(rest0, item.faces.astype(np.int64))
    init = np.vstack([init0, 0.5 * (init0[par[:, 0]] + init0[par[:, 1]])])
    BVg = m.body_vertices(E[1]).astype(np.float64)
    # draped as it is (the service drapes a garment over TRYON_DRAPE_MAX_VERTICES through its
    # simulation mesh: `tryon bench dense`)
    from service.model.drape import Config as _Config

    t0 = time.perf_counter()
    dg = precompute(Vg, Fg, "knit", _Config(proxy_max_vertices=None))
    r = dg.solve(BVg, m.body_faces, init)
    t_10k = time.perf_counter() - t0
    record("white_tshirt_10k", Vg, Fg, BVg, m.body_faces, r)
    # baseline, same run: the body contact's closest points refreshed more often
    # (every vertex every 10 iterations, in between those that moved 0.5 mm)
    t0 = time.perf_counter()
    rb = precompute(Vg, Fg, "knit", _Config(contact_refresh=10, contact_moved_m=0.0005, contact_walk_m=np.inf,
                                            proxy_max_vertices=None)).solve(BVg, m.body_faces, init)
    t_base = time.perf_counter() - t0
    rows["garment_10k_s"] = {"value": t_10k, "goal": 4.0, "n_vertices": len(Vg),
                             "precompute_s": dg.precompute_s, "iterations": r.stats["iterations"],
                             "settled": r.stats["settled"], "local_s": r.stats["local_s"],
                             "global_s": r.stats["global_s"], "contact_s": r.stats["contact_s"],
                             "factor": r.stats["factor"], "baseline_s": t_base, "ratio_to_baseline": t_10k / t_base,
                             "baseline_contact_s": rb.stats["contact_s"],
                             "vs_baseline_mean_mm": float(1000 * np.linalg.norm(
                                 r.vertices.astype(np.float64) - rb.vertices, axis=1).mean())}

    # 6b. a garment of layered pieces (the demo dungarees: a T-shirt under a bib, 4 small parts) on
    # example avatars, its layers tied where they lie together; the baseline: untied, same run
    rows["layered_slide_cm"] = _layered(m, E)

    # 7. the clothing basis through drapes vs direct drapes on held-out people; the build's time
    from service.model.drape import Config
    from service.model.garments.draped import DRAPE_CLEARANCE_M, draped_example_fits
    from service.model.garments.tryon import (build_garment_basis, customer_body, drape_start,
                                              example_set as _example_set, try_on)
    from service.settings import Settings
    from service.model.drape import DrapeError
    from tests.bench.common import heldout_avatars, heldout_genders, surface_distances

    ex = _example_set(m)
    shirt = next(i for i in load_catalogue().garments() if i.id == "mens-tshirt")
    sF = shirt.faces.astype(np.int64)
    s_rest = shirt.binding.fit(np.asarray(m.mean, np.float64)).astype(np.float64)
    population = Settings.model_fields["drape_population"].default
    t0 = time.perf_counter()
    warp_fits = np.stack([shirt.binding.fit(X) for X in E])
    dfits = draped_example_fits(m, ex, E, s_rest, sF, warp_fits, "knit", population,
                                workers=Settings.model_fields["drape_workers"].default, gender=shirt.gender)
    basis = build_garment_basis(m, dfits.fits, sF, ex, start_fits=warp_fits)
    build_s = time.perf_counter() - t0
    # the baseline: the basis of the example drapes' central differences alone (no population)
    basis_cd = build_garment_basis(m, dfits.drapes[: len(E)], sF, ex)
    H = heldout_avatars(m)[: (limit or HELDOUT_PEOPLE)]
    H_gender = heldout_genders()[: len(H)]
    W = m.project(H)
    # the comparison with Newton: the cloth kept off the skin by Newton's particle radius here too
    shirt_draper = precompute(s_rest, sF, "knit", Config(clearance_m=NEWTON_RADIUS_M))
    # ... and with Newton's contact model: vertices kept off the body, no body-vertex / cloth-face pass
    vertex_draper = precompute(s_rest, sF, "knit", Config(clearance_m=NEWTON_RADIUS_M, face_contact_m=0.0))
    # the direct drapes at the build's clearance (the basis's example drapes rest that far off the skin)
    heldout_draper = precompute(s_rest, sF, "knit", Config(clearance_m=DRAPE_CLEARANCE_M))
    err_reg, err_cd, err_gender, err_surface, heldout_failed = [], [], [], [], 0
    for X, w, gender in zip(H, W, H_gender):
        BVh = m.body_vertices(X).astype(np.float64)
        try:
            r = heldout_draper.solve(BVh, m.body_faces, shirt.binding.fit(X).astype(np.float64))
        except DrapeError:
            heldout_failed += 1
            continue
        record("mens_tshirt_heldout", s_rest, sF, BVh, m.body_faces, r)
        # the try-on as the service serves it (the basis, then the push-out of the body)
        cb = customer_body(m, w)
        tried = try_on(basis, cb)[0]
        err_reg.append(np.linalg.norm(tried - r.vertices, axis=1))
        err_surface.append(surface_distances(tried, r.vertices, sF))
        err_cd.append(np.linalg.norm(try_on(basis_cd, cb)[0] - r.vertices, axis=1))
        err_gender.append(gender)
    # the direct drape's own repeatability: the same drape from a start moved by ~2 mm (friction
    # and folds give cloth many resting shapes): the floor under the basis's figure
    rng = np.random.default_rng(0)
    # and from another reasonable start: the basis try-on there (where the exact drape job starts)
    rep, dep, job = [], [], []
    for X, w in zip(H[:REPEAT_BODIES], W[:REPEAT_BODIES]):
        BVh = m.body_vertices(X).astype(np.float64)
        init = shirt.binding.fit(X).astype(np.float64)
        a = heldout_draper.solve(BVh, m.body_faces, init).vertices
        b = heldout_draper.solve(BVh, m.body_faces, init + rng.normal(0, REPEAT_START_NOISE_M, init.shape)).vertices
        rep.append(1000 * np.linalg.norm(a - b, axis=1))
        cb = customer_body(m, w)
        tried = try_on(basis, cb)[0].astype(np.float64)
        c = heldout_draper.solve(BVh, m.body_faces, tried).vertices
        dep.append(1000 * np.linalg.norm(a - c, axis=1))
        # the exact drape job's own start (the basis's start channel: where the build's drapes started)
        d = heldout_draper.solve(BVh, m.body_faces, drape_start(basis, cb)).vertices
        job.append(1000 * np.linalg.norm(tried - d, axis=1))
    rep_mm, dep_mm, job_mm = np.concatenate(rep), np.concatenate(dep), np.concatenate(job)
    rows["drape_repeatability_mm"] = {"value": float(rep_mm.mean()), "p99": float(np.percentile(rep_mm, 99)),
                                      "bodies": len(rep), "start_noise_mm": 1000 * REPEAT_START_NOISE_M}
    rows["drape_start_dependence_mm"] = {"value": float(dep_mm.mean()), "p99": float(np.percentile(dep_mm, 99)),
                                         "bodies": len(dep), "starts": "warp fit vs basis try-on"}
    rows["basis_vs_exact_drape_mm"] = {"value": float(job_mm.mean()), "p99": float(np.percentile(job_mm, 99)),
                                       "bodies": len(job)}
    er, ec = 1000 * np.concatenate(err_reg), 1000 * np.concatenate(err_cd)
    per_gender = {f"{g}_mean_mm": float(1000 * np.concatenate([e for e, eg in zip(err_reg, err_gender)
                                                               if eg == g]).mean()) for g in sorted(set(err_gender))}
    rows["basis_vs_drape_mean_mm"] = {"value": float(er.mean()), "goal": 3.0, "heldout": len(err_reg),
                                      "heldout_failed": heldout_failed, "population": population,
                                      "garment_gender": shirt.gender, **per_gender,
                                      "central_diff_mean_mm": float(ec.mean())}
    rows["basis_vs_drape_p99_mm"] = {"value": float(np.percentile(er, 99)), "goal": 12.0,
                                     "central_diff_p99_mm": float(np.percentile(ec, 99))}
    es = 1000 * np.concatenate(err_surface)
    rows["basis_vs_drape_surface_mm"] = {"value": float(es.mean()), "p99": float(np.percentile(es, 99)),
                                         "heldout": len(err_surface)}
    rows["whole_build_s"] = {"value": build_s, "goal": 300.0, "drapes": len(dfits.drapes),
                             "n_vertices": len(s_rest),
                             "median_drape_s": float(np.median([st["seconds"] for st in dfits.stats])),
                             # the build's own drapes (examples and population bodies, not in the rows
                             # above): crossings left, example avatars' solves that fell back, population
                             # bodies left out (solved without the fallback: those that would need it fail)
                             "build_self_intersections": int(sum(st.get("self_intersections", 0) for st in dfits.stats)),
                             "build_drapes_with_crossings": int(sum(st.get("self_intersections", 0) > 0
                                                                    for st in dfits.stats)),
                             "build_fallbacks": int(sum("fallback" in st for st in dfits.stats)),
                             "build_failed": int(sum("failed" in st for st in dfits.stats))}

    # 8. a catalogue garment on 5 held-out bodies vs Newton VBD: ease at each girth region, hem height
    if newton and why is None:
        from service.model.garments import sizing as SZ
        from service.model.drape import start_outside
        from tests.bench.drape_newton import garment_on_body

        knit = FABRICS["knit"]
        sec = SZ.GarmentSections(sF, len(s_rest))
        ease_diff: list[np.ndarray] = []
        ease_diff_vertex: list[np.ndarray] = []
        ease_diff_cloth: list[np.ndarray] = []  # the cloth's length along the sections instead of a tape
        ease_diff_full: list[np.ndarray] = []
        ours_girths: list[np.ndarray] = []
        full_ours: list[np.ndarray] = []
        hem_diff, hem_diff_full, newton_s, full_s, speeds = [], [], [], [], []
        ref_inside = full_inside = 0
        # the drapes' state under our energy: ours, Newton's (plain) and Newton's with our contacts
        physics: dict[str, list[dict]] = {"ours": [], "newton": [], "newton_full_contact": []}
        people = heldout_avatars(m)[: NEWTON_BODIES]
        spec = SZ.region_spec(m)
        people_regs = [spec.regions(X) for X in people]
        chest = [r["chest"].body_girth for r in people_regs]
        full_people = {int(i) for i in np.argsort(chest)[::-1][:newton_full]}
        for person, X in enumerate(people):
            BVh = m.body_vertices(X).astype(np.float64)
            init = shirt.binding.fit(X).astype(np.float64)
            ours = shirt_draper.solve(BVh, m.body_faces, init).vertices.astype(np.float64)
            start = start_outside(init, BVh, m.body_faces, shirt_draper.config)
            ref = garment_on_body(s_rest, sF, start, BVh, m.body_faces, knit.density_kg_per_m2,
                                  knit.stretch_stiffness_n_per_m, knit.bending_stiffness_nm, knit.friction,
                                  seconds=NEWTON_SECONDS, radius_m=NEWTON_RADIUS_M)
            regs = people_regs[person]
            # the T-shirt is closed all around: a section that runs into a sleeve is no girth
            ours_girths.append(SZ.garment_girths(sec, ours, regs, closed=True, tape=True))
            ref_g = SZ.garment_girths(sec, ref["vertices"], regs, closed=True, tape=True)
            ease_diff_cloth.append(SZ.garment_girths(sec, ours, regs, closed=True)
                                   - SZ.garment_girths(sec, ref["vertices"], regs, closed=True))
            ease_diff.append(ours_girths[-1] - ref_g)
            ours_v = vertex_draper.solve(BVh, m.body_faces, init).vertices.astype(np.float64)
            ease_diff_vertex.append(SZ.garment_girths(sec, ours_v, regs, closed=True, tape=True) - ref_g)
            hem_diff.append(100 * abs(ours[:, 1].min() - ref["vertices"][:, 1].min()))
            physics["ours"].append(_cloth_state(shirt_draper, ours))
            physics["newton"].append(_cloth_state(shirt_draper, ref["vertices"]))
            ref_inside += _inside(ref["vertices"], BVh, m.body_faces)
            newton_s.append(ref["seconds"])
            speeds.append(ref["max_speed_m_s"])
            # the same with Newton's self-contact on and the body's faces in its contact, as ours, on
            # the newton_full people of these with the largest chests (where the contact model matters)
            if person not in full_people:
                continue
            full = garment_on_body(s_rest, sF, start, BVh, m.body_faces, knit.density_kg_per_m2,
                                   knit.stretch_stiffness_n_per_m, knit.bending_stiffness_nm, knit.friction,
                                   seconds=NEWTON_SECONDS, radius_m=NEWTON_RADIUS_M, full_contact=True)
            full_ours.append(ours_girths[-1])
            ease_diff_full.append(ours_girths[-1] - SZ.garment_girths(sec, full["vertices"], regs, closed=True, tape=True))
            hem_diff_full.append(100 * abs(ours[:, 1].min() - full["vertices"][:, 1].min()))
            full_inside += _inside(full["vertices"], BVh, m.body_faces)
            full_s.append(full["seconds"])
            physics["newton_full_contact"].append({"person": person, **_cloth_state(shirt_draper, full["vertices"])})
        per, per_vertex, per_cloth = _per_region(ease_diff), _per_region(ease_diff_vertex), _per_region(ease_diff_cloth)
        # the other garments: hip and thigh (the T-shirt has neither), on people of their gender
        others = {gid: _garment_vs_newton(m, gid, min(newton_full, cap)) for gid, (_, cap) in NEWTON_GARMENTS.items()}
        rows["ease_vs_newton_mm"] = {"value": max([*per.values(), *(b["max_mm"] for b in others.values())]),
                                     "goal": 5.0, "bodies": len(ease_diff),
                                     "garment": "mens-tshirt",
                                     **{f"{r}_max_mm": v for r, v in per.items()},
                                     **{f"{gid}_{k}": v for gid, b in others.items() for k, v in b.items()
                                        if k not in ("hem_cm", "full")},
                                     "cloth_length_max_mm": max(per_cloth.values()),
                                     "vertex_contact_max_mm": max(per_vertex.values()),
                                     **{f"vertex_contact_{r}_max_mm": v for r, v in per_vertex.items()},
                                     "bodies_mm": _bodies_mm(ease_diff),
                                     "newton_s_median": float(np.median(newton_s)),
                                     "newton_max_speed_m_s": float(max(speeds)), "newton_seconds_simulated": NEWTON_SECONDS,
                                     "newton_inside_vertices": ref_inside}
        rows["hem_vs_newton_cm"] = {"value": float(max([*hem_diff, *(b["hem_cm"] for b in others.values())])),
                                    "goal": 1.0, "mens-tshirt": float(max(hem_diff)),
                                    **{gid: b["hem_cm"] for gid, b in others.items()}}
        if not ease_diff_full:
            rows["ease_vs_newton_full_contact_mm"] = {"value": None, "skipped": "off (--newton-full-contact N)"}
        else:
            per_full = _per_region(ease_diff_full)
            full_others = {gid: b["full"] for gid, b in others.items() if b["full"]}
            rows["ease_vs_newton_full_contact_mm"] = {
                "value": max([*per_full.values(), *(b["max_mm"] for b in full_others.values())]),
                "bodies": len(ease_diff_full), "garment": "mens-tshirt",
                **{f"{r}_max_mm": v for r, v in per_full.items()},
                **{f"{gid}_{k}": v for gid, b in full_others.items() for k, v in b.items()},
                "bodies_mm": _bodies_mm(ease_diff_full),
                # girths ours has where the reference's section at that height does not go around the body
                # alone (its armpits lower: the section runs into a sleeve)
                "unmeasured": int((np.isfinite(np.array(full_ours)) & ~np.isfinite(np.array(ease_diff_full))).sum()),
                "hem_cm": float(max(hem_diff_full)), "hem_bodies_cm": [round(float(h), 2) for h in hem_diff_full],
                "newton_s_median": float(np.median(full_s)), "newton_inside_vertices": full_inside}
        rows["membrane_energy_vs_newton"] = _physics_row(physics)
    else:
        rows["ease_vs_newton_mm"] = {"value": None, "goal": 5.0, "skipped": why or "skipped (--no-newton)"}

    # 9. the plain GLB posed by skinning alone: the catalogue's bottoms in the page's poses
    from tests.bench.tryon import bench_pose_stretch, catalogue_bases

    bottoms = {k: v for k, v in catalogue_bases(m, ex, E).items() if v[1] == "bottom"}
    pose = bench_pose_stretch(m, bottoms)
    ps = pose["per_garment"]
    worst = max(ps, key=lambda k: ps[k]["after"])
    rows["walking_step_stretch"] = {"value": float(ps[worst]["after"]), "goal": 1.5, "garment": worst,
                                    "where": ps[worst]["worst"], "percentile": 99.9,
                                    "avatar_skin": round(float(pose["avatar"]), 3),
                                    "relative_to_body": round(float(ps[worst]["after_relative"]), 3),
                                    **{f"{k}": round(float(v["after"]), 3) for k, v in ps.items()}}

    rows["inside_vertices"] = {"value": inside, "goal": 0}
    rows["self_intersections"] = {"value": selfx, "goal": 0}
    return out


def _per_region(diffs: list[np.ndarray]) -> dict[str, float]:
    """{region: mm}: the largest |difference| over the bodies at each of ``GIRTH_REGIONS`` that
    some body has (diffs: per body (R,) cm, NaN where the garment has no such region)."""
    from service.model.garments import sizing as SZ

    D = np.abs(np.array(diffs))
    return {r: float(10 * np.nanmax(D[:, i])) for i, r in enumerate(SZ.GIRTH_REGIONS) if np.isfinite(D[:, i]).any()}


def _bodies_mm(diffs: list[np.ndarray]) -> list[list[float | None]]:
    """Each body's signed differences (diffs: per body (R,) cm) in mm to 0.1, None where NaN."""
    return [[None if not np.isfinite(v) else round(10 * float(v), 1) for v in d] for d in diffs]


def _garment_vs_newton(m, gid: str, full: int = 0) -> dict:
    """A catalogue garment of ``NEWTON_GARMENTS`` (``gid``, in its demo fabric) draped from its
    warp fit on the first ``NEWTON_BODIES`` held-out people of its gender here and by Newton VBD
    (plain contact, as the T-shirt's row): the largest ease difference at each girth region it
    has (mm, ours minus Newton's: ``{region}_max_mm``, ``max_mm`` over them), each person's
    (``bodies_mm``, NaN as None where a section does not go around the region: a low waistband,
    a crotch seam below the thigh's plane), the largest hem height difference (``hem_cm``),
    Newton's seconds (median) and its vertices > 1 mm inside the body. A top's sections are read
    closed, as the T-shirt's (one that runs into a sleeve is no girth); a bottom's may be open.
    On the ``full`` of those people with the largest body girth named in ``NEWTON_GARMENTS``, the
    same against Newton VBD with the contacts ours has (``garment_on_body(full_contact=True)``, as
    the T-shirt's full-contact row): the ``full`` entry, {} when ``full`` is 0."""
    from service.application.demo import DEMO_FABRICS
    from service.model.drape import FABRICS, Config, precompute, start_outside
    from service.model.garments import sizing as SZ
    from service.model.garments.catalogue import load_catalogue
    from tests.bench.common import heldout_avatars, heldout_genders
    from tests.bench.drape_newton import garment_on_body

    item = next(i for i in load_catalogue().garments() if i.id == gid)
    fabric = DEMO_FABRICS.get(gid, "woven")
    F = item.faces.astype(np.int64)
    rest = item.binding.fit(np.asarray(m.mean, np.float64)).astype(np.float64)
    fab = FABRICS[fabric]
    draper = precompute(rest, F, fabric, Config(clearance_m=NEWTON_RADIUS_M))
    sec, spec = SZ.GarmentSections(F, len(rest)), SZ.region_spec(m)
    closed = item.category == "top"
    H, genders = heldout_avatars(m), heldout_genders()
    people = [X for X, g in zip(H, genders) if g == item.gender or item.gender == "unisex"][:NEWTON_BODIES]
    regs_of = [spec.regions(X) for X in people]
    pick_by = [r[NEWTON_GARMENTS[gid][0]].body_girth for r in regs_of]
    full_people = {int(i) for i in np.argsort(pick_by)[::-1][:full]}
    diffs, cloth, hems, seconds, inside = [], [], [], [], 0
    f_diffs, f_hems, f_seconds, f_inside = [], [], [], 0
    for person, (X, regs) in enumerate(zip(people, regs_of)):
        BV = m.body_vertices(X).astype(np.float64)
        init = item.binding.fit(X).astype(np.float64)
        ours = draper.solve(BV, m.body_faces, init).vertices.astype(np.float64)
        start = start_outside(init, BV, m.body_faces, draper.config)
        ref = garment_on_body(rest, F, start, BV, m.body_faces, fab.density_kg_per_m2, fab.stretch_stiffness_n_per_m,
                              fab.bending_stiffness_nm, fab.friction, seconds=NEWTON_SECONDS, radius_m=NEWTON_RADIUS_M)
        ours_g = SZ.garment_girths(sec, ours, regs, closed, tape=True)
        diffs.append(ours_g - SZ.garment_girths(sec, ref["vertices"], regs, closed, tape=True))
        cloth.append(SZ.garment_girths(sec, ours, regs, closed) - SZ.garment_girths(sec, ref["vertices"], regs, closed))
        hems.append(100 * abs(ours[:, 1].min() - ref["vertices"][:, 1].min()))
        seconds.append(ref["seconds"])
        inside += _inside(ref["vertices"], BV, m.body_faces)
        if person not in full_people:
            continue
        ref = garment_on_body(rest, F, start, BV, m.body_faces, fab.density_kg_per_m2, fab.stretch_stiffness_n_per_m,
                              fab.bending_stiffness_nm, fab.friction, seconds=NEWTON_SECONDS, radius_m=NEWTON_RADIUS_M,
                              full_contact=True)
        f_diffs.append(ours_g - SZ.garment_girths(sec, ref["vertices"], regs, closed, tape=True))
        f_hems.append(100 * abs(ours[:, 1].min() - ref["vertices"][:, 1].min()))
        f_seconds.append(ref["seconds"])
        f_inside += _inside(ref["vertices"], BV, m.body_faces)
    per, per_cloth = _per_region(diffs), _per_region(cloth)
    out = {"max_mm": max(per.values(), default=float("nan")), **{f"{r}_max_mm": v for r, v in per.items()},
           "cloth_length_max_mm": max(per_cloth.values(), default=float("nan")),
           "bodies_mm": _bodies_mm(diffs),
           "hem_cm": float(max(hems)), "fabric": fabric, "bodies": len(people),
           "newton_s_median": float(np.median(seconds)), "newton_inside_vertices": inside, "full": {}}
    if f_diffs:
        per_full = _per_region(f_diffs)
        out["full"] = {"max_mm": max(per_full.values(), default=float("nan")),
                       **{f"{r}_max_mm": v for r, v in per_full.items()},
                       "bodies_mm": _bodies_mm(f_diffs),
                       "hem_cm": float(max(f_hems)), "hem_bodies_cm": [round(float(h), 2) for h in f_hems],
                       "bodies": len(f_diffs), "newton_s_median": float(np.median(f_seconds)),
                       "newton_inside_vertices": f_inside}
    return out


def _cloth_state(draper, x: np.ndarray) -> dict:
    """A drape x (N, 3) of ``draper``'s garment under our energy: its membrane energy (J: in-plane
    stretch and shear against the rest shape), total energy (J, gravity's potential included) and
    the shares of its triangles compressed past the fabric's ``compress_limit_pct`` (cloth buckles
    instead) and stretched past its ``stretch_limit_pct``."""
    x = np.asarray(x, np.float64)
    terms = draper.energy_terms(x)
    s = draper.principal_stretches(x)
    fab = draper.fabric
    return {"membrane_j": terms["membrane"], "energy_j": sum(terms.values()),
            "compressed_share": float((s[:, 1] < 1 - fab.compress_limit_pct / 100).mean()),
            "overstretched_share": float((s[:, 0] > 1 + fab.stretch_limit_pct / 100).mean())}


def _physics_row(physics: dict[str, list[dict]]) -> dict:
    """The ``membrane_energy_vs_newton`` row: the median over the people of our drape's membrane
    energy over Newton's (both under our energy), each person's, and the triangle shares of
    :func:`_cloth_state` (medians) for ours and each reference."""
    ours, plain, full = physics["ours"], physics["newton"], physics["newton_full_contact"]
    ratio = [o["membrane_j"] / max(n["membrane_j"], 1e-12) for o, n in zip(ours, plain)]
    row = {"value": float(np.median(ratio)), "bodies": len(ratio),
           "bodies_ratio": [round(r, 2) for r in ratio]}
    for name, states in (("ours", ours), ("newton", plain), ("newton_full_contact", full)):
        if not states:
            continue
        for key in ("membrane_j", "energy_j", "compressed_share", "overstretched_share"):
            row[f"{name}_{key}_median"] = float(np.median([st[key] for st in states]))
    if full:
        row["full_contact_ratio"] = [round(ours[st["person"]]["membrane_j"] / max(st["membrane_j"], 1e-12), 2)
                                     for st in full]
    return row


def _layered(m, E: np.ndarray) -> dict:
    """The ``layered_slide_cm`` row: the catalogue's ``LAYERED_GARMENT`` draped (at the build's
    clearance, in its demo fabric) on the first ``LAYERED_BODIES`` example avatars with its
    layers tied (``Config.tie_m``) and untied: how far its two largest pieces of cloth slid
    apart (the difference of their median height changes, cm, worst body), the face pairs
    crossing between its pieces of cloth (small parts left out: a button may be sewn through the
    cloth at rest) and the solves' seconds."""
    from service.application.demo import DEMO_FABRICS
    from service.model.drape import Config, precompute
    from service.model.drape.solver import small_parts
    from service.model.garments.catalogue import load_catalogue
    from service.model.garments.draped import DRAPE_CLEARANCE_M
    from service.model.geometry import mesh as geometry

    item = next(i for i in load_catalogue().garments() if i.id == LAYERED_GARMENT)
    F = item.faces.astype(np.int64)
    rest = item.binding.fit(np.asarray(m.mean, np.float64)).astype(np.float64)
    fabric = DEMO_FABRICS.get(item.id, "woven")
    label = geometry.vertex_components(F, len(rest))
    _, host = small_parts(rest, F, Config().part_max_extent_m)
    cloth = F[host]
    pieces, counts = np.unique(label[cloth[:, 0]], return_counts=True)
    a, b = pieces[np.argsort(counts)[::-1][:2]]
    out: dict = {"garment": LAYERED_GARMENT, "fabric": fabric, "n_vertices": len(rest), "bodies": LAYERED_BODIES}
    for name, tie in (("tied", Config().tie_m), ("untied", 0.0)):
        draper = precompute(rest, F, fabric, Config(clearance_m=DRAPE_CLEARANCE_M, tie_m=tie))
        slides, crossings, seconds = [], [], []
        for i in range(LAYERED_BODIES):
            init = item.binding.fit(E[i]).astype(np.float64)
            r = draper.solve(m.body_vertices(E[i]).astype(np.float64), m.body_faces, init)
            x = r.vertices.astype(np.float64)
            dy = x[:, 1] - init[:, 1]
            slides.append(100 * abs(float(np.median(dy[label == a]) - np.median(dy[label == b]))))
            pairs = geometry.intersecting_face_pairs(x, cloth)
            crossings.append(int((label[cloth[pairs[:, 0], 0]] != label[cloth[pairs[:, 1], 0]]).sum()) if len(pairs)
                             else 0)
            seconds.append(r.stats["seconds"])
        out[name] = {"slide_cm": [round(v, 2) for v in slides], "crossings": crossings,
                     "seconds_median": float(np.median(seconds)), "ties": int(len(draper.tie_vertex))}
    out["value"] = float(max(out["tied"]["slide_cm"]))
    out["baseline_untied_cm"] = float(max(out["untied"]["slide_cm"]))
    return out


def format_result(res: dict) -> str:
    lines = [f"{'figure':<26}{'value':>10}{'goal':>8}  detail"]
    for k, v in res["rows"].items():
        val = v.get("value")
        sval = "skipped" if val is None else (f"{val:.3f}" if isinstance(val, float) else str(val))
        detail = ", ".join(f"{a}={b:.3g}" if isinstance(b, float) else f"{a}={b}"
                           for a, b in v.items() if a not in ("value", "goal"))
        lines.append(f"{k:<26}{sval:>10}{str(v.get('goal', '-')):>8}  {detail}")
    lines.append("")
    lines.append(f"{'drape':<22}{'verts':>7}{'s':>8}{'iters':>7}{'settled':>9}{'inside':>8}{'selfx':>7}")
    for d in res["drapes"]:
        lines.append(f"{d['case']:<22}{d['n_vertices']:>7}{d['seconds']:>8.2f}{d['iterations']:>7}"
                     f"{str(d['settled']):>9}{d['inside']:>8}{d['self_intersections']:>7}")
    return "\n".join(lines)

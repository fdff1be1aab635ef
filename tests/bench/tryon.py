"""``tryon bench tryon`` and ``tryon bench examples``: garment accuracy of the clothing basis on
held-out avatars, penetration, in-process try-on latency, GLB bytes, HTTP load on loopback; and
the example-set sweep that chose N and c."""
from __future__ import annotations

import asyncio
import time

import numpy as np
from scipy.spatial import cKDTree

from service.model.garments import demo_garments as D
from service.model.formats import gltf
from service.model.body import shape as S
from service.model.garments import tryon as T
from service.model.body.model import load_body_model
from service.model.geometry.mesh import closest_point_on_triangles, vertex_faces, winding_numbers
from tests.bench.common import heldout_avatars, makehuman_garments, median_ms, read_ansur
from tests.harness import run_server


def bench_garments(model) -> dict:
    """All benchmark garments: the demo ones, a 10k-vertex skirt, and MakeHuman's."""
    demos = D.make_demo_garments(model)
    out = {f"demo-{n}": ((lambda X, g=g: g.fit(model, X)), g.faces) for n, g in demos.items()}
    big = D.DemoGarment("skirt", D.skirt_faces(64, 160))
    out["demo-skirt-10k"] = ((lambda X: D.skirt_rings(model, X, rings=64, angles=160)), big.faces)
    out.update({f"mh-{k}": v for k, v in makehuman_garments(model).items()})
    return out


def penetration_depths(garment: np.ndarray, body: np.ndarray, faces: np.ndarray, tree, vert_faces) -> np.ndarray:
    """Depth (m, > 0 inside) of each garment vertex below the body surface: exact distance to
    the closest triangle among those around the 8 nearest body vertices; inside means a
    generalised winding number > 1/2. garment (M, 3), body (V, 3)."""
    _, nn = tree.query(garment, k=8)
    cand = vert_faces[nn].reshape(len(garment), -1)
    valid = cand >= 0
    tri = body[faces[np.where(valid, cand, 0)]]  # (M, C, 3, 3)
    p = garment[:, None, :]
    a, b, c = tri[..., 0, :], tri[..., 1, :], tri[..., 2, :]
    q = closest_point_on_triangles(p, a, b, c)
    d = np.linalg.norm(p - q, axis=-1)
    d = np.where(valid, d, np.inf)
    j = np.argmin(d, axis=1)
    r = np.arange(len(garment))
    n = np.cross(b[r, j] - a[r, j], c[r, j] - a[r, j])
    sign = np.sign(np.einsum("ij,ij->i", garment - q[r, j], n))
    depth = -sign * d[r, j]
    # the face-normal sign misfires near convex edges: confirm every "inside" candidate with
    # the generalised winding number (exact)
    cand = np.flatnonzero(depth > 0)
    if len(cand):
        outside = winding_numbers(garment[cand], body, faces) < 0.5
        depth[cand[outside]] = -depth[cand[outside]]
    return depth


def penetrations(garment: np.ndarray, body: np.ndarray, body_normals: np.ndarray, faces: np.ndarray, tree,
                 vert_faces) -> tuple[np.ndarray, np.ndarray, int]:
    """The penetration figure's count for one try-on: (depths (M,) as
    :func:`penetration_depths`, garment vertices more than 1 mm inside the body (ids), how
    many others were left out as inside the avatar's own self-intersection). garment (M, 3),
    body (V, 3) float64, body_normals (V, 3), tree over body."""
    dep = penetration_depths(np.asarray(garment, np.float64), body, faces, tree, vert_faces)
    bad = np.flatnonzero(dep > 0.001)
    if not len(bad):
        return dep, bad, 0
    # where the avatar's own skin is inside the body (heavy inner thighs overlapping), no
    # cloth between can be outside: count those apart
    _, nn = tree.query(garment[bad])
    probe = body[nn] + 0.002 * body_normals[nn]
    own = winding_numbers(probe, body, faces) > 0.5
    return dep, bad[~own], int(own.sum())


def bench_tryon(limit: int, repeats: int, only: str | None = None) -> dict:
    """The whole suite, or with ``only="latency"`` the in-process try-on latency rows alone
    (sections 3, 4b and the template fast path beside the reference path)."""
    if only is not None and only != "latency":
        raise ValueError(f"--only: 'latency' or nothing, got {only!r}")
    model = load_body_model()
    nb = model.n_body_vertices
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    garments = bench_garments(model)
    if only == "latency":
        return bench_latency(model, ex, EX, garments["demo-skirt-10k"], repeats)
    bases = {}
    for name, (fit, faces) in garments.items():
        fits = np.stack([fit(E) for E in EX])
        bases[name] = T.build_garment_basis(model, fits, faces, ex)
    res: dict = {"suite": "tryon", "examples": {"n": ex.n, "c": ex.c, "count": 1 + 2 * ex.n},
                 "garments": {k: v.n_vertices for k, v in bases.items()}}

    # 1. accuracy on held-out avatars: basis-fitted vs fitted directly by the same method
    H = heldout_avatars(model)
    if limit:
        H = H[:limit]
    W = model.project(H)
    per = {}
    all_err = []
    for name, (fit, _) in garments.items():
        errs = []
        for Xh, w in zip(H, W):
            direct = fit(Xh)
            synth = T.G.synthesize(bases[name].g, bases[name].B, w)
            errs.append(np.linalg.norm(synth - direct, axis=1))
        e = np.concatenate(errs) * 1000
        per[name] = {"mean_mm": float(e.mean()), "p99_mm": float(np.percentile(e, 99))}
        all_err.append(e)
    e = np.concatenate(all_err)
    res["accuracy_mm"] = {"avatars": len(H), "mean": float(e.mean()), "p99": float(np.percentile(e, 99)),
                          "goal": {"mean": 2.0, "p99": 8.0}, "per_garment": per}

    # 2. penetration over random customers (held-out ANSUR subjects' measurements)
    rng = np.random.default_rng(1)
    held = read_ansur(heldout=True)
    specs = {a.name: a for a in model.attributes}
    held = [h for h in held if all(specs[k].min <= v <= specs[k].max for k, v in h["measurements"].items() if k != "gender")]
    n_cust = 200 if not limit else min(200, max(20, limit))
    picks = rng.choice(len(held), size=n_cust, replace=False)
    vert_faces = vertex_faces(model.body_faces, nb)
    inside, selfx, total, worst = 0, 0, 0, 0.0
    per_pen = {k: 0 for k in bases}
    for i in picks:
        fitc = S.avatar_from_measurements(model, held[i]["measurements"])
        body = T.customer_body(model, fitc.weights)
        tree = cKDTree(body.vertices[:nb])
        for name, basis in bases.items():
            v, _ = T.try_on(basis, body)
            Xb = body.vertices[:nb].astype(np.float64)
            dep, bad, own = penetrations(v, Xb, body.normals, model.body_faces, tree, vert_faces)
            selfx += own
            inside += len(bad)
            per_pen[name] += len(bad)
            total += len(v)
            if len(bad):
                worst = max(worst, float(dep[bad].max()))
    res["penetration"] = {"customers": int(n_cust), "garments": len(bases), "vertices_checked": int(total),
                          "vertices_more_than_1mm_inside": int(inside), "deepest_mm": 1000 * worst,
                          "inside_avatar_self_intersections": int(selfx), "per_garment": per_pen, "goal": 0}

    # 3. in-process try-on of a 10k-vertex garment: synthesis + push-out + GLB, beside synthesis
    basis = bases["demo-skirt-10k"]
    bodies = [T.customer_body(model, S.avatar_from_measurements(model, held[i]["measurements"]).weights)
              for i in picks[:10]]
    it = iter(range(10**9))
    g, B = np.asarray(basis.g), np.asarray(basis.B)
    t_syn = median_ms(lambda: T.G.synthesize(g, B, bodies[next(it) % 10].weights), repeats)

    def full(compression=None):
        body = bodies[next(it) % 10]
        v, _ = T.try_on(basis, body)
        return gltf.mesh_to_glb(v, basis.faces, normals=basis.normals(v, body.weights), name="garment",
                                compression=compression)

    t_full = median_ms(full, repeats)
    firsts = []
    for i in picks[10:20]:  # first try-on of a garment on a body: + nearest-vertex binding
        body = T.customer_body(model, S.avatar_from_measurements(model, held[i]["measurements"]).weights)
        t0 = time.perf_counter()
        T.try_on(basis, body)
        firsts.append(time.perf_counter() - t0)
    res["timing_ms"] = {"garment_vertices": basis.n_vertices, "synthesis_3MN": t_syn,
                        "tryon_synthesis_pushout_glb": t_full, "ratio": t_full / t_syn, "goal": 2.0,
                        "first_tryon_per_customer_and_garment": 1000 * float(np.median(firsts)),
                        "multiply_adds": 3 * basis.n_vertices * ex.n}

    # 4. GLB bytes: the fitted 10k garment and its morph-target basis, plain vs compressed
    sizes = {}
    for mode in (None, "quantize", "meshopt"):
        key = mode or "plain"
        sizes[key] = {"tryon_glb": len(full(mode)),
                      "basis_glb": len(gltf.basis_to_glb(basis.g, basis.B, basis.faces, compression=mode))}
    res["glb_bytes"] = {"garment_vertices": basis.n_vertices, "morph_targets": ex.n, **sizes}

    # 4b. textures: the 10k garment textured (UV seams split, base colour + normal map) through
    # the service's try-on path, beside the untextured one; texture bytes per try-on GLB
    res["textures"] = bench_textures(model, basis, bodies, repeats)

    # 5. HTTP on loopback with concurrent clients
    res["http"] = bench_http()

    # 6. pose stretch (skin weights) and layering
    res.update(bench_clothes_motion(limit))
    return res


def customers(model, n: int = 10) -> list:
    """n held-out ANSUR customers' bodies (the same as the suite's first n penetration picks)."""
    rng = np.random.default_rng(1)
    held = read_ansur(heldout=True)
    specs = {a.name: a for a in model.attributes}
    held = [h for h in held if all(specs[k].min <= v <= specs[k].max for k, v in h["measurements"].items() if k != "gender")]
    picks = rng.choice(len(held), size=200, replace=False)
    return [T.customer_body(model, S.avatar_from_measurements(model, held[i]["measurements"]).weights)
            for i in picks[:n]]


def bench_latency(model, ex, EX, skirt, repeats: int) -> dict:
    """``--only latency``: the try-on route's in-process work (``scenes.outfit_glb`` for one
    garment: synthesis, push-out, normals, render layout, GLB bytes) for the 10k-vertex skirt
    (untextured; textured: UV seams split, base colour + normal map) and the demo catalogue's
    largest textured garment (the business suit), every compression mode: the template fast
    path (the basis' static arrays encoded once) beside the reference path (everything per
    request, the code before templates: the same bytes), interleaved in the same run. Wall-clock
    medians, and medians of the thread's CPU time (``time.thread_time``: what a request costs
    without the waits for a core that a shared, loaded machine adds)."""
    import dataclasses

    from service.application import scenes
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment

    fit, faces = skirt
    plain = T.build_garment_basis(model, np.stack([fit(E) for E in EX]), faces, ex)
    cat = load_catalogue()
    lay = skirt_layout()
    textured = dataclasses.replace(plain, render_vertex=lay.vertex.astype(np.int32), render_uv=lay.uv,
                                   render_faces=lay.faces.astype(np.int32),
                                   material=dataclasses.replace(cat.items["cropped-tee"].material),
                                   _render_skin=None, _render_tangents=None)
    suit = cat.items["business-suit"]
    suit_basis = T.build_garment_basis(model, np.stack([suit.fit_to(E) for E in EX]), suit.faces, ex,
                                       layout=suit.render_layout(), material=suit.material)
    cases = {"skirt-10k": plain, "skirt-10k-textured": textured, "business-suit": suit_basis}
    bodies = customers(model)
    rec = Garment(id="bench", body_model=model.version, owner="bench", name="garment", source="demo",
                  color=[0.5, 0.5, 0.5, 1.0], layer=0)
    out: dict = {"suite": "tryon", "only": "latency", "repeats": repeats,
                 "garments": {k: {"vertices": b.n_vertices,
                                  "render_vertices": int(len(b.render_vertex)) if b.has_layout else b.n_vertices}
                              for k, b in cases.items()},
                 "modes": {}, "goal_ms": 2.0}
    for name, basis in cases.items():
        for mode in (None, "quantize", "meshopt"):
            def once(i: int, template: bool) -> bytes:
                return scenes.outfit_glb(model, bodies[i % len(bodies)], [(rec, basis)], mode, with_avatar=False,
                                         template=template)

            for i in range(len(bodies)):  # warm: nearest-vertex bindings, render skin, template
                assert once(i, True) == once(i, False)
            ts: dict = {"reference": [], "template": []}
            cpu: dict = {"reference": [], "template": []}
            for i in range(repeats):  # interleaved: both see the same machine load
                for key in ts:
                    t0, c0 = time.perf_counter(), time.thread_time()
                    once(i, key == "template")
                    ts[key].append(time.perf_counter() - t0)
                    cpu[key].append(time.thread_time() - c0)
            ref, fast = (1000.0 * float(np.median(ts[k])) for k in ("reference", "template"))
            cref, cfast = (1000.0 * float(np.median(cpu[k])) for k in ("reference", "template"))
            out["modes"].setdefault(name, {})[mode or "plain"] = {
                "reference_ms": ref, "template_ms": fast, "speedup": ref / fast,
                "reference_cpu_ms": cref, "template_cpu_ms": cfast, "cpu_speedup": cref / cfast,
                "glb_bytes": len(once(0, True))}
    out["outfit"] = bench_outfit_latency(model, ex, EX, bodies, min(repeats, 12))
    return out


OUTFIT = ("striped-shirt", "casual-jacket")  # a shirt under an open jacket: the layering's hardest pair


def bench_outfit_latency(model, ex, EX, bodies, repeats: int) -> dict:
    """``outfit.glb`` in process (``scenes.outfit_glb``: the avatar, two catalogue garments
    layered -- the shirt pushed inside the jacket and skinned like it where covered -- and, with
    the default look, the underwear pushed inside both), on ``repeats`` customers; median wall
    and thread CPU ms, bare (no look) and with the look."""
    from service.application import look as looks
    from service.application import scenes
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment

    cat = load_catalogue()
    worn = []
    for gid in OUTFIT:
        it = cat.items[gid]
        basis = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex,
                                      layout=it.render_layout(), material=it.material)
        worn.append((Garment(id=gid, body_model=model.version, owner="bench", name=gid, source="demo",
                             color=[0.5, 0.5, 0.5, 1.0], layer=it.layer or 0), basis))
    worn.sort(key=lambda g: g[0].layer)
    out: dict = {"garments": list(OUTFIT), "customers": repeats}
    # bare and look: every request layered (the process cache of layered outfits off: a new
    # customer or outfit); look_again: the same customer and outfit asked again (cache on)
    for label, lk, cache in (("bare", None, False), ("look", looks.resolve("female"), False),
                             ("look_again", looks.resolve("female"), True)):
        wall, cpu = [], []
        for i in range(repeats):
            if cache:
                scenes.outfit_glb(model, bodies[i % len(bodies)], worn, None, look=lk, cache=True)
            t0, c0 = time.perf_counter(), time.thread_time()
            scenes.outfit_glb(model, bodies[i % len(bodies)], worn, None, look=lk, cache=cache)
            wall.append(time.perf_counter() - t0)
            cpu.append(time.thread_time() - c0)
        out[label] = {"wall_ms": 1000.0 * float(np.median(wall)), "cpu_ms": 1000.0 * float(np.median(cpu))}
    return out


def format_latency(r: dict) -> str:
    L = [f"try-on route in process (scenes.outfit_glb, one garment, 10 customers), median ms of {r['repeats']}, "
         f"reference path (everything per request) vs template (static arrays once per basis), interleaved in the "
         f"same run; wall clock and the thread's CPU time; goal <= {r['goal_ms']} ms for 10k vertices",
         f"  {'garment':<20}{'vertices':>9}{'render':>8}  {'mode':<9}{'wall ref':>9}{'templ':>8}{'x':>6}"
         f"{'cpu ref':>9}{'templ':>8}{'x':>6}{'bytes':>9}"]
    for name, modes in r["modes"].items():
        g = r["garments"][name]
        for mode, v in modes.items():
            L.append(f"  {name:<20}{g['vertices']:>9}{g['render_vertices']:>8}  {mode:<9}{v['reference_ms']:>9.3f}"
                     f"{v['template_ms']:>8.3f}{v['speedup']:>6.2f}{v['reference_cpu_ms']:>9.3f}"
                     f"{v['template_cpu_ms']:>8.3f}{v['cpu_speedup']:>6.2f}{v['glb_bytes']:>9}")
    o = r.get("outfit")
    if o:
        L.append(f"outfit.glb in process ({' under '.join(o['garments'])} with the avatar, layered), median of "
                 f"{o['customers']} customers: bare {o['bare']['wall_ms']:.0f} ms wall / {o['bare']['cpu_ms']:.0f} ms CPU; "
                 f"with the default look (underwear layered too) {o['look']['wall_ms']:.0f} / {o['look']['cpu_ms']:.0f} ms; "
                 f"asked again (layering cached) {o['look_again']['wall_ms']:.0f} / {o['look_again']['cpu_ms']:.0f} ms")
    return "\n".join(L)


def skirt_layout(rings: int = 64, angles: int = 160):
    """A render layout of the demo skirt grid (``D.skirt_faces``): u around (a seam where the
    rings close: one extra uv column), v down the rings."""
    from service.model.garments.catalogue import render_layout

    r, a = np.meshgrid(np.arange(rings - 1), np.arange(angles), indexing="ij")
    t0 = (r * (angles + 1) + a).reshape(-1)
    t1 = (r * (angles + 1) + a + 1).reshape(-1)
    face_uv = np.concatenate([np.stack([t0, t1 + angles + 1, t1], 1), np.stack([t0, t0 + angles + 1, t1 + angles + 1], 1)])
    U, V = np.meshgrid(np.arange(angles + 1) / angles, 1.0 - np.arange(rings) / (rings - 1))
    uv = np.stack([U, V], axis=-1).reshape(-1, 2)
    return render_layout(D.skirt_faces(rings, angles), face_uv, uv)


def bench_textures(model, basis, bodies, repeats: int) -> dict:
    """P1 try-on latency of ``basis`` (the 10k-vertex skirt) with and without its look (measured
    in the same run through ``scenes.garment_mesh`` + ``gltf.scene_to_glb``), and the texture
    bytes of every demo-catalogue item's try-on GLB."""
    import dataclasses

    from service.application import scenes
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment

    cat = load_catalogue()
    mat = dataclasses.replace(cat.items["cropped-tee"].material)  # base colour + normal textures
    lay = skirt_layout()
    textured = dataclasses.replace(basis, render_vertex=lay.vertex.astype(np.int32), render_uv=lay.uv,
                                   render_faces=lay.faces.astype(np.int32), material=mat, _render_skin=None,
                                   _render_tangents=None)
    rec = Garment(id="bench", body_model=model.version, owner="bench", name="skirt", source="demo",
                  color=[0.5, 0.5, 0.5, 1.0], layer=1)
    skel = {k: v for k, v in scenes.skeleton(model, bodies[0].vertices).items()}
    it = iter(range(10**9))

    def run(b, compression=None):
        body = bodies[next(it) % len(bodies)]
        return gltf.scene_to_glb([scenes.garment_mesh(b, rec, body, 0)], skin=skel, compression=compression)

    for b in (basis, textured):  # warm: bindings, render skin, mean tangents
        for body in bodies:
            scenes.garment_mesh(b, rec, body, 0)
    ts: dict = {"plain": [], "tex": []}
    for _ in range(repeats):  # interleaved: both see the same machine load
        for key, b in (("plain", basis), ("tex", textured)):
            t0 = time.perf_counter()
            run(b)
            ts[key].append(time.perf_counter() - t0)
    t_plain, t_tex = (1000.0 * float(np.median(ts[k])) for k in ("plain", "tex"))
    sizes = {mode or "plain": {"untextured": len(run(basis, mode)), "textured": len(run(textured, mode))}
             for mode in (None, "quantize", "meshopt")}
    per_item = {}
    for item in cat.garments():
        m = item.material
        per_item[item.id] = sum(len(t.data) for t in (m.base_color_texture, m.normal_texture) if t is not None)
    vals = np.array(list(per_item.values()))
    return {"garment_vertices": basis.n_vertices, "render_vertices": int(len(lay.vertex)),
            "texture_bytes_bench_garment": sum(len(t.data) for t in (mat.base_color_texture, mat.normal_texture)),
            "tryon_glb_ms": {"untextured": t_plain, "textured": t_tex, "ratio": t_tex / t_plain, "goal": 2.0},
            "glb_bytes": sizes,
            "catalogue_texture_bytes": {"items": len(per_item), "min": int(vals.min()), "median": float(np.median(vals)),
                                        "max": int(vals.max()), "per_item": per_item}}


def format_textures(x: dict) -> list[str]:
    t, c = x["tryon_glb_ms"], x["catalogue_texture_bytes"]
    L = [f"\ntextures: {x['garment_vertices']}-vertex garment, {x['render_vertices']} render vertices (UV seams "
         f"split), base colour + normal map ({x['texture_bytes_bench_garment']} texture bytes)",
         f"  skinned try-on GLB (synthesis + push-out + GLB), median ms: untextured {t['untextured']:.3f}, "
         f"textured {t['textured']:.3f} (x{t['ratio']:.2f}; goal <= 2 ms)",
         f"  {'':<10}{'untextured':>12}{'textured':>12}"]
    for k, v in x["glb_bytes"].items():
        L.append(f"  {k:<10}{v['untextured']:>12}{v['textured']:>12}")
    L.append(f"  texture bytes per try-on GLB, {c['items']} demo catalogue items: min {c['min']}, median "
             f"{c['median']:.0f}, max {c['max']}")
    return L


def format_tryon(r: dict) -> str:
    if r.get("only") == "latency":
        return format_latency(r)
    L = [f"examples: N = {r['examples']['n']} components, c = {r['examples']['c']} "
         f"({r['examples']['count']} example avatars); {len(r['garments'])} garments"]
    a = r["accuracy_mm"]
    L.append(f"\ngarment accuracy on {a['avatars']} held-out avatars (basis vs direct fit): mean {a['mean']:.3f} mm, "
             f"p99 {a['p99']:.3f} mm (goal <= 2 / <= 8)")
    L.append(f"  {'garment':<34}{'vertices':>9}{'mean mm':>10}{'p99 mm':>10}")
    for k, v in a["per_garment"].items():
        L.append(f"  {k:<34}{r['garments'][k]:>9}{v['mean_mm']:>10.3f}{v['p99_mm']:>10.3f}")
    p = r["penetration"]
    L.append(f"\npenetration: {p['customers']} customers x {p['garments']} garments, {p['vertices_checked']} vertices: "
             f"{p['vertices_more_than_1mm_inside']} more than 1 mm inside (goal 0); deepest {p['deepest_mm']:.2f} mm; "
             f"plus {p['inside_avatar_self_intersections']} where the avatar's own skin is inside the body "
             f"(overlapping inner thighs)")
    t = r["timing_ms"]
    L.append(f"\nin-process try-on, {t['garment_vertices']}-vertex garment (median ms)")
    L.append(f"  bare synthesis (3MN = {t['multiply_adds']} multiply-adds)   {t['synthesis_3MN']:8.3f}")
    L.append(f"  synthesis + push-out + GLB bytes            {t['tryon_synthesis_pushout_glb']:8.3f}  "
             f"(x{t['ratio']:.1f}; goal <= 2 ms)")
    L.append(f"  first try-on of a garment on a body (+ nearest-vertex binding, then cached) "
             f"{t['first_tryon_per_customer_and_garment']:8.3f}")
    b = r["glb_bytes"]
    L.append(f"\nGLB bytes, {b['garment_vertices']} vertices ({b['morph_targets']} morph targets in the basis)")
    L.append(f"  {'':<10}{'try-on':>12}{'basis':>12}")
    for k in ("plain", "quantize", "meshopt"):
        L.append(f"  {k:<10}{b[k]['tryon_glb']:>12}{b[k]['basis_glb']:>12}")
    if "textures" in r:
        L += format_textures(r["textures"])
    h = r["http"]
    L.append(f"\nHTTP on loopback (same 2 cores for clients and {h['server_workers']} server processes), "
             f"{h['seconds']} s per row; try-on of {h['garments']} demo garments")
    L.append(f"  {'clients':>7}  {'try-on p50':>10} {'p99':>8} {'req/s':>8}   {'healthz p50':>11} {'p99':>7} {'req/s':>8}")
    for row in h["levels"]:
        t, z = row["tryon"], row["healthz"]
        L.append(f"  {row['clients']:>7}  {t['p50_ms']:>8.2f}ms {t['p99_ms']:>6.2f}ms {t['rps']:>8.1f}   "
                 f"{z['p50_ms']:>9.2f}ms {z['p99_ms']:>5.2f}ms {z['rps']:>8.1f}"
                 + (f"  ({t['errors'] + z['errors']} errors)" if t['errors'] + z['errors'] else ""))
    L.append("  goal (try-on): p50 <= 10 ms, p99 <= 30 ms, >= 500 req/s")
    if "pose_stretch" in r:
        L.append(format_clothes_motion(r))
    return "\n".join(L)


# -- HTTP load on loopback ------------------------------------------------------------------
async def _load(port: int, paths: list[str], clients: int, seconds: float,
                headers: str = "") -> tuple[list[float], int]:
    """``clients`` keep-alive connections, each requesting paths round-robin for ``seconds``.
    Returns (latencies in seconds, non-200 count). Raw asyncio streams: light on the client
    side, so the server keeps most of the CPU."""
    lat: list[float] = []
    errors = 0
    stop = time.perf_counter() + seconds

    async def client(k: int):
        nonlocal errors
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        i = k
        while time.perf_counter() < stop:
            path = paths[i % len(paths)]
            i += 1
            t = time.perf_counter()
            writer.write(f"GET {path} HTTP/1.1\r\nHost: bench\r\n{headers}\r\n".encode())
            await writer.drain()
            head = await reader.readuntil(b"\r\n\r\n")
            length = 0
            for line in head.split(b"\r\n"):
                if line.lower().startswith(b"content-length:"):
                    length = int(line.split(b":")[1])
            await reader.readexactly(length)
            lat.append(time.perf_counter() - t)
            if not head.startswith(b"HTTP/1.1 200"):
                errors += 1
        writer.close()

    await asyncio.gather(*(client(k) for k in range(clients)))
    return lat, errors


def bench_http(levels: tuple[int, ...] = (1, 4, 8, 16), seconds: float = 6.0, workers: int = 2) -> dict:
    """p50/p99 and requests/s of try-on GETs (the demo garments, one customer) against a real
    ``tryon serve`` on loopback (its own embedded Redis in a temporary directory), at several
    numbers of concurrent keep-alive clients, beside ``/healthz`` (the framework's own floor)
    measured the same way in the same run. With C clients, p50 ~ C / throughput (Little's law):
    latency is a function of concurrency."""
    with run_server(None, "embedded", workers=workers, log_level="warning", check_log=False) as server:
        client = server.client
        garments = [g["id"] for g in client.get("/v1/garments").json()]
        created = client.post("/v1/customers", json={"measurements": {
            "gender": "female", "height_cm": 166, "weight_kg": 68, "waist_cm": 80}}).json()
        cust, auth = created["id"], f"Authorization: Bearer {created['token']}\r\n"
        paths = [f"/v1/customers/{cust}/garments/{g}.glb" for g in garments]
        for _ in range(4 * workers):  # warm every server process (customer body, mmapped bases)
            for p in paths:
                client.get(p, headers={"Authorization": f"Bearer {created['token']}"})
        out = {"seconds": seconds, "server_workers": workers, "garments": len(paths), "levels": []}
        for clients in levels:
            row = {"clients": clients}
            for name, ps in (("healthz", ["/healthz"]), ("tryon", paths)):
                lat, errors = asyncio.run(_load(server.port, ps, clients, seconds, auth))
                a = np.array(lat) * 1000
                row[name] = {"requests": len(a), "errors": errors, "p50_ms": float(np.percentile(a, 50)),
                             "p99_ms": float(np.percentile(a, 99)), "rps": len(a) / seconds}
            out["levels"].append(row)
        out["goal"] = {"p50_ms": 10, "p99_ms": 30, "rps": 500}
        return out


def bench_examples(limit: int, repeats: int) -> dict:
    """Choose the example avatars by measurement: garment accuracy (basis vs direct fit on
    held-out avatars) for a grid of N (components) and c (std units), over the demo garments
    and a spread of MakeHuman garments."""
    model = load_body_model()
    H = heldout_avatars(model)[: (limit or 20)]
    W = model.project(H)
    garments = bench_garments(model)
    names = [n for n in garments if n.startswith("demo-") and n != "demo-skirt-10k"] + \
        ["mh-male_casualsuit04", "mh-female_elegantsuit01", "mh-shoes01"]
    directs = {n: [garments[n][0](X) for X in H] for n in names}
    rows = []
    for n_comp in (8, 12, 16, 24, 32, 48):
        for c in (0.5, 1.0, 2.0):
            ex = T.example_set(model, n=n_comp, c=c)
            EX = T.example_vertices(model, ex)
            errs = []
            for name in names:
                fit = garments[name][0]
                g, B = T.G.build_basis(np.stack([fit(E) for E in EX]), ex)
                for w, d in zip(W, directs[name]):
                    errs.append(np.linalg.norm(T.G.synthesize(g, B, w) - d, axis=1))
            e = np.concatenate(errs) * 1000
            rows.append({"n": n_comp, "c": c, "examples": 1 + 2 * n_comp, "mean_mm": float(e.mean()),
                         "p99_mm": float(np.percentile(e, 99))})
    return {"suite": "examples", "avatars": len(H), "garments": names, "grid": rows,
            "current": dict(T.EXAMPLES)}


def format_examples(r: dict) -> str:
    L = [f"garment accuracy vs example set ({r['avatars']} held-out avatars; {', '.join(r['garments'])})",
         f"  {'N':>3}{'c':>6}{'examples':>10}{'mean mm':>10}{'p99 mm':>10}"]
    for row in r["grid"]:
        mark = "  <- current" if (row["n"], row["c"]) == (r["current"]["n"], r["current"]["c"]) else ""
        L.append(f"  {row['n']:>3}{row['c']:>6.1f}{row['examples']:>10}{row['mean_mm']:>10.3f}{row['p99_mm']:>10.3f}{mark}")
    return "\n".join(L)


# -- clothes that move like clothes: pose stretch and layering ------------------------------------
FIVE_BODIES = {
    "160/55 woman": {"gender": "female", "height_cm": 160, "weight_kg": 55},
    "185/80 man": {"gender": "male", "height_cm": 185, "weight_kg": 80},
    "165/105 woman": {"gender": "female", "height_cm": 165, "weight_kg": 105},
    "200/130 man": {"gender": "male", "height_cm": 200, "weight_kg": 130},
    "150/45 man": {"gender": "male", "height_cm": 150, "weight_kg": 45},
}
STRETCH_PERCENTILE = 99.9
INSIDE_DEPTH = 0.003  # metres: a garment vertex deeper than this inside the posed body counts
SHOW_THROUGH_DEPTH = 0.0  # metres: the body shows through where the garment is this far inside it
COVER_DISTANCE = 0.05  # metres: a body vertex is covered when the garment is this close over it
SHOW_THROUGH_CATEGORIES = ("bottom", "demo", "suit")


def covered_points(body: np.ndarray, body_faces: np.ndarray, garment: np.ndarray, faces: np.ndarray) -> tuple:
    """The rest body's (V, 3) vertices covered by the garment (M, 3) within ``COVER_DISTANCE``
    (``skin_weights.covered_points``): (body vertex ids (K,), garment face (K,), barycentric
    (K, 3)), fixed garment points to follow through a pose."""
    from service.model.garments.skin_weights import covered_points as covered

    return covered(body, body_faces, garment, faces, max_distance=COVER_DISTANCE)


def show_through(covered: tuple, garment: np.ndarray, faces: np.ndarray, body: np.ndarray,
                 normals: np.ndarray) -> float:
    """Share of the covered body vertices (:func:`covered_points`) whose garment point, posed with
    the garment (M, 3) and body (V, 3) / normals, lies more than ``SHOW_THROUGH_DEPTH`` inside the
    body along its normal: the skin showing through (a skirt's front opened by the forward
    thigh in a walking step)."""
    ids, face, bary = covered
    if not len(ids):
        return 0.0
    q = np.einsum("kc,kcj->kj", bary, np.asarray(garment, np.float64)[np.asarray(faces)[face]])
    along = np.einsum("ij,ij->i", q - body[ids], normals[ids])
    return float((along < -SHOW_THROUGH_DEPTH).mean())


def catalogue_bases(model, ex, EX) -> dict:
    """The MakeHuman catalogue's garments (fit_to each example avatar) and the demo shells as
    clothing bases: {name: (basis, category, layer)}."""
    from service.model.garments.catalogue import load_catalogue

    out = {}
    for n, g in D.make_demo_garments(model).items():
        out[f"demo-{n}"] = (T.build_garment_basis(model, np.stack([g.fit(model, E) for E in EX]), g.faces, ex),
                            "demo", None)
    for it in load_catalogue().garments():
        if it.fit.skinning != "transfer":
            continue
        out[it.id] = (T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex),
                      it.category, it.layer)
    return out


def bench_pose_stretch(model, bases: dict, reference: dict | None = None, correctives: bool = False,
                       ref_switch: str | None = None) -> dict:
    """99.9th-percentile edge stretch (posed / rest length) of every garment in the page's four
    poses (adapted to each body) on the five bodies: nearest-vertex skin weights (before) vs the
    inpainted transfer (after); beside it the avatar's own skin, the garment's stretch relative
    to the body's under it (each edge's ratio over the largest edge ratio of the body triangles
    closest to its two ends), and how well the garment follows the body: the p95 change of each
    garment vertex's distance to the body surface, posed vs rest (mm). Also, per garment, the
    share of its vertices more than ``INSIDE_DEPTH`` inside the posed body (all bodies and poses
    pooled) and, for bottoms, the body showing through it in the walking step
    (:func:`show_through`), worst body. ``reference``: bases of the same garments built another
    way (e.g. the previous skin weights), measured alongside ("ref_*" keys). ``correctives``: the
    garments posed with their pose-corrective morph target at influence 1
    (``service.model.garments.correctives``, as ``?pose_correctives=1`` serves them; the "ref_*" keys
    without), and the time to compute them. ``ref_switch``: the reference ("ref_*", the same
    bases) posed with its corrective targets too, computed with that switch of
    ``service.model.garments.correctives`` off (e.g. ``"STRAIN_LIMITING"``)."""
    from service.model.garments import correctives as C
    from service.model.body import lbs as L
    from service.model.body import poses as P
    from service.model.geometry.mesh import closest_points_on_mesh, mesh_edges

    nb = model.n_body_vertices
    Fb = model.body_faces
    per = {k: {"before": 1.0, "after": 1.0, "after_relative": 1.0, "gap_change_mm_before": 0.0,
               "gap_change_mm_after": 0.0, "worst": "", "inside": 0, "n": 0, "show_through_pct": 0.0,
               "show_through_160_55_pct": 0.0, "ref_after": 1.0, "ref_inside": 0, "ref_show_through_pct": 0.0,
               "ref_show_through_160_55_pct": 0.0} for k in bases}
    vf = vertex_faces(Fb, nb)
    avatar = 1.0
    t_adapt, t_corr, t_posed = [], [], []
    for bname, meas in FIVE_BODIES.items():
        X = S.avatar_from_measurements(model, meas).vertices
        body = T.customer_body(model, model.project(X))
        rest = body.vertices[:nb].astype(np.float64)
        t0 = time.perf_counter()
        poses = P.adapted_poses(model, body.vertices)
        t_adapt.append(time.perf_counter() - t0)
        fits = {k: T.try_on(b, body)[0].astype(np.float64) for k, (b, _, _) in bases.items()}
        under = {k: closest_points_on_mesh(v, rest, Fb) for k, v in fits.items()}
        covered = {k: covered_points(rest, Fb, fits[k], b.faces) for k, (b, c, _) in bases.items()
                   if c in SHOW_THROUGH_CATEGORIES}
        rest_body = C.posed_body(model, body.vertices, np.zeros((len(model.bone_parents), 3))) \
            if correctives else None
        for pname, pose in poses.items():
            posed = model.forward(pose=pose, vertices=body.vertices)
            pb = posed.vertices[:nb]
            tree = cKDTree(pb)
            pn = None
            delta = {k: 0.0 for k in bases}
            ref_delta = {k: 0.0 for k in bases}
            if correctives:
                t0 = time.perf_counter()
                cb = C.posed_body(model, body.vertices, pose)
                t_posed.append(time.perf_counter() - t0)
                for k, (b, _, _) in bases.items():
                    t0 = time.perf_counter()
                    delta[k] = C.corrective_deltas(fits[k], b.skin_idx, b.skin_w, cb, b.smoother(), 0,
                                                   rest=rest_body, faces=b.faces)[0].astype(np.float64)
                    t_corr.append(time.perf_counter() - t0)
                    if ref_switch:
                        keep = getattr(C, ref_switch)
                        setattr(C, ref_switch, False)
                        try:
                            ref_delta[k] = C.corrective_deltas(fits[k], b.skin_idx, b.skin_w, cb, b.smoother(), 0,
                                                               rest=rest_body, faces=b.faces)[0].astype(np.float64)
                        finally:
                            setattr(C, ref_switch, keep)
            for k, (b, _, _) in bases.items():
                for pre, bb in (("", b), ("ref_", (reference or {}).get(k, (None,))[0])):
                    if bb is None:
                        continue
                    pv = L.skin(fits[k] + (delta[k] if pre == "" else ref_delta[k]), posed.transforms, bb.skin_idx,
                                bb.skin_w)
                    per[k][pre + "inside"] += int((penetration_depths(pv, pb, Fb, tree, vf) > INSIDE_DEPTH).sum())
                    if pre == "":
                        per[k]["n"] += len(pv)
                    if pre == "ref_":
                        per[k]["ref_after"] = max(per[k]["ref_after"], float(np.percentile(
                            P.edge_stretch(fits[k], pv, b.faces), STRETCH_PERCENTILE)))
                    if pname == "walking" and k in covered:
                        if pn is None:
                            from service.model.geometry.mesh import vertex_normals
                            pn = vertex_normals(pb, Fb).astype(np.float64)
                        st = 100 * show_through(covered[k], pv, bb.faces, pb, pn)
                        per[k][pre + "show_through_pct"] = max(per[k][pre + "show_through_pct"], st)
                        if bname == "160/55 woman":
                            per[k][pre + "show_through_160_55_pct"] = st
            avatar = max(avatar, float(np.percentile(P.edge_stretch(rest, pb, Fb), STRETCH_PERCENTILE)))
            face_stretch = np.max([np.linalg.norm(pb[Fb[:, a]] - pb[Fb[:, c]], axis=1) /
                                   np.linalg.norm(rest[Fb[:, a]] - rest[Fb[:, c]], axis=1)
                                   for a, c in ((0, 1), (1, 2), (2, 0))], axis=0)
            for k, (b, _, _) in bases.items():
                v = fits[k]
                face, q, _ = under[k]
                gap = np.linalg.norm(v - q, axis=1)
                e = mesh_edges(b.faces)
                ok = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1) > 1e-9
                body_s = np.maximum(face_stretch[face[e[ok, 0]]], face_stretch[face[e[ok, 1]]])
                near = b.binding[:, 0]
                for which, (idx, w) in (("before", (model.lbs_indices[near], model.lbs_weights[near])),
                                        ("after", (b.skin_idx, b.skin_w))):
                    pv = L.skin(v + (delta[k] if which == "after" else 0.0), posed.transforms, idx, w)
                    s = P.edge_stretch(v, pv, b.faces)
                    p = float(np.percentile(s, STRETCH_PERCENTILE))
                    if which == "after":
                        if p > per[k]["after"]:
                            per[k]["worst"] = f"{bname}, {pname}"
                        per[k]["after_relative"] = max(per[k]["after_relative"],
                                                       float(np.percentile(s / body_s, STRETCH_PERCENTILE)))
                    per[k][which] = max(per[k][which], p)
                    _, qp, _ = closest_points_on_mesh(pv, pb, Fb)
                    dg = 1000 * float(np.percentile(np.abs(np.linalg.norm(pv - qp, axis=1) - gap), 95))
                    per[k][f"gap_change_mm_{which}"] = max(per[k][f"gap_change_mm_{which}"], dg)
    garments = {k: v for k, v in per.items() if bases[k][1] != "shoes"}
    return {"bodies": list(FIVE_BODIES), "poses": 4, "percentile": STRETCH_PERCENTILE, "per_garment": per,
            "avatar": avatar, "goal": 1.5, "adapt_poses_s_median": float(np.median(t_adapt)),
            "worst_before": max(v["before"] for v in per.values()),
            "worst_after": max(v["after"] for v in per.values()),
            "median_after": float(np.median([v["after"] for v in garments.values()])),
            "median_after_relative": float(np.median([v["after_relative"] for v in garments.values()])),
            "median_gap_change_mm_before": float(np.median([v["gap_change_mm_before"] for v in garments.values()])),
            "median_gap_change_mm_after": float(np.median([v["gap_change_mm_after"] for v in garments.values()])),
            "reference": reference is not None, "correctives": correctives, "ref_switch": ref_switch,
            "correctives_ms_median": 1000 * float(np.median(t_corr)) if t_corr else None,
            "posed_body_ms_median": 1000 * float(np.median(t_posed)) if t_posed else None,
            "show_through": [k for k, (_, c, _) in bases.items() if c in SHOW_THROUGH_CATEGORIES]}


LAYER_PAIRS = [(b, t) for t in ("womens-tshirt", "pinstripe-blouse", "cropped-tee")
               for b in ("womens-jeans", "pencil-skirt", "sports-trousers")] + \
    [("mens-jeans", t) for t in ("mens-tshirt", "longsleeve-tee", "striped-shirt", "white-tshirt")] + \
    [("striped-shirt", "casual-jacket"), ("white-tshirt", "casual-jacket")]


def bench_layering(model, bases: dict, people: int, posed_people: int = 3, correctives: bool = False) -> dict:
    """Share of the body covered by two garments where the inner one is outside the outer one,
    before and after ``service.model.garments.layering.layer_outfit`` as ``outfit.glb`` runs it (the
    inner garment pushed inside and skinned like the outer one where covered), on top/bottom
    pairs and jacket over shirt, on held-out people; rest pose, and the page poses on the first
    ``posed_people``: "posed" re-matches closest points on the posed body, a garment covering
    only body vertices it moves with (``layering.MOVES_WITH``: a hand resting on a hip is not
    covered by the clothes there), "posed_any" without that test (the hand counts, as before
    2026-11-27), "posed_fixed" follows the rest pose's covered points through the pose
    (``layering.posed_outside``). ``correctives``: also the posed figures with both garments'
    pose-corrective targets at influence 1 (inner rank 0, outer rank 1, the inner one following
    the outer one where covered, as ``outfit.glb`` makes them): rows "posed_correctives" and "posed_fixed_correctives", before = layered without
    them (the "after" of "posed" / "posed_fixed"), after = with them."""
    from service.model.garments import correctives as C
    from service.model.garments import layering as LY
    from service.model.body import lbs as L
    from service.model.body import poses as P
    from service.model.body.model import BONES
    from service.model.geometry.mesh import vertex_normals

    nb = model.n_body_vertices
    H = heldout_avatars(model)[:people]
    tot = {"rest": [0, 0, 0], "posed": [0, 0, 0], "posed_any": [0, 0, 0], "posed_fixed": [0, 0, 0]}  # both covered, inner outside before, after
    if correctives:
        tot.update({"posed_correctives": [0, 0, 0], "posed_fixed_correctives": [0, 0, 0]})
    per = {f"{i} under {o}": [0, 0, 0] for i, o in LAYER_PAIRS}
    t_layer = []
    for h, Xh in enumerate(H):
        body = T.customer_body(model, model.project(Xh))
        Bv = body.vertices[:nb].astype(np.float64)
        Bn = body.normals.astype(np.float64)
        poses = P.adapted_poses(model, body.vertices) if h < posed_people else {}
        cbodies = {k: C.posed_body(model, body.vertices, p) for k, p in poses.items()} if correctives else {}
        rest_body = C.posed_body(model, body.vertices, np.zeros((len(BONES), 3))) if correctives else None
        for inner, outer in LAYER_PAIRS:
            bi, bo = bases[inner][0], bases[outer][0]
            vi = T.try_on(bi, body, 0)[0].astype(np.float64)
            vo = T.try_on(bo, body, 1)[0].astype(np.float64)
            si, so = (bi.skin_idx, bi.skin_w), (bo.skin_idx, bo.skin_w)
            t0 = time.perf_counter()
            (vi2, _), sk = LY.layer_outfit([(vi, bi.faces), (vo, bo.faces)], Bv, Bn, skins=[si, so], n_joints=len(BONES))
            t_layer.append(time.perf_counter() - t0)
            si2 = sk[0]
            body_skin = (model.lbs_indices[:nb], model.lbs_weights[:nb])
            states = [("rest", Bv, Bn, vi, vi2, vo)]
            pairs = LY.layered_pairs(vi2, bi.faces, vo, bo.faces, Bv, Bn)  # the same surface points before/after
            for name, pose in poses.items():
                if name == "a-pose":
                    continue
                G = model.forward(pose=pose, vertices=body.vertices).transforms
                PB = L.skin(Bv, G, model.lbs_indices[:nb], model.lbs_weights[:nb])
                PN = vertex_normals(PB, model.body_faces).astype(np.float64)
                a, b, o = L.skin(vi, G, *si), L.skin(vi2, G, *si2), L.skin(vo, G, *so)
                states.append(("posed", PB, PN, a, b, o))
                acc = tot["posed_fixed"]
                acc[0] += len(pairs[0])
                acc[1] += LY.posed_outside(pairs, a, bi.faces, o, bo.faces, PB, PN)
                acc[2] += LY.posed_outside(pairs, b, bi.faces, o, bo.faces, PB, PN)
                if correctives and name in cbodies:
                    cb = cbodies[name]
                    po = C.posed_pushes(vo, *so, cb, bo.smoother(), 1, rest=rest_body, faces=bo.faces)[0]
                    pi = C.posed_pushes(vi2, *si2, cb, bi.smoother(), 0, rest=rest_body, faces=bi.faces)[0]
                    pi = C.follow_outer(pi, C.cover_map(vi2, vo, bo.faces, Bv, Bn), po, bo.faces)
                    di, do = C.to_rest(pi, G, *si2), C.to_rest(po, G, *so)
                    bc, oc = L.skin(vi2 + di, G, *si2), L.skin(vo + do, G, *so)
                    acc = tot["posed_fixed_correctives"]
                    acc[0] += len(pairs[0])
                    acc[1] += LY.posed_outside(pairs, b, bi.faces, o, bo.faces, PB, PN)
                    acc[2] += LY.posed_outside(pairs, bc, bi.faces, oc, bo.faces, PB, PN)
                    both, out0 = LY.inner_outside_share(b, o, bo.faces, bi.faces, PB, PN, model.body_faces,
                                                        skins=(body_skin, si2, so))
                    _, out1 = LY.inner_outside_share(bc, oc, bo.faces, bi.faces, PB, PN, model.body_faces,
                                                     skins=(body_skin, si2, so))
                    acc = tot["posed_correctives"]
                    acc[0] += both
                    acc[1] += out0
                    acc[2] += out1
            for key, PB, PN, a, b, o in states:
                for k, s0, s1 in ((key, (body_skin, si, so), (body_skin, si2, so)),
                                  *((("posed_any", None, None),) if key == "posed" else ())):
                    both, out0 = LY.inner_outside_share(a, o, bo.faces, bi.faces, PB, PN, model.body_faces, skins=s0)
                    _, out1 = LY.inner_outside_share(b, o, bo.faces, bi.faces, PB, PN, model.body_faces, skins=s1)
                    for acc in (tot[k], per[f"{inner} under {outer}"] if k == "rest" else [0, 0, 0]):
                        acc[0] += both
                        acc[1] += out0
                        acc[2] += out1
    share = {k: {"both_covered": v[0], "before_pct": 100 * v[1] / max(v[0], 1), "after_pct": 100 * v[2] / max(v[0], 1)}
             for k, v in tot.items()}
    return {"people": len(H), "posed_people": min(posed_people, len(H)), "pairs": len(LAYER_PAIRS), **share,
            "per_pair_rest": {k: {"both": v[0], "before_pct": 100 * v[1] / max(v[0], 1),
                                  "after_pct": 100 * v[2] / max(v[0], 1)} for k, v in per.items()},
            "layer_outfit_ms_median": 1000 * float(np.median(t_layer)), "goal_pct": 1.0}


def bench_clothes_motion(limit: int) -> dict:
    model = load_body_model()
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    bases = catalogue_bases(model, ex, EX)
    return {"pose_stretch": bench_pose_stretch(model, bases),
            "layering": bench_layering(model, bases, people=limit or 10)}


def pose_stretch_catalogue(before: str | None = None) -> dict:
    """Only the pose-stretch rows of :func:`bench_clothes_motion` (the catalogue's bases built
    as at service start). ``before="leg_ramp"`` / ``"limb_side"``: also the bases without
    ``T.SKIN_LEG_RAMP`` / ``T.SKIN_LIMB_SIDE``, measured alongside. ``before="correctives"``:
    the garments with their pose-corrective morph targets (this) and without (reference);
    ``"strain_limit"``: with them, and with them computed without their strain limiting."""
    model = load_body_model()
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    reference = None
    switch = {"leg_ramp": "SKIN_LEG_RAMP", "limb_side": "SKIN_LIMB_SIDE", "screening": "SKIN_SCREENING"}.get(before or "")
    if switch:
        keep = getattr(T, switch)
        setattr(T, switch, False)
        try:
            reference = catalogue_bases(model, ex, EX)
        finally:
            setattr(T, switch, keep)
    t0 = time.perf_counter()
    bases = catalogue_bases(model, ex, EX)
    t_build = time.perf_counter() - t0
    ref_switch = {"strain_limit": "STRAIN_LIMITING"}.get(before or "")
    if before == "correctives" or ref_switch:
        reference = bases
    r = bench_pose_stretch(model, bases, reference, correctives=before == "correctives" or bool(ref_switch),
                           ref_switch=ref_switch)
    r["build_bases_s"] = t_build
    return r


def correctives_latency(repeats: int = 20, garments: tuple[str, ...] = ("pinstripe-blouse", "casual-jacket",
                                                                        "business-suit")) -> dict:
    """The try-on route's in-process work (``scenes.outfit_glb``, one garment, no avatar) without
    and with ``poses`` (pose-corrective targets), interleaved on 10 customers: "cached" (the
    same customer and garment again: the targets from the process cache), "targets" (computed;
    the posed bodies cached on the customer, as from the second garment on) and "cold" (the
    body posed anew too: a customer's first request), and "targets_no_strain_limit" (computed
    without the correctives' step 4, ``C.STRAIN_LIMITING``: its cost); the poses' adaptation
    (cached per customer by the service) apart. Median wall ms, and the GLB bytes."""
    from service.application import scenes
    from service.model.garments import correctives as C
    from service.model.body import poses as P
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment
    from service.storage.cache import VersionedLRU

    model = load_body_model()
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    cat = load_catalogue()
    bodies = customers(model)
    t0 = time.perf_counter()
    poses = [P.adapted_poses(model, b.vertices) for b in bodies]
    adapt = (time.perf_counter() - t0) / len(bodies)
    out: dict = {"repeats": repeats, "customers": len(bodies), "adapt_poses_ms_mean": 1000 * adapt, "garments": {}}
    for gid in garments:
        it = cat.items[gid]
        basis = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex,
                                      layout=it.render_layout(), material=it.material)
        rec = Garment(id=gid, body_model=model.version, owner="bench", name=gid, source="demo",
                      color=[0.5, 0.5, 0.5, 1.0], layer=0)
        for i, b in enumerate(bodies):  # warm: bindings, templates
            scenes.outfit_glb(model, b, [(rec, basis)], None, with_avatar=False)
        ts: dict = {"plain": [], "cached": [], "targets": [], "targets_no_strain_limit": [], "cold": []}
        sizes = {}
        for r in range(repeats):
            i = r % len(bodies)
            for key in ts:
                C.STRAIN_LIMITING = key != "targets_no_strain_limit"  # step 4 of the correctives off: its cost
                if key in ("targets", "targets_no_strain_limit", "cold"):  # the targets computed anew (a new
                    scenes._correctives = VersionedLRU(scenes.CORRECTIVES_CACHE_SIZE)  # outfit or garment)
                if key == "cold":  # and the posed bodies (the customer's first request)
                    bodies[i]._posed.clear()
                if key == "cached":  # the same customer and garment asked again
                    scenes.outfit_glb(model, bodies[i], [(rec, basis)], None, with_avatar=False, poses=poses[i])
                t0 = time.perf_counter()
                glb = scenes.outfit_glb(model, bodies[i], [(rec, basis)], None, with_avatar=False,
                                        poses=None if key == "plain" else poses[i])
                ts[key].append(time.perf_counter() - t0)
                sizes[key] = len(glb)
        med = {k: 1000 * float(np.median(v)) for k, v in ts.items()}
        out["garments"][gid] = {"vertices": basis.n_vertices, "ms": med,
                                "added_ms": {k: med[k] - med["plain"] for k in ("cached", "targets",
                                                                                 "targets_no_strain_limit", "cold")},
                                "glb_bytes": sizes}
    return out


def layering_catalogue(people: int = 3, correctives: bool = True) -> dict:
    """Only the layering rows of :func:`bench_clothes_motion` on ``people`` held-out people (all
    posed), with the pose correctives' rows (:func:`bench_layering`)."""
    model = load_body_model()
    ex = T.example_set(model)
    bases = catalogue_bases(model, ex, T.example_vertices(model, ex))
    return bench_layering(model, bases, people=people, posed_people=people, correctives=correctives)


def format_layering(y: dict) -> str:
    return "\n".join(format_clothes_motion({"pose_stretch": None, "layering": y}).splitlines()[1:])


def format_pose_stretch(s: dict) -> str:
    L = [f"\npose stretch: p{s['percentile']} edge length ratio in the 4 page poses (adapted per body) on "
         f"{len(s['bodies'])} bodies, worst body and pose (goal <= {s['goal']}); the avatar's own skin "
         f"{s['avatar']:.2f}; pose adaptation {s['adapt_poses_s_median']:.1f} s per body (median)",
         f"  {'garment':<22}{'before (nearest vertex)':>24}{'after (inpainted)':>19}{'after / body':>14}"
         f"{'gap change p95 mm':>20}  worst body, pose"]
    for k, v in s["per_garment"].items():
        L.append(f"  {k:<22}{v['before']:>24.2f}{v['after']:>19.2f}{v['after_relative']:>14.2f}"
                 f"{v['gap_change_mm_before']:>11.1f} -> {v['gap_change_mm_after']:<5.1f}  {v['worst']}")
    L.append(f"  worst {s['worst_before']:.2f} -> {s['worst_after']:.2f}; median garment (no shoes) after "
             f"{s['median_after']:.2f}, relative to the body under it {s['median_after_relative']:.2f}; gap change "
             f"median {s['median_gap_change_mm_before']:.1f} -> {s['median_gap_change_mm_after']:.1f} mm")
    L.append(f"  garment vertices > {1000 * INSIDE_DEPTH:.0f} mm inside the posed body (5 bodies x 4 poses pooled), "
             f"and the body showing through bottoms in the walking step (covered body vertices > "
             f"{1000 * SHOW_THROUGH_DEPTH:.0f} mm outside the garment; worst body | 160/55 woman)"
             + ("; reference -> this" if s.get("reference") else ""))
    for k, v in s["per_garment"].items():
        n = max(v["n"], 1)
        row = f"    {k:<22}inside {100 * v['inside'] / n:6.2f} %"
        if s.get("reference"):
            row = (f"    {k:<22}p99.9 {v['ref_after']:5.2f} -> {v['after']:5.2f}   inside "
                   f"{100 * v['ref_inside'] / n:6.2f} -> {100 * v['inside'] / n:6.2f} %")
        if k in s.get("show_through", ()):
            row += (f"   show-through {v['ref_show_through_pct']:5.1f} | {v['ref_show_through_160_55_pct']:5.1f} -> "
                    if s.get("reference") else "   show-through ") + \
                f"{v['show_through_pct']:5.1f} | {v['show_through_160_55_pct']:5.1f} %"
        L.append(row)
    if s.get("correctives"):
        ref = f"with, computed with {s['ref_switch']} off" if s.get("ref_switch") else "without"
        L.append(f"  pose correctives (reference: {ref}; this: with): {s['posed_body_ms_median']:.1f} ms per posed "
                 f"body (once per customer and pose), {s['correctives_ms_median']:.2f} ms per garment and pose (median)")
    if "build_bases_s" in s:
        L.append(f"  building the {len(s['per_garment'])} bases (fits + skin weights): {s['build_bases_s']:.1f} s")
    return "\n".join(L)


def format_clothes_motion(r: dict) -> str:
    y = r["layering"]
    L = [format_pose_stretch(r["pose_stretch"]) if r["pose_stretch"] else "",
         f"\nlayering: body vertices covered by two garments where the inner one is outside the outer "
         f"(goal <= {y['goal_pct']} %), {y['pairs']} pairs, {y['people']} held-out people "
         f"(posed: the 3 page poses on {y['posed_people']}); layer_outfit per pair {y['layer_outfit_ms_median']:.0f} ms median"]
    for k in [k for k in ("rest", "posed", "posed_any", "posed_fixed", "posed_correctives", "posed_fixed_correctives")
              if k in y]:
        L.append(f"  {k:<23} {y[k]['both_covered']:>8} covered by both: {y[k]['before_pct']:6.2f} % -> "
                 f"{y[k]['after_pct']:6.2f} %")
    for k, v in y["per_pair_rest"].items():
        L.append(f"    {k:<40}{v['both']:>8}{v['before_pct']:>8.2f} %{v['after_pct']:>8.2f} %")
    return "\n".join(L)

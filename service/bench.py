"""``tryon bench <suite> [--json]``: performance and accuracy figures.

Suites:
  body  PCA reconstruction of held-out avatars; measurements -> avatar on held-out ANSUR II
        subjects (all 12 entered: ISO 20685-1 share; gender + height + weight entered:
        estimation error beside a linear regression fitted on the training subjects in the
        same run); median times of measurements -> avatar and of measuring an avatar, beside
        baselines timed in the same run.
  fitting  body fitting of synthetic clothed/unclothed scans and point clouds of held-out
        avatars (``service/bench_fitting.py``; default 12 avatars, ``--limit`` sets the number),
        then jobs lost while workers are killed (``--no-kill`` skips it; needs Redis).

Held-out ANSUR subjects are those whose row index in their file is a multiple of 5 (no build
step sees them). ANSUR II is read from ``../shared/data`` (or ``TRYON_SHARED_DATA``).
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from service.model import measurements as M
from service.model import shape as S
from service.model.body import load_body_model
from service.model.geometry import closest_point_on_triangles, vertex_faces, winding_numbers


def heldout_avatars(model) -> np.ndarray:
    """(n, V, 3) held-out evaluation avatars stored beside the model artifact."""
    z = np.load(Path(model.path).parent / "heldout_avatars.npz")
    return model.mean[None].astype(np.float64) + z["offsets"].astype(np.float64) * float(z["scale"])


def shared_data_dir() -> Path:
    env = os.environ.get("TRYON_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def read_ansur(heldout: bool) -> list[dict]:
    """ANSUR II subjects in API units: {"row", "measurements": {12 attributes}}."""
    base = shared_data_dir() / "anthropometry" / "ansur2"
    out = []
    for fname, gender, enc in (("ANSUR_II_MALE_Public.csv", "male", "latin-1"),
                               ("ANSUR_II_FEMALE_Public.csv", "female", "ascii")):
        with open(base / fname, encoding=enc, newline="") as f:
            for i, r in enumerate(csv.DictReader(f)):
                if (i % 5 == 0) != heldout:
                    continue
                m = {"gender": gender}
                for name in M.ATTRIBUTES[1:]:
                    v = float(r[M.ANSUR_COLUMNS[name]])
                    m[name] = v / 10.0  # mm -> cm, and weightkg is in 0.1 kg
                out.append({"row": i, "measurements": m})
    return out


def _median_ms(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(ts))


def bench_body(limit: int, repeats: int) -> dict:
    model = load_body_model()
    rng = np.random.default_rng(0)
    res: dict = {"suite": "body", "components": model.n_components}

    # 1. PCA reconstruction of held-out avatars
    X = heldout_avatars(model)
    W = model.project(X)
    R = model.vertices(W).astype(np.float64)
    err = np.linalg.norm(R - X, axis=2) * 1000
    res["pca_reconstruction_mm"] = {"avatars": len(X), "mean": float(err.mean()),
                                    "max": float(err.max()),
                                    "goal": {"mean": 0.5, "max": 5.0}}

    held = read_ansur(heldout=True)
    train = read_ansur(heldout=False)
    if limit:
        held = [held[i] for i in sorted(rng.choice(len(held), size=min(limit, len(held)), replace=False))]
    specs = {a.name: a for a in model.attributes}

    def in_range(m):
        return all(specs[k].min <= v <= specs[k].max for k, v in m.items() if k != "gender")

    # 2. all 12 entered: re-measured error, ISO share
    names = list(M.ATTRIBUTES[1:])
    errs, ok, skipped = [], [], 0
    for s in held:
        m = s["measurements"]
        if not in_range(m):
            skipped += 1
            continue
        fit = S.avatar_from_measurements(model, m)
        e = np.array([fit.measurements[n] - m[n] for n in names])
        tol = np.array([M.ISO_TOLERANCE[n] * M.api_scale(n) for n in names])
        errs.append(e)
        ok.append(bool(np.all(np.abs(e) <= tol)))
    E = np.abs(np.array(errs))
    res["all12"] = {
        "subjects": len(errs), "outside_accepted_range": skipped,
        "within_iso_all_attributes": float(np.mean(ok)), "goal": 0.95,
        "per_attribute": {n: {"mean_abs": float(E[:, i].mean()), "p95_abs": float(np.percentile(E[:, i], 95)),
                              "within_iso": float(np.mean(E[:, i] <= M.ISO_TOLERANCE[n] * M.api_scale(n))),
                              "unit": "kg" if n == "weight_kg" else "cm"}
                          for i, n in enumerate(names)},
    }

    # 3. gender + height + weight entered: estimated attributes vs truth, beside a linear
    # regression (gender, height, weight -> attribute) fitted on the training subjects now
    given = ("gender", "height_cm", "weight_kg")
    est_names = [n for n in names if n not in given]

    def design(rows):
        return np.array([[1.0, 1.0 if r["gender"] == "male" else 0.0, r["height_cm"], r["weight_kg"]] for r in rows])

    Xtr = design([t["measurements"] for t in train])
    Ytr = np.array([[t["measurements"][n] for n in est_names] for t in train])
    coef, *_ = np.linalg.lstsq(Xtr, Ytr, rcond=None)
    ours, base = [], []
    for s in held:
        m = s["measurements"]
        if not in_range(m):
            continue
        fit = S.avatar_from_measurements(model, {k: m[k] for k in given})
        ours.append([fit.measurements[n] - m[n] for n in est_names])
        base.append(list(design([m])[0] @ coef - np.array([m[n] for n in est_names])))
    O, B = np.abs(np.array(ours)), np.abs(np.array(base))
    res["estimation_from_gender_height_weight"] = {
        "subjects": len(O),
        "per_attribute_mae_cm": {n: {"ours": float(O[:, i].mean()), "linear_regression": float(B[:, i].mean()),
                                     "ratio": float(O[:, i].mean() / B[:, i].mean())}
                                 for i, n in enumerate(est_names)},
        "mean_ratio": float(np.mean(O.mean(0) / B.mean(0))),
        "goal": "ratio <= 1 (no worse than the regression)",
    }

    # 4. timings (medians), beside baselines measured in the same run
    sample = held[: max(1, min(20, len(held)))]
    full = [s["measurements"] for s in sample if in_range(s["measurements"])]
    three = [{k: m[k] for k in given} for m in full]
    it = iter(range(10**9))

    t_avatar12 = _median_ms(lambda: S.avatar_from_measurements(model, full[next(it) % len(full)]), repeats)
    t_avatar3 = _median_ms(lambda: S.avatar_from_measurements(model, three[next(it) % len(three)]), repeats)
    prior = S._prior(model)

    def regression_only():
        m = full[next(it) % len(full)]
        prior.condition({i: (S.GENDER_CODE[m[n]] if n == "gender" else m[n]) for i, n in enumerate(M.ATTRIBUTES)}, {})

    t_regress = _median_ms(regression_only, repeats)
    Xs = [model.vertices(S.avatar_from_measurements(model, m).weights) for m in full[:5]]
    t_measure = _median_ms(lambda: model.measure(Xs[next(it) % len(Xs)], "male"), repeats)
    t_reference = _median_ms(lambda: M.reference_measure(model.measurement_spec, Xs[next(it) % len(Xs)], "male"),
                             max(3, repeats // 10))
    res["timing_ms"] = {
        "measurements_to_avatar_all12": t_avatar12, "measurements_to_avatar_3": t_avatar3,
        "baseline_regression_only": t_regress,
        "measure_avatar": t_measure, "baseline_reference_plane_slicing": t_reference,
        "measure_speedup_vs_reference": t_reference / t_measure,
        "goal": {"measurements_to_avatar": 50.0, "measure_avatar": 5.0},
    }
    return res


def format_body(r: dict) -> str:
    L = []
    p = r["pca_reconstruction_mm"]
    L.append(f"body model: {r['components']} PCA components")
    L.append(f"PCA reconstruction, {p['avatars']} held-out avatars: mean {p['mean']:.3f} mm, max {p['max']:.3f} mm "
             f"(goal < 0.5 / < 5)")
    a = r["all12"]
    L.append(f"\nall 12 entered, {a['subjects']} held-out ANSUR subjects ({a['outside_accepted_range']} outside range):"
             f" within ISO 20685-1 on every attribute: {100 * a['within_iso_all_attributes']:.1f} % (goal >= 95 %)")
    L.append(f"  {'attribute':<20}{'mean |err|':>12}{'p95 |err|':>12}{'within ISO':>12}")
    for n, v in a["per_attribute"].items():
        L.append(f"  {n:<20}{v['mean_abs']:>10.3f} {v['unit']:<2}{v['p95_abs']:>9.3f} {v['unit']:<2}{100 * v['within_iso']:>10.1f} %")
    e = r["estimation_from_gender_height_weight"]
    L.append(f"\ngender + height + weight entered, {e['subjects']} subjects: mean absolute error of estimates (cm)")
    L.append(f"  {'attribute':<20}{'ours':>10}{'lin. regr.':>12}{'ratio':>8}")
    for n, v in e["per_attribute_mae_cm"].items():
        L.append(f"  {n:<20}{v['ours']:>10.2f}{v['linear_regression']:>12.2f}{v['ratio']:>8.2f}")
    L.append(f"  mean ratio {e['mean_ratio']:.3f} (goal <= 1)")
    t = r["timing_ms"]
    L.append("\nmedian times (ms)")
    L.append(f"  measurements -> avatar, all 12 given   {t['measurements_to_avatar_all12']:8.2f}  (goal <= 50)")
    L.append(f"  measurements -> avatar, 3 given        {t['measurements_to_avatar_3']:8.2f}")
    L.append(f"  baseline: conditioning only (regression){t['baseline_regression_only']:7.2f}")
    L.append(f"  measuring an avatar                    {t['measure_avatar']:8.2f}  (goal <= 5)")
    L.append(f"  baseline: trimesh plane slicing        {t['baseline_reference_plane_slicing']:8.2f}  "
             f"(x{t['measure_speedup_vs_reference']:.1f} slower)")
    return "\n".join(L)


# -- try-on ---------------------------------------------------------------------------------
def makehuman_garments(model) -> dict:
    """The MakeHuman CC0 garments of ../shared/data (tests and benchmarks only): name ->
    (fit function avatar -> (M, 3), faces)."""
    from service.model import mhclo

    out = {}
    base = shared_data_dir() / "makehuman_clothes"
    for f in sorted(base.glob("*/*.mhclo")):
        b = mhclo.parse_mhclo(f.read_text(encoding="utf-8", errors="replace"), model.mean.shape[0])
        _, faces = mhclo.parse_obj_faces(f.with_suffix(".obj").read_text(encoding="utf-8", errors="replace"))
        out[f.stem] = (b.fit, faces)
    return out


def bench_garments(model) -> dict:
    """All benchmark garments: the demo ones, a 10k-vertex skirt, and MakeHuman's."""
    from service.model import demo_garments as D

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


def bench_tryon(limit: int, repeats: int) -> dict:
    from scipy.spatial import cKDTree

    from service.model import gltf
    from service.model import tryon as T

    model = load_body_model()
    nb = model.n_body_vertices
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    garments = bench_garments(model)
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
            dep = penetration_depths(v.astype(np.float64), Xb, model.body_faces, tree, vert_faces)
            bad = np.flatnonzero(dep > 0.001)
            if len(bad):
                # where the avatar's own skin is inside the body (heavy inner thighs overlapping),
                # no cloth between can be outside: count those apart
                _, nn = tree.query(v[bad])
                probe = Xb[nn] + 0.002 * body.normals[nn]
                own = winding_numbers(probe, Xb, model.body_faces) > 0.5
                selfx += int(own.sum())
                bad = bad[~own]
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
    t_syn = _median_ms(lambda: T.G.synthesize(g, B, bodies[next(it) % 10].weights), repeats)

    def full(compression=None):
        body = bodies[next(it) % 10]
        v, _ = T.try_on(basis, body)
        return gltf.mesh_to_glb(v, basis.faces, normals=basis.normals(v, body.weights), name="garment",
                                compression=compression)

    t_full = _median_ms(full, repeats)
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

    # 5. HTTP on loopback with concurrent clients
    res["http"] = bench_http()
    return res


def format_tryon(r: dict) -> str:
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
    return "\n".join(L)


# -- HTTP load on loopback ------------------------------------------------------------------
async def _load(port: int, paths: list[str], clients: int, seconds: float) -> tuple[list[float], int]:
    """``clients`` keep-alive connections, each requesting paths round-robin for ``seconds``.
    Returns (latencies in seconds, non-200 count). Raw asyncio streams: light on the client
    side, so the server keeps most of the CPU."""
    import asyncio

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
            writer.write(f"GET {path} HTTP/1.1\r\nHost: bench\r\n\r\n".encode())
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
    """p50/p99 and requests/s of try-on GETs (the 3 demo garments, one customer) against a real
    ``tryon serve`` on loopback, at several numbers of concurrent keep-alive clients, beside
    ``/healthz`` (the framework's own floor) measured the same way in the same run. With C
    clients, p50 ~ C / throughput (Little's law): latency is a function of concurrency."""
    import asyncio
    import socket
    import subprocess
    import tempfile

    import httpx

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    tmp = tempfile.mkdtemp(prefix="tryon-bench-")
    env = dict(os.environ, TRYON_DATA_DIR=tmp)
    env.pop("REDIS_URL", None)
    proc = subprocess.Popen([sys.executable, "-m", "service.cli", "serve", "--port", str(port),
                             "--workers", str(workers), "--log-level", "warning"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        base = f"http://127.0.0.1:{port}"
        for _ in range(600):
            try:
                if httpx.get(base + "/v1/garments", timeout=2).status_code == 200:
                    break
            except httpx.HTTPError:
                pass
            time.sleep(0.2)
        garments = [g["id"] for g in httpx.get(base + "/v1/garments").json()]
        cust = httpx.post(base + "/v1/customers", json={"measurements": {
            "gender": "female", "height_cm": 166, "weight_kg": 68, "waist_cm": 80}}).json()["id"]
        paths = [f"/v1/customers/{cust}/garments/{g}.glb" for g in garments]
        for _ in range(4 * workers):  # warm every server process (customer body, mmapped bases)
            for p in paths:
                httpx.get(base + p)
        out = {"seconds": seconds, "server_workers": workers, "garments": len(paths), "levels": []}
        for clients in levels:
            row = {"clients": clients}
            for name, ps in (("healthz", ["/healthz"]), ("tryon", paths)):
                lat, errors = asyncio.run(_load(port, ps, clients, seconds))
                a = np.array(lat) * 1000
                row[name] = {"requests": len(a), "errors": errors, "p50_ms": float(np.percentile(a, 50)),
                             "p99_ms": float(np.percentile(a, 99)), "rps": len(a) / seconds}
            out["levels"].append(row)
        out["goal"] = {"p50_ms": 10, "p99_ms": 30, "rps": 500}
        return out
    finally:
        proc.terminate()
        proc.wait(timeout=30)
        _stop_embedded_redis(Path(tmp))


def _stop_embedded_redis(data_dir: Path) -> None:
    """Shut down the embedded redis-server a server left under ``data_dir`` (with several
    server processes the one that started it may exit while another is still connected)."""
    import redis

    sock = data_dir / "redis" / "redis.sock"
    if sock.exists():
        try:
            redis.Redis(unix_socket_path=str(sock), socket_timeout=5).shutdown(nosave=True)
        except redis.ConnectionError:
            pass  # shutting down closes the connection: expected


def bench_examples(limit: int, repeats: int) -> dict:
    """Choose the example avatars by measurement: garment accuracy (basis vs direct fit on
    held-out avatars) for a grid of N (components) and c (std units), over the demo garments
    and a spread of MakeHuman garments."""
    from service.model import tryon as T

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


def bench_fitting(limit: int, repeats: int, kill: bool = True, max_pose_deg: float = 45.0) -> dict:
    """Body fitting of synthetic scans, and jobs under worker kills: ``service.bench_fitting``."""
    from service import bench_fitting as F

    return F.bench_fitting(limit, repeats, kill=kill, max_pose_deg=max_pose_deg)


def format_fitting(r: dict) -> str:
    from service import bench_fitting as F

    return F.format_fitting(r)


SUITES = {"body": (bench_body, format_body), "tryon": (bench_tryon, format_tryon),
          "examples": (bench_examples, format_examples), "fitting": (bench_fitting, format_fitting)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tryon bench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=sorted(SUITES))
    ap.add_argument("--json", action="store_true", help="print JSON for machines")
    ap.add_argument("--limit", type=int, default=0, help="held-out subjects to use (0 = all)")
    ap.add_argument("--repeats", type=int, default=50, help="repetitions per timing")
    ap.add_argument("--no-kill", action="store_true", help="fitting: skip the jobs-under-worker-kills part")
    ap.add_argument("--max-pose-deg", type=float, default=45.0,
                    help="fitting: largest random rotation per bone of the synthetic scans (default 45)")
    args = ap.parse_args(argv)
    run, fmt = SUITES[args.suite]
    extra = {"kill": not args.no_kill, "max_pose_deg": args.max_pose_deg} if args.suite == "fitting" else {}
    res = run(args.limit, args.repeats, **extra)
    print(json.dumps(res, indent=2) if args.json else fmt(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

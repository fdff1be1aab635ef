"""Measurements -> avatar: the fast path (``shape.avatar_from_measurements``) beside the slow,
obvious one it replaced (``shape.avatar_from_measurements_reference``), on held-out ANSUR II
subjects, in the same run: median times (wall clock and this thread's CPU time, the two paths
called alternately subject by subject so that they share the machine's load), how far apart
their avatars and measurements are, and the accuracy figures of both (all 12 entered: share
within ISO 20685-1; gender + height + weight entered: mean absolute error of the estimates).

``python -m tests.bench.avatar_speed [--limit N] [--json]``; as a ``tryon bench`` suite: ``run`` /
``format_result``. Timings depend on BLAS threads (``OPENBLAS_NUM_THREADS``, printed): on a
shared machine run it with 1.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from service.model.body import measurements as M
from service.model.body import shape as S
from service.model.body.model import load_body_model
from tests.bench.common import read_ansur

INPUTS = {"all 12": None, "gender + height + weight": ("gender", "height_cm", "weight_kg")}


def _timed(fn, *args):
    t, c = time.perf_counter(), time.thread_time()
    out = fn(*args)
    return out, time.perf_counter() - t, time.thread_time() - c


def run(limit: int = 0, repeats: int = 50) -> dict:
    model = load_body_model()
    t = time.perf_counter()
    S.weight_measures(model)  # once per process
    precompute_s = time.perf_counter() - t
    held = read_ansur(heldout=True)
    if limit:
        rng = np.random.default_rng(0)
        held = [held[i] for i in sorted(rng.choice(len(held), size=min(limit, len(held)), replace=False))]
    specs = {a.name: a for a in model.attributes}
    held = [s for s in held if all(specs[k].min <= v <= specs[k].max
                                   for k, v in s["measurements"].items() if k != "gender")]
    names = list(M.ATTRIBUTES[1:])
    tol = np.array([M.ISO_TOLERANCE[n] * M.api_scale(n) for n in names])
    nb = model.n_body_vertices
    S.avatar_from_measurements(model, held[0]["measurements"])  # warm caches
    S.avatar_from_measurements_reference(model, held[0]["measurements"])
    res: dict = {"suite": "avatar_speed", "subjects": len(held), "precompute_s": precompute_s,
                 "openblas_num_threads": os.environ.get("OPENBLAS_NUM_THREADS", "(default)"), "inputs": {}}
    for k, (label, keys) in enumerate(INPUTS.items()):
        wall = {"fast": [], "reference": []}
        cpu = {"fast": [], "reference": []}
        err = {"fast": [], "reference": []}
        diff, dvert, steps, jacobians = [], [], [], []
        for i, s in enumerate(held):
            truth = s["measurements"]
            m = truth if keys is None else {n: truth[n] for n in keys}
            fits = {}
            for path in (("fast", "reference") if (i + k) % 2 == 0 else ("reference", "fast")):
                fn = S.avatar_from_measurements if path == "fast" else S.avatar_from_measurements_reference
                fits[path], w, c = _timed(fn, model, m)
                wall[path].append(w)
                cpu[path].append(c)
                err[path].append([fits[path].measurements[n] - truth[n] for n in names])
            f, r = fits["fast"], fits["reference"]
            diff.append([abs(f.measurements[n] - r.measurements[n]) for n in names])
            dvert.append(float(np.abs(f.vertices[:nb] - r.vertices[:nb]).max()))
            given = S.validate_measurements(model, m)
            gender, w0, cov_w = S._condition(model, given)
            fit = S.refine(model, w0, cov_w, {n: v for n, v in given.items() if n != "gender"}, gender)
            steps.append(fit.steps)
            jacobians.append(fit.jacobians)
        D = np.array(diff) / tol
        out: dict = {
            "median_ms": {p: {"wall": 1000 * float(np.median(wall[p])), "cpu": 1000 * float(np.median(cpu[p]))}
                          for p in wall},
            "speedup": {c: float(np.median(v["reference"]) / np.median(v["fast"])) for c, v in
                        (("wall", wall), ("cpu", cpu))},
            "fast_minus_reference": {
                "max_over_iso_tolerance": float(D.max()), "p99_over_iso_tolerance": float(np.percentile(D, 99)),
                "body_vertices_mm": {"median": 1000 * float(np.median(dvert)), "p99": 1000 * float(np.percentile(dvert, 99)),
                                     "max": 1000 * float(np.max(dvert))},
            },
            "steps": np.bincount(steps).tolist(), "jacobians": np.bincount(jacobians).tolist(),
        }
        for p in err:
            E = np.abs(np.array(err[p]))
            if keys is None:
                out[f"{p}_within_iso_all_attributes"] = float(np.mean(np.all(E <= tol, axis=1)))
            else:
                est = [j for j, n in enumerate(names) if n not in keys]
                out[f"{p}_estimate_mae_cm"] = {names[j]: float(E[:, j].mean()) for j in est}
        res["inputs"][label] = out
    X = model.vertices(S.avatar_from_measurements(model, held[0]["measurements"]).weights)
    ts = []
    for _ in range(repeats):
        _, w, _ = _timed(model.measure, X, "male")
        ts.append(w)
    res["measure_avatar_median_ms"] = 1000 * float(np.median(ts))
    return res


def format_result(r: dict) -> str:
    L = [f"measurements -> avatar, {r['subjects']} held-out ANSUR II subjects; fast path vs the reference, "
         f"called alternately (OPENBLAS_NUM_THREADS={r['openblas_num_threads']})",
         f"  precomputing WeightMeasures (once per process): {r['precompute_s']:.2f} s",
         f"  measuring an avatar (model.measure), median: {r['measure_avatar_median_ms']:.2f} ms"]
    for label, o in r["inputs"].items():
        t = o["median_ms"]
        d = o["fast_minus_reference"]
        L.append(f"\n{label} entered")
        L.append(f"  median ms      wall {t['fast']['wall']:7.2f} (reference {t['reference']['wall']:7.2f}, "
                 f"x{o['speedup']['wall']:.1f})   cpu {t['fast']['cpu']:7.2f} (reference {t['reference']['cpu']:7.2f}, "
                 f"x{o['speedup']['cpu']:.1f})")
        L.append(f"  fast - reference: measurements max {d['max_over_iso_tolerance']:.3f} / p99 "
                 f"{d['p99_over_iso_tolerance']:.3f} of the ISO tolerance; body vertices median "
                 f"{d['body_vertices_mm']['median']:.4f} / p99 {d['body_vertices_mm']['p99']:.3f} / max "
                 f"{d['body_vertices_mm']['max']:.3f} mm")
        L.append(f"  Gauss-Newton steps (count by number) {o['steps']}, Jacobians {o['jacobians']}")
        if "fast_within_iso_all_attributes" in o:
            L.append(f"  within ISO 20685-1 on every attribute: fast {100 * o['fast_within_iso_all_attributes']:.1f} %, "
                     f"reference {100 * o['reference_within_iso_all_attributes']:.1f} %")
        else:
            f, ref = o["fast_estimate_mae_cm"], o["reference_estimate_mae_cm"]
            L.append("  estimates, mean |error| (cm): " + ", ".join(f"{n} {f[n]:.2f} ({ref[n]:.2f})" for n in f)
                     + "  (reference in brackets)")
    return "\n".join(L)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tests.bench.avatar_speed", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print JSON for machines")
    ap.add_argument("--limit", type=int, default=0, help="held-out subjects to use (0 = all)")
    ap.add_argument("--repeats", type=int, default=50, help="repetitions of the measuring timing")
    args = ap.parse_args(argv)
    res = run(args.limit, args.repeats)
    print(json.dumps(res, indent=2) if args.json else format_result(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

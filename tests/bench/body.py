"""``tryon bench body``: PCA reconstruction of held-out avatars; measurements -> avatar on
held-out ANSUR II subjects (all 12 entered: ISO 20685-1 share; gender + height + weight entered:
estimation error beside a linear regression fitted on the training subjects in the same run);
median times of measurements -> avatar and of measuring an avatar, beside baselines timed in
the same run."""
from __future__ import annotations

import numpy as np

from service.model.body import measurements as M
from service.model.body import shape as S
from service.model.body.model import load_body_model
from tests.bench.common import heldout_avatars, median_ms, read_ansur


def run(limit: int, repeats: int) -> dict:
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

    t_avatar12 = median_ms(lambda: S.avatar_from_measurements(model, full[next(it) % len(full)]), repeats)
    t_avatar3 = median_ms(lambda: S.avatar_from_measurements(model, three[next(it) % len(three)]), repeats)
    prior = S._prior(model)

    def regression_only():
        m = full[next(it) % len(full)]
        prior.condition({i: (S.GENDER_CODE[m[n]] if n == "gender" else m[n]) for i, n in enumerate(M.ATTRIBUTES)}, {})

    t_regress = median_ms(regression_only, repeats)
    Xs = [model.vertices(S.avatar_from_measurements(model, m).weights) for m in full[:5]]
    t_measure = median_ms(lambda: model.measure(Xs[next(it) % len(Xs)], "male"), repeats)
    t_reference = median_ms(lambda: M.reference_measure(model.measurement_spec, Xs[next(it) % len(Xs)], "male"),
                             max(3, repeats // 10))
    res["timing_ms"] = {
        "measurements_to_avatar_all12": t_avatar12, "measurements_to_avatar_3": t_avatar3,
        "baseline_regression_only": t_regress,
        "measure_avatar": t_measure, "baseline_reference_plane_slicing": t_reference,
        "measure_speedup_vs_reference": t_reference / t_measure,
        "goal": {"measurements_to_avatar": 50.0, "measure_avatar": 5.0},
    }
    return res


def format_result(r: dict) -> str:
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

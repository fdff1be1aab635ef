"""``tryon bench look``: the added latency of the avatar's look (issue 11) on avatar.glb.

For the five bodies of issue 11, the customer's avatar GLB as ``CustomerService.avatar_glb``
builds it once the body is cached: the bare body (the baseline, as before the look) beside the
default look (skin, eyes, eyebrows, hair, underwear; its fitted meshes cached per avatar and look,
as a customer's repeated avatar/outfit requests find them), and the look's fitting alone, uncached
(binding, push-out, normals: the first request's extra; no GLB writing); medians of ``repeats`` runs, same process, same run."""
from __future__ import annotations

import time

import numpy as np

BODIES = {"f160-55": ("female", 160, 55), "m185-80": ("male", 185, 80), "f165-105": ("female", 165, 105),
          "m200-130": ("male", 200, 130), "m150-45": ("male", 150, 45)}


def _median_ms(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts) * 1e3)


def run(limit: int = 0, repeats: int = 30) -> dict:
    from service.application import look as looks
    from service.application import scenes
    from service.model.body.model import load_body_model
    from service.model.body.shape import avatar_from_measurements
    from service.model.garments.tryon import customer_body

    model = load_body_model()
    rows = {}
    for name, (g, h, w) in list(BODIES.items())[: limit or None]:
        a = avatar_from_measurements(model, {"gender": g, "height_cm": h, "weight_kg": w})
        body = customer_body(model, a.weights)
        gender = looks.gender_of(a.measurements)
        scenes.avatar_glb(model, body.vertices, normals=body.normals, look=looks.resolve(gender))  # warm
        bare = _median_ms(lambda: scenes.avatar_glb(model, body.vertices, normals=body.normals), repeats)
        look = _median_ms(lambda: scenes.avatar_glb(model, body.vertices, normals=body.normals,
                                                    look=looks.resolve(gender)), repeats)
        fit = _median_ms(lambda: looks._fit_items(model, body.vertices, body.normals, looks.resolve(gender)), repeats)
        n_bare = len(scenes.avatar_glb(model, body.vertices, normals=body.normals))
        n_look = len(scenes.avatar_glb(model, body.vertices, normals=body.normals, look=looks.resolve(gender)))
        rows[name] = {"bare_ms": bare, "look_ms": look, "added_ms": look - bare, "ratio": look / bare,
                      "fit_ms": fit, "bare_bytes": n_bare, "look_bytes": n_look}
    return {"repeats": repeats, "bodies": rows,
            "median_added_ms": float(np.median([r["added_ms"] for r in rows.values()]))}


def format_result(r: dict) -> str:
    lines = [f"avatar.glb, bare body vs the default look (medians of {r['repeats']} runs, ms)",
             f"{'body':<10}{'bare':>8}{'look':>8}{'added':>8}{'ratio':>7}{'fit':>7}{'bytes bare':>12}{'look':>11}"]
    for k, v in r["bodies"].items():
        lines.append(f"{k:<10}{v['bare_ms']:8.2f}{v['look_ms']:8.2f}{v['added_ms']:8.2f}{v['ratio']:7.2f}"
                     f"{v['fit_ms']:7.2f}{v['bare_bytes']:12,}{v['look_bytes']:11,}")
    lines.append(f"median added latency: {r['median_added_ms']:.2f} ms")
    return "\n".join(lines)

"""The try-on route's in-process work timed against whichever checkout is first on PYTHONPATH,
for before/after comparisons across commits (``tryon bench tryon --only latency`` compares the
template path with the reference path inside one checkout). Uses only what older checkouts have:

    PYTHONPATH=/path/to/old/checkout python tests/bench/route_latency.py 100
    PYTHONPATH=. python tests/bench/route_latency.py 100

Run the two alternately (A B A B) on a shared machine. Prints JSON: "garment/mode" -> [median
wall ms, median thread CPU ms] of ``scenes.outfit_glb`` for one garment (the 10k-vertex demo
skirt untextured and textured, the demo catalogue's business suit), 10 held-out customers.
"""
import service  # noqa: F401  (one BLAS thread, set before numpy is imported)

import dataclasses
import json
import sys
import time

import numpy as np

from service.application import scenes
from service.model.garments import demo_garments as D
from service.model.body import shape as S
from service.model.garments import tryon as T
from service.model.body.model import load_body_model
from service.model.garments.catalogue import load_catalogue
from service.records import Garment
from tests.bench.common import read_ansur
from tests.bench.tryon import skirt_layout


def main(repeats: int) -> dict:
    model = load_body_model()
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    cat = load_catalogue()
    suit = cat.items["business-suit"]
    suit_basis = T.build_garment_basis(model, np.stack([suit.fit_to(E) for E in EX]), suit.faces, ex,
                                       layout=suit.render_layout(), material=suit.material)
    skirt = D.DemoGarment("skirt", D.skirt_faces(64, 160))
    plain = T.build_garment_basis(model, np.stack([D.skirt_rings(model, E, rings=64, angles=160) for E in EX]),
                                  skirt.faces, ex)
    lay = skirt_layout()
    textured = dataclasses.replace(plain, render_vertex=lay.vertex.astype(np.int32), render_uv=lay.uv,
                                   render_faces=lay.faces.astype(np.int32),
                                   material=dataclasses.replace(cat.items["cropped-tee"].material),
                                   _render_skin=None, _render_tangents=None)
    rng = np.random.default_rng(1)  # the customers of tryon bench tryon (its first 10 picks)
    held = read_ansur(heldout=True)
    specs = {a.name: a for a in model.attributes}
    held = [h for h in held if all(specs[k].min <= v <= specs[k].max for k, v in h["measurements"].items()
                                   if k != "gender")]
    picks = rng.choice(len(held), size=200, replace=False)
    bodies = [T.customer_body(model, S.avatar_from_measurements(model, held[i]["measurements"]).weights)
              for i in picks[:10]]
    rec = Garment(id="bench", body_model=model.version, owner="bench", name="garment", source="demo",
                  color=[0.5, 0.5, 0.5, 1.0], layer=0)
    out = {}
    for name, basis in (("skirt-10k", plain), ("skirt-10k-textured", textured), ("business-suit", suit_basis)):
        for mode in (None, "quantize", "meshopt"):
            for body in bodies:  # warm: bindings, render skin, caches
                scenes.outfit_glb(model, body, [(rec, basis)], mode, with_avatar=False)
            wall, cpu = [], []
            for i in range(repeats):
                t0, c0 = time.perf_counter(), time.thread_time()
                scenes.outfit_glb(model, bodies[i % len(bodies)], [(rec, basis)], mode, with_avatar=False)
                wall.append(time.perf_counter() - t0)
                cpu.append(time.thread_time() - c0)
            out[f"{name}/{mode or 'plain'}"] = [1000 * float(np.median(wall)), 1000 * float(np.median(cpu))]
    return out


if __name__ == "__main__":
    print(json.dumps(main(int(sys.argv[1]) if len(sys.argv) > 1 else 100)))

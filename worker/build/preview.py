"""Offline previews: render avatars wearing catalogue items to PNG (three.js in headless
Chromium through ``preview.mjs``; needs node, ``node_modules`` and /usr/bin/chromium).

A scene is a list of meshes (``mesh(...)``); ``render(scenes, outdir)`` writes
``outdir/<scene>-<view>.png``. UVs are given in glTF's convention (origin top-left), as a GLB
would carry them: the preview checks what a customer's viewer will show.
"""
from __future__ import annotations

import base64
import json
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from service.model.geometry.mesh import vertex_normals

HERE = Path(__file__).resolve().parent


def _b64(a: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(a, dtype=dtype).tobytes()).decode()


def mesh(name: str, vertices: np.ndarray, faces: np.ndarray, *, uv: np.ndarray | None = None,
         color=(0.8, 0.8, 0.8, 1.0), texture: tuple[bytes, str] | None = None,
         normal_texture: tuple[bytes, str] | None = None, alpha_mode: str = "OPAQUE", alpha_cutoff: float = 0.5,
         double_sided: bool = False, roughness: float = 0.85, render_order: int = 0,
         frame: bool = True) -> dict:
    """A mesh for the preview: vertices (N, 3), faces (F, 3), optional per-vertex uv (N, 2) in
    glTF convention, textures as (bytes, mime)."""
    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.uint32)
    out = {"name": name, "positions": _b64(v, np.float32), "normals": _b64(vertex_normals(v, f), np.float32),
           "indices": _b64(f, np.uint32), "color": [float(c) for c in color], "alphaMode": alpha_mode,
           "alphaCutoff": alpha_cutoff, "doubleSided": double_sided, "roughness": roughness,
           "renderOrder": render_order, "noFrame": not frame}
    if uv is not None:
        out["uvs"] = _b64(uv, np.float32)
    for key, tex in (("map", texture), ("normalMap", normal_texture)):
        if tex is not None:
            out[key] = {"mime": tex[1], "data": base64.b64encode(tex[0]).decode()}
    return out


def render(scenes: list[dict], outdir: Path, timeout: int = 600) -> dict:
    """Render scenes ({name, meshes, views, width, height, target?, distance?, fov?}); returns
    the renderer's summary ({images, errors})."""
    outdir = Path(outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "scenes.json"
        path.write_text(json.dumps(scenes))
        proc = subprocess.run(["node", str(HERE / "preview.mjs"), str(path), str(outdir)], capture_output=True,
                              text=True, timeout=timeout, cwd=HERE.parent.parent)
    if proc.returncode != 0:
        raise RuntimeError(f"preview renderer failed: {proc.stderr[-2000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- the catalogue preview: avatars wearing catalogue items ------------------------------------
def dress(model, catalogue, vertices: np.ndarray, item_ids: list[str], *, gender: str = "female",
          skin: str | None = None, hair: str | None = "default", hide_covered: bool = True,
          layered: bool = True) -> list[dict]:
    """Preview meshes of an avatar (V, 3) wearing catalogue items over its default look: items
    fitted through their bindings, pushed out of the body in layer order (as a try-on does:
    clearance grows with the layer), then (``layered``) crudely out of the items under them
    (``_over``: a stand-in for the service's layering), textures as a GLB would carry them."""
    from scipy.spatial import cKDTree

    from service.model.garments import garment as G

    look = catalogue.look(gender)
    X = np.asarray(vertices, np.float64)
    nb = model.n_body_vertices
    normals = vertex_normals(X[:nb], model.body_faces)
    tree = cKDTree(X[:nb])
    items = [*look["base_layer"], *[catalogue.items[i] for i in item_ids]]
    if hair:
        items.append(catalogue.items[look["hair"].id if hair == "default" else hair])
    items += [look["eyes"], look["eyebrows"]]
    out, hidden, worn = [], np.zeros(nb, bool), []
    for it in sorted(items, key=lambda i: -1 if i.layer is None else i.layer):
        P = it.fit_to(X)
        if it.fit.push_out:
            clearance = it.fit.clearance if it.fit.clearance is not None else G.CLEARANCE + (it.layer or 0) * G.LAYER_GAP
            bind = tree.query(P)[1][:, None]
            P, _ = G.push_out(P, X[:nb], normals, bind, G.laplacian_smoother(it.faces, len(P)), clearance)
            if layered:
                P = _over(P, worn, it)
            worn.append((it, np.asarray(P, np.float64)))
        if hide_covered and len(it.hidden):
            hidden[it.hidden] = True
        out.append(item_mesh(it, P))
    sk = catalogue.skins[skin or look["skin"].id]
    keep = ~hidden[model.body_faces].all(axis=1) if hide_covered else np.ones(len(model.body_faces), bool)
    lay = sk.render_layout(model.body_faces)
    m = sk.material
    if lay is None:
        out.insert(0, mesh("body", X[:nb], model.body_faces[keep], color=m.base_color_factor, roughness=m.roughness))
    else:
        out.insert(0, mesh("body", X[lay.vertex], lay.faces[keep], uv=lay.uv, color=m.base_color_factor,
                           texture=(m.base_color_texture.data, m.base_color_texture.mime), roughness=m.roughness))
    return out


LAYER_RADIUS = 0.03  # m: an outer item is pushed out of an inner one only where they are this close
LAYER_CLEARANCE = 0.003


def _over(P: np.ndarray, worn: list, outer) -> np.ndarray:
    """Crude layering for the preview: push the vertices of ``outer`` that lie within
    LAYER_RADIUS of an item worn under it out along that item's normals (tangent plane of the
    nearest vertex). Hair counts as under a hat; eyes and eyebrows never."""
    from scipy.spatial import cKDTree

    from service.model.garments import garment as G

    P = np.asarray(P, np.float64)
    for it, Q in worn:
        if it.kind in ("eyes", "eyebrows") or (it.kind == "hair" and outer.category != "hat"):
            continue
        if it.kind != "hair" and (it.layer is None or outer.layer is None or it.layer >= outer.layer):
            continue
        d, i = cKDTree(Q).query(P)
        near = np.flatnonzero(d < LAYER_RADIUS)
        if len(near) == 0:
            continue
        n = vertex_normals(Q, it.faces)
        moved, _ = G.push_out(P[near], Q, n, i[near][:, None], None, LAYER_CLEARANCE)
        P[near] = moved
    return P


def item_mesh(it, P: np.ndarray) -> dict:
    lay = it.render_layout()
    m = it.material
    tex = (m.base_color_texture.data, m.base_color_texture.mime) if m.base_color_texture else None
    nrm = (m.normal_texture.data, m.normal_texture.mime) if m.normal_texture else None
    return mesh(it.id, P[lay.vertex], lay.faces, uv=lay.uv, color=m.base_color_factor, texture=tex,
                normal_texture=nrm, alpha_mode=m.alpha_mode, alpha_cutoff=m.alpha_cutoff or 0.5,
                double_sided=m.double_sided, roughness=m.roughness,
                render_order={"eyebrows": 2, "hair": 1}.get(it.kind, 0))


def example_avatars(model) -> dict[str, np.ndarray]:
    """The mean avatar, the heaviest of the example avatars, and two of the issue's stress
    bodies from measurements: a heavy woman (165 cm, 105 kg) and a tall man (200 cm, 95 kg)."""
    from service.model.body.shape import avatar_from_measurements
    from service.model.garments.tryon import example_set, example_vertices

    E = example_vertices(model, example_set(model))
    ms = [model.measure(e, "female") for e in E]
    ex = int(np.argmax([m["weight_kg"] for m in ms]))
    heavy = avatar_from_measurements(model, {"gender": "female", "height_cm": 165, "weight_kg": 105})
    tall = avatar_from_measurements(model, {"gender": "male", "height_cm": 200, "weight_kg": 95})
    return {"mean": E[0], "example-heavy": E[ex], "heavy": model.vertices(heavy.weights),
            "tall": model.vertices(tall.weights)}


OUTFITS = [  # (scene name, avatar, gender, items, skin, hair)
    ("mean-base-female", "mean", "female", [], None, "default"),
    ("mean-base-male", "mean", "male", [], None, "default"),
    ("mean-blouse-skirt", "mean", "female", ["pinstripe-blouse", "pencil-skirt", "leather-shoes"], None, "default"),
    ("heavy-tee-jeans", "heavy", "female", ["womens-tshirt", "womens-jeans", "sneakers"], None, "default"),
    ("heavy-jacket-jeans", "heavy", "male", ["casual-jacket", "mens-jeans", "leather-shoes"], None, "default"),
    ("tall-suit-hat", "tall", "male", ["business-suit", "dress-shoes", "fedora"], None, "hair-short04"),
    ("tall-sport", "tall", "female", ["cropped-tee", "sports-trousers", "sneakers"], "skin-textured", "hair-short04"),
    ("heavy-sport", "heavy", "female", ["cropped-tee", "sports-trousers", "sneakers"], None, "default"),
    ("mean-tee-jeans-male", "mean", "male", ["white-tshirt", "mens-jeans", "sneakers"], None, "default"),
    ("mean-dungarees", "mean", "male", ["dungarees", "sneakers"], "skin-textured", "default"),
    ("example-heavy-tee-skirt", "example-heavy", "female", ["womens-tshirt", "pencil-skirt", "dress-shoes"], None,
     "default"),
]


def main(argv: list[str] | None = None) -> int:
    import argparse

    from service.model.body.model import load_body_model
    from service.model.garments.catalogue import read_catalogue, DEFAULT_CATALOGUE_DIR

    ap = argparse.ArgumentParser(prog="python -m worker.build.preview",
                                 description="Render avatars wearing catalogue items to PNG.")
    ap.add_argument("--out", type=Path, default=Path("tests/artifacts/catalogue"))
    ap.add_argument("--catalogue", type=Path, default=DEFAULT_CATALOGUE_DIR)
    ap.add_argument("--only", default=None, help="comma-separated scene names")
    args = ap.parse_args(argv)
    model = load_body_model()
    cat = read_catalogue(args.catalogue)
    av = example_avatars(model)
    scenes = []
    for name, who, gender, items, skin, hair in OUTFITS:
        if args.only and name not in args.only.split(","):
            continue
        scenes.append({"name": name, "meshes": dress(model, cat, av[who], items, gender=gender, skin=skin, hair=hair),
                       "views": ["front", "side", "back"], "width": 500, "height": 900})
    for hair in [h.id for h in cat.hair()]:
        if args.only and f"face-{hair}" not in args.only.split(","):
            continue
        X = av["mean"]
        head = model.joints(X)[4]
        scenes.append({"name": f"face-{hair}", "meshes": dress(model, cat, X, [], hair=hair,
                                                                gender="male" if "short" in hair else "female"),
                       "views": ["front", "threequarter", "side", "back"], "width": 500, "height": 600,
                       "target": [0.0, float(head[1]) + 0.07, 0.03], "distance": 0.75})
    res = render(scenes, args.out)
    print(json.dumps(res, indent=1))
    return 0 if not res["errors"] else 1


if __name__ == "__main__":
    import sys

    sys.exit(main())

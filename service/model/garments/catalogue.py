"""The compiled demo catalogue and avatar look (``service/data/catalogue/``): pure numpy + json.

Built offline by ``tryon build-catalogue`` (``worker/build/catalogue.py``; sources, licence and
processing in ``service/data/catalogue/PROVENANCE.md``). Read once per process by
:func:`load_catalogue`. Every item is a MakeHuman-style ``.mhclo`` garment or asset:

* ``binding`` -- a :class:`~service.model.formats.mhclo.Binding` to the hm08 base mesh (all 19,158
  vertices, helpers included): ``item.binding.fit(avatar_vertices)`` -> (M, 3) metres;
* ``faces`` (F, 3) int64 over those M vertices; ``face_uv`` (F, 3) int64 per-corner indices into
  ``uv`` (T, 2) float32 (OBJ convention, origin bottom-left); :func:`render_layout` splits the
  seams for a GPU mesh (glTF convention);
* ``material`` -- base colour factor (linear RGBA), base-colour and normal textures (bytes and
  mime type), alpha mode, double-sided, metallic/roughness;
* metadata: display name, category (top, bottom, suit, shoes, hat, underwear; eyes, eyebrows,
  hair, skin), gender, outfit ``layer`` (0 innermost; None for avatar assets), swatch colour,
  ``fit`` (whether the try-on push-out applies, and how to skin it), ``hidden`` body vertices.

Shapes: avatar vertices (V, 3) metres; item vertices (M, 3).
"""
from __future__ import annotations

import functools
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.model.formats.mhclo import Binding

DEFAULT_CATALOGUE_DIR = Path(__file__).resolve().parents[2] / "data" / "catalogue"
FORMAT = 1
GARMENT_CATEGORIES = ("top", "bottom", "suit", "shoes", "hat", "underwear")
MIME = {".jpg": "image/jpeg", ".jpeg": "image/jpeg", ".png": "image/png"}


@dataclass(frozen=True)
class Texture:
    """An encoded image: its file name, mime type and bytes (embed as-is in a GLB)."""

    name: str
    mime: str
    data: bytes = field(repr=False)


@dataclass(frozen=True)
class Material:
    """glTF-style PBR material. base_color_factor: (4,) linear RGBA (multiplies the texture)."""

    base_color_factor: tuple[float, float, float, float]
    base_color_texture: Texture | None
    normal_texture: Texture | None
    alpha_mode: str  # OPAQUE | MASK | BLEND
    alpha_cutoff: float | None
    double_sided: bool
    metallic: float
    roughness: float


@dataclass(frozen=True)
class Fit:
    """How the service should fit the item per customer: ``push_out`` out of the body after
    synthesis (garments, hair) or not (eyes sit inside the head, eyebrows on the skin);
    ``skinning`` 'transfer' (weights transferred from the body) or 'head' (rigid to the head bone);
    ``clearance`` of the push-out."""

    push_out: bool
    skinning: str
    clearance: float | None = None  # metres; None: the try-on's rule (grows with the layer)


@dataclass(frozen=True)
class RenderLayout:
    """A mesh ready for a GPU / glTF primitive: one vertex per distinct (vertex, uv) corner.
    vertex (R,) int64 index of each render vertex into the item's vertices; uv (R, 2) float32 in
    glTF convention (origin top-left); faces (F, 3) int64 into the render vertices."""

    vertex: np.ndarray
    uv: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True, eq=False)
class CatalogueItem:
    id: str
    name: str
    kind: str  # garment | underwear | eyes | eyebrows | hair
    category: str
    type: str  # finer: t-shirt, jeans, skirt, shoes, ...
    gender: str  # female | male | unisex
    layer: int | None
    color: str  # '#rrggbb' sRGB swatch
    binding: Binding
    faces: np.ndarray
    face_uv: np.ndarray
    uv: np.ndarray
    hidden: np.ndarray  # (H,) int64 body vertices under the item
    material: Material
    fit: Fit
    meta: dict = field(repr=False)

    @property
    def n_vertices(self) -> int:
        return int(len(self.binding.indices))

    def fit_to(self, vertices: np.ndarray) -> np.ndarray:
        """The item on an avatar (V, 3) (all hm08 vertices, metres) -> (M, 3) float64."""
        return self.binding.fit(vertices)

    def render_layout(self) -> RenderLayout:
        return render_layout(self.faces, self.face_uv, self.uv)


@dataclass(frozen=True, eq=False)
class Skin:
    """A skin material for the avatar's body surface; a textured one comes with the body's UVs:
    body_face_uv (F_body, 3) int64 per corner of ``model.body_faces`` into body_uv (T, 2)."""

    id: str
    name: str
    color: str
    material: Material
    body_uv: np.ndarray | None
    body_face_uv: np.ndarray | None
    meta: dict = field(repr=False)

    def render_layout(self, body_faces: np.ndarray) -> RenderLayout | None:
        if self.body_uv is None:
            return None
        return render_layout(body_faces, self.body_face_uv, self.body_uv)


@dataclass(frozen=True, eq=False)
class Catalogue:
    items: dict[str, CatalogueItem]
    skins: dict[str, Skin]
    defaults: dict[str, dict]  # gender -> {skin, eyes, eyebrows, hair, base_layer: [ids]}
    layers: dict[str, int]
    body_model: str  # the body model version the base layer was generated on
    path: Path

    def garments(self) -> list[CatalogueItem]:
        """The shop's items (clothes, shoes, hats; not the base layer), in catalogue order."""
        return [i for i in self.items.values() if i.kind == "garment"]

    def base_layer(self, gender: str) -> list[CatalogueItem]:
        return [self.items[i] for i in self.defaults[_gender(gender)]["base_layer"]]

    def look(self, gender: str) -> dict:
        """The default look for a gender: {'skin': Skin, 'eyes', 'eyebrows', 'hair':
        CatalogueItem, 'base_layer': [CatalogueItem]}."""
        d = self.defaults[_gender(gender)]
        return {"skin": self.skins[d["skin"]], "eyes": self.items[d["eyes"]],
                "eyebrows": self.items[d["eyebrows"]], "hair": self.items[d["hair"]],
                "base_layer": self.base_layer(gender)}

    def hair(self) -> list[CatalogueItem]:
        return [i for i in self.items.values() if i.kind == "hair"]


def _gender(g: str) -> str:
    return "male" if str(g).lower().startswith("m") else "female"


def render_layout(faces: np.ndarray, face_uv: np.ndarray, uv: np.ndarray) -> RenderLayout:
    """Split a mesh at its UV seams: faces (F, 3) vertex indices and face_uv (F, 3) uv indices
    per corner, uv (T, 2) in OBJ convention -> one render vertex per distinct (vertex, uv) pair,
    uv flipped to glTF's convention (v' = 1 - v)."""
    f = np.asarray(faces, np.int64).reshape(-1)
    t = np.asarray(face_uv, np.int64).reshape(-1)
    pairs, inverse = np.unique(np.stack([f, t], axis=1), axis=0, return_inverse=True)
    uv_gl = np.asarray(uv, np.float32)[pairs[:, 1]].copy()
    uv_gl[:, 1] = 1.0 - uv_gl[:, 1]
    return RenderLayout(pairs[:, 0], uv_gl, inverse.reshape(-1, 3).astype(np.int64))


def _texture(root: Path, rel: str | None, cache: dict) -> Texture | None:
    if not rel:
        return None
    if rel not in cache:
        p = root / rel
        cache[rel] = Texture(p.name, MIME[p.suffix.lower()], p.read_bytes())
    return cache[rel]


def _material(root: Path, m: dict, cache: dict) -> Material:
    return Material(tuple(float(c) for c in m["base_color_factor"]),  # type: ignore[arg-type]
                    _texture(root, m.get("base_color_texture"), cache), _texture(root, m.get("normal_texture"), cache),
                    m["alpha_mode"], m.get("alpha_cutoff"), bool(m["double_sided"]), float(m["metallic"]),
                    float(m["roughness"]))


def read_catalogue(path: str | Path = DEFAULT_CATALOGUE_DIR) -> Catalogue:
    """Read a compiled catalogue directory (no caching: see :func:`load_catalogue`)."""
    root = Path(path)
    doc = json.loads((root / "catalogue.json").read_text(encoding="utf-8"))
    if doc.get("format") != FORMAT:
        raise ValueError(f"{root}: catalogue format {doc.get('format')}, this service reads {FORMAT}")
    n_base = int(doc["n_base_vertices"])
    cache: dict = {}
    items: dict[str, CatalogueItem] = {}
    skins: dict[str, Skin] = {}
    with np.load(root / "arrays.npz", allow_pickle=False) as z:
        arr = {k: z[k] for k in z.files}
    for m in doc["items"]:
        iid = m["id"]
        mat = _material(root, m["material"], cache)
        if m["kind"] == "skin":
            uv = arr.get("skin/body_uv") if mat.base_color_texture is not None else None
            fuv = arr.get("skin/body_face_uv") if uv is not None else None
            skins[iid] = Skin(iid, m["name"], m["color"], mat, None if uv is None else uv.astype(np.float32),
                              None if fuv is None else fuv.astype(np.int64), m)
            continue
        a = {k.split("/", 1)[1]: v for k, v in arr.items() if k.startswith(iid + "/")}
        sc = a["binding_scales"]
        binding = Binding(a["binding_indices"].astype(np.int64), a["binding_weights"].astype(np.float64),
                          a["binding_offsets"].astype(np.float64),
                          [(int(r[0]), int(r[1]), float(r[2])) for r in sc], iid)
        if binding.indices.max() >= n_base:
            raise ValueError(f"{root}: item {iid} binds vertex {binding.indices.max()} (base mesh: {n_base})")
        fit = m.get("fit") or {"push_out": True, "skinning": "transfer"}
        clearance = fit.get("clearance")
        items[iid] = CatalogueItem(
            id=iid, name=m["name"], kind=m["kind"], category=m["category"], type=m["type"], gender=m["gender"],
            layer=m["layer"], color=m["color"], binding=binding, faces=a["faces"].astype(np.int64),
            face_uv=a["face_uv"].astype(np.int64), uv=a["uv"].astype(np.float32), hidden=a["hidden"].astype(np.int64),
            material=mat, fit=Fit(bool(fit["push_out"]), str(fit["skinning"]), None if clearance is None else float(clearance)),
            meta=m)
    for it in items.values():  # shared by the whole process: read-only
        for a in (it.binding.indices, it.binding.weights, it.binding.offsets, it.faces, it.face_uv, it.uv, it.hidden):
            a.setflags(write=False)
    return Catalogue(items, skins, doc["defaults"], doc["layers"], doc["body_model"], root)


def catalogue_path(path: str | Path | None = None) -> Path:
    """The directory to load: ``path``, else ``TRYON_CATALOGUE``, else the packaged one."""
    return Path(path or os.environ.get("TRYON_CATALOGUE") or DEFAULT_CATALOGUE_DIR)


@functools.lru_cache(maxsize=4)
def _load(path: Path) -> Catalogue:
    return read_catalogue(path)


def load_catalogue(path: str | Path | None = None) -> Catalogue:
    """The process-wide catalogue (read once per process and path)."""
    return _load(catalogue_path(path).resolve())

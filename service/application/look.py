"""The avatar's look (issue 11): skin, eyes with irises, eyebrows, optional hair and a modest
base layer (underwear), from the compiled catalogue (``service/data/catalogue``), so that an
avatar looks like a person in underwear rather than a bald, grey, nude figure.

Choices per request: ``hair`` (a catalogue hair id, ``none``, or omitted: the catalogue's
default for the avatar's gender) and ``underwear`` (default true; false shows the bare body).
The catalogue items are prepared once per process and body model (``model.look.prepare_item``);
a request only fits them to the avatar (a few sparse gathers and a push-out, no k-d tree).
"""
from __future__ import annotations

import functools
import hashlib
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.model.body.model import BodyModel
from service.model.garments.catalogue import Catalogue, CatalogueItem, Material, Skin, load_catalogue
from service.model.formats.gltf import MeshTemplate
from service.model.garments.look import PreparedItem, merge_meshes, prepare_item, visible_body_faces
from service.model.garments.tryon import surface_body

from service.storage.cache import VersionedLRU

from .errors import Invalid

HAIR_NONE = "none"
GENDERS = ("female", "male")
FITTED_CACHE_SIZE = 64  # fitted looks kept per process (~0.5 MB each), keyed by avatar and look
# node names of the look's meshes (the body is "avatar")
EYES, EYEBROWS, HAIR, UNDERWEAR = "eyes", "eyebrows", "hair", "underwear"


@dataclass(frozen=True, eq=False)
class Look:
    """A resolved look: the skin, the items to wear (eyes, eyebrows, hair or None, the base
    layer, possibly empty) and the body vertices hidden under them (H,)."""

    gender: str
    skin: Skin
    eyes: CatalogueItem
    eyebrows: CatalogueItem
    hair: CatalogueItem | None
    base_layer: tuple[CatalogueItem, ...]
    hidden: np.ndarray
    catalogue: Catalogue

    @property
    def key(self) -> str:
        """What the look is made of, for ETags: the items chosen and the catalogue's digest."""
        ids = [self.skin.id, self.eyes.id, self.eyebrows.id, self.hair.id if self.hair else HAIR_NONE,
               *[i.id for i in self.base_layer]]
        return "look:" + ",".join(ids) + ":" + catalogue_digest(self.catalogue)


def catalogue() -> Catalogue:
    """The process-wide compiled catalogue (``TRYON_CATALOGUE`` or the packaged one)."""
    return load_catalogue()


@functools.lru_cache(maxsize=4)
def catalogue_digest(cat: Catalogue) -> str:
    """SHA-256 (16 hex) of the catalogue's files: a new catalogue changes every look ETag."""
    h = hashlib.sha256()
    for p in sorted(q for q in cat.path.rglob("*") if q.is_file()):
        h.update(p.relative_to(cat.path).as_posix().encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def gender_of(measurements: dict[str, Any] | None) -> str:
    """The gender an avatar's look is chosen for: its ``gender`` measurement (given or
    estimated from the shape), female when unknown (the page's default)."""
    g = str((measurements or {}).get("gender") or "female").lower()
    return "male" if g.startswith("m") else "female"


def hair_choices(cat: Catalogue | None = None) -> list[dict[str, str]]:
    """The hair styles a shopper can choose: [{id, name, gender, color}] in catalogue order."""
    cat = cat or catalogue()
    return [{"id": h.id, "name": h.name, "gender": h.gender, "color": h.color} for h in cat.hair()]


def defaults(cat: Catalogue | None = None) -> dict[str, dict[str, Any]]:
    """Per gender: the default hair id and whether underwear is shown by default."""
    cat = cat or catalogue()
    return {g: {"hair": cat.look(g)["hair"].id, "underwear": True} for g in GENDERS}


def resolve(gender: str, hair: str | None = None, underwear: bool = True, cat: Catalogue | None = None) -> Look:
    """The look for an avatar of ``gender``: ``hair`` a catalogue hair id, ``none``, or None
    (the gender's default); ``underwear`` the gender's base layer or none. An unknown hair id
    is a 422 naming the choices."""
    cat = cat or catalogue()
    d = cat.look(gender)
    if hair is None:
        hair_item = d["hair"]
    elif hair.strip().lower() == HAIR_NONE:
        hair_item = None
    else:
        ids = {h.id: h for h in cat.hair()}
        hair_item = ids.get(hair.strip())
        if hair_item is None:
            raise Invalid(("query", "hair"), f"unknown hair '{hair}': one of {', '.join(ids)} or '{HAIR_NONE}' "
                                             "(GET /v1/looks)")
    base = tuple(d["base_layer"]) if underwear else ()
    hidden = np.unique(np.concatenate([i.hidden for i in base])) if base else np.zeros(0, np.int64)
    return Look(gender_of({"gender": gender}), d["skin"], d["eyes"], d["eyebrows"], hair_item, base, hidden, cat)


@functools.lru_cache(maxsize=64)
def _prepared(model: BodyModel, item: CatalogueItem) -> PreparedItem:
    return prepare_item(item, model.mean, model.n_body_vertices, model.lbs_indices, model.lbs_weights,
                        model.body_faces)


def prepared(model: BodyModel, item: CatalogueItem) -> PreparedItem:
    """``item`` prepared for ``model`` (once per process)."""
    return _prepared(model, item)


@functools.lru_cache(maxsize=32)
def _group_template(model: BodyModel, items: tuple[CatalogueItem, ...], textured: bool) -> MeshTemplate:
    """The static arrays of a look group's merged render mesh (what :meth:`PreparedItem.fit`
    returns besides vertices and normals: faces, uv, skinning), checked and encoded once per
    process and shared by every avatar wearing the group."""
    parts = []
    for item in items:
        p = prepared(model, item)
        v = p.layout.vertex
        parts.append({"vertices": v, "faces": p.layout.faces, "uv": p.layout.uv, "vertex_joints": p.skin_idx[v],
                      "vertex_weights": p.skin_w[v]})
    m = merge_meshes(parts)
    return MeshTemplate(m["faces"], len(m["vertices"]), uv=m["uv"] if textured else None,
                        vertex_joints=m["vertex_joints"], vertex_weights=m["vertex_weights"],
                        n_joints=len(model.bone_parents))


def material_fields(material: Material) -> dict[str, Any]:
    """The scene-mesh fields of a catalogue material (``service.model.formats.gltf`` mesh dict)."""
    return {"color": tuple(material.base_color_factor), "double_sided": material.double_sided,
            "material": material}


def body_fields(model: BodyModel, look: Look | None, hidden: tuple[np.ndarray, ...] = ()) -> dict[str, Any]:
    """The avatar (body) mesh's fields under ``look`` (or None: no look) with garments over it
    hiding body vertices ``hidden`` (each (H_i,) int, e.g. ``GarmentBasis.hidden_body``): the
    skin's material, and the faces left after hiding the body under the base layer and those
    garments (none left out when nothing hides it)."""
    out = material_fields(look.skin.material) if look is not None else {}
    sets = ([look.hidden] if look is not None and look.base_layer else []) + [h for h in hidden if len(h)]
    if sets:
        out["faces"] = visible_faces(model, sets)
    return out


VISIBLE_FACES_CACHE_SIZE = 16  # hidden-vertex sets (looks x outfits' garments) kept per process (~0.3 MB each)
_visible: OrderedDict[tuple[int, str], tuple[BodyModel, np.ndarray]] = OrderedDict()
_visible_lock = threading.Lock()


def visible_faces(model: BodyModel, hidden: list[np.ndarray]) -> np.ndarray:
    """The body faces (F', 3) left to draw when the body vertices in ``hidden`` (a list of
    (H_i,) int arrays: a base layer's, worn garments') are hidden (``visible_body_faces`` of
    their union), cached per process by the union: the same set gives the same read-only
    array object, which keys the avatar's mesh template (``scenes._body_template``)."""
    h = np.unique(np.concatenate([np.asarray(x, np.int64) for x in hidden])) if hidden else np.zeros(0, np.int64)
    key = (id(model), hashlib.sha1(h.tobytes()).hexdigest())
    with _visible_lock:
        hit = _visible.get(key)
        if hit is not None and hit[0] is model:
            _visible.move_to_end(key)
            return hit[1]
    faces = visible_body_faces(model.body_faces, h, model.n_body_vertices)
    faces.setflags(write=False)
    with _visible_lock:
        hit = _visible.setdefault(key, (model, faces))  # a racing thread's array wins: one object per set
        _visible.move_to_end(key)
        while len(_visible) > VISIBLE_FACES_CACHE_SIZE:
            _visible.popitem(last=False)
    return hit[1]


_fitted = VersionedLRU(FITTED_CACHE_SIZE)


def item_meshes(model: BodyModel, vertices: np.ndarray, body_normals: np.ndarray, look: Look,
                template: bool = True) -> list[dict[str, Any]]:
    """The look's scene meshes on an avatar (V, 3) with body normals (Vb, 3): eyes, eyebrows,
    hair (if any) and underwear (the base layer's items as one mesh, if any), each skinned and
    named; the avatar's own mesh is ``scenes.avatar_mesh``. Cached per process by (avatar
    vertices' digest, look): a customer's avatar and outfits fit the look once. Each carries
    its static arrays also as a ``template`` (:class:`service.model.formats.gltf.MeshTemplate`, made
    with the cache entry); ``template=False`` leaves it out (the reference path)."""
    X = np.ascontiguousarray(vertices, np.float32)
    key = hashlib.sha1(X.tobytes()).hexdigest() + "|" + look.key + f"|{id(model)}"
    hit = _fitted.get(key, None)
    if hit is None:
        hit = _fit_items(model, X, body_normals, look)
        _fitted.put(key, None, hit)
    if template:
        return [dict(m) for m in hit]
    return [{k: v for k, v in m.items() if k != "template"} for m in hit]


def _fit_items(model: BodyModel, vertices: np.ndarray, body_normals: np.ndarray, look: Look) -> list[dict[str, Any]]:
    X = np.asarray(vertices, np.float64)
    n = np.asarray(body_normals, np.float32)
    groups: list[tuple[str, list[CatalogueItem]]] = [(EYES, [look.eyes]), (EYEBROWS, [look.eyebrows])]
    if look.hair is not None:
        groups.append((HAIR, [look.hair]))
    if look.base_layer:
        groups.append((UNDERWEAR, list(look.base_layer)))
    out = []
    body = surface_body(model, X, n)  # the push-outs' nearest vertices and crease anchors
    for name, items in groups:
        mesh = merge_meshes([prepared(model, i).fit(X, n, body) for i in items])
        mat = items[0].material
        mesh.update(material_fields(mat))
        if mat.base_color_texture is None and mat.normal_texture is None:
            del mesh["uv"]  # untextured (the base layer): no TEXCOORD_0 to ship
        mesh["name"] = name
        for v in mesh.values():
            if isinstance(v, np.ndarray):
                v.setflags(write=False)
        mesh["template"] = _group_template(model, tuple(items), "uv" in mesh)
        out.append(mesh)
    return out

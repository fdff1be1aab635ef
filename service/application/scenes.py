"""GLB and OBJ assembly from model arrays: the avatar, a garment tried on, an outfit, a
clothing basis. Shapes follow ``service.model``: avatar vertices (V, 3) metres, garment
vertices (M, 3), faces (F, 3)."""
from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Callable
from typing import Any

import numpy as np

from service.model.garments import correctives
from service.model.formats import gltf
from service.model.body import lbs
from service.model.body.model import BONES, BodyModel
from service.model.geometry.mesh import vertex_normals
from service.model.garments import sizing as SZ
from service.model.garments.layering import layer_outfit
from service.model.garments.tryon import CustomerBody, GarmentBasis, strain_map, try_on
from service.records import Garment
from service.storage.cache import VersionedLRU

from . import look as looks
from .parallel import per_pose
from .look import Look

AVATAR_COLOR = (0.8, 0.7, 0.62, 1.0)
SCENE_VERSION = 6  # bump when the GLB assembly changes: every scene ETag changes with it


def etag(kind: str, body_model: str, weights: list[float] | None, compression: str | None,
         garments: list[tuple[str, str]] = ()) -> str:
    """A strong ETag (quoted) of a scene from everything it is made of: its kind, the body
    model, the customer's weights, the garments' (id, basis etag) in order, the options."""
    h = hashlib.sha256(np.asarray(weights or [], np.float64).tobytes())
    h.update(json.dumps([SCENE_VERSION, kind, body_model, compression, list(garments)]).encode())
    return f'"{h.hexdigest()[:32]}"'


def etag_matches(tag: str, if_none_match: list[str] | None) -> bool:
    """``If-None-Match`` (its tags, quoted, ``W/`` dropped, or ``*``) matches ``tag``."""
    return bool(if_none_match) and ("*" in if_none_match or tag in if_none_match)  # type: ignore[operator]
DEFAULT_GARMENT_COLOR = (0.55, 0.55, 0.58, 1.0)


def skeleton(model: BodyModel, vertices: np.ndarray) -> dict[str, Any]:
    """The skeleton of a rest-pose avatar (V, 3) for GLB skins: rest joints, parents, names."""
    return {"joints": model.joints(vertices), "parents": np.asarray(model.bone_parents),
            "joint_names": list(BONES)}


# body mesh templates: (model, faces) -> (model, faces, template); the key objects are kept
# alive with their entry (ids stay theirs) and checked by identity
_body_templates: dict[tuple[int, int], tuple[BodyModel, np.ndarray, gltf.MeshTemplate]] = {}
MAX_BODY_TEMPLATES = 16  # body models x visible-face sets (looks' base layers x outfits' garments)


def _body_template(model: BodyModel, faces: np.ndarray) -> gltf.MeshTemplate:
    """The avatar body's static arrays (faces, cleaned skin weights) as a mesh template, once
    per (body model, faces) per process; for a subset of the body's faces (the body under a
    look or an outfit left out), sharing the whole body's skin and its encoded views
    (``MeshTemplate.with_faces``: 0.46 MB per face set with its plain and meshopt views
    instead of 2.2; tracemalloc, one-off)."""
    hit = _body_templates.get((id(model), id(faces)))
    if hit is not None and hit[0] is model and hit[1] is faces:
        return hit[2]
    if faces is model.body_faces:
        nb = model.n_body_vertices
        tpl = gltf.MeshTemplate(faces, nb, vertex_joints=model.lbs_indices[:nb],
                                vertex_weights=model.lbs_weights[:nb], n_joints=len(model.bone_parents))
    else:
        tpl = _body_template(model, model.body_faces).with_faces(faces)
    if len(_body_templates) >= MAX_BODY_TEMPLATES:
        # the oldest face set goes; a whole body's template stays while face sets share it
        old = next((k for k, v in _body_templates.items() if v[1] is not v[0].body_faces), None)
        _body_templates.pop(old if old is not None else next(iter(_body_templates)))
    _body_templates[(id(model), id(faces))] = (model, faces, tpl)
    return tpl


def avatar_mesh(model: BodyModel, vertices: np.ndarray, normals: np.ndarray | None = None,
                look: Look | None = None, template: bool = True,
                hidden: tuple[np.ndarray, ...] = ()) -> dict[str, Any]:
    """The customer-visible skinned body surface of an avatar (V, 3) as a scene mesh, named
    ``avatar``; under a ``look``, with its skin's material and without the faces hidden under
    its base layer, nor under garments worn over it that hide body vertices ``hidden`` (each
    (H_i,) int: ``GarmentBasis.hidden_body``). ``template``: its static arrays also as a mesh
    template (see :func:`look_mesh`)."""
    nb = model.n_body_vertices
    mesh = {"vertices": model.body_vertices(vertices), "faces": model.body_faces, "normals": normals,
            "color": AVATAR_COLOR, "name": "avatar",
            "vertex_joints": model.lbs_indices[:nb], "vertex_weights": model.lbs_weights[:nb]}
    if look is not None or hidden:
        mesh.update(looks.body_fields(model, look, hidden))
    if template:
        mesh["template"] = _body_template(model, mesh["faces"])
    return mesh


def avatar_meshes(model: BodyModel, vertices: np.ndarray, normals: np.ndarray | None = None,
                  look: Look | None = None, template: bool = True,
                  hidden: tuple[np.ndarray, ...] = ()) -> list[dict[str, Any]]:
    """The avatar (V, 3) as scene meshes: the body (``avatar``, without the faces ``hidden``
    under garments: :func:`avatar_mesh`), then, under a ``look``, its ``eyes``, ``eyebrows``,
    ``hair`` and ``underwear`` (each skinned with the body's skeleton)."""
    body = avatar_mesh(model, vertices, normals, look, template, hidden)
    if look is None:
        return [body]
    if normals is None:
        normals = vertex_normals(model.body_vertices(np.asarray(vertices, np.float64)), model.body_faces)
    return [body, *looks.item_meshes(model, vertices, normals, look, template)]


def avatar_glb(model: BodyModel, vertices: np.ndarray, compression: str | None = None,
               normals: np.ndarray | None = None, look: Look | None = None, template: bool = True) -> bytes:
    """The skinned avatar (V, 3) as GLB bytes (``compression``: None, "quantize" or
    "meshopt"): the body surface alone, or wearing ``look`` (see :func:`avatar_meshes`).
    ``template=False``: the reference path (the same bytes)."""
    return gltf.scene_to_glb(avatar_meshes(model, vertices, normals, look, template), skin=skeleton(model, vertices),
                             compression=compression)


def garment_mesh(basis: GarmentBasis, record: Garment, body: CustomerBody, layer: int,
                 template: bool = True) -> dict[str, Any]:
    """The garment tried on ``body`` as a scene mesh (skinned with the basis' skinning); with
    the basis' render layout and material: UVs, textures (static bytes) and, for a normal
    map, tangents. ``template``: see :func:`look_mesh`."""
    v, _moved = try_on(basis, body, layer=layer)
    return look_mesh(basis, record, np.asarray(v, np.float32), basis.normals(v, body.weights), template)


def look_mesh(basis: GarmentBasis, record: Garment, v: np.ndarray, n: np.ndarray,
              template: bool = True, skin: tuple[np.ndarray, np.ndarray] | None = None,
              colors: np.ndarray | None = None) -> dict[str, Any]:
    """Garment vertices (M, 3) and normals (M, 3) as a skinned scene mesh (for the body
    model's skeleton): gathered into the render layout (R render vertices: one fancy-index
    each) when the basis has one. With ``template``, the static arrays (faces, UVs, skinning)
    come as the basis' :meth:`GarmentBasis.mesh_template` (built once per basis: the same GLB
    bytes); without, as plain arrays (the reference path, for tests and benchmarks). ``skin``
    (joints (M, 4), weights (M, 4)): skinned with these instead of the basis' own (an outfit's
    inner garment skinned like the garment over it), as plain arrays. ``colors`` (M, 4) uint8: a
    fit map as COLOR_0 on a white, untextured material."""
    mesh: dict[str, Any] = {"color": tuple(record.color or DEFAULT_GARMENT_COLOR), "name": record.name or "garment",
                            "double_sided": True}
    if basis.has_layout:
        idx = np.asarray(basis.render_vertex)
        rn = np.take(n, idx, axis=0)  # np.take: ~4x faster than n[idx] on 3-wide rows
        mesh.update(vertices=np.take(v, idx, axis=0), normals=rn, tangents=basis.render_tangents(rn))
        if not template or skin is not None:
            mesh.update(faces=np.asarray(basis.render_faces), uv=np.asarray(basis.render_uv))
            mesh["vertex_joints"], mesh["vertex_weights"] = basis.render_skin() if skin is None else \
                (np.take(skin[0], idx, axis=0), np.take(skin[1], idx, axis=0))
    else:
        mesh.update(vertices=v, normals=n)
        if not template or skin is not None:
            j, w = (basis.skin_idx, basis.skin_w) if skin is None else skin
            mesh.update(faces=np.asarray(basis.faces), vertex_joints=np.asarray(j), vertex_weights=np.asarray(w))
    if template and skin is None:
        mesh["template"] = basis.mesh_template(len(BONES))
    if colors is not None:
        mesh["colors"] = np.take(colors, np.asarray(basis.render_vertex), axis=0) if basis.has_layout else colors
        mesh["color"] = (1.0, 1.0, 1.0, 1.0)
        return mesh
    if basis.material is not None and (basis.has_layout or _untextured(basis.material)):
        mesh["material"] = basis.material
    return mesh


def fitmap_colors(kind: str, basis: GarmentBasis, record: Garment, v: np.ndarray, body: CustomerBody,
                  synthesised: bool = True) -> np.ndarray:
    """COLOR_0 (M, 4) uint8 of a garment worn as ``v`` (M, 3) on ``body``: ``strain`` (each
    vertex's mean edge stretch against the size's rest shape: ``tryon.strain_map``, from the
    basis's strain channel for a basis try-on (``synthesised``), measured on v for the customer's
    own drape) or ``ease`` (its gap over the body); ``sizing.strain_colors`` / ``ease_colors`` for
    the garment's fabric."""
    fabric = record.fabric if record.fabric in SZ.FIT_THRESHOLDS else SZ.DEFAULT_FABRIC
    if kind == "strain":
        return SZ.strain_colors(strain_map(basis, body.weights, v, synthesised), fabric)
    nearest = body.push_binding(basis, v)[0][:, 0]
    nb = len(body.normals)
    return SZ.ease_colors(SZ.body_gap(v, body.vertices[:nb], body.normals, nearest), fabric)


def _opaque(record: Garment) -> bool:
    """Whether the garment's colour is opaque (for a basis without a material; a material's
    alpha mode is ``GarmentBasis.hidden_body``'s to judge)."""
    return record.color is None or len(record.color) < 4 or float(record.color[3]) >= 1.0


def _untextured(material: Any) -> bool:
    return material.base_color_texture is None and material.normal_texture is None


LAYERED_CACHE_SIZE = 32  # layered outfits kept per process (~0.5 MB each for three layers)
_layered = VersionedLRU(LAYERED_CACHE_SIZE)


def layered_outfit(layers: list[tuple[np.ndarray, np.ndarray]], body: np.ndarray, body_normals: np.ndarray,
                   skins: list[tuple[np.ndarray, np.ndarray]], n_joints: int, cache: bool = True
                   ) -> tuple[list[np.ndarray], list[tuple[np.ndarray, np.ndarray]]]:
    """``layering.layer_outfit`` of layers [(vertices (M_i, 3), faces)] with their skins on a body
    (Vb, 3), cached per process by the digest of everything it reads (the same customer trying
    the same outfit again, in another compression or after a page reload, is not layered again).
    Returns new lists of (read-only) arrays."""
    h = hashlib.sha1(np.asarray([n_joints, len(layers)], np.int64).tobytes())
    for a in (body, body_normals, *[x for layer in layers for x in layer], *[x for sk in skins for x in sk]):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    key = h.hexdigest()
    hit = _layered.get(key, None) if cache else None
    if hit is None:
        layered, new_skins = layer_outfit(layers, body, body_normals, skins=skins, n_joints=n_joints)
        assert new_skins is not None
        for a in (*layered, *[x for sk in new_skins for x in sk]):
            a.setflags(write=False)
        hit = (layered, new_skins)
        _layered.put(key, None, hit)
    return list(hit[0]), list(hit[1])


def outfit_glb(model: BodyModel, body: CustomerBody, garments: list[tuple[Garment, GarmentBasis]],
               compression: str | None, with_avatar: bool = True, look: Look | None = None,
               template: bool = True, cache: bool = True,
               poses: dict[str, np.ndarray] | Callable[[], dict[str, np.ndarray] | None] | None = None,
               fitmap: str | None = None, worn: list[np.ndarray] | None = None) -> bytes:
    """Garments (already in layer order, inner first) on a customer's body, sharing one
    skeleton; with the avatar as the first mesh when ``with_avatar``. ``template``: the
    garments' static arrays from their bases' templates (see :func:`look_mesh`; False: the
    reference path, the same bytes). ``cache``: the layering from the process cache when the
    same layers were layered on the same body before (:func:`layered_outfit`; False: always
    layered, for benchmarks). ``fitmap``: ``strain`` or ``ease``: each garment coloured by
    :func:`fitmap_colors` (COLOR_0). ``worn``: each garment's vertices (M_i, 3) on this body
    from elsewhere (a per-customer drape) instead of its basis try-on, normals from its mesh
    (None for a garment: its basis try-on). ``poses`` ({name: (17, 3) axis-angle}, the page's poses for this
    body): each garment also gets one pose-corrective morph target per pose
    (:func:`add_pose_correctives`); or a function returning them, called once the outfit is
    layered (the poses' adaptation may be under way in another server process meanwhile)."""
    meshes: list[dict[str, Any]] = []
    if with_avatar:  # the body under opaque garments is left out (it cannot show, and skinning or
        # a pose would let it poke through): each basis' hidden_body, once per basis
        hidden = tuple(basis.hidden_body(model) for rec, basis in garments
                       if basis.material is not None or _opaque(rec))
        meshes = avatar_meshes(model, body.vertices, body.normals, look, template, hidden)
    given = worn if worn is not None else [None] * len(garments)  # None: that garment's basis try-on
    worn = [np.asarray(try_on(basis, body, layer=rank)[0] if v is None else v, np.float32)
            for rank, (v, (_, basis)) in enumerate(zip(given, garments))]
    normals = [basis.normals(v, body.weights) if g is None else basis.normals(v)
               for g, v, (_, basis) in zip(given, worn, garments)]
    # the look's base layer is the innermost layer: a bra never shows through a blouse
    under = next((m for m in meshes if m.get("name") == "underwear"), None) if worn else None
    layers = ([(np.asarray(under["vertices"], np.float32), np.asarray(under["faces"]))] if under is not None else []) \
        + [(v, basis.faces) for v, (_, basis) in zip(worn, garments)]
    skins: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(garments)
    if len(layers) > 1:  # inner layers pushed back inside the outer ones (service.model.garments.layering),
        nb = model.n_body_vertices  # garments on their welded vertices, before any split at UV seams;
        # each inner layer skinned like the layer over it where covered, so it stays inside when posed
        layer_skins = ([(under["vertex_joints"], under["vertex_weights"])] if under is not None else []) \
            + [(basis.skin_idx, basis.skin_w) for _, basis in garments]
        layered, new_skins = layered_outfit(layers, body.vertices[:nb], np.asarray(body.normals, np.float64),
                                            layer_skins, len(BONES), cache)
        if under is not None:
            v = layered.pop(0).astype(np.float32)
            under["vertex_joints"], under["vertex_weights"] = new_skins.pop(0)
            under.pop("template", None)  # its template holds the look's own skin weights
            if not np.array_equal(v, under["vertices"]):
                under["vertices"], under["normals"] = v, vertex_normals(v, under["faces"]).astype(np.float32)
        skins = list(new_skins)
        for i, (v, (_, basis)) in enumerate(zip(layered, garments)):
            if not np.array_equal(v, worn[i]):
                worn[i] = v.astype(np.float32)
                normals[i] = basis.normals(worn[i])
    garment_meshes = [look_mesh(basis, rec, v, n, template, sk,
                                None if fitmap is None else fitmap_colors(fitmap, basis, rec, v, body, g is None))
                      for g, v, n, sk, (rec, basis) in zip(given, worn, normals, skins, garments)]
    if callable(poses):
        poses = poses()
    if poses:
        avatar = next((m for m in meshes if m.get("name") == "avatar"), None)
        base = None if under is None else (np.asarray(under["vertices"]), np.asarray(under["faces"]),
                                           (np.asarray(under["vertex_joints"]), np.asarray(under["vertex_weights"])))
        add_pose_correctives(garment_meshes, model, body, [b for _, b in garments], worn, skins, poses, avatar, base)
    meshes += garment_meshes
    return gltf.scene_to_glb(meshes, skin=skeleton(model, body.vertices), compression=compression)


POSED_BODIES_PER_CUSTOMER = 4  # pose sets (posed bodies, k-d trees) kept per customer body
REST = ""  # posed_bodies' key of the unposed body
CORRECTIVES_CACHE_SIZE = 64  # outfits' pose targets kept per process (~100 kB per 2k-vertex garment, 4 poses)
_correctives = VersionedLRU(CORRECTIVES_CACHE_SIZE)


def posed_bodies(model: BodyModel, body: CustomerBody, poses: dict[str, np.ndarray]) -> dict[str, correctives.PosedBody]:
    """The customer's body in each of ``poses`` (:func:`correctives.posed_body`) and unposed
    (key ``REST``), cached on the body per pose set (every garment of an outfit, and the next
    try-on, reuse them)."""
    h = hashlib.sha1()
    for name, p in poses.items():
        h.update(name.encode() + b"\0" + np.ascontiguousarray(p, np.float64).tobytes())
    key = h.hexdigest()
    hit = body._posed.get(key)
    if hit is None:
        todo = {**poses, REST: np.zeros((len(BONES), 3))}
        hit = dict(zip(todo, per_pose(lambda p: correctives.posed_body(model, body.vertices, p), list(todo.values()))))
        if len(body._posed) >= POSED_BODIES_PER_CUSTOMER:
            body._posed.pop(next(iter(body._posed)))
        body._posed[key] = hit
    return hit


def add_pose_correctives(meshes: list[dict[str, Any]], model: BodyModel, body: CustomerBody,
                         bases: list[GarmentBasis], worn: list[np.ndarray],
                         skins: list[tuple[np.ndarray, np.ndarray] | None], poses: dict[str, np.ndarray],
                         avatar: dict[str, Any] | None = None,
                         base: tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None) -> None:
    """Give an outfit's garment scene meshes (:func:`look_mesh` of ``worn`` (M_i, 3) skinned with
    ``skins``, or the bases' own skin; inner first) one morph target per pose, ``pose:<name>``:
    rest-space deltas that keep each garment outside the posed body
    (``correctives.posed_pushes``; outer layers with more clearance), an inner garment moved as
    the garment over it where covered (``correctives.follow_outer``: the layers keep their
    order), gathered into the render layout, stored sparse. With the ``avatar`` scene mesh
    (:func:`avatar_mesh`, its drawn faces), the body gets one too: skin still showing through
    the posed garments pulled back under them (``correctives.body_tucks``), the look's ``base``
    layer included ((M, 3) vertices, faces, skin as layered under the garments; it has no pose
    targets of its own: under a loose jacket the trunks move with the jacket, and in the walking
    step the forward thigh came up through them). Cached per process by the digest of
    everything they are made of (the same customer and outfit asked again)."""
    sk = [(b.skin_idx, b.skin_w) if s is None else s for b, s in zip(bases, skins)]
    bodies = posed_bodies(model, body, poses)
    tucks = avatar is not None and correctives.BODY_TUCKS
    h = hashlib.sha1(json.dumps([sorted(bodies), tucks]).encode())
    for a in (*worn, *[x for pair in sk for x in pair], *[b.faces for b in bases],
              *[bodies[k].transforms for k in sorted(bodies)], *([avatar["faces"]] if tucks else []),
              *((base[0], base[1], *base[2]) if tucks and base is not None else ())):
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    key = h.hexdigest()
    hit = _correctives.get(key, None)
    if hit is None:
        deltas = [np.zeros((len(poses), len(v), 3), np.float32) for v in worn]
        nb = model.n_body_vertices
        covers = [correctives.cover_map(worn[i], worn[i + 1], bases[i + 1].faces, body.vertices[:nb], body.normals)
                  for i in range(len(worn) - 1)]
        body_deltas = np.zeros((len(poses), nb, 3), np.float32) if tucks else None
        shown = _shown(avatar, nb) if tucks else None
        for b in bases:
            b.smoother()  # the smoothers made once, before the threads share them
        if tucks:
            correctives.body_smoother(model)

        names = list(poses)

        def one_pose(k: int) -> None:
            name = names[k]
            above = None  # the posed pushes of the garment over this one
            for i in range(len(worn) - 1, -1, -1):  # outermost first
                d, _ = correctives.posed_pushes(worn[i], *sk[i], bodies[name], bases[i].smoother(), i,
                                                rest=bodies[REST], faces=np.asarray(bases[i].faces))
                if above is not None:
                    d = correctives.follow_outer(d, covers[i], above, bases[i + 1].faces)
                deltas[i][k] = correctives.to_rest(d, bodies[name].transforms, *sk[i])
                above = d
            if body_deltas is not None:
                body_deltas[k] = _body_tuck(model, bodies[name], [dl[k] for dl in deltas], bases, worn, sk, shown,
                                            base)

        per_pose(one_pose, list(range(len(poses))))
        for d in (*deltas, *([body_deltas] if body_deltas is not None else [])):
            d.setflags(write=False)
        hit = (deltas, body_deltas)
        _correctives.put(key, None, hit)
    deltas, body_deltas = hit
    if body_deltas is not None and np.any(body_deltas) and avatar is not None:
        avatar.update(targets=body_deltas, target_names=correctives.target_names(poses), sparse_targets=True)
    for mesh, d, basis in zip(meshes, deltas, bases):
        if basis.has_layout:
            d = np.take(d, np.asarray(basis.render_vertex), axis=1)
        mesh.update(targets=d, target_names=correctives.target_names(poses), sparse_targets=True)


def _shown(avatar: dict[str, Any], nb: int) -> np.ndarray:
    """(Vb,) bool: the body vertices the avatar scene mesh draws (those on its faces)."""
    shown = np.zeros(nb, bool)
    shown[np.asarray(avatar["faces"]).ravel()] = True
    return shown


def _body_tuck(model: BodyModel, posed: correctives.PosedBody, deltas: list[np.ndarray], bases: list[GarmentBasis],
               worn: list[np.ndarray], sk: list[tuple[np.ndarray, np.ndarray]], shown: np.ndarray,
               base: tuple[np.ndarray, np.ndarray, tuple[np.ndarray, np.ndarray]] | None = None) -> np.ndarray:
    """The avatar's rest-space target (Vb, 3) float32 for one pose: the garments posed as the
    page shows them (rest + their pose target ``deltas`` (M_i, 3), skinned), and the look's
    ``base`` layer (vertices, faces, skin) posed, and ``correctives.body_tucks`` of the drawn
    body vertices (``shown``) back under them."""
    nb = model.n_body_vertices
    G = posed.transforms
    garments = [(lbs.skin(np.asarray(v, np.float64) + d, G, *s), b.faces)
                for v, d, s, b in zip(worn, deltas, sk, bases)]
    if base is not None:
        garments.append((lbs.skin(np.asarray(base[0], np.float64), G, *base[2]), base[1]))
    d = correctives.body_tucks(posed, garments, shown, correctives.body_smoother(model), model.body_faces)
    return correctives.to_rest(d, G, model.lbs_indices[:nb], model.lbs_weights[:nb])


def basis_glb(basis: GarmentBasis, record: Garment, compression: str | None, components: int | None = None) -> bytes:
    """The mean garment with the clothing basis rows (the first ``components``; None: all; 0:
    none, the mean garment alone) as morph targets."""
    B, g, faces, uv = np.asarray(basis.B)[:components], np.asarray(basis.g), np.asarray(basis.faces), None
    if basis.has_layout:  # split at the UV seams
        idx = np.asarray(basis.render_vertex)
        B, g, faces, uv = B[:, idx], g[idx], np.asarray(basis.render_faces), np.asarray(basis.render_uv)
    material = basis.material if basis.material is not None and (uv is not None or _untextured(basis.material)) \
        else None
    return gltf.basis_to_glb(g, B, faces, color=tuple(record.color or DEFAULT_GARMENT_COLOR),
                             name=record.name or "garment", target_names=[f"pc{i:02d}" for i in range(B.shape[0])],
                             compression=compression, uv=uv, material=material)


def obj_text(vertices: np.ndarray, faces: np.ndarray, comment: str = "") -> str:
    """A minimal OBJ (``v`` and 1-based ``f`` lines)."""
    out = io.StringIO()
    for line in comment.splitlines():
        out.write(f"# {line}\n")
    np.savetxt(out, np.asarray(vertices, np.float64), fmt="v %.6f %.6f %.6f")
    np.savetxt(out, np.asarray(faces, np.int64) + 1, fmt="f %d %d %d")
    return out.getvalue()

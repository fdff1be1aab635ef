"""Garment bases on disk and the try-on itself (pure numpy; no web or queue imports).

``GarmentBasis`` holds everything a try-on needs for one garment: the mean garment g (M, 3),
the clothing basis B (N, M, 3), faces (F, 3), the push-out binding (M, k) to body vertices,
skinning transferred from the body (M, 4) + (M, 4), a colour and a layer; optionally its look:
a render layout (the mesh split at its UV seams: render_vertex (R,) index into the M welded
vertices, render_uv (R, 2) glTF convention, render_faces (F, 3) into the R render vertices) and
a material (:class:`service.model.garments.catalogue.Material`, textures stored as files beside the
arrays). It is stored as plain ``.npy`` files in one directory and memory-mapped by every API
process; bases saved before the look existed load without it.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from service.model.garments import garment as G
from service.model.garments import skin_weights as SW
from service.model.body.model import BONES
from service.model.body.measurements import ATTRIBUTES
from service.model.garments.catalogue import Material, RenderLayout, Texture
from service.model.geometry.mesh import (face_bounds, face_incidence, mesh_edges, row_dot, vertex_faces, vertex_mean_strain,
                                         vertex_normals)
from service.model.formats.gltf import MeshTemplate
from service.model.formats.gltf_buffers import vertex_tangents
from service.model.garments.correctives import skin_under_faces
from service.model.garments.layering import covered_body
from service.model.body.poses import preset_transforms, stride_poses
from service.model.garments.skin_weights import leg_frame, transfer_skin_weights

# Example avatars: E0 and E(i, +/-) = m +/- c sqrt(lambda_i) U_i for i < N. N and c were chosen
# with `tryon bench tryon` (garment accuracy on held-out avatars; see README "Figures").
EXAMPLES = {"n": 32, "c": 0.5}
ARRAYS = ("g", "B", "faces", "binding", "skin_idx", "skin_w", "gn", "Bn", "rest", "gs", "Bs", "gw", "Bw", "render_vertex",
          "render_uv", "render_faces")
# normal basis, rest shape, strain and start channels, render layout: bases saved before they
# existed load without them
OPTIONAL = ("gn", "Bn", "rest", "gs", "Bs", "gw", "Bw", "render_vertex", "render_uv", "render_faces")
MATERIAL_FILE = "material.json"
TEXTURE_EXT = {"image/png": ".png", "image/jpeg": ".jpg"}


# the release step of skin_weights.release_stretched (edges the page's presets stretch): off.
# It lowered the 99.9th-percentile pose stretch (worst 5.3 -> 2.3) but let sleeves lag the arms
# and the arms show through them (pinstripe blouse: 0.8 % -> 2.5 % of its vertices > 3 mm inside
# the posed body, median over 6 people x 3 poses; seen in the page's screenshots)
SKIN_RELEASE_IN_POSES = False
# step 4 of skin_weights (the legs' share ramped left/right below the crotch, skirts only): the
# pencil skirt's front opened over the forward thigh in the page's walking step without it
SKIN_LEG_RAMP = True
# step 1's release on the limb side of steep inpainted edges (skin_weights.release_limb_side):
# the tops' armpit seams stretched up to 5.3x in the page's poses without it
SKIN_LIMB_SIDE = True
# inpainting screened toward the closest-point matches (skin_weights.SCREENING): a loose jacket's
# front took the sleeves' arm weight without it, and its hem rose with the arms
SKIN_SCREENING = True
# step 6 of skin_weights (the legs' weights refined in strides, skin_weights.refine_in_strides): the
# crotch's front stretched up to 1.9x in the page's walking step on a heavy body without it
SKIN_STRIDES = True
STRIDE_AMPLITUDES = (0.6, 1.2)  # the strides it is refined in: the page's walking step (and its mirror) at these
STRIDE_PERCENTILES = (1.0, 99.0)  # on the mean avatar, the training population's people at these percentiles of
# the first component (the smallest and the largest bodies) ...
STRIDE_BMI_PERCENTILE = 99.0  # ... and of each gender the one at this percentile of the body mass index
# the version of the skin weights a basis carries (meta "skinning"; absent: 1): bases built by an
# older version get their weights recomputed (:func:`refresh_skinning`) when next served.
# 2: step 4, the legs' ramp; 3: the limb side of steep inpainted edges released (armpits);
# 4: the inpainting screened toward the closest-point matches (loose tops' fronts); 5: step 6, the legs'
# weights refined in strides
SKINNING_VERSION = 5

def example_set(model, n: int | None = None, c: float | None = None) -> G.ExampleSet:
    n = min(n or EXAMPLES["n"], model.n_components)
    return G.ExampleSet(n=n, c=float(c or EXAMPLES["c"]), sigma=np.sqrt(model.variances[:n]))


# the share of a gendered garment's population bodies (``population_sample``) of its own gender; the
# rest are of the other, so that its basis still holds, less closely, for anyone trying it on.
# Measured on the men's T-shirt, 49 held-out people (docs/drape.md, Figures): a men's-only
# population fits men's drapes best and women's worst, three quarters nearly as well for men
POPULATION_GENDER_SHARE = 0.75


def population_sample(model, count: int, gender: str | None = None, seed: int = 0) -> np.ndarray:
    """(count, K) body weights of ``count`` people of the body model's own training population
    (``model.population``: ANSUR II's training rows and NHANES's heavy adults, as the model
    fits them), the same for a given seed: the bodies a regressed clothing basis is fitted over
    (``G.regress_basis``). Real people, not independent normal components: heights, girths and
    proportions go together as they do in shoppers. ``gender`` ``female`` / ``male``:
    ``POPULATION_GENDER_SHARE`` of them of that gender, the rest of the other; otherwise half
    each. Drawn without replacement while the population has enough of a gender."""
    rng = np.random.default_rng(seed)
    pop_w = np.asarray(model.population["weights"], np.float64)
    male = np.asarray(model.population["attributes"], np.float64)[:, 0] >= 0.5
    share = 0.5 if gender not in ("female", "male") else (
        POPULATION_GENDER_SHARE if gender == "male" else 1.0 - POPULATION_GENDER_SHARE)
    n_male = int(round(share * count))
    picks = []
    for rows, n in ((np.flatnonzero(male), n_male), (np.flatnonzero(~male), count - n_male)):
        if n and not len(rows):
            rows = np.arange(len(pop_w))
        if n:
            picks.append(rng.choice(rows, n, replace=n > len(rows)))
    idx = np.concatenate(picks) if picks else np.zeros(0, np.int64)
    return pop_w[idx]


def example_vertices(model, examples: G.ExampleSet) -> np.ndarray:
    """(1 + 2N, V, 3) float32 example avatars in listing order."""
    W = np.zeros((1 + 2 * examples.n, model.n_components))
    W[:, : examples.n] = examples.weights()
    return model.vertices(W)


@contextmanager
def atomic_directory(directory: Path) -> Iterator[Path]:
    """Yield a temporary sibling of ``directory`` to write into; on success it replaces
    ``directory`` in one rename, on failure it is removed and ``directory`` is left as it was."""
    directory = Path(directory)
    directory.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".tmp-", dir=directory.parent))
    try:
        yield tmp
        if directory.exists():
            shutil.rmtree(directory)
        os.replace(tmp, directory)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


@dataclass
class GarmentBasis:
    g: np.ndarray
    B: np.ndarray
    faces: np.ndarray
    binding: np.ndarray
    skin_idx: np.ndarray
    skin_w: np.ndarray
    gn: np.ndarray | None = None  # (M, 3) normals of the mean garment
    Bn: np.ndarray | None = None  # (N, M, 3) their basis (central differences, like B)
    rest: np.ndarray | None = None  # (M, 3) the garment's rest shape (its size; the strain map's reference)
    gs: np.ndarray | None = None  # (M,) the strain map of the mean garment (vertex_strain against rest) ...
    Bs: np.ndarray | None = None  # (N, M) ... and its basis: the strain map is a linear channel like the normals
    # where a drape of this garment starts on a body (:func:`drape_start`): the basis (M, 3) / (N, M, 3) of
    # the example fits the build's drapes started from (the warp's), for a basis built from drapes; None:
    # the basis's own try-on
    gw: np.ndarray | None = None
    Bw: np.ndarray | None = None
    render_vertex: np.ndarray | None = None  # (R,) int32 welded vertex of each render vertex
    render_uv: np.ndarray | None = None  # (R, 2) float32, glTF convention (origin top-left)
    render_faces: np.ndarray | None = None  # (F, 3) int32 into the render vertices
    material: Material | None = None
    meta: dict = field(default_factory=dict)
    _smoother: object = None
    _incidence: object = None
    _render_skin: object = None
    _render_tangents: object = None
    # per n_joints; init=False: dataclasses.replace (a new layout or material) starts empty
    _templates: dict = field(default_factory=dict, init=False, repr=False, compare=False)
    _hidden: dict = field(default_factory=dict, init=False, repr=False, compare=False)  # per body model

    @property
    def n_vertices(self) -> int:
        return int(self.g.shape[0])

    def smoother(self):
        if self._smoother is None:
            self._smoother = G.laplacian_smoother(np.asarray(self.faces), self.n_vertices)
        return self._smoother

    def normals(self, vertices: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
        """Unit vertex normals (M, 3) float32 of the garment. With the customer's ``weights``
        and a normal basis: synthesized like the positions (gn + w Bn, renormalised; 3MN
        multiply-adds) instead of recomputed from the mesh."""
        if weights is not None and self.gn is not None:
            n = G.synthesize(np.asarray(self.gn), np.asarray(self.Bn), weights)
            return n / np.sqrt(row_dot(n, n))[:, None]
        if self._incidence is None:
            self._incidence = face_incidence(np.asarray(self.faces), self.n_vertices)
        return vertex_normals(vertices, self.faces, self._incidence)

    # -- the look: render layout and material ----------------------------------------------------
    @property
    def has_layout(self) -> bool:
        return self.render_vertex is not None

    def render_skin(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, 4) joints and (R, 4) weights of the render vertices (gathered once per basis)."""
        if self._render_skin is None:
            idx = np.asarray(self.render_vertex)
            self._render_skin = (np.asarray(self.skin_idx)[idx], np.asarray(self.skin_w)[idx])
        return self._render_skin  # type: ignore[return-value]

    def render_tangents(self, normals: np.ndarray) -> np.ndarray | None:
        """TANGENT (R, 4) for a normal-mapped material: the mean garment's UV tangents (computed
        once per basis) made orthogonal to this try-on's render normals (R, 3) (one
        Gram-Schmidt step, w kept); None without a normal texture."""
        if self.material is None or self.material.normal_texture is None or not self.has_layout:
            return None
        if self._render_tangents is None:
            idx = np.asarray(self.render_vertex)
            g = np.asarray(self.g)[idx]
            t0 = vertex_tangents(g, np.asarray(self.render_faces), np.asarray(self.render_uv),
                                 vertex_normals(g, np.asarray(self.render_faces)))
            self._render_tangents = (np.ascontiguousarray(t0[:, :3]), np.ascontiguousarray(t0[:, 3]))
        t0, w = self._render_tangents  # type: ignore[misc]
        n = np.asarray(normals, np.float32)
        t = t0 - n * row_dot(n, t0)[:, None]
        out = np.empty((len(w), 4), np.float32)
        out[:, :3] = t / np.maximum(np.sqrt(row_dot(t, t)), 1e-12)[:, None]
        out[:, 3] = w
        return out

    def mesh_template(self, n_joints: int) -> MeshTemplate:
        """The static part of this garment's try-on GLB mesh for a skeleton of ``n_joints``:
        faces, skinning and, with a render layout, its faces, UVs and gathered skinning, checked,
        cleaned and encoded once per basis (and compression mode) instead of per request."""
        hit = self._templates.get(n_joints)
        if hit is None:
            if self.has_layout:
                j, w = self.render_skin()
                hit = MeshTemplate(np.asarray(self.render_faces), len(self.render_vertex), uv=np.asarray(self.render_uv),
                                   vertex_joints=j, vertex_weights=w, n_joints=n_joints)
            else:
                hit = MeshTemplate(np.asarray(self.faces), self.n_vertices, vertex_joints=np.asarray(self.skin_idx),
                                   vertex_weights=np.asarray(self.skin_w), n_joints=n_joints)
            self._templates[n_joints] = hit
        return hit

    def hidden_body(self, model) -> np.ndarray:
        """The body vertices (H,) int64 this garment hides (``layering.covered_body`` of the mean
        garment on ``model``'s mean body), once per basis and body model; none for a material that
        is not opaque (lace, sheer cloth: the skin shows through). Read-only."""
        hit = self._hidden.get(id(model))
        if hit is not None and hit[0] is model:
            return hit[1]
        if self.material is not None and self.material.alpha_mode != "OPAQUE":
            hidden = np.zeros(0, np.int64)
        else:
            nb = model.n_body_vertices
            X = np.asarray(model.mean[:nb], np.float64)
            hidden = covered_body(X, vertex_normals(X, model.body_faces), np.asarray(self.g), np.asarray(self.faces))
        hidden.setflags(write=False)
        self._hidden[id(model)] = (model, hidden)
        return hidden

    def save(self, directory: Path) -> None:
        """Write atomically: a temporary sibling directory renamed into place."""
        with atomic_directory(directory) as tmp:
            for k in ARRAYS:
                if getattr(self, k) is not None:
                    np.save(tmp / f"{k}.npy", np.ascontiguousarray(getattr(self, k)))
            if self.material is not None:
                save_material(self.material, tmp)
            (tmp / "meta.json").write_text(json.dumps(self.meta, sort_keys=True))

    @classmethod
    def load(cls, directory: Path, mmap: bool = True) -> "GarmentBasis":
        directory = Path(directory)
        arrs = {k: np.load(directory / f"{k}.npy", mmap_mode="r" if mmap else None) for k in ARRAYS
                if k not in OPTIONAL or (directory / f"{k}.npy").exists()}
        meta = json.loads((directory / "meta.json").read_text())
        material = load_material(directory) if (directory / MATERIAL_FILE).exists() else None
        return cls(**arrs, material=material, meta=meta)

    def etag(self) -> str:
        return self.meta.get("etag", "")


def save_material(material: Material, directory: Path) -> None:
    """``material.json`` plus its textures as ``base_color.jpg|png`` / ``normal.jpg|png``."""
    doc: dict = {"base_color_factor": [float(c) for c in material.base_color_factor],
                 "alpha_mode": material.alpha_mode, "alpha_cutoff": material.alpha_cutoff,
                 "double_sided": bool(material.double_sided), "metallic": float(material.metallic),
                 "roughness": float(material.roughness)}
    for key, tex in (("base_color", material.base_color_texture), ("normal", material.normal_texture)):
        if tex is not None:
            fname = key + TEXTURE_EXT[tex.mime]
            (Path(directory) / fname).write_bytes(tex.data)
            doc[f"{key}_texture"] = {"file": fname, "name": tex.name, "mime": tex.mime}
    (Path(directory) / MATERIAL_FILE).write_text(json.dumps(doc, sort_keys=True))


def load_material(directory: Path) -> Material:
    doc = json.loads((Path(directory) / MATERIAL_FILE).read_text())

    def tex(key: str) -> Texture | None:
        t = doc.get(f"{key}_texture")
        return None if t is None else Texture(t["name"], t["mime"], (Path(directory) / t["file"]).read_bytes())

    return Material(tuple(float(c) for c in doc["base_color_factor"]), tex("base_color"), tex("normal"),  # type: ignore[arg-type]
                    doc["alpha_mode"], doc.get("alpha_cutoff"), bool(doc["double_sided"]), float(doc["metallic"]),
                    float(doc["roughness"]))


def material_digest(material: Material | None) -> bytes:
    """Bytes that change with anything a viewer sees of ``material`` (for the basis etag)."""
    if material is None:
        return b""
    h = hashlib.sha256(json.dumps([list(material.base_color_factor), material.alpha_mode, material.alpha_cutoff,
                                   material.double_sided, material.metallic, material.roughness]).encode())
    for tex in (material.base_color_texture, material.normal_texture):
        h.update(b"-" if tex is None else tex.mime.encode() + hashlib.sha256(tex.data).digest())
    return h.digest()


def build_garment_basis(model, fits: np.ndarray, faces: np.ndarray, examples: G.ExampleSet,
                        meta: dict | None = None, layout: RenderLayout | None = None,
                        material: Material | None = None, rest: np.ndarray | None = None,
                        strain_fits: np.ndarray | None = None, start_fits: np.ndarray | None = None) -> GarmentBasis:
    """fits: (1 + 2N, M, 3) the garment fitted to each example avatar (listing order);
    start_fits: (1 + 2N, M, 3) the example fits ``fits`` were draped from, when they are drapes
    (kept as the start channel (gw, Bw): :func:`drape_start`);
    rest: (M, 3) the garment's rest shape (its own size), kept for the strain map, whose channel
    (gs, Bs) is built from ``strain_fits`` (1 + 2N, M) (e.g. regressed over many drapes:
    ``draped.DrapedFits``) or else from the fits' own strain maps (:func:`strain_maps`);
    layout: optional render layout over the M vertices (UVs), material: optional look."""
    g, B = G.build_basis(fits, examples)
    inc = face_incidence(np.asarray(faces), fits.shape[1])
    gn, Bn = G.build_basis(np.stack([vertex_normals(f, faces, inc) for f in fits]), examples)
    gs = Bs = None
    if rest is not None:
        S = np.asarray(strain_fits if strain_fits is not None else strain_maps(rest, faces, fits), np.float64)
        gs, Bs = G.build_basis(S[:, :, None], examples)
        gs, Bs = gs[:, 0], Bs[:, :, 0]
    gw, Bw = (None, None) if start_fits is None else G.build_basis(np.asarray(start_fits, np.float64), examples)
    nb = model.n_body_vertices
    binding = G.bind_to_body(g, model.mean[:nb])
    skin_idx, skin_w = garment_skin_weights(model, g, faces, fits, B)
    meta = dict(meta or {})
    meta.update({"n_vertices": int(g.shape[0]), "n_faces": int(len(faces)), "n_components": int(examples.n),
                 "examples_c": examples.c, "skinning": SKINNING_VERSION})
    look: dict = {}
    if layout is not None:
        look = {"render_vertex": np.asarray(layout.vertex, np.int32), "render_uv": np.asarray(layout.uv, np.float32),
                "render_faces": np.asarray(layout.faces, np.int32)}
        if look["render_vertex"].min() < 0 or look["render_vertex"].max() >= g.shape[0]:
            raise ValueError("the render layout refers to a vertex out of range")
    basis = GarmentBasis(g=g, B=B, faces=np.asarray(faces, np.int32), binding=binding,
                         skin_idx=skin_idx, skin_w=skin_w,
                         gn=gn, Bn=Bn, meta=meta, rest=None if rest is None else np.asarray(rest, np.float32),
                         gs=gs, Bs=Bs, gw=gw, Bw=Bw)
    basis.render_vertex, basis.render_uv, basis.render_faces = (look.get(k) for k in ARRAYS[-3:])
    basis.material = material
    meta["etag"] = basis_digest(basis)
    return basis


def vertex_strain(vertices: np.ndarray, edges: np.ndarray, rest_len: np.ndarray) -> np.ndarray:
    """(M,) the strain map's per-vertex stretch: the mean over its edges (E, 2) of |edge| /
    rest - 1, at least 0 (a fold is not strain; the mean rather than the largest, so that one
    sliver edge at a seam does not colour its vertex)."""
    return np.maximum(vertex_mean_strain(vertices, edges, rest_len), 0.0)


def strain_maps(rest: np.ndarray, faces: np.ndarray, fits: np.ndarray) -> np.ndarray:
    """(K, M) float32: the strain map (``vertex_strain``) of each of ``fits`` (K, M, 3)
    against the rest shape (M, 3)."""
    e = mesh_edges(np.asarray(faces))
    r = np.asarray(rest, np.float64)
    rest_len = np.linalg.norm(r[e[:, 0]] - r[e[:, 1]], axis=1)
    return np.stack([vertex_strain(np.asarray(f, np.float64), e, rest_len) for f in fits]).astype(np.float32)


def strain_map(basis: GarmentBasis, weights: np.ndarray, vertices: np.ndarray, synthesised: bool = True) -> np.ndarray:
    """(M,) the strain map of the garment tried on as ``vertices`` (M, 3) by a customer of
    ``weights`` (N,): for a basis try-on (``synthesised``), the basis's strain channel gs + w Bs
    where it has one (fitted to the example drapes' own strain maps: the synthesised positions'
    millimetre errors along short edges would read as strain); else (the customer's own drape,
    or a basis without the channel) ``vertex_strain`` of the vertices against the rest shape
    (or the mean garment)."""
    if synthesised and basis.gs is not None and basis.Bs is not None:
        return np.maximum(G.synthesize(np.asarray(basis.gs)[:, None], np.asarray(basis.Bs)[:, :, None], weights)[:, 0],
                          0.0)
    return strain_maps(basis.rest if basis.rest is not None else basis.g, basis.faces, [vertices])[0]


def stride_bodies(model) -> list[np.ndarray]:
    """Body weights (K,) of the training population's people the leg weights are refined on beside
    the mean avatar (:func:`stride_cases`): those at ``STRIDE_PERCENTILES`` of the first component
    (the smallest and the largest bodies), and of each gender the one at ``STRIDE_BMI_PERCENTILE``
    of the body mass index (the heaviest for their height: thighs that squeeze the crotch)."""
    pop = np.asarray(model.population["weights"], np.float64)
    att = np.asarray(model.population["attributes"], np.float64)  # (N, 12) in ATTRIBUTES order
    gender, height, weight = (att[:, ATTRIBUTES.index(a)] for a in ("gender", "height_cm", "weight_kg"))
    order = np.argsort(pop[:, 0], kind="stable")
    out = [pop[order[int(round(q / 100 * (len(order) - 1)))]] for q in STRIDE_PERCENTILES]
    bmi = weight / (height / 100) ** 2
    for male in (False, True):
        ids = np.flatnonzero((gender >= 0.5) == male)
        if len(ids):
            ids = ids[np.argsort(bmi[ids], kind="stable")]
            out.append(pop[ids[int(round(STRIDE_BMI_PERCENTILE / 100 * (len(ids) - 1)))]])
    return out


def stride_cases(model, g: np.ndarray, B: np.ndarray | None) -> list[SW.StrideCase]:
    """The bodies and strides a garment's leg weights are refined in (``SW.refine_in_strides``):
    the mean avatar with the garment g (M, 3), and, with its basis B (N, M, 3), the people of
    :func:`stride_bodies` with the garment synthesised on them; each in ``poses.stride_poses`` at
    ``STRIDE_AMPLITUDES``."""
    nb = model.n_body_vertices
    bodies = [(np.asarray(model.mean, np.float64), np.asarray(g, np.float64))]
    if B is not None and len(B):
        for w in stride_bodies(model):
            bodies.append((np.asarray(model.vertices(w), np.float64),
                           G.synthesize(np.asarray(g, np.float32), np.asarray(B, np.float32), w).astype(np.float64)))
    cases = []
    for full, garment in bodies:
        posed = [model.forward(pose=p, vertices=full) for p in stride_poses(model, full, STRIDE_AMPLITUDES)]
        cases.append(SW.StrideCase(garment=garment, body=full[:nb], transforms=np.stack([p.transforms for p in posed]),
                                   posed=np.stack([p.vertices[:nb] for p in posed])))
    return cases


def garment_skin_weights(model, g: np.ndarray, faces: np.ndarray, fits: np.ndarray,
                         B: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Skin weights (M, 4) int + (M, 4) float of a garment g (M, 3) on the mean avatar
    (``skin_weights.transfer_skin_weights``), tested in the page's poses on the mean body
    with each edge at its shortest over the example fits (1 + 2N, M, 3) (a heavy body squeezes
    the armpit and crotch); the legs' weights then refined in strides (:func:`stride_cases`,
    on the population's extremes too where the basis B (N, M, 3) is given)."""
    switches = (SKINNING_VERSION, SKIN_STRIDES, SKIN_RELEASE_IN_POSES, SKIN_LEG_RAMP, SKIN_LIMB_SIDE, SKIN_SCREENING,
                STRIDE_AMPLITUDES, STRIDE_PERCENTILES, STRIDE_BMI_PERCENTILE, id(model))
    h = hashlib.sha256(repr((switches, sorted((k, v) for k, v in vars(SW).items() if k.isupper()))).encode())
    for a in (g, faces, fits, B):
        h.update(b"-" if a is None else np.ascontiguousarray(a, np.float64).tobytes())
    key = h.hexdigest()
    if key in _SKIN_MEMO:
        return tuple(a.copy() for a in _SKIN_MEMO[key])  # type: ignore[return-value]
    idx, w = _transferred_skin_weights(model, g, faces, fits)
    if SKIN_STRIDES:
        idx, w = SW.refine_in_strides(SW.dense_weights(idx, w, len(model.bone_parents)), faces, model.body_faces,
                                      stride_cases(model, g, B),
                                      np.array([BONES.index(b) for c in SW.LEG_BONES for b in c]))
    if len(_SKIN_MEMO) >= SKIN_MEMO_SIZE:
        _SKIN_MEMO.pop(next(iter(_SKIN_MEMO)))
    _SKIN_MEMO[key] = (idx.copy(), w.copy())
    return idx, w


# the weights of the last few garments, by their inputs: a process building the same garment again
# (the demo set, in every test app of a run) takes them from here (the refinement takes seconds)
SKIN_MEMO_SIZE = 16
_SKIN_MEMO: dict[str, tuple[np.ndarray, np.ndarray]] = {}


def _transferred_skin_weights(model, g: np.ndarray, faces: np.ndarray, fits: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    nb = model.n_body_vertices
    body0 = model.mean[:nb]
    e = mesh_edges(faces)
    shortest = np.linalg.norm(fits[:, e[:, 0]] - fits[:, e[:, 1]], axis=2).min(axis=0)
    return transfer_skin_weights(g, faces, body0, model.body_faces, model.lbs_indices[:nb],
                                 model.lbs_weights[:nb], len(model.bone_parents),
                                 test_transforms=preset_transforms(model, model.mean)
                                 if SKIN_RELEASE_IN_POSES else None,
                                 rest_lengths=shortest,
                                 legs=leg_frame(body0, model.joints(model.mean), list(BONES))
                                 if SKIN_LEG_RAMP else None,
                                 parents=model.bone_parents if SKIN_LIMB_SIDE else None,
                                 screening=SW.SCREENING if SKIN_SCREENING else 0.0)


def drape_start(basis: GarmentBasis, body: CustomerBody) -> np.ndarray:
    """(M, 3) float64: where a drape of the garment starts on ``body`` (its weights): for a basis
    built from drapes, the start channel gw + w Bw, where the build's population drapes started
    (``draped.draped_example_fits``: the warp fits' basis), so that the drape settles as the
    drapes the basis was fitted to did; else (or for a basis saved before the channel) the basis
    try-on."""
    if basis.gw is not None and basis.Bw is not None and body.weights is not None:
        return G.synthesize(np.asarray(basis.gw), np.asarray(basis.Bw), body.weights).astype(np.float64)
    return np.asarray(try_on(basis, body, layer=0)[0], np.float64)


def basis_digest(basis: GarmentBasis) -> str:
    """The content digest of a basis (its ETag): geometry, skinning, render layout, material."""
    h = hashlib.sha256()
    for a in (basis.g, basis.B, basis.faces, basis.skin_idx, basis.skin_w,
              *(x for x in (basis.render_vertex, basis.render_uv, basis.render_faces, basis.gs, basis.Bs)
                if x is not None)):
        h.update(np.ascontiguousarray(a).tobytes())
    h.update(material_digest(basis.material))
    return h.hexdigest()[:32]


def refresh_skinning(model, basis: GarmentBasis) -> GarmentBasis | None:
    """A basis whose skin weights an older ``SKINNING_VERSION`` made, with weights made by this
    one (and a new ETag); None when they are current. The example fits are the basis's own
    central differences undone: g +- c sigma_i B_i (exact for the mean, the shortest-edge test
    needs no more)."""
    if int(basis.meta.get("skinning", 1)) >= SKINNING_VERSION:
        return None
    g, B = np.asarray(basis.g, np.float64), np.asarray(basis.B, np.float64)
    step = (float(basis.meta.get("examples_c", EXAMPLES["c"])) * np.sqrt(model.variances[: len(B)]))[:, None, None]
    fits = np.concatenate([g[None], np.stack([g + step * B, g - step * B], 1).reshape(-1, *g.shape)])
    skin_idx, skin_w = garment_skin_weights(model, g, np.asarray(basis.faces), fits, B)
    meta = {**basis.meta, "skinning": SKINNING_VERSION}
    out = GarmentBasis(g=np.asarray(basis.g), B=np.asarray(basis.B), faces=np.asarray(basis.faces),
                       binding=np.asarray(basis.binding), skin_idx=skin_idx, skin_w=skin_w,
                       gn=np.asarray(basis.gn), Bn=np.asarray(basis.Bn), meta=meta,
                       rest=None if basis.rest is None else np.asarray(basis.rest),
                       gs=None if basis.gs is None else np.asarray(basis.gs),
                       Bs=None if basis.Bs is None else np.asarray(basis.Bs),
                       gw=None if basis.gw is None else np.asarray(basis.gw),
                       Bw=None if basis.Bw is None else np.asarray(basis.Bw))
    out.render_vertex, out.render_uv, out.render_faces = basis.render_vertex, basis.render_uv, basis.render_faces
    out.material = basis.material
    meta["etag"] = basis_digest(out)
    return out


@dataclass
class CustomerBody:
    """What a try-on needs of a customer's body, computed once per customer (and, lazily,
    once per garment: the exact nearest body vertex of each synthesized garment vertex)."""

    weights: np.ndarray | None  # (K,); None: a body for push-outs only (tryon.surface_body)
    vertices: np.ndarray  # (V, 3) float32
    normals: np.ndarray  # (n_body, 3) float32
    faces: np.ndarray | None = None  # (F, 3) the body's triangles; None: no crease anchors
    _tree: object = None
    _vert_faces: np.ndarray | None = None
    _face_bounds: tuple | None = None  # geometry.face_bounds of the body, once per customer
    _bindings: dict = field(default_factory=dict)
    _posed: dict = field(default_factory=dict)  # pose set digest -> posed bodies (application.scenes)
    _girths: object = None  # sizing.REGIONS girths and lengths (R,) cm, measured on first need

    def binding(self, basis: "GarmentBasis", garment: np.ndarray) -> np.ndarray:
        """(M, 1) nearest body vertex of each garment vertex on this body (cached per garment)."""
        return self.push_binding(basis, garment)[0]

    def push_binding(self, basis: "GarmentBasis", garment: np.ndarray) -> tuple[np.ndarray, tuple | None, tuple]:
        """The push-out's binding of a garment on this body, cached per garment: (M, 1) nearest
        body vertex of each garment vertex, the crease anchors (:func:`crease_anchors`; None
        without ``faces``) and the body vertices that poke through the garment between its
        vertices, or come within ``FACE_PUSH_TRIGGER_M`` of it (``correctives.skin_under_faces``:
        the push-out's face pass keeps them ``clearance`` under the cloth)."""
        key = basis.etag() or id(basis)
        hit = self._bindings.get(key)
        if hit is None:
            nn = self.nearest(garment, G.CREASE_K)
            nb = len(self.normals)
            under = skin_under_faces(garment, basis.faces, self.vertices[:nb], self.normals, FACE_PUSH_TRIGGER_M)
            if self.faces is None:
                hit = (nn[:, :1].astype(np.int32), None, under)
            else:
                hit = (nn[:, :1].astype(np.int32), self.crease_anchors(garment, nn), under)
            if len(self._bindings) >= MAX_BINDINGS_PER_BODY:
                self._bindings.pop(next(iter(self._bindings)))
            self._bindings[key] = hit
        return hit

    def face_pass(self, basis: "GarmentBasis", garment: np.ndarray, clearance: float) -> tuple:
        """The pairs of the push-out's face pass (``push_binding``'s third) that a try-on of this
        garment at this ``clearance`` lifts, cached: the synthesized garment is the same at every
        try-on of a basis on a body, so the pairs whose face stays more than
        ``FACE_PUSH_SLACK_M`` clear after the vertex push-out are dropped once (most of them: a
        try-on then costs the pairs it pushes only)."""
        key = (basis.etag() or id(basis), round(float(clearance), 6))
        hit = self._bindings.get(key)
        if hit is None:
            nearest, anchors, under = self.push_binding(basis, garment)
            faces = np.asarray(basis.faces)
            pushed, _ = G.push_out(garment, self.vertices, self.normals, nearest, basis.smoother(), clearance, anchors)
            keep = G.face_pass_depths(pushed, self.vertices, self.normals, under, faces, clearance) > -FACE_PUSH_SLACK_M
            # only cloth lying on the same skin: the face's vertices rest on skin facing the way
            # the body vertex does, and none is in a crease (skin facing skin: a face over the
            # crotch pushed along one thigh's normal goes into the other thigh)
            tri = faces[under[1]]
            keep &= np.einsum("rkc,rc->rk", self.normals[nearest[tri, 0]],
                              self.normals[under[0]]).min(axis=1) > FACE_PUSH_MIN_COS
            if anchors is not None and len(anchors[0]):
                in_crease = np.zeros(len(garment), bool)
                in_crease[anchors[0]] = True
                keep &= ~in_crease[tri].any(axis=1)
            hit = tuple(a[keep] for a in under)
            if len(self._bindings) >= MAX_BINDINGS_PER_BODY:
                self._bindings.pop(next(iter(self._bindings)))
            self._bindings[key] = hit
        return hit

    def nearest(self, points: np.ndarray, k: int) -> np.ndarray:
        """(P,) with k = 1, else (P, k): the nearest body vertices of points (P, 3), nearest
        first (the body's k-d tree made on first use and kept)."""
        return self._kdtree().query(points, k=k)[1]

    def _kdtree(self) -> cKDTree:
        if self._tree is None:  # unbalanced: ~2x faster to build, no slower to query here
            self._tree = cKDTree(self.vertices[: len(self.normals)], balanced_tree=False, compact_nodes=False)
        return self._tree

    def crease_anchors(self, garment: np.ndarray, nearest: np.ndarray) -> tuple[np.ndarray, ...]:
        """``garment.crease_anchors`` of garment (M, 3) on this body (needs ``faces``), nearest
        (M, k) body vertex ids of each garment vertex on it, nearest first; the k-d tree and the
        triangles' bounds are made on first need and kept."""
        nb = len(self.normals)
        idx = G.in_crease(nearest, self.normals)
        if len(idx):
            self._kdtree()
            if self._vert_faces is None:
                self._vert_faces = vertex_faces(self.faces, nb)
            if self._face_bounds is None:
                self._face_bounds = face_bounds(np.asarray(self.vertices[:nb], np.float64), self.faces)
        return G.crease_anchors(garment, idx, nearest, self.vertices[:nb], self.normals, self.faces, self._tree,
                                self._vert_faces, self._face_bounds)


MAX_BINDINGS_PER_BODY = 64  # push-out bindings and face-pass pairs (two per garment) kept per body
# body vertices nearer a garment's face than this (before its push-out) are kept outside it by the
# push-out's face pass: twice the try-on's clearance, the vertex push-out then moves the face
FACE_PUSH_TRIGGER_M = 2 * G.CLEARANCE
FACE_PUSH_SLACK_M = 0.001  # ... and of those, the pairs a try-on can lift (CustomerBody.face_pass) ...
FACE_PUSH_MIN_COS = 0.5  # ... under a face resting on skin facing within 60 degrees of the body vertex's


@functools.lru_cache(maxsize=4)
def _topology(model) -> tuple[np.ndarray, np.ndarray]:
    """The body model's triangles (F, 3) int64 and ``geometry.vertex_faces`` of them, once per
    model (every customer shares them)."""
    F = np.asarray(model.body_faces, np.int64)
    return F, vertex_faces(F, model.n_body_vertices)


def customer_body(model, weights: np.ndarray) -> CustomerBody:
    X = model.vertices(weights)
    nb = model.n_body_vertices
    n = vertex_normals(X[:nb], model.body_faces).astype(np.float32)
    return surface_body(model, X, n, np.asarray(weights, np.float64))


def surface_body(model, vertices: np.ndarray, normals: np.ndarray, weights: np.ndarray | None = None) -> CustomerBody:
    """A body of the model's topology for push-outs: vertices (V, 3), body normals (Vb, 3);
    ``weights`` (K,) when known (a try-on needs them, the look does not)."""
    F, vf = _topology(model)
    return CustomerBody(weights, vertices, normals, F, _vert_faces=vf)


def try_on(basis: GarmentBasis, body: CustomerBody, layer: int = 0) -> tuple[np.ndarray, int]:
    """The fitted garment (M, 3) float32 for a customer and how many vertices were pushed out.

    Synthesis g + w B (3MN multiply-adds), then push-out of the customer's body with a
    clearance growing with the layer (outer garments over inner ones). The first try-on of a
    garment on a body also finds each garment vertex's nearest body vertex (a k-d tree query,
    cached on the body)."""
    v = G.synthesize(np.asarray(basis.g), np.asarray(basis.B), body.weights)
    clearance = G.CLEARANCE + layer * G.LAYER_GAP
    nearest, anchors, _ = body.push_binding(basis, v)
    faces = np.asarray(basis.faces)
    under = body.face_pass(basis, v, clearance)
    return G.push_out(v, body.vertices, body.normals, nearest, basis.smoother(), clearance, anchors, under, faces)

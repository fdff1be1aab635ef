"""The upload gateway: every uploaded file (avatar meshes, scans, point clouds, garment meshes,
MakeHuman garments) is read here, with the one hardened reader (``service.model.formats.mesh_io``) and
the one unit/axis detector (``service.model.formats.frames``), and refused with :class:`Invalid`
(a 422 naming the field and why) before anything is stored or queued."""
from __future__ import annotations

import io
import json
import unicodedata
import warnings
from dataclasses import dataclass

import numpy as np
from PIL import Image, UnidentifiedImageError
from scipy.spatial import cKDTree

from service.model.formats import mesh_io
from service.model.formats.avatar_io import AvatarMeshError, Projection, project_mesh
from service.model.body.model import BodyModel
from service.model.formats.frames import UNITS, UnitError, detect_unit, rotation_to_y
from service.model.body.measurements import ATTRIBUTES
from service.model.formats.mesh_io import Scan, ScanError
from service.model.geometry.mesh import weld_seams
from service.model.formats import gltf_read
from service.model.garments.catalogue import Material, RenderLayout, Texture, render_layout
from service.model.formats.declared_sizes import DeclaredSizeError, check_gltf, check_text_lines
from service.model.formats.mhclo import Binding, MhcloError, parse_mhclo, parse_obj

from .errors import Invalid

SCAN_FORMATS = "OBJ, PLY, STL, GLB/glTF (embedded buffers only) or XYZ"
MAX_GARMENT_VERTICES = 100_000
MAX_GARMENT_FACES = 400_000
MIN_GARMENT_VERTICES = 3
MAX_MHCLO_LINES = MAX_GARMENT_VERTICES + 10_000  # one binding line per vertex plus headers
MAX_NAME_LENGTH = 200
# bidirectional overrides and isolates: they reorder how a name is shown (spoofing)
_BIDI_CONTROLS = {chr(c) for c in (*range(0x202A, 0x202F), *range(0x2066, 0x206A))}
TRUE_WORDS, FALSE_WORDS = ("true", "1", "yes", "on"), ("false", "0", "no", "off")


@dataclass
class TemplateAvatar:
    """An uploaded avatar mesh in the template topology, projected onto the shape space."""

    projection: Projection


BodyUpload = TemplateAvatar | Scan


# Bytes of arrays a reader holds per point and per face of a mesh file (float64 points, their
# normals and transformed copies, a k-d tree; int64 faces and their copies), and per byte of
# the file (the text or chunk it is parsed from): the memory estimate of an upload.
READ_BYTES_PER_POINT = 6 * 3 * 8
READ_BYTES_PER_FACE = 3 * 3 * 8
READ_BYTES_PER_FILE_BYTE = 2


def upload_memory(data: bytes, filename: str | None) -> int:
    """Estimated bytes needed to read one uploaded file, from its declared sizes (headers, line
    counts, glTF accessors), before it is parsed: what the process's memory budget reserves.
    A file whose sizes cannot be told costs its bytes times :data:`READ_BYTES_PER_FILE_BYTE`
    (its reader then refuses it quickly)."""
    base = READ_BYTES_PER_FILE_BYTE * len(data)
    try:
        kind = mesh_io.scan_type(data, filename)
    except ScanError:
        return base  # a texture or an unknown type
    if kind in ("glb", "gltf"):
        try:
            doc, blob = gltf_read._parse_glb(data) if kind == "glb" else (json.loads(data.decode("utf-8-sig")), None)
            return base + check_gltf(doc, None if blob is None else len(blob), len(data))
        except Exception:
            return base
    points, faces = mesh_io.declared_size(data, kind)
    return base + READ_BYTES_PER_POINT * points + READ_BYTES_PER_FACE * faces


def read_body_upload(model: BodyModel, data: bytes, filename: str | None, loc: tuple = ("body", "mesh")) -> BodyUpload:
    """An uploaded body: a :class:`TemplateAvatar` when the mesh has the template's body or
    full vertex count (``/v1/body-model/template.obj``), else the :class:`Scan` to fit (any
    topology, or a point cloud), checked to be person-sized in m, cm or mm, and simplified to
    ``mesh_io.KEPT_SCAN_POINTS`` when denser (``Scan.source_points``)."""
    counts = (model.n_body_vertices, int(model.mean.shape[0]))
    try:
        mesh = mesh_io.read_mesh_file(data, filename, keep_unused=True, min_points=MIN_GARMENT_VERTICES)
    except ScanError as exc:
        raise Invalid(loc, str(exc)) from exc
    if mesh.faces is not None and len(mesh.points) in counts:
        try:
            return TemplateAvatar(project_mesh(model, mesh.points))
        except AvatarMeshError as exc:
            raise Invalid(loc, str(exc)) from exc
    try:
        scan = mesh_io.compact(mesh)
        detect_unit(scan.points)  # a file that is no person in m, cm or mm would only become a failed job
    except (ScanError, UnitError) as exc:
        hint = (f" (an avatar in the template topology has {counts[0]} vertices: /v1/body-model/template.obj)"
                if mesh.faces is not None else "")
        raise Invalid(loc, f"{exc}{hint}") from exc
    try:
        return mesh_io.simplified(scan)  # a body scanner's dense mesh: KEPT_SCAN_POINTS of it
    except ScanError as exc:
        raise Invalid(loc, str(exc)) from exc


def read_garment_mesh(data: bytes, filename: str | None, loc: tuple, label: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (M, 3) float64 in the file's units and order, and faces (F, 3) int32, of one
    garment mesh (OBJ/PLY/GLB/glTF/STL), within the garment size limits."""
    try:
        mesh = mesh_io.read_mesh_file(data, filename, keep_unused=True, require_faces=True,
                                      min_points=MIN_GARMENT_VERTICES, max_points=MAX_GARMENT_VERTICES)
    except ScanError as exc:
        raise Invalid(loc, f"{label}: {exc}") from exc
    assert mesh.faces is not None
    if len(mesh.faces) > MAX_GARMENT_FACES:
        raise Invalid(loc, f"{label}: {len(mesh.faces)} faces; at most {MAX_GARMENT_FACES} per garment")
    return mesh.points, mesh.faces.astype(np.int32)


def one_cloth(vertices: np.ndarray, faces: np.ndarray,
              layout: RenderLayout | None) -> tuple[np.ndarray, np.ndarray, RenderLayout | None, np.ndarray]:
    """A draped garment's file as the one cloth the drape engine takes: joined at its seams
    (``geometry.mesh.weld_seams``: a GLB repeats every vertex on a UV seam, and split panels
    would part in the drape) and without vertices on no face. vertices (N, 3), faces (F, 3),
    its render layout (texture coordinates) or None -> the cloth's vertices (M, 3) and faces
    (F, 3) int32, the layout onto them (its texture seams kept, render vertices on no face
    dropped), and ``first`` (M,) int64: the file vertex each cloth vertex was taken from."""
    weld, welded = weld_seams(vertices, faces)
    used = np.unique(welded)  # welded vertices on a face, in file order
    cloth = np.full(int(weld.max()) + 1 if len(weld) else 0, -1, np.int64)
    cloth[used] = np.arange(len(used))
    first = np.unique(weld, return_index=True)[1][used]
    if layout is not None:
        kept = np.unique(layout.faces)
        render = np.full(len(layout.vertex), -1, np.int64)
        render[kept] = np.arange(len(kept))
        layout = RenderLayout(cloth[weld[layout.vertex[kept]]], layout.uv[kept], render[layout.faces])
    return np.asarray(vertices)[first], cloth[welded].astype(np.int32), layout, first


def _text(data: bytes, field: str) -> str:
    if not data:
        raise Invalid(("body", field), f"the {field} file is empty")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return data.decode("latin-1")


def read_mhclo(model: BodyModel, mhclo: bytes, obj: bytes) -> tuple[Binding, np.ndarray]:
    """A MakeHuman garment: its ``.mhclo`` binding to the hm08 base mesh and the faces (F, 3)
    of its ``.obj`` (same vertices), within the garment size limits."""
    binding, faces, _ = read_mhclo_layout(model, mhclo, obj)
    return binding, faces


def read_mhclo_layout(model: BodyModel, mhclo: bytes, obj: bytes) -> tuple[Binding, np.ndarray, RenderLayout | None]:
    """:func:`read_mhclo` plus the render layout of the OBJ's texture coordinates (``vt``;
    None when some face corner has none)."""
    try:  # line counts before the text is split into lines and numbers
        check_text_lines(mhclo, MAX_MHCLO_LINES, "mhclo")
    except DeclaredSizeError as exc:
        raise Invalid(("body", "mhclo"), f"mhclo: {exc}") from exc
    try:
        mesh_io.check_declared_size(obj, "obj", MAX_GARMENT_VERTICES)
    except ScanError as exc:
        raise Invalid(("body", "obj"), f"obj: {exc}") from exc
    try:
        binding = parse_mhclo(_text(mhclo, "mhclo"), model.mean.shape[0])
    except MhcloError as exc:
        raise Invalid(("body", "mhclo"), f"mhclo: {exc}") from exc
    try:
        mesh = parse_obj(_text(obj, "obj"))
    except MhcloError as exc:
        raise Invalid(("body", "obj"), f"obj: {exc}") from exc
    n_v, faces = mesh.n_vertices, mesh.faces
    n_b = len(binding.indices)
    if n_v != n_b:
        raise Invalid(("body", "obj"), f"the OBJ has {n_v} vertices but the mhclo binds {n_b}: they are not the "
                                       "same garment")
    if n_v > MAX_GARMENT_VERTICES:
        raise Invalid(("body", "obj"), f"{n_v} vertices; at most {MAX_GARMENT_VERTICES} per garment")
    if len(faces) > MAX_GARMENT_FACES:
        raise Invalid(("body", "obj"), f"{len(faces)} faces; at most {MAX_GARMENT_FACES} per garment")
    layout = None if mesh.face_uv is None else render_layout(faces, mesh.face_uv, mesh.uv)
    return binding, faces.astype(np.int32), layout


def _face_set(faces: np.ndarray) -> np.ndarray:
    f = np.sort(np.asarray(faces, np.int64), axis=1)
    return f[np.lexsort(f.T[::-1])]


def obj_layout(data: bytes, faces: np.ndarray) -> tuple[np.ndarray, RenderLayout] | None:
    """The faces (F, 3) int32 and render layout of an OBJ garment's ``vt`` texture coordinates,
    when every face corner has one and the OBJ's own triangulation is the same set of triangles
    as ``faces`` (as read by the mesh reader, which may order them differently); else None (the
    garment is kept untextured)."""
    try:
        mesh = parse_obj(data.decode("utf-8", errors="replace"))
    except MhcloError:
        return None
    if mesh.face_uv is None or mesh.faces.shape != np.shape(faces) \
            or not np.array_equal(_face_set(mesh.faces), _face_set(faces)):
        return None
    return mesh.faces.astype(np.int32), render_layout(mesh.faces, mesh.face_uv, mesh.uv)


def glb_look(data: bytes, faces: np.ndarray) -> tuple[RenderLayout, Texture | None] | None:
    """The texture coordinates and embedded base-colour texture of a GLB garment with one mesh
    primitive (its vertices are already split at the UV seams: the layout is the identity),
    when its indices are ``faces`` (as read by the mesh reader); else None. A broken embedded
    image is a 422 (field ``garment``)."""
    try:
        doc, blob = gltf_read._parse_glb(data)
        check_gltf(doc, len(blob), len(data))  # what read_glb decodes (meshopt views too) is bounded
        out = gltf_read.read_glb(data)
    except Exception:
        return None
    doc = out["json"]
    if len(out["meshes"]) != 1 or len(doc["meshes"][0].get("primitives", [])) != 1 or out["uv"] is None:
        return None
    if out["indices"].shape != np.shape(faces) or not np.array_equal(out["indices"], faces):
        return None
    uv = np.asarray(out["uv"], np.float32)
    if not np.all(np.isfinite(uv)):
        return None
    texture = None
    try:
        mat = doc["materials"][out["material"]] if out["material"] is not None else {}
        ti = mat.get("pbrMetallicRoughness", {}).get("baseColorTexture", {}).get("index")
        src = doc["textures"][ti]["source"] if ti is not None else None
        img = doc["images"][src] if src is not None else None
    except (KeyError, IndexError, TypeError):
        img = None
    if img is not None and "bufferView" in img:
        raw = gltf_read._view_bytes(doc, gltf_read._parse_glb(data)[1], img["bufferView"])
        texture = read_texture(raw, img.get("name") or "texture", field="garment")
    n = len(uv)
    return RenderLayout(np.arange(n, dtype=np.int64), uv, np.asarray(faces, np.int64)), texture


MAX_TEXTURE_BYTES = 8 * 1024 * 1024
MAX_TEXTURE_PX = 8192
MAX_TEXTURE_PIXELS = 4096 * 4096  # decoded: 64 MiB as RGBA
# Pillow's decompression-bomb limit from the texture limits: an image declaring more pixels is
# refused on its header (Pillow raises at twice this; read_texture refuses above it).
Image.MAX_IMAGE_PIXELS = MAX_TEXTURE_PIXELS
TEXTURE_FORMATS = {"PNG": "image/png", "JPEG": "image/jpeg"}
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
JPEG_MAGIC = b"\xff\xd8\xff"
JPEG_QUALITY = 90


def read_texture(data: bytes, filename: str | None, field: str = "texture") -> Texture:
    """An uploaded texture: a PNG or JPEG of at most :data:`MAX_TEXTURE_BYTES`,
    :data:`MAX_TEXTURE_PX` a side and :data:`MAX_TEXTURE_PIXELS`, decoded whole (Pillow) and
    re-encoded in its format (metadata dropped), so that only a real image of allowed size is
    stored and served; anything else is a 422 naming the field."""
    loc = ("body", field)
    if not data:
        raise Invalid(loc, f"the {field} file is empty")
    if len(data) > MAX_TEXTURE_BYTES:
        raise Invalid(loc, f"the {field} is {len(data)} bytes; at most {MAX_TEXTURE_BYTES} (downscale it, e.g. to "
                           "2048 px JPEG)")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", Image.DecompressionBombWarning)
            image = Image.open(io.BytesIO(data), formats=list(TEXTURE_FORMATS))
            fmt = image.format or ""
            w, h = image.size
            if max(w, h) > MAX_TEXTURE_PX or w * h > MAX_TEXTURE_PIXELS:
                raise Invalid(loc, f"the {field} is {w}x{h} px; at most {MAX_TEXTURE_PX} px a side and "
                                   f"{MAX_TEXTURE_PIXELS} pixels")
            image.load()
    except Invalid:
        raise
    except UnidentifiedImageError:
        kind = "PNG" if data.startswith(PNG_MAGIC) else "JPEG" if data.startswith(JPEG_MAGIC) else None
        raise Invalid(loc, f"the {field} is not a readable {kind} image" if kind
                      else f"the {field} must be a PNG or JPEG image") from None
    except (Image.DecompressionBombError, Image.DecompressionBombWarning):
        raise Invalid(loc, f"the {field} declares more than {MAX_TEXTURE_PIXELS} pixels") from None
    except (OSError, ValueError, SyntaxError, EOFError) as exc:  # truncated, corrupt, unsupported mode
        raise Invalid(loc, f"the {field} is not a readable {fmt or 'PNG or JPEG'} image "
                           f"({' '.join(str(exc).split())[:80]})") from None
    if min(w, h) < 1:
        raise Invalid(loc, f"the {field} is empty ({w}x{h} px)")
    keep = ("RGB", "L") if fmt == "JPEG" else ("RGB", "RGBA", "L", "LA")
    if image.mode not in keep:
        alpha = fmt == "PNG" and (image.mode in ("PA", "RGBa", "La") or "transparency" in image.info
                                  or image.mode.endswith("A"))
        image = image.convert("RGBA" if alpha else "RGB")
    out = io.BytesIO()
    if fmt == "JPEG":
        image.save(out, "JPEG", quality=JPEG_QUALITY)
    else:
        image.save(out, "PNG")
    image.close()
    name = (filename or field).rsplit("/", 1)[-1][:100]
    return Texture(name, TEXTURE_FORMATS[fmt], out.getvalue())


def parse_color(value: str | None, default: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    """'#rrggbb' (sRGB) -> linear RGBA; None -> ``default``."""
    if not value:
        return default
    h = value.lstrip("#")
    if len(h) != 6 or any(c not in "0123456789abcdefABCDEF" for c in h):
        raise Invalid(("body", "color"), "color must be #rrggbb")
    srgb = np.array([int(h[i:i + 2], 16) / 255.0 for i in (0, 2, 4)])
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    return (float(lin[0]), float(lin[1]), float(lin[2]), 1.0)


def clean_name(value: str, field: str = "name") -> str:
    """A garment's display name: Unicode NFC, surrounding whitespace stripped; refused (422)
    when empty or whitespace only, longer than :data:`MAX_NAME_LENGTH`, or with control
    characters (newlines, tabs, NUL, ...), bidirectional overrides, unassigned code points or
    lone surrogates."""
    name = unicodedata.normalize("NFC", str(value)).strip()
    if not name:
        raise Invalid(("body", field), f"{field} must not be empty or only whitespace")
    if len(name) > MAX_NAME_LENGTH:
        raise Invalid(("body", field), f"{field} is longer than {MAX_NAME_LENGTH} characters")
    for ch in name:
        if unicodedata.category(ch) in ("Cc", "Cs", "Cn", "Co", "Zl", "Zp") or ch in _BIDI_CONTROLS:
            raise Invalid(("body", field), f"{field} contains a control character (U+{ord(ch):04X}); "
                                           "use printable characters only")
    return name


def parse_bool(value: object, field: str, default: bool) -> bool:
    """A form field's boolean (true/false, 1/0, yes/no, on/off)."""
    if value is None:
        return default
    word = str(value).strip().lower()
    if word not in TRUE_WORDS + FALSE_WORDS:
        raise Invalid(("body", field), f"{field} must be true or false")
    return word in TRUE_WORDS


# a scan upload's optional measurements of the person: form fields named after the attributes
KNOWN_FIELDS = tuple(a for a in ATTRIBUTES if a != "gender")
KNOWN_FIELD_DOC = ("Scans, optional: the person's own {name}, measured (a tailor's tape, a scale): the "
                   "fitted body keeps it (within ~0.5 cm / 1 kg), also where the scan cannot tell (loose "
                   "clothes). Shown as `entered`")


def parse_known_measurements(model, form: dict[str, object]) -> dict[str, float]:
    """A scan upload's optional measurements of the person (form fields named after the body
    model's attributes but gender: cm, kg), checked as the measurements of a new customer are
    (``shape.validate_measurements``). Fields not given are left out."""
    from service.model.body.shape import MeasurementError, validate_measurements

    raw: dict[str, object] = {}
    units = {a.name: a.unit for a in model.attributes}
    for name in KNOWN_FIELDS:
        value = form.get(name)
        if value is None or str(value).strip() == "":
            continue
        try:
            raw[name] = float(str(value))
        except ValueError:
            raise Invalid(("body", name), f"{name} must be a number in {units.get(name, 'cm')}") from None
    try:
        return validate_measurements(model, raw)
    except MeasurementError as exc:
        raise Invalid(("body", str(exc.field)), exc.message) from exc


def parse_gender(value: object) -> str | None:
    if value is None:
        return None
    if value not in ("female", "male"):
        raise Invalid(("body", "gender"), "gender must be 'female' or 'male'")
    return str(value)


# -- a garment draped on one body --------------------------------------------------------------
DRAPED_NEAR_MEDIAN_M = 0.08  # median distance of a draped garment to the body it claims
DRAPED_FORMAT = 1


def _npz_bytes(arrays: dict[str, np.ndarray]) -> bytes:
    """A stored upload's arrays as compressed ``.npz`` bytes."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


# the up axes tried for a garment draped on an example avatar: as is (Y up), or Z up
GARMENT_UPS = {"+y": np.eye(3), "+z": rotation_to_y(np.array([0.0, 0.0, 1.0]))}


@dataclass
class DrapedGarment:
    """A garment draped on one body, checked, waiting for its build job.

    vertices (M, 3) float64 and faces (F, 3) int32: in our frame (metres, Y up) when ``on`` is
    an example avatar; in the ``avatar`` file's frame otherwise (the job's fit of the avatar
    maps both into ours). ``avatar``: the retailer's body (any topology), or None."""

    vertices: np.ndarray
    faces: np.ndarray
    on: str | None
    unit: str
    up: str | None
    avatar: Scan | None = None
    layout: RenderLayout | None = None  # the OBJ's texture coordinates, seams split
    texture: Texture | None = None  # the uploaded base-colour texture
    graded: np.ndarray | None = None  # (S, M, 3) every size's mesh in chart order (graded uploads), same frame

    def to_bytes(self) -> bytes:
        arrays: dict[str, np.ndarray] = {"format": np.array(DRAPED_FORMAT), "vertices": self.vertices,
                                         "faces": self.faces, "on": np.array(self.on or ""),
                                         "unit": np.array(self.unit), "up": np.array(self.up or "")}
        if self.avatar is not None:
            arrays["avatar"] = np.frombuffer(mesh_io.scan_to_npz_bytes(self.avatar), np.uint8)
        if self.layout is not None:
            arrays.update(layout_vertex=self.layout.vertex, layout_uv=self.layout.uv, layout_faces=self.layout.faces)
        if self.graded is not None:
            arrays["graded"] = np.asarray(self.graded, np.float64)
        if self.texture is not None:
            arrays.update(texture=np.frombuffer(self.texture.data, np.uint8), texture_mime=np.array(self.texture.mime),
                          texture_name=np.array(self.texture.name))
        return _npz_bytes(arrays)

    @classmethod
    def from_bytes(cls, data: bytes) -> "DrapedGarment":
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if int(z["format"]) != DRAPED_FORMAT:
                raise ValueError(f"unknown stored garment upload format {int(z['format'])}")
            avatar = mesh_io.scan_from_npz_bytes(z["avatar"].tobytes()) if "avatar" in z.files else None
            layout = texture = None
            if "layout_vertex" in z.files:
                layout = RenderLayout(np.asarray(z["layout_vertex"], np.int64), np.asarray(z["layout_uv"], np.float32),
                                      np.asarray(z["layout_faces"], np.int64))
            if "texture" in z.files:
                texture = Texture(str(z["texture_name"]), str(z["texture_mime"]), z["texture"].tobytes())
            return cls(vertices=np.asarray(z["vertices"], np.float64), faces=np.asarray(z["faces"], np.int32),
                       on=str(z["on"]) or None, unit=str(z["unit"]), up=str(z["up"]) or None, avatar=avatar,
                       layout=layout, texture=texture,
                       graded=np.asarray(z["graded"], np.float64) if "graded" in z.files else None)


def is_textured(material: Material | None, layout: RenderLayout | None) -> bool:
    """Whether a garment's look has a texture its render layout can show."""
    return bool(material is not None and layout is not None
                and (material.base_color_texture is not None or material.normal_texture is not None))


MHCLO_FORMAT = 1  # MhcloUpload.to_bytes


@dataclass
class MhcloUpload:
    """A MakeHuman garment's files (``.mhclo``, its ``.obj``, the optional texture and the
    ``color`` as sent), checked at the upload, waiting for its build job (with the drape on)."""

    mhclo: bytes
    obj: bytes
    texture: tuple[bytes, str | None] | None = None
    color: str | None = None

    def to_bytes(self) -> bytes:
        arrays: dict[str, np.ndarray] = {"mhclo_format": np.array(MHCLO_FORMAT),
                                         "mhclo": np.frombuffer(self.mhclo, np.uint8),
                                         "obj": np.frombuffer(self.obj, np.uint8), "color": np.array(self.color or "")}
        if self.texture is not None:
            arrays.update(texture=np.frombuffer(self.texture[0], np.uint8), texture_name=np.array(self.texture[1] or ""))
        return _npz_bytes(arrays)

    @classmethod
    def from_bytes(cls, data: bytes) -> "MhcloUpload":
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if "mhclo_format" not in z.files or int(z["mhclo_format"]) != MHCLO_FORMAT:
                raise ValueError("not a stored MakeHuman garment upload")
            texture = (z["texture"].tobytes(), str(z["texture_name"]) or None) if "texture" in z.files else None
            return cls(mhclo=z["mhclo"].tobytes(), obj=z["obj"].tobytes(), texture=texture,
                       color=str(z["color"]) or None)


def place_on_body(vertices: np.ndarray, body_tree: cKDTree, loc: tuple) -> tuple[np.ndarray, str, str]:
    """A garment exported on one of our avatars, in our frame: the unit (m, cm, mm) and up axis
    (Y, or Z as Blender's default) that put it closest to the body. Returns (vertices in metres,
    Y up, unit, up); :class:`Invalid` when it is not around the body (median distance > 8 cm)."""
    best = None
    for unit, scale in UNITS.items():
        for up, R in GARMENT_UPS.items():
            v = (vertices * scale) @ R.T
            med = float(np.median(body_tree.query(v)[0]))
            if best is None or med < best[0]:
                best = (med, v, unit, up)
    assert best is not None
    med, v, unit, up = best
    if med > DRAPED_NEAR_MEDIAN_M:
        raise Invalid(loc, f"the garment is not around the body it was draped on: its vertices are "
                           f"{100 * med:.1f} cm from the body surface (median; limit {100 * DRAPED_NEAR_MEDIAN_M:.0f} "
                           "cm). Export it on that avatar, in its frame (metres, Y up)")
    return v, unit, up


def read_draped_avatar(data: bytes, filename: str | None, garment: np.ndarray) -> tuple[Scan, str]:
    """The retailer's own body a garment was draped on (any topology, unit and up axis), and
    the garment checked to be around it (same file frame). Returns (the avatar as a scan, its
    unit)."""
    loc = ("body", "avatar")
    try:
        avatar = mesh_io.simplified(mesh_io.compact(mesh_io.read_mesh_file(data, filename, keep_unused=True)))
        unit, scale = detect_unit(avatar.points, what="the avatar")
    except (ScanError, UnitError) as exc:
        raise Invalid(loc, f"avatar: {exc}") from exc
    med = float(np.median(cKDTree(avatar.points * scale).query(garment * scale)[0]))
    if med > DRAPED_NEAR_MEDIAN_M:
        raise Invalid(("body", "garment"), f"the garment is not around the avatar it was draped on: its vertices are "
                                           f"{100 * med:.1f} cm from the avatar (median; limit "
                                           f"{100 * DRAPED_NEAR_MEDIAN_M:.0f} cm). Export both in the same frame")
    return avatar, unit

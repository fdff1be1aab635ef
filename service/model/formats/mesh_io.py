"""The one reader of uploaded meshes and point clouds (the upload gateway's parser): avatars in
the template topology, body scans, clothed avatars, point clouds and garments.

Reads OBJ, PLY (ascii/binary), STL (ascii/binary), GLB, glTF (embedded buffers only) and XYZ
text into a :class:`Scan` (:func:`read_mesh_file`; :func:`read_scan` for the body-fitting
job), with a :class:`ScanError` (shown to the uploader as a 422) for anything unusable. Plain functions over numpy arrays; OBJ is read by
:mod:`service.model.formats.obj_io` (in bounded memory), XYZ by numpy, and trimesh
parses the other formats (``process=False``, materials skipped, nothing outside the upload is
ever opened or fetched).

Shapes: points (P, 3) float64 in the file's units and axes; faces (F, 3) int64 or None (a point
cloud); normals (P, 3) float64 unit or None.
"""
from __future__ import annotations

import io
import json
import logging
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import trimesh
from trimesh.grouping import unique_rows

from service.model.geometry.mesh import estimate_normals, simplify, vertex_normals  # noqa: F401 (re-exported)
from service.model.formats.declared_sizes import DeclaredSizeError, check_gltf, check_ply, compressed_views
from service.model.formats.gltf_buffers import FLOAT
from service.model.formats.gltf_read import _parse_glb
from service.model.formats.obj_io import ObjError, read_obj

log = logging.getLogger("tryon.scan_io")

MAX_SCAN_POINTS = 2_000_000  # vertices/points accepted from a file
# ... and kept of a body scan (:func:`simplified`): a body scanner's raw mesh has 0.2-2 M
# vertices, the fit draws 100,000 of them (``FitParams.max_points``), and the mesh kept for
# editing costs ~1.5 kB of editor memory per vertex (930k vertices: 1.4 GB, an 11 s build)
KEPT_SCAN_POINTS = 250_000
MIN_SCAN_POINTS = 500
SCAN_TYPES = ("obj", "ply", "stl", "glb", "gltf", "xyz")
MAX_FACES_PER_POINT = 4  # a closed triangle mesh has ~2 faces per vertex; more is padding or an attack
FLAT_RATIO = 1e-3  # smallest / largest standard deviation of the points below which they are flat
MAX_GLTF_NODES = 10_000  # avatars have tens to hundreds; a huge scene graph is slow to build
STRAY_RATIO = 1e3  # full extent / extent of the central 98% (per axis) above which points are corrupt
NPZ_FORMAT = 1
# glTF extensions whose data trimesh cannot decode (it would read compressed bytes as floats)
_UNSUPPORTED_GLTF_EXTENSIONS = ("KHR_draco_mesh_compression", "EXT_meshopt_compression")


class ScanError(ValueError):
    """An unusable scan upload; the message is shown to the uploader as a 422."""


@dataclass
class Scan:
    """points (P, 3) float64 (file units and axes, finite); faces (F, 3) int64 or None for a
    point cloud; normals (P, 3) float64 unit or None (meshes: area-weighted vertex normals;
    point clouds: the file's, when it has usable ones); kind: one of :data:`SCAN_TYPES`."""

    points: np.ndarray
    faces: np.ndarray | None
    normals: np.ndarray | None
    kind: str
    source_points: int | None = None  # the file's point count, when :func:`simplified` kept fewer

    @property
    def is_point_cloud(self) -> bool:
        return self.faces is None


# -- file type ---------------------------------------------------------------------------------
def _is_binary_stl(data: bytes) -> bool:
    """80-byte header, uint32 triangle count, 50 bytes per triangle: the size must match."""
    return len(data) >= 84 and 84 + 50 * int.from_bytes(data[80:84], "little") == len(data)


def scan_type(data: bytes, filename: str | None) -> str:
    """One of :data:`SCAN_TYPES` from the magic bytes (``glTF`` -> glb, ``ply``, a binary STL's
    size or an ascii ``solid``, a JSON ``{`` -> gltf), else the filename's extension; else
    :class:`ScanError` listing the accepted types."""
    head = data[:256].lstrip(b"\xef\xbb\xbf \t\r\n")
    if data[:4] == b"glTF":
        return "glb"
    if data[:3].lower() == b"ply":
        return "ply"
    if _is_binary_stl(data) or head[:5].lower() == b"solid":
        return "stl"
    if head[:1] == b"{":
        return "gltf"
    name = (filename or "").replace("\\", "/").rsplit("/", 1)[-1]
    ext = name.rsplit(".", 1)[-1].lower() if "." in name else ""
    if ext in SCAN_TYPES:
        return ext
    raise ScanError(f"unknown scan file type{f' (.{ext})' if ext else ''}: send one of "
                    f"{', '.join('.' + t for t in SCAN_TYPES)}")


# -- cheap size checks (before any parse builds arrays) -----------------------------------------
def _ply_counts(data: bytes) -> tuple[int, int]:
    """(vertices, faces) declared by a PLY header (0 when not declared)."""
    end = data.find(b"end_header", 0, 65536)
    counts = {b"vertex": 0, b"face": 0}
    for line in data[:end if end >= 0 else 65536].splitlines():
        words = line.split()
        if len(words) == 3 and words[0] == b"element" and words[1] in counts and words[2].isdigit():
            counts[words[1]] = int(words[2])
    return counts[b"vertex"], counts[b"face"]


def declared_size(data: bytes, kind: str) -> tuple[int, int]:
    """(points, faces) of an upload, from its header or a byte count (no parse, no arrays):
    PLY's ``element`` lines, a binary STL's triangle count (3 corners each before merging),
    lines starting with ``v ``/``f `` in an OBJ, number lines in an XYZ. Approximate from above
    for text (a line indented before its ``v`` is missed; the parse checks exactly); (0, 0) when
    the format declares nothing (glTF is checked by :func:`_check_gltf`)."""
    if kind == "ply":
        return _ply_counts(data)
    if kind == "stl":
        n = int.from_bytes(data[80:84], "little") if _is_binary_stl(data) else data.count(b"endfacet")
        return 3 * n, n
    if kind == "obj":
        def lines(tag: bytes) -> int:
            return sum(data.count(b"\n" + tag + sep) + data.startswith(tag + sep) for sep in (b" ", b"\t"))
        return lines(b"v"), lines(b"f")
    if kind == "xyz":
        n = data.count(b"\n") + 1 - data.count(b"\n#") - data.count(b"\n\n") - data.count(b"\n\r\n")
        return max(n - data.endswith(b"\n"), 0), 0
    return 0, 0


def check_declared_size(data: bytes, kind: str, max_points: int) -> None:
    """Refuse (:class:`ScanError`) a file whose header or line counts show more points, or more
    faces, than :func:`_finish` would accept, before parsing it (a 45 MB file over the limit
    would otherwise be parsed whole, into hundreds of MB of arrays, only to be refused)."""
    points, faces = declared_size(data, kind)
    if kind == "stl":  # a triangle soup: corners are merged into vertices after reading
        if faces > MAX_FACES_PER_POINT * max_points:
            raise ScanError(f"the scan has {faces} triangles; at most {MAX_FACES_PER_POINT * max_points} are "
                            "accepted (decimate it)")
        return
    if points > max_points:
        raise ScanError(f"the scan has {points} points; at most {max_points} are accepted (decimate it)")
    if faces > MAX_FACES_PER_POINT * max(max_points, MIN_SCAN_POINTS):
        raise ScanError(f"the scan has {faces} faces; at most {MAX_FACES_PER_POINT * max_points} are accepted")
    if kind == "ply":  # every element's rows must fit in the data after the header
        try:
            check_ply(data)
        except DeclaredSizeError as exc:
            raise ScanError(f"the PLY file is malformed or too large: {exc}") from exc


# -- readers -----------------------------------------------------------------------------------
def _given_normals(normals: Any, n_points: int, *, unit_only: bool = False) -> np.ndarray | None:
    """A file's per-point normals (P, 3) made unit, or None when unusable (wrong shape, any
    non-finite or zero-length row; with ``unit_only`` also rows far from unit length: XYZ
    columns 4-6 may be colours)."""
    if normals is None:
        return None
    n = np.asarray(normals, np.float64)
    if n.shape != (n_points, 3) or not np.all(np.isfinite(n)):
        return None
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    if n_points == 0 or length.min() < 1e-6:
        return None
    if unit_only and np.abs(length - 1.0).max() > 0.1:
        return None
    return n / length[:, None]


def _read_xyz(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """``x y z`` or ``x y z nx ny nz`` rows (comma or whitespace separated, ``#`` comments)."""
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ScanError("cannot read the file as XYZ: it is not UTF-8 text") from exc
    try:
        with np.errstate(all="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "input contained no data"
            rows = np.loadtxt(io.StringIO(text.replace(",", " ")), dtype=np.float64, comments="#", ndmin=2)
    except Exception as exc:  # ragged rows, words, ...
        raise ScanError(f"cannot read the file as XYZ (rows of 'x y z' or 'x y z nx ny nz'): "
                        f"{_reason(exc)}") from exc
    if rows.size == 0:
        raise ScanError("no points found in the XYZ file")
    if rows.shape[1] < 3:
        raise ScanError(f"the XYZ rows have {rows.shape[1]} number(s); expected 'x y z' or 'x y z nx ny nz'")
    normals = _given_normals(rows[:, 3:6], len(rows), unit_only=True) if rows.shape[1] >= 6 else None
    return np.ascontiguousarray(rows[:, :3]), normals


def _read_obj(data: bytes) -> tuple[np.ndarray, np.ndarray | None]:
    """Vertices and faces (None when there are none: a point cloud) of an OBJ."""
    try:
        mesh = read_obj(data)
    except ObjError as exc:
        raise ScanError(f"cannot read the file as OBJ: {exc}") from exc
    return mesh.vertices, (mesh.faces if len(mesh.faces) else None)


class _NoResolver:
    """A trimesh resolver that refuses everything: nothing outside the upload is read."""

    def get(self, key: Any) -> bytes:
        raise ScanError("the file refers to other files; embed everything in one file")

    __getitem__ = get

    def keys(self) -> list[str]:
        return []

    def __contains__(self, key: Any) -> bool:
        return False

    def namespaced(self, namespace: str) -> "_NoResolver":
        return self

    def write(self, name: str, data: Any) -> None:
        raise ScanError("writing is not supported")


def _check_gltf(data: bytes, kind: str, max_points: int) -> None:
    """Before trimesh sees a glTF/GLB: refuse buffers that are not embedded (anything but the
    GLB chunk or a ``data:`` URI), mesh compression trimesh cannot decode, and node or instance
    counts far beyond the point limit."""
    try:
        if kind == "glb":
            doc, blob = _parse_glb(data)
        else:
            doc, blob = json.loads(data.decode("utf-8-sig")), None
    except Exception as exc:
        raise ScanError(f"cannot read the file as {kind.upper()}: {_reason(exc)}") from exc
    if not isinstance(doc, dict):
        raise ScanError(f"cannot read the file as {kind.upper()}: the JSON is not a glTF document")
    buffers = doc.get("buffers", [])
    if not isinstance(buffers, list) or not all(isinstance(b, dict) for b in buffers):
        raise ScanError(f"cannot read the file as {kind.upper()}: malformed 'buffers'")
    for b in buffers:
        uri = b.get("uri")
        if uri is None and kind == "glb":
            continue
        if not isinstance(uri, str) or not uri.strip().lower().startswith("data:"):
            raise ScanError(f"the {kind.upper()} file refers to a buffer outside it ({str(uri)[:80]!r}): "
                            "external buffer URIs are not accepted; embed the buffers (GLB or data: URIs)")
    used = [e for key in ("extensionsRequired", "extensionsUsed") if isinstance(doc.get(key), list)
            for e in doc[key] if isinstance(e, str)]
    bad = sorted(set(used) & set(_UNSUPPORTED_GLTF_EXTENSIONS))
    if bad:
        raise ScanError(f"the {kind.upper()} file uses mesh compression ({', '.join(bad)}), which is not "
                        "supported: export it without compression")
    try:  # every declared size, used or not, before trimesh allocates for any of them
        check_gltf(doc, None if blob is None else len(blob), len(data))
        compressed = compressed_views(doc)
    except DeclaredSizeError as exc:
        raise ScanError(f"the {kind.upper()} file is malformed or too large: {exc}") from exc
    if compressed:  # trimesh would read the views' uncompressed fallback, declared or not
        raise ScanError(f"the {kind.upper()} file has meshopt-compressed buffer views (EXT_meshopt_compression), "
                        "which are not supported: export it without compression")
    nodes = doc.get("nodes", [])
    if isinstance(nodes, list) and len(nodes) > MAX_GLTF_NODES:
        raise ScanError(f"the {kind.upper()} file has {len(nodes)} nodes; at most {MAX_GLTF_NODES} are accepted")
    instances = _gltf_instances(doc)
    try:
        instanced = sum(int(acc.get("count", 0)) for _, acc in instances)
    except Exception:
        instanced = 0
    if instanced > 2 * max_points:
        raise ScanError(f"the scan has more than {max_points} points; at most {max_points} are accepted")
    # quantized skinned positions are dequantized by the skin's bind matrices, which trimesh ignores
    if any("skin" in nd and acc.get("componentType", FLOAT) != FLOAT for nd, acc in instances
           if isinstance(acc, dict)):
        raise ScanError(f"the {kind.upper()} file has quantized skinned meshes (KHR_mesh_quantization), which "
                        "are not supported: export it without compression")


def _gltf_instances(doc: dict[str, Any]) -> list[tuple[dict[str, Any], dict[str, Any]]]:
    """(node, POSITION accessor) of every mesh primitive instance (nodes form a forest: one
    instance per node with a mesh); [] when the document is too malformed to tell (trimesh
    then decides)."""
    try:
        meshes, accessors = doc.get("meshes", []), doc.get("accessors", [])
        return [(nd, accessors[p["attributes"]["POSITION"]])
                for nd in doc.get("nodes", []) if isinstance(nd, dict) and "mesh" in nd
                for p in meshes[nd["mesh"]]["primitives"]]
    except Exception:
        return []


def _reason(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 200 else text[:197] + "..."


def _transformed(points: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    return points @ matrix[:3, :3].T + matrix[:3, 3]


def _trimesh_arrays(loaded: Any, max_points: int) -> tuple[np.ndarray, np.ndarray | None, Any]:
    """(points, faces or None, the point cloud's source geometry or None) of what trimesh
    loaded: a Trimesh, a PointCloud or a Scene (every geometry instance moved by its node
    transform; meshes concatenated; point clouds used only when there is no mesh)."""
    if isinstance(loaded, trimesh.Scene):
        instances = []
        for node in loaded.graph.nodes_geometry:
            matrix, name = loaded.graph[node]
            instances.append((np.asarray(matrix, np.float64), loaded.geometry[name]))
    else:
        instances = [(np.eye(4), loaded)]
    mesh_parts: list[tuple[np.ndarray, np.ndarray]] = []
    cloud_parts: list[np.ndarray] = []
    total = 0
    source = None
    for matrix, geom in instances:
        v = getattr(geom, "vertices", None)
        if v is None:  # paths, voxels, ...
            continue
        v = np.asarray(v, np.float64).reshape(-1, 3)
        total += len(v)
        if total > 2 * max_points:  # instancing or padding: refuse before building huge arrays
            raise ScanError(f"the scan has more than {max_points} points; at most {max_points} are accepted")
        f = np.asarray(getattr(geom, "faces", None) if isinstance(geom, trimesh.Trimesh) else [], np.int64)
        v = _transformed(v, matrix)
        if f.size:
            f = f.reshape(-1, 3)
            if np.linalg.det(matrix[:3, :3]) < 0:  # a mirroring node: keep the faces' outside
                f = f[:, ::-1]
            mesh_parts.append((v, f))
        else:
            cloud_parts.append(v)
            source = geom
    if mesh_parts:
        offsets = np.cumsum([0] + [len(v) for v, _ in mesh_parts])
        return (np.concatenate([v for v, _ in mesh_parts]),
                np.concatenate([f + o for (_, f), o in zip(mesh_parts, offsets)]), None)
    if cloud_parts:
        return np.concatenate(cloud_parts), None, (source if len(cloud_parts) == 1 else None)
    return np.zeros((0, 3)), None, None


def _ply_normals(geom: Any, n_points: int) -> np.ndarray | None:
    """``nx ny nz`` vertex properties of a PLY point cloud (trimesh keeps them raw)."""
    try:
        vertex = geom.metadata["_ply_raw"]["vertex"]["data"]
        return _given_normals(np.column_stack([np.asarray(vertex[c], np.float64).reshape(-1)
                                               for c in ("nx", "ny", "nz")]), n_points)
    except Exception:  # no such properties
        return None


def _read_with_trimesh(data: bytes, kind: str, max_points: int) -> tuple[np.ndarray, np.ndarray | None,
                                                                          np.ndarray | None]:
    if kind in ("glb", "gltf"):
        _check_gltf(data, kind, max_points)
        data = data[3:] if data[:3] == b"\xef\xbb\xbf" else data  # trimesh's JSON reader wants no BOM
    kwargs: dict[str, Any] = {"process": False, "skip_materials": True}
    try:
        loaded = trimesh.load(io.BytesIO(data), file_type=kind, resolver=_NoResolver(), **kwargs)
        points, faces, cloud = _trimesh_arrays(loaded, max_points)
    except ScanError:
        raise
    except Exception as exc:  # trimesh raises many kinds of errors on garbage
        raise ScanError(f"cannot read the file as {kind.upper()}: {_reason(exc)}") from exc
    normals = None
    if faces is None and cloud is not None and kind == "ply":
        normals = _ply_normals(cloud, len(points))
    if kind == "stl" and faces is not None and len(points):
        # STL is a triangle soup: merge the copies of each vertex so vertex normals make sense
        with np.errstate(all="ignore"):
            keep, inverse = unique_rows(points, keep_order=True)
        points, faces = points[keep], np.asarray(inverse, np.int64)[faces]
    return points, faces, normals


# -- checks ------------------------------------------------------------------------------------
def _check_extent(points: np.ndarray) -> None:
    """Refuse coincident, collinear or flat point sets (no 3D extent), and absurdly far stray
    points (corrupt coordinates, which would otherwise pass for a flat or linear scan)."""
    full = float(np.ptp(points, axis=0).max())
    if full == 0.0:
        raise ScanError("all the points coincide: the scan has no extent")
    lo, hi = np.percentile(points, [1.0, 99.0], axis=0)
    robust = float((hi - lo).max())
    if robust == 0.0:
        raise ScanError("almost all the points coincide: the scan has no extent")
    if full > STRAY_RATIO * robust:
        raise ScanError(f"the points span {full:.3g} units but almost all lie within {robust:.3g}: the file has "
                        "stray or corrupt points")
    X = points - points.mean(axis=0)
    X = X / np.abs(X).max()
    sd = np.sqrt(np.maximum(np.linalg.eigvalsh(X.T @ X / len(X)), 0.0))  # ascending
    if sd[0] < FLAT_RATIO * sd[2]:
        raise ScanError("the points are degenerate: they all lie on a line or in a plane (no 3D extent)")


def _mesh_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals (P, 3) float64 (computed centred and scaled: float32)."""
    X = points - points.mean(axis=0)
    X /= np.abs(X).max()
    n = vertex_normals(X, faces).astype(np.float64)
    return n / np.sqrt(np.einsum("ij,ij->i", n, n))[:, None]


def _finish(points: np.ndarray, faces: np.ndarray | None, normals: np.ndarray | None, kind: str,
            max_points: int, min_points: int = MIN_SCAN_POINTS, keep_unused: bool = False) -> Scan:
    points = np.asarray(points, np.float64).reshape(-1, 3)
    if len(points) == 0:
        raise ScanError(f"no points found in the {kind.upper()} file")
    if not np.all(np.isfinite(points)):
        raise ScanError("the scan has non-finite (NaN or infinite) coordinates")
    if faces is not None:
        faces = np.asarray(faces, np.int64).reshape(-1, 3)
        if len(faces) == 0:
            faces = None
    if faces is not None:
        lo, hi = int(faces.min()), int(faces.max())
        if lo < 0 or hi >= len(points):
            bad = lo if lo < 0 else hi
            raise ScanError(f"a face refers to vertex {bad}, but the file has {len(points)} vertices "
                            f"(0 to {len(points) - 1})")
        used = np.zeros(len(points), bool)
        used[faces.reshape(-1)] = True
        if not used.all() and not keep_unused:  # vertices on no face have no normal: drop them
            remap = np.cumsum(used) - 1
            points, faces = points[used], remap[faces]
            normals = None
    n = len(points)
    if n > max_points:
        raise ScanError(f"the scan has {n} points; at most {max_points} are accepted (decimate it)")
    if n < min_points:
        raise ScanError(f"the file has only {n} points; at least {min_points} are needed")
    if faces is not None and len(faces) > MAX_FACES_PER_POINT * max(n, MIN_SCAN_POINTS):
        raise ScanError(f"the scan has {len(faces)} faces for {n} vertices; at most "
                        f"{MAX_FACES_PER_POINT} per vertex are accepted")
    _check_extent(points)
    if faces is not None:
        normals = _mesh_normals(points, faces)
    else:
        normals = _given_normals(normals, n)
    return Scan(points=np.ascontiguousarray(points), faces=None if faces is None else np.ascontiguousarray(faces),
                normals=normals, kind=kind)


def compact(scan: Scan, min_points: int = MIN_SCAN_POINTS) -> Scan:
    """A mesh read with ``keep_unused`` as a scan: vertices on no face dropped (their normals
    are meaningless), at least ``min_points`` left. Raises :class:`ScanError`."""
    if scan.faces is None:
        out = scan
    else:
        used = np.zeros(len(scan.points), bool)
        used[scan.faces.reshape(-1)] = True
        out = scan
        if not used.all():
            remap = np.cumsum(used) - 1
            points, faces = scan.points[used], remap[scan.faces]
            out = Scan(points=np.ascontiguousarray(points), faces=np.ascontiguousarray(faces),
                       normals=_mesh_normals(points, faces), kind=scan.kind)
    if len(out.points) < min_points:
        raise ScanError(f"the file has only {len(out.points)} points; at least {min_points} are needed")
    return out


def simplified(scan: Scan, max_points: int = KEPT_SCAN_POINTS) -> Scan:
    """The scan with at most ``max_points`` points: a denser one by vertex clustering
    (``geometry.simplify``: each kept point is one of the scan's own, with its normal from
    the whole scan), ``source_points`` its count before; a smaller one as it is. Raises
    :class:`ScanError` when fewer than ``MIN_SCAN_POINTS`` are left."""
    if len(scan.points) <= max_points:
        return scan
    keep, faces = simplify(scan.points, scan.faces, max_points)
    if len(keep) < MIN_SCAN_POINTS:  # a mesh of slivers whose every triangle collapsed
        raise ScanError(f"the scan's {len(scan.points)} points make no surface: simplified, {len(keep)} are left")
    return Scan(points=np.ascontiguousarray(scan.points[keep]), faces=None if faces is None else np.ascontiguousarray(faces),
                normals=None if scan.normals is None else np.ascontiguousarray(scan.normals[keep]), kind=scan.kind,
                source_points=int(len(scan.points)))


def read_scan(data: bytes, filename: str | None = None, *, max_points: int = MAX_SCAN_POINTS) -> Scan:
    """Read an uploaded scan (any topology) into a :class:`Scan`; raises :class:`ScanError`
    with a reason for anything unusable (and only that, whatever the bytes)."""
    return read_mesh_file(data, filename, max_points=max_points)


def read_mesh_file(data: bytes, filename: str | None = None, *, max_points: int = MAX_SCAN_POINTS,
                   min_points: int = MIN_SCAN_POINTS, keep_unused: bool = False,
                   require_faces: bool = False) -> Scan:
    """Read any uploaded mesh or point cloud (see the module docstring). ``keep_unused``: keep
    vertices on no face (the file's vertex order is then exactly kept, for template-topology
    avatars and garment sets); ``require_faces``: refuse point clouds. Raises
    :class:`ScanError` with a reason for anything unusable (and only that, whatever the bytes)."""
    if not data:
        raise ScanError("the file is empty")
    kind = scan_type(data, filename)
    check_declared_size(data, kind, max_points)
    try:
        if kind == "xyz":
            points, normals = _read_xyz(data)
            faces = None
        elif kind == "obj":
            points, faces = _read_obj(data)
            normals = None
        else:
            points, faces, normals = _read_with_trimesh(data, kind, max_points)
        if require_faces and (faces is None or len(faces) == 0):
            raise ScanError(f"no triangle faces found in the {kind.upper()} file")
        with np.errstate(all="ignore"):
            return _finish(points, faces, normals, kind, max_points, min_points, keep_unused)
    except ScanError:
        raise
    except Exception as exc:  # a crafted file must not turn into a 500
        log.warning("unexpected error reading a %s scan", kind, exc_info=True)
        raise ScanError(f"cannot read the file as {kind.upper()}: {_reason(exc)}") from exc


# -- queue storage -----------------------------------------------------------------------------
def scan_to_npz_bytes(scan: Scan) -> bytes:
    """Compact storage of a scan (``np.savez_compressed``): points as float32 offsets from a
    float64 origin, faces exact (int32 when they fit), normals float32."""
    points = np.asarray(scan.points, np.float64)
    origin = points.mean(axis=0) if len(points) else np.zeros(3)
    arrays: dict[str, np.ndarray] = {
        "format": np.array(NPZ_FORMAT, np.int64), "kind": np.array(str(scan.kind)),
        "origin": origin, "points": (points - origin).astype(np.float32),
    }
    if scan.faces is not None:
        faces = np.asarray(scan.faces, np.int64)
        arrays["faces"] = faces.astype(np.int32) if faces.size == 0 or faces.max() < 2**31 - 1 else faces
    if scan.normals is not None:
        arrays["normals"] = np.asarray(scan.normals, np.float32)
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def scan_from_npz_bytes(data: bytes) -> Scan:
    """The :class:`Scan` stored by :func:`scan_to_npz_bytes` (points to float32 precision,
    faces exact, normals re-normalised). Raises ValueError on anything else."""
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            if int(z["format"]) != NPZ_FORMAT:
                raise ValueError(f"unknown stored scan format {int(z['format'])}")
            kind = str(z["kind"][()])
            points = np.asarray(z["origin"], np.float64).reshape(1, 3) + np.asarray(z["points"], np.float64)
            faces = np.asarray(z["faces"], np.int64) if "faces" in z.files else None
            normals = np.asarray(z["normals"], np.float64) if "normals" in z.files else None
    except Exception as exc:
        raise ValueError(f"not a stored scan: {_reason(exc)}") from exc
    if kind not in SCAN_TYPES or points.ndim != 2 or points.shape[1] != 3:
        raise ValueError("not a stored scan: bad kind or points")
    if faces is not None and (faces.ndim != 2 or faces.shape[1] != 3):
        raise ValueError("not a stored scan: bad faces")
    if normals is not None:
        if normals.shape != points.shape:
            raise ValueError("not a stored scan: bad normals")
        normals = normals / np.maximum(np.sqrt(np.einsum("ij,ij->i", normals, normals)), 1e-12)[:, None]
    return Scan(points=points, faces=faces, normals=normals, kind=kind)

"""Declared sizes of an upload checked before anything is allocated: every glTF accessor,
buffer view (compressed or not, whether or not the document declares the extension), buffer
and image, used by a node or not; every PLY element. The work of decoding a file is bounded by
the upload's real size: at most :func:`decode_budget` bytes of arrays may come out of it.

Plain functions over the parsed JSON document and byte counts (no arrays are built). A refusal
is a :class:`DeclaredSizeError` (the upload gateway answers 422).
"""
from __future__ import annotations

import re
from typing import Any

# The arrays decoded from an upload (float64 copies included) may be at most this many times
# its size, plus a floor for tiny files (a sparse morph target or a meshopt view legitimately
# decodes to more than it stores: meshopt compresses vertex data 2-8x).
DECODE_FACTOR = 32
DECODE_FLOOR_BYTES = 16 * 1024 * 1024
MAX_ACCESSOR_COUNT = 16_000_000  # elements of one accessor (a 2M-vertex scan's indices: 12M)
MAX_GLTF_ITEMS = 100_000  # accessors, buffer views, buffers, images, meshes or primitives
READ_BYTES_PER_COMPONENT = 8  # readers convert accessors to float64 / int64
MESHOPT_EXTENSIONS = ("EXT_meshopt_compression", "KHR_meshopt_compression")

_COMPONENT_BYTES = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
_TYPE_COMPONENTS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


class DeclaredSizeError(ValueError):
    """A declared size is impossible, or more than the upload can hold or the limits allow."""


def decode_budget(upload_bytes: int) -> int:
    """The most bytes of arrays that decoding an upload of ``upload_bytes`` may produce."""
    return DECODE_FACTOR * max(int(upload_bytes), 0) + DECODE_FLOOR_BYTES


def _int(value: Any, what: str, low: int = 0, high: int | None = None) -> int:
    """``value`` as a non-negative int within [low, high]; :class:`DeclaredSizeError` otherwise
    (bools, floats, strings and out-of-range numbers alike)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise DeclaredSizeError(f"{what} must be an integer, not {str(value)[:40]!r}")
    if value < low or (high is not None and value > high):
        raise DeclaredSizeError(f"{what} is {value}; it must be within {low}..{high if high is not None else 'inf'}")
    return value


def _items(doc: dict[str, Any], key: str) -> list[Any]:
    items = doc.get(key, [])
    if not isinstance(items, list) or not all(isinstance(i, dict) for i in items):
        raise DeclaredSizeError(f"malformed '{key}'")
    if len(items) > MAX_GLTF_ITEMS:
        raise DeclaredSizeError(f"{len(items)} {key}; at most {MAX_GLTF_ITEMS}")
    return items


_DATA_URI = re.compile(r"^\s*data:[^,]*?(;base64)?,", re.IGNORECASE)


def data_uri_length(uri: str) -> int | None:
    """Decoded bytes of a ``data:`` URI (counted, not decoded), or None for any other URI."""
    m = _DATA_URI.match(uri)
    if m is None:
        return None
    payload = uri[m.end():]
    if not m.group(1):
        return len(payload)
    n = len(payload.rstrip().rstrip("="))
    return n * 3 // 4


def buffer_lengths(doc: dict[str, Any], glb_bin_bytes: int | None) -> list[int]:
    """The real bytes behind each buffer: the GLB binary chunk for a GLB's buffer 0 without a
    URI, a ``data:`` URI's payload, 0 for anything else (an external URI, a meshopt fallback
    buffer: nothing to read)."""
    out = []
    for i, b in enumerate(_items(doc, "buffers")):
        uri = b.get("uri")
        if uri is None:
            out.append(glb_bin_bytes if (i == 0 and glb_bin_bytes is not None) else 0)
        elif isinstance(uri, str):
            out.append(data_uri_length(uri) or 0)
        else:
            raise DeclaredSizeError(f"buffer {i} has a malformed uri")
    return out


def _meshopt(view: dict[str, Any]) -> dict[str, Any] | None:
    ext = view.get("extensions")
    if ext is None:
        return None
    if not isinstance(ext, dict):
        raise DeclaredSizeError("malformed bufferView extensions")
    for name in MESHOPT_EXTENSIONS:
        if name in ext:
            if not isinstance(ext[name], dict):
                raise DeclaredSizeError(f"malformed {name}")
            return ext[name]
    return None


def compressed_views(doc: dict[str, Any]) -> list[int]:
    """Indices of the buffer views stored meshopt-compressed (declared in ``extensionsUsed``
    or not)."""
    return [i for i, v in enumerate(_items(doc, "bufferViews")) if _meshopt(v) is not None]


def check_gltf(doc: dict[str, Any], glb_bin_bytes: int | None, upload_bytes: int) -> int:
    """Check every declared size of a glTF document against the bytes really there and the
    decode budget of an upload of ``upload_bytes``; returns the bytes its arrays decode to
    (float64/int64 copies of every accessor, meshopt views decoded). ``glb_bin_bytes``: the
    GLB's binary chunk length (None for a .gltf). :class:`DeclaredSizeError` when a view or
    accessor reaches past its data, a count is impossible, or the decoded size is over budget."""
    real = buffer_lengths(doc, glb_bin_bytes)
    for i, b in enumerate(_items(doc, "buffers")):
        _int(b.get("byteLength"), f"buffer {i} byteLength")
    views = _items(doc, "bufferViews")
    decoded = 0
    view_len: list[int] = []
    for i, v in enumerate(views):
        buf = _int(v.get("buffer"), f"bufferView {i} buffer", 0, len(real) - 1) if real else None
        if buf is None:
            raise DeclaredSizeError(f"bufferView {i} refers to a buffer but there is none")
        length = _int(v.get("byteLength"), f"bufferView {i} byteLength", 1)
        offset = _int(v.get("byteOffset", 0), f"bufferView {i} byteOffset")
        if "byteStride" in v:
            _int(v["byteStride"], f"bufferView {i} byteStride", 4, 252)
        mo = _meshopt(v)
        if mo is not None:  # the view's own buffer is a fallback; the data is in the extension's
            src = _int(mo.get("buffer"), f"bufferView {i} meshopt buffer", 0, len(real) - 1)
            m_len = _int(mo.get("byteLength"), f"bufferView {i} meshopt byteLength", 1)
            m_off = _int(mo.get("byteOffset", 0), f"bufferView {i} meshopt byteOffset")
            if m_off + m_len > real[src]:
                raise DeclaredSizeError(f"bufferView {i}'s compressed data ({m_off}+{m_len} bytes) reaches past "
                                        f"its buffer ({real[src]} bytes)")
            count = _int(mo.get("count"), f"bufferView {i} meshopt count", 1, MAX_ACCESSOR_COUNT)
            stride = _int(mo.get("byteStride"), f"bufferView {i} meshopt byteStride", 1, 256)
            if count * stride > length:
                raise DeclaredSizeError(f"bufferView {i} decompresses to {count * stride} bytes; it declares "
                                        f"{length}")
            decoded += count * stride
        elif offset + length > real[buf]:
            raise DeclaredSizeError(f"bufferView {i} ({offset}+{length} bytes) reaches past its buffer "
                                    f"({real[buf]} bytes)")
        view_len.append(length)

    def within(view: Any, offset: Any, count: int, elem: int, what: str) -> None:
        vi = _int(view, f"{what} bufferView", 0, len(views) - 1) if views else None
        if vi is None:
            raise DeclaredSizeError(f"{what} refers to a bufferView but there is none")
        start = _int(offset if offset is not None else 0, f"{what} byteOffset")
        stride = views[vi].get("byteStride", elem)
        if stride < elem and "byteStride" in views[vi]:
            raise DeclaredSizeError(f"{what}: byteStride {stride} is less than its element ({elem} bytes)")
        need = start + (count - 1) * max(stride, elem) + elem if count else start
        if need > view_len[vi]:
            raise DeclaredSizeError(f"{what} needs {need} bytes; its bufferView {vi} has {view_len[vi]}")

    for i, a in enumerate(_items(doc, "accessors")):
        what = f"accessor {i}"
        ctype, atype = a.get("componentType"), a.get("type")
        if ctype not in _COMPONENT_BYTES or atype not in _TYPE_COMPONENTS:
            raise DeclaredSizeError(f"{what} has an unknown componentType or type")
        count = _int(a.get("count"), f"{what} count", 0, MAX_ACCESSOR_COUNT)
        ncomp = _TYPE_COMPONENTS[atype]
        elem = _COMPONENT_BYTES[ctype] * ncomp
        if "bufferView" in a:
            within(a["bufferView"], a.get("byteOffset"), count, elem, what)
        decoded += count * ncomp * READ_BYTES_PER_COMPONENT
        sparse = a.get("sparse")
        if sparse is not None:
            if not isinstance(sparse, dict) or not isinstance(sparse.get("indices"), dict) \
                    or not isinstance(sparse.get("values"), dict):
                raise DeclaredSizeError(f"{what} has a malformed sparse")
            k = _int(sparse.get("count"), f"{what} sparse count", 1, count)
            ind, val = sparse["indices"], sparse["values"]
            if ind.get("componentType") not in (5121, 5123, 5125):
                raise DeclaredSizeError(f"{what} sparse indices have an unknown componentType")
            within(ind.get("bufferView"), ind.get("byteOffset"), k, _COMPONENT_BYTES[ind["componentType"]],
                   f"{what} sparse indices")
            within(val.get("bufferView"), val.get("byteOffset"), k, elem, f"{what} sparse values")
            decoded += k * (ncomp + 1) * READ_BYTES_PER_COMPONENT
    for i, im in enumerate(_items(doc, "images")):
        if "bufferView" in im:
            _int(im["bufferView"], f"image {i} bufferView", 0, max(len(views) - 1, 0))
            if not views:
                raise DeclaredSizeError(f"image {i} refers to a bufferView but there is none")
        elif isinstance(im.get("uri"), str) and data_uri_length(im["uri"]) is None:
            raise DeclaredSizeError(f"image {i} refers to a file outside the upload; embed it")
    for i, m in enumerate(_items(doc, "meshes")):
        prims = m.get("primitives", [])
        if not isinstance(prims, list) or len(prims) > MAX_GLTF_ITEMS:
            raise DeclaredSizeError(f"mesh {i} has malformed primitives")
        for p in prims:
            if isinstance(p, dict) and isinstance(p.get("extensions"), dict) \
                    and "KHR_draco_mesh_compression" in p["extensions"]:
                raise DeclaredSizeError("Draco-compressed primitives (KHR_draco_mesh_compression) are not "
                                        "supported: export without compression")
    budget = decode_budget(upload_bytes)
    if decoded > budget:
        raise DeclaredSizeError(f"the file declares {decoded // 2**20} MiB of data, more than a "
                                f"{upload_bytes}-byte upload can hold (at most {budget // 2**20} MiB)")
    return decoded


# -- PLY -----------------------------------------------------------------------------------------
_PLY_SIZES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
              "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}
PLY_HEADER_MAX_BYTES = 65536


def check_ply(data: bytes) -> None:
    """Every element a PLY header declares must fit in the data after the header: rows of at
    least their fixed properties' bytes (binary; a list counts its length field) or one line
    each (ascii). Checked on the header alone, before trimesh allocates rows for the counts."""
    end = data.find(b"end_header", 0, PLY_HEADER_MAX_BYTES)
    if end < 0:
        raise DeclaredSizeError("no PLY end_header in the first 64 KiB")
    body = data.find(b"\n", end)
    body_bytes = len(data) - (body + 1 if body >= 0 else len(data))
    ascii_ = False
    elements: list[list[int]] = []  # [count, min row bytes]
    for raw in data[:end].splitlines():
        words = raw.decode("latin-1").split()
        if not words:
            continue
        if words[0] == "format" and len(words) > 1:
            ascii_ = words[1] == "ascii"
        elif words[0] == "element" and len(words) == 3:
            if not words[2].isdigit():
                raise DeclaredSizeError(f"PLY element {words[1][:40]!r} has a malformed count")
            elements.append([int(words[2]), 0])
        elif words[0] == "property" and elements and len(words) >= 3:
            if words[1] == "list" and len(words) >= 5:
                elements[-1][1] += _PLY_SIZES.get(words[2], 1)
            else:
                elements[-1][1] += _PLY_SIZES.get(words[1], 1)
    if ascii_:
        lines = data.count(b"\n", body + 1 if body >= 0 else len(data)) + 1
        rows = sum(c for c, _ in elements)
        if rows > lines:
            raise DeclaredSizeError(f"the PLY header declares {rows} rows; the file has {lines} lines after it")
        return
    need = sum(c * max(size, 1) for c, size in elements)
    if need > body_bytes:
        raise DeclaredSizeError(f"the PLY header declares at least {need} bytes of data; the file has {body_bytes}")


def check_text_lines(data: bytes, max_lines: int, what: str) -> None:
    """A text format read line by line (``.mhclo``): at most ``max_lines`` lines, counted before
    the text is split."""
    lines = data.count(b"\n") + 1
    if lines > max_lines:
        raise DeclaredSizeError(f"the {what} file has {lines} lines; at most {max_lines}")


__all__ = ["DECODE_FACTOR", "DECODE_FLOOR_BYTES", "DeclaredSizeError", "buffer_lengths", "check_gltf",
           "check_ply", "check_text_lines", "compressed_views", "data_uri_length", "decode_budget"]

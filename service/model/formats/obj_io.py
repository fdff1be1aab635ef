"""The project's one Wavefront OBJ reader: vertices, faces fanned from each polygon's first
corner, and optionally the faces' texture coordinates, read in bounded memory.

A 45 MB scan (500,000 vertices, 1 M faces) is read in ~1 MB slices of whole lines, each turned
into numbers by numpy in C, so the transient memory is a few MB above the result's arrays
(trimesh's OBJ loader, used before, held about 280 MB more than the file for that scan).

Plain functions over bytes and numpy arrays. Shapes: vertices (V, 3) float64 in the file's
units and order; faces (F, 3) int64 (0-based); face_uv (F, 3) int64 into uv (T, 2) float64
(OBJ convention: origin bottom-left).

Supported: ``v x y z [w | r g b]``, ``vt u v [w]``, ``f`` with ``i``, ``i/t``, ``i//n`` or
``i/t/n`` corners, negative (relative) indices, polygons of any size (fanned), comments and
every other statement ignored (``vn``, ``o``, ``g``, ``s``, ``usemtl``, ``mtllib``, ``l``, ...).
A face with fewer than 3 corners is skipped.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

SLICE_BYTES = 1 << 20  # bytes of whole lines turned into numbers at a time
# the rest of each statement's line, by keyword (leading blanks allowed)
_STATEMENT = {word: re.compile(rb"^[ \t]*" + word + rb"[ \t]+([^\r\n]*)", re.MULTILINE) for word in (b"v", b"vt", b"f")}
_SLASH_TAIL = re.compile(rb"/\S*")  # the "/t/n" of a face corner
_TEXTURE = re.compile(rb"(?<!\S)[^\s/]+/([^\s/]*)")  # the t of a face corner "i/t" or "i/t/n"


class ObjError(ValueError):
    """An OBJ that cannot be read; the message says which statement and why."""


@dataclass
class ObjArrays:
    """vertices (V, 3) float64; faces (F, 3) int64; face_uv (F, 3) int64 and uv (T, 2)
    float64 when asked for and every face corner names a texture vertex, else None."""

    vertices: np.ndarray
    faces: np.ndarray
    face_uv: np.ndarray | None = None
    uv: np.ndarray | None = None


def _slices(data: bytes, size: int):
    """Pieces of ``data`` of ~``size`` bytes, each ending at a line end."""
    start, n = 0, len(data)
    while start < n:
        end = data.find(b"\n", min(start + size, n))
        end = n if end < 0 else end + 1
        yield data[start:end]
        start = end


def _words_per_row(text: bytes, n: int) -> np.ndarray:
    """(n,) int64: the number of blank-separated words on each of the n rows of ``text``
    (rows joined by newlines)."""
    b = np.frombuffer(text, np.uint8)
    blank = (b == 32) | ((b >= 9) & (b <= 13))
    first = ~blank
    first[1:] &= blank[:-1]
    return np.bincount(np.cumsum(b == 10)[first], minlength=n)


def _quote(word: bytes, row: bytes) -> str:
    return repr((word + b" " + row[:80]).decode(errors="replace"))


def _numbers(rows: list[bytes], word: bytes, columns: int) -> np.ndarray:
    """The first ``columns`` numbers of each row (a statement's line after its keyword),
    (len(rows), columns) float64. Fast path (numpy's C parser): every row has the same number
    of words; else row by row, which also names a bad row."""
    n = len(rows)
    text = b"\n".join(rows)
    counts = _words_per_row(text, n)
    k = int(counts[0])
    if k >= columns and np.all(counts == k):
        try:
            values = np.fromstring(text, dtype=np.float64, sep=" ")
            if len(values) == n * k:
                return np.ascontiguousarray(values.reshape(n, k)[:, :columns])
        except ValueError:  # a word that is not a number: found below
            pass
    out = np.empty((n, columns))
    for i, row in enumerate(rows):
        words = row.split()
        if len(words) < columns:
            raise ObjError(f"a '{word.decode()}' statement needs {columns} numbers: {_quote(word, row)}")
        try:
            out[i] = [float(w) for w in words[:columns]]
        except ValueError:
            raise ObjError(f"a '{word.decode()}' statement has a word that is not a number: "
                           f"{_quote(word, row)}") from None
    return out


def _indices(text: bytes, rows: list[bytes], count: int, what: str) -> np.ndarray:
    """``count`` whole numbers from the blank-separated ``text`` (made from ``rows``), (count,)
    int64; :class:`ObjError` naming the first row with a word that is not one."""
    try:
        values = np.fromstring(text, dtype=np.int64, sep=" ")
        if len(values) == count:
            return values
    except ValueError:
        pass
    for row in rows:
        for w in row.split():
            try:
                int(w.split(b"/")[0] if what == "vertex" else w.split(b"/")[1])
            except (ValueError, IndexError):
                raise ObjError(f"a face's {what} index is not a whole number: {_quote(b'f', row)}") from None
    raise ObjError(f"the faces' {what} indices cannot be read")


def _fan(corners: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Triangles (sum(max(sizes - 2, 0)), 3) of polygons of ``sizes`` corners stored one after
    the other in ``corners`` (C,), each fanned from its first corner: (c0, ck, ck+1); polygons
    of fewer than 3 corners give none."""
    if np.all(sizes == 3):
        return corners.reshape(-1, 3)
    first = np.cumsum(sizes) - sizes
    n_tri = np.maximum(sizes - 2, 0)
    poly = np.repeat(np.arange(len(sizes)), n_tri)
    k = np.arange(len(poly)) - np.repeat(np.cumsum(n_tri) - n_tri, n_tri) + 1
    start = first[poly]
    return np.stack([corners[start], corners[start + k], corners[start + k + 1]], axis=1)


def _relative(idx: np.ndarray, piece: bytes, word: bytes, sizes: np.ndarray, before: int) -> np.ndarray:
    """0-based indices from OBJ's 1-based ones, negative ones counted back from the ``word``
    statements before each face's line (``before`` of them precede ``piece``)."""
    if (idx > 0).all():
        return idx - 1
    if not idx.all():
        raise ObjError("a face refers to index 0 (OBJ counts from 1)")
    defined = np.array([m.start() for m in _STATEMENT[word].finditer(piece)], np.int64)
    at = np.array([m.start() for m in _STATEMENT[b"f"].finditer(piece)], np.int64)
    count = before + np.searchsorted(defined, at)  # statements defined before each face line
    return np.where(idx > 0, idx - 1, idx + np.repeat(count, sizes))


def read_obj(data: bytes, *, uv: bool = False, slice_bytes: int = SLICE_BYTES) -> ObjArrays:
    """Read an OBJ file's bytes (see the module docstring). ``uv``: also read the faces'
    texture coordinates. Raises :class:`ObjError` on a malformed statement or an index out of
    range. Faces may be empty (a point cloud)."""
    vertices: list[np.ndarray] = []
    texcoords: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    face_uv: list[np.ndarray] = []
    n_v = n_t = 0
    all_uv = uv
    for piece in _slices(data, slice_bytes):
        rows = _STATEMENT[b"v"].findall(piece)
        if rows:
            vertices.append(_numbers(rows, b"v", 3))
        trows = _STATEMENT[b"vt"].findall(piece) if uv else []
        if trows:
            texcoords.append(_numbers(trows, b"vt", 2))
        frows = _STATEMENT[b"f"].findall(piece)
        if frows:
            text = b"\n".join(frows)
            corners = _SLASH_TAIL.sub(b"", text) if b"/" in text else text
            sizes = _words_per_row(corners, len(frows))
            idx = _indices(corners, frows, int(sizes.sum()), "vertex")
            faces.append(_fan(_relative(idx, piece, b"v", sizes, n_v), sizes))
            if all_uv:
                tex = _TEXTURE.findall(text)  # the t of each corner that has one
                t = _indices(b" ".join(tex), frows, len(idx), "texture") if len(tex) == len(idx) and all(tex) else None
                if t is not None and t.all():
                    face_uv.append(_fan(_relative(t, piece, b"vt", sizes, n_t), sizes))
                else:  # some corner has no texture vertex ("i", "i//n", "i/0"): no texture layout
                    all_uv = False
        n_v += len(rows)
        n_t += len(trows)
    V = np.concatenate(vertices) if vertices else np.zeros((0, 3))
    F = np.concatenate(faces) if faces else np.zeros((0, 3), np.int64)
    if len(F) and (F.min() < 0 or F.max() >= len(V)):
        bad = int(F.min()) if F.min() < 0 else int(F.max())
        raise ObjError(f"a face refers to vertex {bad + 1 if bad >= 0 else bad - len(V)}, but the file has "
                       f"{len(V)} vertices")
    if all_uv and len(F) and texcoords:
        FT, UV = np.concatenate(face_uv), np.concatenate(texcoords)
        if FT.min() < 0 or FT.max() >= len(UV):
            bad = int(FT.min()) if FT.min() < 0 else int(FT.max())
            raise ObjError(f"a face refers to texture vertex {bad + 1 if bad >= 0 else bad - len(UV)}, but the "
                           f"file has {len(UV)}")
        return ObjArrays(V, F, FT, UV)
    return ObjArrays(V, F)

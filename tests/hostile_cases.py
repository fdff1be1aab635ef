"""Hostile uploads, built in memory: declared-size bombs in every input format (glTF/GLB
accessors, buffer views compressed or not, images; PLY, STL, OBJ, XYZ counts; .mhclo lines),
fake and decompression-bomb images, deep and huge JSON. Each is at most ~1 MB and is refused
by the service (or, for the PNG bomb behind a small header, decoded to its small size). Shared
by tests/test_hostile.py and ``tryon bench hostile``."""
from __future__ import annotations

import base64
import functools
import json
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tests.harness import RETAILERS

KEY = {"X-API-Key": RETAILERS["acme"]}
TRIANGLE = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)


def glb(doc: dict[str, Any], blob: bytes) -> bytes:
    """A GLB of ``doc`` and its binary chunk (both padded to 4 bytes)."""
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    blob += b"\0" * (-len(blob) % 4)
    total = 12 + 8 + len(js) + 8 + len(blob)
    return (struct.pack("<III", 0x46546C67, 2, total) + struct.pack("<II", len(js), 0x4E4F534A) + js
            + struct.pack("<II", len(blob), 0x004E4942) + blob)


def triangle_doc(extra_accessors: list[dict[str, Any]] = (), extra_views: list[dict[str, Any]] = (),
                 blob_extra: int = 0, **top: Any) -> tuple[dict[str, Any], bytes]:
    """A valid one-triangle glTF document (positions + indices in buffer 0) with more
    accessors and views appended (used by no node) and ``blob_extra`` zero bytes after the data."""
    pos = TRIANGLE.tobytes()
    idx = np.array([0, 1, 2, 0], np.uint16).tobytes()
    blob = pos + idx + b"\0" * blob_extra
    views = [{"buffer": 0, "byteOffset": 0, "byteLength": len(pos)},
             {"buffer": 0, "byteOffset": len(pos), "byteLength": 6}, *extra_views]
    accessors = [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                  "min": [0, 0, 0], "max": [1, 1, 0]},
                 {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}, *extra_accessors]
    doc = {"asset": {"version": "2.0"}, "buffers": [{"byteLength": len(blob)}], "bufferViews": views,
           "accessors": accessors, "meshes": [{"primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
           "nodes": [{"mesh": 0}], "scenes": [{"nodes": [0]}], "scene": 0, **top}
    return doc, blob


def glb_unused_accessor() -> bytes:
    """~10 KB: an accessor no node uses declares 200 million VEC4 floats on a small view."""
    doc, blob = triangle_doc([{"bufferView": 2, "componentType": 5126, "count": 200_000_000, "type": "VEC4"}],
                             [{"buffer": 0, "byteOffset": 0, "byteLength": 36}], blob_extra=10_000)
    return glb(doc, blob)


def glb_viewless_accessor() -> bytes:
    """An accessor with no buffer view (zeros by the spec) of 15 million MAT4s."""
    doc, blob = triangle_doc([{"componentType": 5126, "count": 15_000_000, "type": "MAT4"}])
    return glb(doc, blob)


def glb_sparse_bomb() -> bytes:
    """A sparse accessor: one substituted value over 12 million zero VEC3s."""
    doc, blob = triangle_doc(
        [{"componentType": 5126, "count": 12_000_000, "type": "VEC3",
          "sparse": {"count": 1, "indices": {"bufferView": 2, "componentType": 5125},
                     "values": {"bufferView": 3}}}],
        [{"buffer": 0, "byteOffset": 0, "byteLength": 4}, {"buffer": 0, "byteOffset": 0, "byteLength": 12}])
    return glb(doc, blob)


def glb_meshopt_undeclared() -> bytes:
    """A meshopt-compressed view (not named in extensionsUsed) that decompresses to 3 GB."""
    doc, blob = triangle_doc(
        [{"bufferView": 2, "componentType": 5126, "count": 3, "type": "VEC3"}],
        [{"buffer": 0, "byteOffset": 0, "byteLength": 3_000_000_000,
          "extensions": {"EXT_meshopt_compression": {"buffer": 0, "byteOffset": 0, "byteLength": 36,
                                                     "byteStride": 250, "count": 12_000_000,
                                                     "mode": "ATTRIBUTES"}}}], blob_extra=100_000)
    return glb(doc, blob)


def glb_view_past_buffer() -> bytes:
    """Buffer 0 declares 2 GB; a view reaches past the 48 bytes really there."""
    doc, blob = triangle_doc([{"bufferView": 2, "componentType": 5126, "count": 100_000_000, "type": "VEC4"}],
                             [{"buffer": 0, "byteOffset": 0, "byteLength": 1_600_000_000}])
    doc["buffers"][0]["byteLength"] = 2_000_000_000
    return glb(doc, blob)


def glb_image_view_bomb() -> bytes:
    """An image on a view that reaches far past the binary chunk."""
    doc, blob = triangle_doc([], [{"buffer": 0, "byteOffset": 0, "byteLength": 900_000_000}],
                             images=[{"bufferView": 2, "mimeType": "image/png"}])
    return glb(doc, blob)


def gltf_data_uri_bomb() -> bytes:
    """A .gltf (JSON, data: URI buffer of 48 bytes) whose accessor declares 100 million VEC3s."""
    doc, blob = triangle_doc([{"bufferView": 0, "componentType": 5126, "count": 100_000_000, "type": "VEC3"}])
    doc["buffers"] = [{"byteLength": len(blob),
                       "uri": "data:application/octet-stream;base64," + base64.b64encode(blob).decode()}]
    return json.dumps(doc).encode()


def ply_element_bomb() -> bytes:
    """A binary PLY: 3 vertices, then an element of 4 billion rows and no data for it."""
    head = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
            b"property float z\nelement junk 4000000000\nproperty double a\nproperty double b\nend_header\n")
    return head + TRIANGLE.tobytes()


def ply_ascii_rows() -> bytes:
    """An ascii PLY declaring 1.9 million vertices with 3 lines of data."""
    return (b"ply\nformat ascii 1.0\nelement vertex 1900000\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")


def stl_lying_count() -> bytes:
    """A binary STL header declaring 40 million triangles, with 1 KB behind it."""
    return b"\0" * 80 + struct.pack("<I", 40_000_000) + b"\0" * 1000


def obj_points_1mb() -> bytes:
    """1 MB of OBJ vertices, all on one line through the origin."""
    return b"".join(b"v %d 0 0\n" % (i % 7) for i in range(110_000))


def xyz_1mb() -> bytes:
    return b"0 0 0\n" * 170_000


def mhclo_lines() -> bytes:
    """1 MB of one-number binding lines (each would become a 9-number row)."""
    return b"name x\nx_scale 1 2 1\ny_scale 1 2 1\nz_scale 1 2 1\nverts 0\n" + b"1\n" * 500_000


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def png(width: int, height: int, raw: bytes, color_type: int = 2) -> bytes:
    """A PNG of 8-bit samples whose IDAT inflates to ``raw``."""
    ihdr = struct.pack(">IIBBBBB", width, height, 8, color_type, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(raw, 9))
            + png_chunk(b"IEND", b""))


def png_script() -> bytes:
    """A PNG signature followed by script text."""
    return b"\x89PNG\r\n\x1a\n<script>alert(document.cookie)</script>" + b" " * 200


@functools.lru_cache(maxsize=1)
def png_inflate_bomb() -> bytes:
    """A 16x16 RGB PNG whose image data inflates to ~400 MB (zeros): one 16 MiB block
    compressed after a full flush (which resets the compressor) is the same bytes every time,
    so it is compressed once and repeated 24 times (the stream's checksum is the first block's,
    as an attacker's would be wrong)."""
    block = b"\0" * (16 * 1024 * 1024)
    comp = zlib.compressobj(9)
    first = comp.compress(block) + comp.flush(zlib.Z_FULL_FLUSH)
    again = comp.compress(block) + comp.flush(zlib.Z_FULL_FLUSH)
    data = first + again * 23 + comp.flush()
    ihdr = struct.pack(">IIBBBBB", 16, 16, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", data) + png_chunk(b"IEND", b""))


def png_dimension_bomb() -> bytes:
    """A PNG header declaring 30000 x 30000 pixels (3.6 GB as RGBA), 1 KB of data."""
    ihdr = struct.pack(">IIBBBBB", 30_000, 30_000, 8, 6, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IDAT", zlib.compress(b"\0" * 1000))
            + png_chunk(b"IEND", b""))


SMALL_OBJ = b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"


@dataclass
class Case:
    """One hostile request: ``send(client)`` -> response; ``expect``: the statuses that count as
    handled; ``seconds``, ``mib``: its budgets of answer time and server memory growth."""

    name: str
    send: Callable[[Any], Any]
    expect: tuple[int, ...] = (422,)
    seconds: float = 5.0
    mib: float = 100.0
    notes: dict[str, Any] = field(default_factory=dict)


def _scan(data: bytes, name: str) -> Callable[[Any], Any]:
    return lambda c: c.post("/v1/customers", files={"mesh": (name, data)})


def _garment(data: bytes, name: str, texture: tuple[str, bytes] | None = None) -> Callable[[Any], Any]:
    def send(c: Any) -> Any:
        files: dict[str, Any] = {"garment": (name, data)}
        if texture is not None:
            files["texture"] = texture
        return c.post("/v1/garments", data={"name": "hostile"}, files=files, headers=KEY)
    return send


def upload_cases() -> list[Case]:
    """Every hostile upload of at most ~1 MB, each refused with a 4xx within its budgets."""
    deep = b"[" * 400_000 + b"]" * 400_000
    big_key = json.dumps({"measurements": {"k" * 900_000: 1}}).encode()
    return [
        Case("glb: unused accessor, 200M VEC4", _scan(glb_unused_accessor(), "a.glb")),
        Case("glb: accessor without a view, 15M MAT4", _scan(glb_viewless_accessor(), "a.glb")),
        Case("glb: sparse accessor over 12M zeros", _scan(glb_sparse_bomb(), "a.glb")),
        Case("glb: view past its buffer (2 GB declared)", _scan(glb_view_past_buffer(), "a.glb")),
        Case("glb garment: meshopt view, undeclared, 3 GB", _garment(glb_meshopt_undeclared(), "g.glb")),
        Case("glb garment: image view past the chunk", _garment(glb_image_view_bomb(), "g.glb")),
        Case("gltf: data: URI, 100M VEC3 accessor", _scan(gltf_data_uri_bomb(), "a.gltf")),
        Case("ply: element of 4G rows, no data", _scan(ply_element_bomb(), "a.ply")),
        Case("ply ascii: 1.9M rows declared, 3 given", _scan(ply_ascii_rows(), "a.ply")),
        Case("stl: 40M triangles declared", _scan(stl_lying_count(), "a.stl")),
        Case("obj: 1 MB of collinear vertices", _scan(obj_points_1mb(), "a.obj")),
        Case("xyz: 1 MB of one point", _scan(xyz_1mb(), "a.xyz")),
        Case("mhclo: 500k one-number lines", lambda c: c.post(
            "/v1/garments", data={"name": "hostile"}, headers=KEY,
            files={"mhclo": ("g.mhclo", mhclo_lines()), "obj": ("g.obj", SMALL_OBJ)})),
        Case("texture: PNG signature + script", _garment(SMALL_OBJ, "g.obj", ("t.png", png_script()))),
        Case("texture: 16x16 PNG inflating to 400 MB", _garment(SMALL_OBJ, "g.obj", ("t.png", png_inflate_bomb()))),
        Case("texture: PNG header 30000x30000", _garment(SMALL_OBJ, "g.obj", ("t.png", png_dimension_bomb()))),
        Case("json: nested 400k deep", lambda c: c.post("/v1/avatars", content=deep,
                                                         headers={"Content-Type": "application/json"})),
        Case("json: 900 KB measurement name", lambda c: c.post("/v1/customers", content=big_key,
                                                                headers={"Content-Type": "application/json"})),
    ]

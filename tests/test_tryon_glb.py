"""The try-on GLB's fast path: each garment basis' static arrays (faces, UVs, skinning) come as
a mesh template built once per basis; the GLB bytes equal the reference path's (plain mesh
dicts, everything redone per request) in every compression mode, and the validator is clean."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from service.application import scenes
from service.model.garments import demo_garments as D
from service.model.garments import tryon as T
from service.model.body.model import BONES
from service.model.garments.catalogue import load_catalogue
from service.model.formats.gltf_read import read_glb
from service.records import Garment
from tests.conftest import format_issues

COMPRESSIONS = [None, "quantize", "meshopt"]


@pytest.fixture(scope="module")
def garments(model, tmp_path_factory) -> list[tuple[Garment, T.GarmentBasis]]:
    """A normal-mapped catalogue garment (render layout + material; saved and memory-mapped
    back, as the service serves it) and an untextured demo garment (no layout)."""
    ex = T.example_set(model, n=3)
    EX = T.example_vertices(model, ex)
    item = load_catalogue().items["cropped-tee"]  # base colour + normal textures
    tee = T.build_garment_basis(model, np.stack([item.fit_to(E) for E in EX]), item.faces, ex,
                                layout=item.render_layout(), material=item.material)
    where = tmp_path_factory.mktemp("bases") / "tee"
    tee.save(where)
    tee = T.GarmentBasis.load(where)
    skirt = D.make_demo_garments(model)["skirt"]
    plain = T.build_garment_basis(model, np.stack([skirt.fit(model, E) for E in EX]), skirt.faces, ex)

    def rec(name: str, layer: int) -> Garment:
        return Garment(id=name, body_model=model.version, owner="test", name=name, source="demo",
                       color=[0.4, 0.5, 0.6, 1.0], layer=layer)

    return [(rec("skirt", 0), plain), (rec("tee", 1), tee)]


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_templated_tryon_glb_equals_the_reference(model, garments, compression: str | None,
                                                  validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    bodies = [T.customer_body(model, model.population["weights"][i]) for i in (3, 17)]
    for body in bodies:
        for g in garments:  # one garment (the try-on route)
            fast = scenes.outfit_glb(model, body, [g], compression, with_avatar=False)
            assert fast == scenes.outfit_glb(model, body, [g], compression, with_avatar=False, template=False)
        # an outfit with the avatar, layered (the skirt under the tee)
        fast = scenes.outfit_glb(model, body, garments, compression)
        assert fast == scenes.outfit_glb(model, body, garments, compression, template=False)
    report = validate_glb(fast)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, format_issues(report)
    out = read_glb(fast)
    tee = out["meshes"][-1]
    assert tee["tangents"] is not None and tee["uv"] is not None and len(out["images"]) == 2
    assert [m["name"] for m in out["json"]["meshes"]] == ["avatar", "skirt", "tee"]


def test_template_is_built_once_per_basis(garments) -> None:
    _, basis = garments[1]
    t = basis.mesh_template(len(BONES))
    assert basis.mesh_template(len(BONES)) is t and t.n == len(basis.render_vertex) and t.uv is not None
    assert t.views("meshopt") is t.views("meshopt")


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_templated_avatar_glb_equals_the_reference(model, garments, compression: str | None,
                                                   validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    """The avatar's body and its look's items (eyes, eyebrows, hair, underwear) with templates:
    the same bytes as without, bare and under a look; and an outfit under a look (the underwear
    layered under the garments)."""
    from service.application import look as looks

    body = T.customer_body(model, model.population["weights"][8])
    for lk in (None, looks.resolve("female"), looks.resolve("male", "none", False)):
        fast = scenes.avatar_glb(model, body.vertices, compression, normals=body.normals, look=lk)
        assert fast == scenes.avatar_glb(model, body.vertices, compression, normals=body.normals, look=lk,
                                         template=False)
    if compression == "quantize":  # layering under a look is slow (~0.5 s): one mode
        lk = looks.resolve("female")
        fast = scenes.outfit_glb(model, body, garments, compression, look=lk)
        assert fast == scenes.outfit_glb(model, body, garments, compression, look=lk, template=False)
    report = validate_glb(scenes.avatar_glb(model, body.vertices, compression, normals=body.normals,
                                            look=looks.resolve("female")))
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, format_issues(report)


def test_unskinned_avatar_mesh_without_template(model) -> None:
    """``pose=scan`` avatars drop the skin arrays: the reference mesh (no template) still writes."""
    mesh = scenes.avatar_mesh(model, model.mean, template=False)
    mesh = {k: v for k, v in mesh.items() if k not in ("vertex_joints", "vertex_weights")}
    assert "skins" not in read_glb(scenes.gltf.scene_to_glb([mesh]))["json"]
    with pytest.raises(ValueError, match="joints"):  # a skinned template needs the skin
        scenes.gltf.scene_to_glb([{**mesh, "template": scenes.avatar_mesh(model, model.mean)["template"]}])


def test_layered_outfit_is_cached_with_the_same_bytes(model, garments, monkeypatch: pytest.MonkeyPatch) -> None:
    """The layering of an outfit under a look is kept per process (``scenes.layered_outfit``):
    asked again, the same customer and outfit get the same bytes without layering again; another
    customer is layered."""
    from service.application import look as looks

    calls = []
    layer = scenes.layer_outfit
    monkeypatch.setattr(scenes, "layer_outfit", lambda *a, **k: calls.append(1) or layer(*a, **k))
    lk = looks.resolve("female")
    body = T.customer_body(model, model.population["weights"][5])
    ref = scenes.outfit_glb(model, body, garments, None, look=lk, cache=False)
    assert scenes.outfit_glb(model, body, garments, None, look=lk) == ref
    n = len(calls)
    assert scenes.outfit_glb(model, body, garments, None, look=lk) == ref  # a hit: read-only arrays, same bytes
    assert scenes.outfit_glb(model, body, garments, "meshopt", look=lk) is not None
    assert len(calls) == n
    other = T.customer_body(model, model.population["weights"][6])
    scenes.outfit_glb(model, other, garments, None, look=lk)
    assert len(calls) == n + 1

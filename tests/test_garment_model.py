"""Clothing bases, synthesis, push-out, MakeHuman bindings, demo garments, avatar projection."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.model import avatar_io, demo_garments as D, garment as G, mhclo, lbs, tryon as T

from service.model.geometry import vertex_normals

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"




def test_basis_is_exact_for_garments_linear_in_the_weights(model):
    ex = T.example_set(model, n=6, c=1.5)
    EX = T.example_vertices(model, ex)
    rng = np.random.default_rng(0)
    ids = rng.choice(model.n_body_vertices, 500, replace=False)
    fits = EX[:, ids] * 1.02 + 0.01  # an affine function of the avatar: linear in w
    g, B = G.build_basis(fits, ex)
    w = np.zeros(model.n_components)
    w[:6] = rng.normal(size=6) * np.sqrt(model.variances[:6])
    expect = model.vertices(w)[ids] * 1.02 + 0.01
    np.testing.assert_allclose(G.synthesize(g, B, w), expect, atol=2e-5)


def test_synthesis_matches_slow_loop():
    rng = np.random.default_rng(1)
    g = rng.normal(size=(7, 3)).astype(np.float32)
    B = rng.normal(size=(4, 7, 3)).astype(np.float32)
    w = rng.normal(size=9)
    slow = g.astype(np.float64).copy()
    for i in range(4):
        for v in range(7):
            slow[v] += w[i] * B[i, v]
    np.testing.assert_allclose(G.synthesize(g, B, w), slow, atol=1e-5)


def test_push_out_leaves_no_vertex_inside(model):
    from scipy.spatial import cKDTree

    from tests.bench.tryon import penetration_depths
    from service.model.geometry import vertex_faces
    from service.model.body import BONES

    body = T.customer_body(model, np.zeros(model.n_components))
    nb = model.n_body_vertices
    dom = model.lbs_indices[:nb][np.arange(nb), np.argmax(model.lbs_weights[:nb], axis=1)]
    torso = np.flatnonzero(np.isin(dom, [BONES.index("spine"), BONES.index("chest")]))
    rng = np.random.default_rng(2)
    n = min(800, len(torso))
    ids = rng.choice(torso, n, replace=False)
    # a "garment" hugging the skin, half of it sunk 5 mm into the body
    depth = np.where(rng.random(n) < 0.5, -0.005, 0.004)
    garment = body.vertices[ids] + depth[:, None] * body.normals[ids]
    X = body.vertices[:nb].astype(np.float64)
    args = (X, model.body_faces, cKDTree(X), vertex_faces(model.body_faces, nb))
    assert penetration_depths(garment.astype(np.float64), *args).max() > 0.004
    binding = G.bind_to_body(garment, model.mean[:nb])
    out, moved = G.push_out(garment, body.vertices[:nb], body.normals, binding)
    assert moved >= 0.4 * n
    assert penetration_depths(out.astype(np.float64), *args).max() < 0  # all of it outside now


def test_try_on_pushes_outer_layers_further(model):
    ex = T.example_set(model, n=4)
    EX = T.example_vertices(model, ex)
    shirt = D.make_demo_garments(model)["tshirt"]
    basis = T.build_garment_basis(model, np.stack([shirt.fit(model, E) for E in EX]), shirt.faces, ex)
    body = T.customer_body(model, model.population["weights"][5])
    v0, _ = T.try_on(basis, body, layer=0)
    v2, _ = T.try_on(basis, body, layer=2)
    d0 = np.einsum("ij,ij->i", v0 - body.vertices[basis.binding[:, 0]], body.normals[basis.binding[:, 0]])
    d2 = np.einsum("ij,ij->i", v2 - body.vertices[basis.binding[:, 0]], body.normals[basis.binding[:, 0]])
    assert np.median(d2 - d0) >= 0
    assert basis.etag() and len(basis.etag()) == 32


def test_garment_basis_save_load_round_trip(model, tmp_path):
    ex = T.example_set(model, n=3)
    EX = T.example_vertices(model, ex)
    skirt = D.make_demo_garments(model)["skirt"]
    basis = T.build_garment_basis(model, np.stack([skirt.fit(model, E) for E in EX]), skirt.faces, ex,
                                  meta={"name": "skirt"})
    basis.save(tmp_path / "g1")
    back = T.GarmentBasis.load(tmp_path / "g1")
    for k in T.ARRAYS:
        np.testing.assert_array_equal(getattr(back, k), getattr(basis, k))
    assert back.meta["name"] == "skirt" and back.etag() == basis.etag()
    assert not list(tmp_path.glob(".tmp-*"))


def test_demo_garments_are_outside_the_body_they_were_fitted_to(model):
    X = model.vertices(model.population["weights"][11]).astype(np.float64)
    nb = model.n_body_vertices
    from scipy.spatial import cKDTree

    normals = vertex_normals(X[:nb], model.body_faces)
    tree = cKDTree(X[:nb])
    for name, g in D.make_demo_garments(model).items():
        P = g.fit(model, X)
        assert P.shape[0] == g.faces.max() + 1, name
        _, j = tree.query(P)
        signed = np.einsum("ij,ij->i", P - X[j], normals[j])
        assert np.percentile(signed, 1) > 0, name  # essentially all of it on the outside
    tshirt, trousers = (D.make_demo_garments(model)[k].fit(model, X) for k in ("tshirt", "trousers"))
    assert tshirt[:, 1].min() < trousers[:, 1].max()  # the shirt hem overlaps the trousers' waist


def test_mhclo_binding_fits_any_avatar(model):
    d = SHARED / "makehuman_clothes" / "male_casualsuit04"
    b = mhclo.parse_mhclo((d / "male_casualsuit04.mhclo").read_text(), model.mean.shape[0])
    n, faces = mhclo.parse_obj_faces((d / "male_casualsuit04.obj").read_text())
    assert n == len(b.indices) == 1696 and faces.max() < n
    X = model.mean.astype(np.float64)
    P = b.fit(X)
    # a T-shirt and jeans sit on the body: within a few cm of it everywhere
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(X[: model.n_body_vertices]).query(P)
    assert np.median(dist) < 0.03 and dist.max() < 0.1
    # scaling the avatar about the origin scales the bound garment (offsets scale per axis)
    np.testing.assert_allclose(b.fit(X * 1.1), P * 1.1, atol=1e-9)


@pytest.mark.parametrize("text, words", [
    ("verts 0\n1 2 3 0.3 0.3 0.4 0 0 0\n", "missing"),
    ("x_scale 1 2 1.0\ny_scale 1 2 1.0\nz_scale 1 2 1.0\nverts 0\n1 2\n", "expected 9"),
    ("x_scale 1 2 1.0\ny_scale 1 2 1.0\nz_scale 1 2 1.0\nverts 0\n1 2 99999 0.3 0.3 0.4 0 0 0\n", "base mesh"),
    ("x_scale 1 2 1.0\ny_scale 1 2 1.0\nz_scale 1 2 1.0\n", "no vertex bindings"),
])
def test_bad_mhclo_is_refused_with_a_reason(text, words):
    with pytest.raises(mhclo.MhcloError) as e:
        mhclo.parse_mhclo(text, 19158)
    assert words in str(e.value)


def test_projection_of_uploaded_avatars(model):
    w = model.population["weights"][21].astype(np.float64)
    X = model.vertices(w).astype(np.float64)
    R = lbs.axis_angle_to_matrix(np.array([-np.pi / 2, 0.0, 0.0]))  # Y up -> Z up
    for verts, unit in ((X, "m"), (X[: model.n_body_vertices] * 100 @ R.T + [3, 1, 2], "cm"),
                        (X[: model.n_body_vertices] * 1000, "mm")):
        p = avatar_io.project_mesh(model, verts)
        assert p.unit == unit and p.residual_mm < 0.5
        rec = model.vertices(p.weights)[: model.n_body_vertices]
        tru = X[: model.n_body_vertices]
        body_err = np.linalg.norm((rec - rec.mean(0)) - (tru - tru.mean(0)), axis=1)
        assert body_err.max() < 1e-3  # the same body shape, to under a millimetre
    with pytest.raises(avatar_io.AvatarMeshError, match="template topology has"):
        avatar_io.project_mesh(model, X[:1000])
    with pytest.raises(avatar_io.AvatarMeshError, match="units"):
        avatar_io.project_mesh(model, X * 0.01)
    with pytest.raises(avatar_io.AvatarMeshError, match="not an avatar"):
        avatar_io.project_mesh(model, np.random.default_rng(0).random((model.n_body_vertices, 3)) * 1.7)


def test_winding_numbers_tell_inside_from_outside():
    import trimesh

    from service.model.geometry import winding_numbers

    box = trimesh.creation.box(extents=(1, 1, 1))
    pts = np.array([[0, 0, 0], [0.49, 0.49, 0.49], [0.51, 0, 0], [2, 2, 2], [0.6, 0.6, 0.0]])
    w = winding_numbers(pts, box.vertices, box.faces)
    np.testing.assert_allclose(w, [1, 1, 0, 0, 0], atol=1e-9)

"""Clothing bases, synthesis, push-out, MakeHuman bindings, demo garments, avatar projection."""
from __future__ import annotations


import numpy as np
import pytest

from service.model.formats import avatar_io
from service.model.garments import demo_garments as D
from service.model.garments import garment as G
from service.model.formats import mhclo
from service.model.body import lbs
from service.model.garments import tryon as T

from service.model.geometry.mesh import vertex_faces, vertex_normals
from tests.bench.common import shared_data_dir

SHARED = shared_data_dir()




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


def _normal_weights(examples: G.ExampleSet, count: int, seed: int = 0) -> np.ndarray:
    """(count, N) weights of independent normal components of std sigma_i: a synthetic population."""
    return np.random.default_rng(seed).standard_normal((count, examples.n)) * examples.sigma[None, :]


def test_regressed_basis_is_exact_for_linear_fits_and_stored_as_examples(model):
    """G.regress_basis through linear data recovers it; G.example_equivalent gives example fits
    whose central differences (build_basis) are that basis exactly."""
    ex = T.example_set(model, n=5, c=0.5)
    rng = np.random.default_rng(2)
    g_true = rng.normal(size=(30, 3))
    B_true = rng.normal(size=(5, 30, 3))
    W = np.vstack([ex.weights(), _normal_weights(ex, 20)])
    fits = g_true[None] + np.einsum("ki,imd->kmd", W, B_true)
    g, B = G.regress_basis(fits, W, ex.sigma, ridge=0.0)
    np.testing.assert_allclose(g, g_true, atol=1e-4)
    np.testing.assert_allclose(B, B_true, rtol=1e-3, atol=1e-3)
    g2, B2 = G.build_basis(G.example_equivalent(g, B, ex), ex)
    np.testing.assert_allclose(g2, g, atol=1e-6)
    np.testing.assert_allclose(B2, B, rtol=1e-3, atol=1e-3)
    with pytest.raises(ValueError, match="at least 6"):
        G.regress_basis(fits[:4], W[:4], ex.sigma)


def test_population_sample_draws_real_people_of_the_garments_gender(model):
    """T.population_sample: whole rows of the body model's training population, the garment's
    gender POPULATION_GENDER_SHARE of them (half each without one), the same for a seed."""
    pop_w = np.asarray(model.population["weights"], np.float64)
    male = np.asarray(model.population["attributes"])[:, 0] >= 0.5
    for gender, n_male in (("female", 10), ("male", 30), (None, 20), ("unisex", 20)):
        W = T.population_sample(model, 40, gender)
        assert W.shape == (40, model.n_components)
        rows = [int(np.flatnonzero((pop_w == w).all(axis=1))[0]) for w in W]  # each a person of the population
        assert int(male[rows].sum()) == n_male, gender
        assert len(set(rows)) == 40  # without replacement
    assert T.POPULATION_GENDER_SHARE == 0.75
    np.testing.assert_array_equal(T.population_sample(model, 8, "male"), T.population_sample(model, 8, "male"))
    assert not np.array_equal(T.population_sample(model, 8, seed=1), T.population_sample(model, 8, seed=2))
    assert T.population_sample(model, 0).shape == (0, model.n_components)


def test_regressed_basis_fits_a_kinked_garment_better_than_two_examples():
    """Cloth that hangs (constant) on small bodies and follows large ones (a kink at w = 0, as
    contact makes it): the least-squares line over the population misses it by less, over the
    population, than the central difference of two examples half a std from the mean."""
    ex = G.ExampleSet(n=1, c=0.5, sigma=np.array([1.0]))
    W = np.vstack([ex.weights(), _normal_weights(ex, 200, seed=3)])
    kink = lambda w: np.maximum(w, 0.0)[:, None, None] * np.ones((1, 4, 3))  # noqa: E731
    g, B = G.regress_basis(kink(W[:, 0]), W, ex.sigma)
    g0, B0 = G.build_basis(kink(ex.weights()[:, 0]), ex)
    test = _normal_weights(ex, 500, seed=4)
    truth = kink(test[:, 0])
    err = lambda g, B: np.mean([np.abs(G.synthesize(g, B, w) - t).mean() for w, t in zip(test, truth)])  # noqa: E731
    assert err(g, B) < 0.75 * err(g0, B0), (err(g, B), err(g0, B0))


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
    from service.model.geometry.mesh import vertex_faces
    from service.model.body.model import BONES

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


def _sheet(x: float, normal_x: float, offset: float) -> tuple[np.ndarray, np.ndarray]:
    """A square sheet (vertices (n, 3), triangles) in the plane x = const, 24 cm wide, a 3 cm
    grid shifted by ``offset`` in y and z, its triangles' normals along +-x (``normal_x``)."""
    t = np.arange(-0.12, 0.12 + 1e-9, 0.03) + offset
    yy, zz = np.meshgrid(t, t, indexing="ij")
    V = np.stack([np.full(yy.size, x), yy.ravel(), zz.ravel()], axis=1)
    k = len(t)
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1), indexing="ij")
    a, b, c, d = (i * k + j).ravel(), ((i + 1) * k + j).ravel(), ((i + 1) * k + j + 1).ravel(), (i * k + j + 1).ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])[:, 0]
    if np.sign(n[0]) != np.sign(normal_x):
        F = F[:, ::-1]
    return V, F


def test_a_vertex_inside_facing_skin_is_pushed_out_of_it():
    """A crease: skin A (x = 0, normal +x) faces skin B (x = 1 cm, normal -x), both meshed
    coarser than the gap, as a heavy crotch is. A garment vertex 2 mm into B, right over one
    of A's vertices, is nearest to that vertex, whose tangent plane says it is 1.2 cm outside.
    Its crease anchor is B's surface, and it is pushed out of B by the clearance; against the
    slow reference (the signed distance to each plane)."""
    from scipy.spatial import cKDTree

    A, FA = _sheet(0.0, +1.0, 0.0)
    B, FB = _sheet(0.01, -1.0, 0.015)
    V = np.concatenate([A, B])
    F = np.concatenate([FA, FB + len(A)])
    N = vertex_normals(V, F)
    garment = np.array([[0.012, 0.0, 0.0], [0.005, 0.03, 0.03], [0.011, 0.045, -0.03]])
    tree = cKDTree(V)
    _, nn = tree.query(garment, k=G.CREASE_K)
    assert nn[0, 0] < len(A)  # the nearest skin vertex is A's
    anchors = G.crease_anchors(garment, G.in_crease(nn, N), nn, V, N, F, tree, vertex_faces(F, len(V)))
    idx, q, n, most = anchors
    assert set(idx) >= {0, 2}
    k = list(idx).index(0)
    np.testing.assert_allclose(q[k], [0.01, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(n[k], [-1.0, 0.0, 0.0], atol=1e-6)
    assert most[k] == pytest.approx(0.005, abs=1e-6)  # half the 1 cm gap
    without, _ = G.push_out(garment, V, N, nn[:, :1], None, 0.003)
    out, _ = G.push_out(garment, V, N, nn[:, :1], None, 0.003, anchors)
    assert without[0, 0] > 0.01  # the bound vertex's plane alone leaves it inside B
    # the slow reference: inside B is x > 0.01, inside A is x < 0; 3 mm of clearance from
    # the skin each vertex is nearest to
    assert out[0, 0] == pytest.approx(0.01 - 0.003, abs=1e-6)
    assert out[2, 0] == pytest.approx(0.01 - 0.003, abs=1e-6)
    np.testing.assert_allclose(out[1], garment[1], atol=1e-7)  # mid-gap, 4-5 mm from both: untouched
    # a clearance wider than the gap: the vertex stops in the middle, inside neither side
    wide, _ = G.push_out(garment, V, N, nn[:, :1], None, 0.008, anchors)
    assert wide[0, 0] == pytest.approx(0.005, abs=1e-6) and wide[2, 0] == pytest.approx(0.005, abs=1e-6)


@pytest.mark.slow
def test_heavy_crotch_keeps_the_bottoms_outside(model):
    """The penetration figure's misses (`tryon bench tryon`): a 179 cm / 111 kg man in
    MakeHuman's jeans and denim shorts, whose crotch is a crease (skin facing skin). No
    try-on vertex more than 1 mm inside him (exact closest triangle, confirmed by the winding
    number); without the crease anchors, 9 are."""
    from scipy.spatial import cKDTree

    from service.model.body import shape as S
    from tests.bench.common import makehuman_garments
    from tests.bench.tryon import penetrations

    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    garments = makehuman_garments(model)
    fit = S.avatar_from_measurements(model, {
        "gender": "male", "height_cm": 179.1, "weight_kg": 111.4, "chest_cm": 111.5, "waist_cm": 109.1,
        "hip_cm": 113.5, "thigh_cm": 75.5, "calf_cm": 45.1, "waist_height_cm": 106.5, "shoulder_width_cm": 45.9,
        "inseam_cm": 87.8, "arm_length_cm": 62.4})
    body = T.customer_body(model, fit.weights)
    plain = T.CustomerBody(body.weights, body.vertices, body.normals)  # no faces: no crease anchors
    assert body.faces is not None and plain.faces is None
    nb = model.n_body_vertices
    X = body.vertices[:nb].astype(np.float64)
    args = (X, body.normals, model.body_faces, cKDTree(X), vertex_faces(model.body_faces, nb))
    before = after = 0
    for name in ("male_casualsuit01", "female_casualsuit02"):
        g, faces = garments[name]
        basis = T.build_garment_basis(model, np.stack([g(E) for E in EX]), faces, ex)
        after += len(penetrations(T.try_on(basis, body)[0], *args)[1])
        before += len(penetrations(T.try_on(basis, plain)[0], *args)[1])
    assert before >= 3
    assert after == 0


def test_a_body_detail_between_garment_vertices_is_pushed_out_of_the_face():
    """A flat skin (y = 0, normal +y, 1 cm grid) with one vertex raised 6 mm (a nipple) under the
    middle of one 6 cm garment triangle lying 3 mm over the skin: every garment vertex clears
    its nearest skin vertex, so the vertex push-out leaves the face 3 mm under the bump's tip.
    The face pass (``correctives.skin_under_faces`` then ``push_out``'s pairs) lifts the face
    until its point over the bump is the clearance out, each vertex by its barycentric share;
    against the slow reference (the face point's height over the tip)."""
    from scipy.spatial import cKDTree

    from service.model.garments.correctives import skin_under_faces

    xs = np.arange(-0.05, 0.0501, 0.01)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], axis=1)
    n = len(xs)
    q = np.arange(n * n).reshape(n, n)
    F = np.concatenate([np.stack([q[:-1, :-1].ravel(), q[:-1, 1:].ravel(), q[1:, 1:].ravel()], 1),
                        np.stack([q[:-1, :-1].ravel(), q[1:, 1:].ravel(), q[1:, :-1].ravel()], 1)])
    tip = int(np.argmin(np.linalg.norm(V - [0.0, 0.0, 0.0], axis=1)))
    V[tip, 1] = 0.006
    N = np.tile([0.0, 1.0, 0.0], (len(V), 1))  # the skin's normal (the bump's own is near it)
    garment = np.array([[-0.03, 0.003, -0.02], [0.03, 0.003, -0.02], [0.0, 0.003, 0.04]])
    faces = np.array([[0, 2, 1]])
    nn = cKDTree(V).query(garment, k=1)[1][:, None]
    plain, _ = G.push_out(garment, V, N, nn, None, 0.003)
    under = skin_under_faces(plain, faces, V, N, 0.006)
    assert tip in set(under[0].tolist())
    out, moved = G.push_out(garment, V, N, nn, None, 0.003, None, under, faces)
    k = list(under[0]).index(tip)
    point = under[2][k] @ out[faces[under[1][k]]]
    assert (under[2][k] @ plain[faces[under[1][k]]])[1] < V[tip, 1]  # the vertex pass alone: through
    assert point[1] == pytest.approx(V[tip, 1] + 0.003, abs=1e-6) and moved == 3
    np.testing.assert_allclose(out[:, [0, 2]], garment[:, [0, 2]], atol=1e-7)  # straight out along the normal


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
    fits = np.stack([skirt.fit(model, E) for E in EX])
    # a basis of drapes keeps the fits they started from (here: the fits moved 1 cm) as its start channel
    starts = fits + np.float32(0.01)
    basis = T.build_garment_basis(model, fits, skirt.faces, ex, meta={"name": "skirt"}, rest=skirt.fit(model, EX[0]),
                                  start_fits=starts)
    assert basis.gs is not None and basis.Bs is not None  # the strain channel is stored too
    assert basis.gw is not None and basis.Bw is not None  # and the start channel
    basis.save(tmp_path / "g1")
    back = T.GarmentBasis.load(tmp_path / "g1")
    for k in T.ARRAYS:
        np.testing.assert_array_equal(getattr(back, k), getattr(basis, k))
    assert back.meta["name"] == "skirt" and back.etag() == basis.etag()
    assert not list(tmp_path.glob(".tmp-*"))
    # a drape starts from the start channel at the customer's weights; without one, from the try-on
    body = T.customer_body(model, model.population["weights"][5])
    plain = T.build_garment_basis(model, fits, skirt.faces, ex)
    assert plain.gw is None
    want = G.synthesize(np.asarray(plain.g), np.asarray(plain.B), body.weights) + 0.01  # the same fits, 1 cm on
    np.testing.assert_allclose(T.drape_start(back, body), want, atol=1e-5)
    np.testing.assert_array_equal(T.drape_start(plain, body), T.try_on(plain, body)[0])


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

    from service.model.geometry.mesh import winding_numbers

    box = trimesh.creation.box(extents=(1, 1, 1))
    pts = np.array([[0, 0, 0], [0.49, 0.49, 0.49], [0.51, 0, 0], [2, 2, 2], [0.6, 0.6, 0.0]])
    w = winding_numbers(pts, box.vertices, box.faces)
    np.testing.assert_allclose(w, [1, 1, 0, 0, 0], atol=1e-9)


def test_the_strain_map_is_a_linear_channel_of_the_basis(model):
    """With a rest shape the basis keeps the strain map (``tryon.vertex_strain`` against it) as
    its own channel (gs, Bs), built like the positions: at the mean the mean fit's strain map,
    from ``strain_fits`` where given (e.g. regressed over drapes); a basis without one (stored
    before it existed) measures the map on the tried-on positions."""
    ex = T.example_set(model, n=3)
    EX = T.example_vertices(model, ex)
    shirt = D.make_demo_garments(model)["tshirt"]
    fits = np.stack([shirt.fit(model, E) for E in EX])
    rest = 0.97 * fits[0]  # a size smaller than the mean fit: stretched on every example
    basis = T.build_garment_basis(model, fits, shirt.faces, ex, rest=rest)
    M = len(rest)
    assert basis.gs.shape == (M,) and basis.Bs.shape == (ex.n, M)
    S0 = T.strain_maps(rest, shirt.faces, fits)
    assert S0.shape == (len(fits), M) and 0.02 < np.median(S0[0]) < 0.04
    w0 = np.zeros(model.n_components)
    np.testing.assert_allclose(T.strain_map(basis, w0, fits[0]), S0[0], atol=1e-6)
    # the channel, not the positions: a given strain (0.1 at the mean, growing along component 0)
    given = np.full((len(fits), M), 0.1, np.float32)
    given[1], given[2] = 0.1 + 0.05, 0.1 - 0.05
    b2 = T.build_garment_basis(model, fits, shirt.faces, ex, rest=rest, strain_fits=given)
    w = w0.copy()
    w[0] = ex.c * ex.sigma[0]
    np.testing.assert_allclose(T.strain_map(b2, w, fits[0]), 0.15, atol=1e-6)
    # the customer's own drape (not synthesised): measured on its vertices
    np.testing.assert_allclose(T.strain_map(b2, w, fits[0], synthesised=False), S0[0], atol=1e-4)
    # no channel: measured on the vertices
    b3 = T.build_garment_basis(model, fits, shirt.faces, ex)
    assert b3.gs is None
    np.testing.assert_allclose(T.strain_map(b3, w0, 1.02 * np.asarray(b3.g)), 0.02, atol=1e-4)


def test_the_push_outs_compiled_diffusion_equals_scipys(model, monkeypatch):
    """``garment.push_out``'s vertex pass (the planes of the bound body vertices and of the
    crease anchors, the pushes diffused through the smoother's columns of the pushed vertices,
    each topped up to its depth) in one compiled loop (``kernels.push_vertices``) gives what
    numpy and scipy's ``S[:, bad] @ X`` give, bit for bit, and so does the diffusion alone
    (``kernels.columns_product``, for bindings of several body vertices)."""
    from service.model.geometry import kernels

    if not kernels.AVAILABLE:
        pytest.skip("numba not installed")
    ex = T.example_set(model, n=3)
    EX = T.example_vertices(model, ex)
    shirt = D.make_demo_garments(model)["tshirt"]
    basis = T.build_garment_basis(model, np.stack([shirt.fit(model, E) for E in EX]), shirt.faces, ex)
    body = T.customer_body(model, model.population["weights"][7])
    v = 0.97 * np.asarray(basis.g)  # shrunk: many vertices inside, pushed out
    nearest, anchors, under = body.push_binding(basis, v)
    assert len(anchors[0]) and len(under[0])
    several = body.nearest(v, 3).astype(np.int32)
    for args in ((nearest,), (nearest, G.CLEARANCE, anchors, under, np.asarray(basis.faces)), (several,)):
        out = {}
        for compiled in (True, False):
            monkeypatch.setattr(G, "COMPILED", compiled)
            out[compiled] = G.push_out(v, body.vertices, body.normals, args[0], basis.smoother(), *args[1:])
        assert out[True][1] == out[False][1] > 100
        np.testing.assert_array_equal(out[True][0], out[False][0])

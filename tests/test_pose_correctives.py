"""Pose-corrective morph targets (issue 11): with the target of the page's pose at influence 1,
the skinned garment stays outside the posed body; the targets survive a GLB round trip (sparse
accessors, every compression mode) and the Khronos validator is clean."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.application import parallel, scenes
from service.model.garments import correctives as C
from service.model.body import lbs as L
from service.model.body import poses as P
from service.model.body import shape as S
from service.model.garments import tryon as T
from service.model.garments.catalogue import load_catalogue
from service.model.geometry.mesh import vertex_faces
from service.model.formats.gltf_read import read_glb
from service.records import Garment
from service.storage.cache import VersionedLRU
from tests.bench.tryon import INSIDE_DEPTH, penetration_depths
from tests.conftest import format_issues

HEAVY = {"gender": "male", "height_cm": 200, "weight_kg": 130}  # the page's screenshots: chest through the blouse


def record(name: str, layer: int) -> Garment:
    return Garment(id=name, body_model="test", owner="test", name=name, source="demo", color=[0.4, 0.5, 0.6, 1.0],
                   layer=layer)


@pytest.fixture(scope="module")
def setup(model):
    """The heavy man, his adapted page poses, and the pinstripe blouse and casual jacket (render
    layouts, materials) tried on him."""
    ex = T.example_set(model, n=8)
    EX = T.example_vertices(model, ex)
    cat = load_catalogue()
    bases = {}
    for gid in ("pinstripe-blouse", "casual-jacket"):
        it = cat.items[gid]
        bases[gid] = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex,
                                           layout=it.render_layout(), material=it.material)
    X = S.avatar_from_measurements(model, HEAVY).vertices
    body = T.customer_body(model, model.project(X))
    return bases, body, P.adapted_poses(model, body.vertices)


def inside_share(model, v, skin, posed: C.PosedBody, delta=None) -> float:
    """Share of the garment's vertices more than INSIDE_DEPTH inside the posed body (exact)."""
    nb = model.n_body_vertices
    x = np.asarray(v, np.float64) + (0.0 if delta is None else delta)
    pv = L.skin(x, posed.transforms, *skin)
    d = penetration_depths(pv, posed.vertices, model.body_faces, cKDTree(posed.vertices),
                           vertex_faces(model.body_faces, nb))
    return float((d > INSIDE_DEPTH).mean())


def test_correctives_keep_the_blouse_outside_the_heavy_body_walking(model, setup) -> None:
    bases, body, poses = setup
    b = bases["pinstripe-blouse"]
    v = T.try_on(b, body)[0]
    posed = C.posed_body(model, body.vertices, poses["walking"])
    delta, pushed = C.corrective_deltas(v, b.skin_idx, b.skin_w, posed, b.smoother(), faces=b.faces)
    before = inside_share(model, v, (b.skin_idx, b.skin_w), posed)
    after = inside_share(model, v, (b.skin_idx, b.skin_w), posed, delta)
    assert pushed > 0 and before > 0.004, before  # the problem is there: 0.77 % measured
    assert after < 0.003 and after < 0.35 * before, (before, after)
    # sparse: most of the garment has no delta, and no spike (at most a few cm)
    moved = np.linalg.norm(delta, axis=1)
    assert (moved > 0).mean() < 0.4 and moved.max() < 0.05
    # the rest pose needs none
    rest = C.posed_body(model, body.vertices, poses["a-pose"])
    assert not np.any(C.corrective_deltas(v, b.skin_idx, b.skin_w, rest, b.smoother())[0])


def test_posed_delta_maps_back_exactly(model, setup) -> None:
    """skin(v + delta) = the pushed-out posed garment: the inverse blended matrix is right."""
    bases, body, poses = setup
    b = bases["casual-jacket"]
    v = T.try_on(b, body)[0].astype(np.float64)
    posed = C.posed_body(model, body.vertices, poses["arms-down"])
    d, _ = C.posed_pushes(v, b.skin_idx, b.skin_w, posed, b.smoother(), faces=b.faces)
    delta = C.to_rest(d, posed.transforms, b.skin_idx, b.skin_w)
    got = L.skin(v + delta, posed.transforms, b.skin_idx, b.skin_w) - L.skin(v, posed.transforms, b.skin_idx, b.skin_w)
    keep = np.linalg.norm(d, axis=1) > C.MIN_DELTA
    assert keep.sum() > 10 and np.abs(got[keep] - d[keep]).max() < 1e-5


@pytest.mark.parametrize("compression", [None, "quantize", "meshopt"])
def test_outfit_glb_carries_the_pose_targets(model, setup, compression,
                                             validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    bases, body, poses = setup
    worn = [(record("blouse", 0), bases["pinstripe-blouse"]), (record("jacket", 1), bases["casual-jacket"])]
    plain = scenes.outfit_glb(model, body, worn, compression, with_avatar=True)
    data = scenes.outfit_glb(model, body, worn, compression, with_avatar=True, poses=poses)
    report = validate_glb(data)
    assert report["issues"]["numErrors"] == 0 and report["issues"]["numWarnings"] == 0, format_issues(report)
    out, ref = read_glb(data), read_glb(plain)
    names = [f"pose:{p}" for p in poses]
    for m, r, (_, b) in zip(out["meshes"][-2:], ref["meshes"][-2:], worn):
        assert m["target_names"] == names and m["morph_weights"] == [0.0] * len(names)
        assert np.allclose(m["positions"], r["positions"], atol=1e-4)  # the same garment under them
        t = m["targets"]
        assert t.shape == (len(names), len(b.render_vertex), 3)
        # at rest only the triangles the body pokes through move, by millimetres
        assert np.abs(t[names.index("pose:a-pose")]).max() < 0.01
        assert np.abs(t[names.index("pose:walking")]).max() > 0.002
    acc = out["json"]["accessors"]
    prim = out["json"]["meshes"][-1]["primitives"][0]
    assert all("sparse" in acc[tg["POSITION"]] or "bufferView" not in acc[tg["POSITION"]] for tg in prim["targets"])
    assert len(data) < len(plain) + 0.5 * sum(4 * 12 * len(b.render_vertex) for _, b in worn)  # sparse: < half dense
    # the avatar's own (correctives.body_tucks: skin still through the clothes pulled under them,
    # by at most TUCK_MAX_DEPTH + TUCK_MARGIN, about as much in rest space);
    # without poses nothing changes
    av = out["meshes"][0]
    assert av["target_names"] == names, av["target_names"]
    assert 0 < np.abs(av["targets"]).max() < 1.5 * (C.TUCK_MAX_DEPTH + C.TUCK_MARGIN)
    assert all(m["targets"] is None for m in ref["meshes"])


@pytest.mark.slow
def test_pose_targets_on_threads_are_those_of_one_thread(model, setup, monkeypatch: pytest.MonkeyPatch) -> None:
    """An outfit's pose targets and posed bodies made one pose per thread (parallel.WORKERS)
    give the same GLB bytes as made one after another, on a body new to both."""
    bases, body, poses = setup
    worn = [(record("blouse", 0), bases["pinstripe-blouse"]), (record("jacket", 1), bases["casual-jacket"])]
    out = {}
    for workers in (1, 3):
        monkeypatch.setattr(parallel, "WORKERS", workers)
        monkeypatch.setattr(scenes, "_correctives", VersionedLRU(scenes.CORRECTIVES_CACHE_SIZE))
        fresh = T.customer_body(model, body.weights)  # no posed bodies cached on it
        out[workers] = scenes.outfit_glb(model, fresh, worn, None, with_avatar=True, poses=poses, cache=False)
        assert len(fresh._posed) == 1
    assert out[1] == out[3]
    assert np.abs(read_glb(out[3])["meshes"][-1]["targets"]).max() > 0.002


def test_round_trip_values(model, setup) -> None:
    """The deltas read back from the GLB (plain float) are the ones computed, gathered to the
    render vertices."""
    bases, body, poses = setup
    g = (record("blouse", 0), bases["pinstripe-blouse"])
    out = read_glb(scenes.outfit_glb(model, body, [g], None, with_avatar=False, poses=poses))
    b = g[1]
    v = T.try_on(b, body)[0]
    bodies = scenes.posed_bodies(model, body, poses)
    for k, name in enumerate(poses):
        d = C.corrective_deltas(v, b.skin_idx, b.skin_w, bodies[name], b.smoother(), rest=bodies[scenes.REST],
                                faces=b.faces)[0]
        assert np.allclose(out["meshes"][0]["targets"][k], d[np.asarray(b.render_vertex)], atol=1e-7)


@pytest.mark.slow
def test_outfit_correctives_keep_the_layer_order(model, setup) -> None:
    """The blouse under the jacket on the heavy man, the three page poses: with both garments'
    targets at 1 (as outfit.glb makes them), the blouse is outside the jacket over no more of
    the rest pose's doubly covered body than without them (``layering.posed_outside``), and
    without following the jacket (each garment corrected alone) it would be outside more."""
    from service.model.garments import layering as LY
    from service.model.body.model import BONES
    from service.model.geometry.mesh import vertex_normals

    bases, body, poses = setup
    nb = model.n_body_vertices
    bi, bo = bases["pinstripe-blouse"], bases["casual-jacket"]
    Bv, Bn = body.vertices[:nb].astype(np.float64), body.normals.astype(np.float64)
    vi, vo = T.try_on(bi, body, 0)[0], T.try_on(bo, body, 1)[0]
    (vi, vo), (si, so) = LY.layer_outfit([(vi, bi.faces), (vo, bo.faces)], Bv, Bn,
                                         skins=[(bi.skin_idx, bi.skin_w), (bo.skin_idx, bo.skin_w)], n_joints=len(BONES))
    vi, vo = (np.asarray(x, np.float32).astype(np.float64) for x in (vi, vo))  # as outfit.glb keeps them
    pairs = LY.layered_pairs(vi, bi.faces, vo, bo.faces, Bv, Bn)
    out = read_glb(scenes.outfit_glb(model, body, [(record("blouse", 0), bi), (record("jacket", 1), bo)], None,
                                     with_avatar=False, poses=poses))
    names = out["meshes"][0]["target_names"]
    rest = C.posed_body(model, body.vertices, np.zeros((len(BONES), 3)))
    cover = C.cover_map(vi, vo, bo.faces, Bv, Bn)
    counts = np.zeros(3, int)
    for name in ("walking", "arms-down", "hands-on-hips"):
        posed = C.posed_body(model, body.vertices, poses[name])
        G, PB = posed.transforms, posed.vertices
        PN = vertex_normals(PB, model.body_faces).astype(np.float64)
        po = C.posed_pushes(vo, *so, posed, bo.smoother(), 1, rest=rest, faces=bo.faces)[0]
        pi = C.posed_pushes(vi, *si, posed, bi.smoother(), 0, rest=rest, faces=bi.faces)[0]
        di, do = C.to_rest(C.follow_outer(pi, cover, po, bo.faces), G, *si), C.to_rest(po, G, *so)
        alone = C.to_rest(pi, G, *si)
        k = names.index(f"pose:{name}")
        # each welded vertex's first render vertex
        served = [out["meshes"][j]["targets"][k][np.unique(np.asarray(b.render_vertex), return_index=True)[1]]
                  for j, b in ((0, bi), (1, bo))]
        assert np.allclose(served[0], di, atol=1e-6) and np.allclose(served[1], do, atol=1e-6)
        for c, (a, o) in enumerate(((vi, vo), (vi + di, vo + do), (vi + alone, vo + do))):
            counts[c] += LY.posed_outside(pairs, L.skin(a, G, *si), bi.faces, L.skin(o, G, *so), bo.faces, PB, PN)
    none, served, alone = counts
    print("posed_outside none / served / alone:", counts, "of", 3 * len(pairs[0]))
    assert served <= none + 0.002 * len(pairs[0]) * 3, counts
    assert alone > served, counts


def test_body_pokes_through_the_blouse_are_pushed_out(model, setup, monkeypatch: pytest.MonkeyPatch) -> None:
    """The page's screenshot: the heavy man's chest through the pinstripe blouse in front of the
    arm in the walking step, with hardly a blouse vertex inside him (the skin pokes through
    triangles between them). Step 3 (``BODY_POKES``) pushes those triangles out: far fewer body
    vertices poke through than with steps 1-2 alone."""
    bases, body, poses = setup
    b = bases["pinstripe-blouse"]
    v = T.try_on(b, body)[0].astype(np.float64)
    posed = C.posed_body(model, body.vertices, poses["walking"])
    rest = C.posed_body(model, body.vertices, np.zeros((17, 3)))
    counts = {}
    for on in (False, True):
        monkeypatch.setattr(C, "BODY_POKES", on)
        d = C.corrective_deltas(v, b.skin_idx, b.skin_w, posed, b.smoother(), rest=rest, faces=b.faces)[0]
        pv = L.skin(v + d, posed.transforms, b.skin_idx, b.skin_w)
        counts[on] = len(C.body_pokes(pv, b.faces, posed, 0.0)[0]) // 3
    none = len(C.body_pokes(L.skin(v, posed.transforms, b.skin_idx, b.skin_w), b.faces, posed, 0.0)[0]) // 3
    assert counts[True] < 0.6 * counts[False] and counts[False] <= none, (none, counts)


def on_the_heavy_woman(model, garment_id: str):
    """A catalogue garment's basis (8 examples) tried on the 165 cm / 105 kg woman: (basis,
    customer body, garment vertices (M, 3) float64, her unposed :class:`C.PosedBody`)."""
    ex = T.example_set(model, n=8)
    EX = T.example_vertices(model, ex)
    it = load_catalogue().items[garment_id]
    b = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex)
    X = S.avatar_from_measurements(model, {"gender": "female", "height_cm": 165, "weight_kg": 105}).vertices
    body = T.customer_body(model, model.project(X))
    return b, body, T.try_on(b, body)[0].astype(np.float64), C.posed_body(model, body.vertices, np.zeros((17, 3)))


def vertex_pass_only(b, body) -> np.ndarray:
    """(M, 3) float64: the try-on of basis ``b`` on ``body`` without the push-out's face pass."""
    syn = T.G.synthesize(np.asarray(b.g), np.asarray(b.B), body.weights)
    nearest, anchors, _ = body.push_binding(b, syn)
    return T.G.push_out(syn, body.vertices, body.normals, nearest, b.smoother(), T.G.CLEARANCE,
                        anchors)[0].astype(np.float64)


def test_body_pokes_through_the_jeans_at_rest_are_pushed_out(model) -> None:
    """The page's A-pose (the rest pose): the 165 cm / 105 kg woman's skin showed through the
    women's jeans (screenshot ``body-w165-105-outfit1``): no jeans vertex is inside her, but 36
    body vertices poked through the triangles between them. The try-on's push-out now keeps the
    body vertices under its faces outside them too (its face pass); the rest pose's corrective
    target pushes what is left out (step 3 alone; no vertex push at rest)."""
    b, body, v, rest = on_the_heavy_woman(model, "womens-jeans")
    vertex_pass = vertex_pass_only(b, body)
    under = body.face_pass(b, None, T.G.CLEARANCE)
    without = len(C.body_pokes(vertex_pass.astype(np.float64), b.faces, rest, 0.0)[0]) // 3
    before = len(C.body_pokes(v, b.faces, rest, 0.0)[0]) // 3
    assert without >= 10 and len(under[0]) >= without and before <= 0.25 * without, (without, before)
    d, pushed = C.corrective_deltas(v, b.skin_idx, b.skin_w, rest, b.smoother(), rest=rest, faces=b.faces)
    after = len(C.body_pokes(v + d, b.faces, rest, 0.0)[0]) // 3
    assert after <= before, (before, after)
    assert np.linalg.norm(d, axis=1).max() < 0.01  # a few millimetres, no spike
    assert np.linalg.norm(v - vertex_pass, axis=1).max() < 0.01  # the face pass too


def exact_pokes(pv: np.ndarray, faces: np.ndarray, posed: C.PosedBody) -> int:
    """Body vertices (no hands) poking through a posed garment (M, 3) / (F, 3), every one tested
    (no prefilter, unlike ``C.body_pokes``): the closest garment point is within 2 cm, within 45
    degrees of the vertex normal, on a triangle with no rim vertex, and behind the vertex."""
    from service.model.geometry.mesh import closest_points_on_mesh
    from service.model.garments.layering import boundary_vertices

    F = np.asarray(faces, np.int64)
    X, N = posed.vertices[posed.ids], posed.normals[posed.ids]
    rim = np.zeros(len(pv), bool)
    rim[boundary_vertices(F, len(pv))] = True
    face, q, _ = closest_points_on_mesh(X, pv, F)
    off = q - X
    dist = np.linalg.norm(off, axis=1)
    s = np.einsum("ij,ij->i", off, N)
    return int((~rim[F[face]].any(axis=1) & (dist < 0.02) & (np.abs(s) > np.cos(np.pi / 4) * dist) & (s < 0)).sum())


@pytest.mark.slow
def test_body_pokes_through_the_jeans_are_pushed_out_in_a_pose_that_pushes_no_vertex(model) -> None:
    """The page's arms-down and hands-on-hips poses leave the legs as at rest: no jeans vertex
    gets into the 165 cm / 105 kg woman (step 1 pushes nothing), yet body vertices poke through
    the jeans' triangles as at rest (skin showed through the jeans in the page's "hands on hips"
    screenshot, ``03-dressed``). Step 3 runs whether or not step 1 pushed a vertex, and tests
    every body vertex within 2 cm of a triangle, also under the middle of a long one (the jeans'
    edges are ~4 cm, up to 12). Counted without ``body_pokes``' own prefilter."""
    b, body, tried, rest = on_the_heavy_woman(model, "womens-jeans")
    v = vertex_pass_only(b, body)  # the try-on without its face pass: the jeans as they poked through
    for name in ("arms-down", "hands-on-hips"):
        posed = C.posed_body(model, body.vertices, P.adapted_poses(model, body.vertices)[name])
        before = exact_pokes(L.skin(v, posed.transforms, b.skin_idx, b.skin_w), b.faces, posed)
        d = C.corrective_deltas(v, b.skin_idx, b.skin_w, posed, b.smoother(), rest=rest, faces=b.faces)[0]
        after = exact_pokes(L.skin(v + d, posed.transforms, b.skin_idx, b.skin_w), b.faces, posed)
        assert before >= 10 and after <= 0.1 * before, (name, before, after)
        # the try-on's own face pass at rest already keeps most of them out in these poses
        assert exact_pokes(L.skin(tried, posed.transforms, b.skin_idx, b.skin_w), b.faces, posed) <= 0.5 * before


def test_limit_strain_shortens_only_the_overstretched_edges(model) -> None:
    """Step 4 on a tiny strip far from the body: a 6 x 2 grid whose middle column is pulled 2.5
    times longer across the strip's length ends with every edge within ``STRAIN_LIMIT`` of its
    rest length, the strain spread over the neighbours; an edge already within the limit in a
    part of the strip that nothing pulls does not move."""
    from service.model.geometry.mesh import mesh_edges

    xs, ys = np.meshgrid(np.arange(7) * 0.01, np.arange(3) * 0.01)
    rest = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1) + [1.5, 0.0, 0.0]  # 1.5 m off the body
    faces = np.array([(r * 7 + c, r * 7 + c + 1, r * 7 + c + 8) for r in range(2) for c in range(6)] +
                     [(r * 7 + c, r * 7 + c + 8, r * 7 + c + 7) for r in range(2) for c in range(6)])
    posed = rest.copy()
    posed[rest[:, 0] > 1.5 + 0.035, 0] += 0.015  # the edges across x = 3..4 cm stretched 1 -> 2.5 cm
    body = C.posed_body(model, model.mean, np.zeros((17, 3)))
    edges = mesh_edges(faces)
    x = C.limit_strain(rest, posed, edges, body, C.CLEARANCE)
    ratio = lambda p: np.linalg.norm(p[edges[:, 0]] - p[edges[:, 1]], axis=1) / np.linalg.norm(
        rest[edges[:, 0]] - rest[edges[:, 1]], axis=1)
    assert ratio(posed).max() > 2.4
    assert ratio(x).max() <= C.STRAIN_LIMIT * 1.01, ratio(x).max()
    assert np.ptp(x[:, 0]) > np.ptp(rest[:, 0])  # shortened, not collapsed back to rest
    assert np.allclose(x[:, 2], 0.0)  # in the strip's plane: nothing pushes it off (the body is far)
    # within the limit already: a strip stretched 1.2 everywhere is returned as it is
    even = rest + (rest - rest.mean(0)) * [0.2, 0.0, 0.0]
    assert np.array_equal(C.limit_strain(rest, even, edges, body, C.CLEARANCE), even)


def test_strain_limiting_keeps_the_cropped_tee_from_tearing_open(model, monkeypatch: pytest.MonkeyPatch) -> None:
    """Issue 11's pose stretch: the cropped tee on the 165/105 woman, walking and hands on hips,
    stretched its edges beside the armpits and under the bust 2.3-2.9 times (p99.9; 8 examples) with the
    correctives' steps 1-3. With step 4 (``limit_strain``) the p99.9 is within 1.5 (the goal),
    and hardly more of the tee is inside the posed body than without it."""
    from service.model.geometry.mesh import mesh_edges

    b, body, v, rest = on_the_heavy_woman(model, "cropped-tee")
    poses = P.adapted_poses(model, body.vertices)
    e = mesh_edges(b.faces)
    r = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    for name in ("walking", "hands-on-hips"):
        posed = C.posed_body(model, body.vertices, poses[name])
        got = {}
        for on in (False, True):
            monkeypatch.setattr(C, "STRAIN_LIMITING", on)
            d = C.corrective_deltas(v, b.skin_idx, b.skin_w, posed, b.smoother(), rest=rest, faces=b.faces)[0]
            pv = L.skin(v + d, posed.transforms, b.skin_idx, b.skin_w)
            s = np.linalg.norm(pv[e[:, 0]] - pv[e[:, 1]], axis=1)[r > 1e-9] / r[r > 1e-9]
            got[on] = (float(np.percentile(s, 99.9)), inside_share(model, v, (b.skin_idx, b.skin_w), posed, d))
        print(name, got)
        assert got[False][0] > 2.0 and got[True][0] <= 1.5, got
        assert got[True][1] <= got[False][1] + 2e-3, got  # 1.32 -> 1.43 % walking (a few vertices)


def test_the_underwear_under_a_jacket_stays_out_of_the_thighs(model, setup) -> None:
    """The look's base layer is the outfit's innermost layer, skinned like the garment over it
    where covered. Under the casual jacket on the heavy man in the arms-down pose, the trunks'
    sides followed the jacket's hem (which carried the sleeves' arm weight, inpainted over its
    loose front) up into his thighs: the page's screenshot showed notches of skin in the trunks,
    35 % of their vertices more than 3 mm inside the posed body. With the screened inpainting
    (``skin_weights.SCREENING``) the jacket's front keeps the torso's bones, and so do they."""
    from service.application import look as LK

    bases, body, poses = setup
    out = read_glb(scenes.outfit_glb(model, body, [(record("jacket", 0), bases["casual-jacket"])], None,
                                     with_avatar=True, look=LK.resolve("male"), poses=poses))
    m = next(x for x in out["meshes"] if x["name"] == "underwear")
    posed = C.posed_body(model, body.vertices, poses["arms-down"])
    inside = inside_share(model, np.asarray(m["positions"], np.float64),
                          (np.asarray(m["joints"]), np.asarray(m["weights"])), posed)
    assert inside < 0.01, inside


def test_body_tucks_pull_skin_showing_through_the_cloth_under_it() -> None:
    """``correctives.body_tucks`` on a flat patch of 'skin' (normals +z) under a 'cloth' sheet
    over its middle: where the skin is 5 mm out of the cloth it is pulled to ``TUCK_MARGIN``
    under it, the pull fading out over the neighbours; skin not shown, skin beyond the sheet,
    and skin farther out than ``TUCK_MAX_DEPTH`` (a limb through the cloth) are left."""
    import dataclasses

    from service.model.garments import garment as G
    from service.model.geometry.mesh import vertex_normals

    def grid(n, size, z):
        x = np.linspace(-size, size, n)
        X, Y = np.meshgrid(x, x, indexing="ij")
        V = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
        i, j = np.meshgrid(np.arange(n - 1), np.arange(n - 1), indexing="ij")
        a = (i * n + j).ravel()
        F = np.concatenate([np.stack([a, a + n, a + 1], 1), np.stack([a + 1, a + n, a + n + 1], 1)])
        return V, F

    B, BF = grid(21, 0.1, 0.0)  # 1 cm spacing
    nb = len(B)
    posed = C.PosedBody(np.tile(np.eye(4), (17, 1, 1)), B, vertex_normals(B, BF).astype(np.float64),
                        np.arange(nb), BF, None, None, None)
    assert np.allclose(posed.normals, [0, 0, 1])
    smoother = G.laplacian_smoother(BF, nb)
    shown = np.ones(nb, bool)
    shown[np.flatnonzero(B[:, 0] < -0.03)] = False  # under another garment: not drawn
    cloth, CF = grid(9, 0.06, -0.005)  # the skin 5 mm out of it, over |x|, |y| < 6 cm
    d = C.body_tucks(posed, [(cloth, CF)], shown, smoother, BF)
    z = B[:, 2] + d[:, 2]
    inner = (np.abs(B[:, :2]) < 0.035).all(axis=1) & shown  # > 2.5 cm from the sheet's rim
    assert np.all(z[inner] <= -0.005 - C.TUCK_MARGIN + 1e-9), z[inner].max()
    assert np.allclose(d[:, :2], 0.0)  # along the normal
    assert np.all(d[~shown] == 0) or np.abs(d[~shown]).max() < 0.005  # only by the spread of a neighbour's pull
    far = (np.abs(B[:, :2]) > 0.09).any(axis=1)
    assert np.allclose(d[far], 0.0)  # beyond the sheet (and its smoothing): untouched
    # no cloth within reach under it, or the skin 4 cm out of it: nothing
    deep = C.body_tucks(posed, [(cloth - [0, 0, 0.035], CF)], shown, smoother, BF)
    assert not deep.any()
    assert not C.body_tucks(dataclasses.replace(posed), [(cloth + [0, 0, 0.01], CF)], shown, smoother, BF).any()


def drawn_pokes(model, body, glb: dict, mesh: dict, pose: np.ndarray, name: str, tucked: bool) -> int:
    """Body vertices drawn by the avatar (``body``'s, the first mesh of ``glb``, read_glb) and
    poking through ``mesh`` (with its own ``pose:<name>`` target, if it has one) in ``pose``,
    the avatar's own target for it applied or not (``tucked``); counted exactly
    (:func:`exact_pokes`)."""
    import dataclasses

    from service.model.geometry.mesh import vertex_normals

    av = glb["meshes"][0]
    shown = np.zeros(model.n_body_vertices, bool)
    shown[np.asarray(av["indices"]).ravel()] = True
    posed = C.posed_body(model, body.vertices, pose)
    tuck = av["targets"][av["target_names"].index(f"pose:{name}")] if tucked else 0.0
    pb = L.skin(np.asarray(av["positions"], np.float64) + tuck, posed.transforms, av["joints"], av["weights"])
    pp = dataclasses.replace(posed, vertices=pb, normals=vertex_normals(pb, model.body_faces),
                             ids=posed.ids[shown[posed.ids]])
    own = mesh["targets"][mesh["target_names"].index(f"pose:{name}")] if mesh.get("targets") is not None else 0.0
    pv = L.skin(np.asarray(mesh["positions"], np.float64) + own, posed.transforms, mesh["joints"], mesh["weights"])
    return exact_pokes(pv, np.asarray(mesh["indices"]), pp)


def test_body_tucks_hide_the_skin_showing_through_an_outfit_in_the_page_poses(model, setup) -> None:
    """The heavy man in the blouse under the jacket (``outfit.glb`` with pose targets): body
    vertices drawn and poking through a garment, counted exactly over the page's poses with
    the garments' targets, are at most a fifth with the avatar's own targets (body_tucks)
    than without (measured: 36 -> 0)."""
    bases, body, poses = setup
    worn = [(record("blouse", 0), bases["pinstripe-blouse"]), (record("jacket", 1), bases["casual-jacket"])]
    out = read_glb(scenes.outfit_glb(model, body, worn, None, with_avatar=True, poses=poses))
    counts = np.zeros(2, int)
    for name in poses:
        for c, tucked in enumerate((False, True)):
            counts[c] += sum(drawn_pokes(model, body, out, g, poses[name], name, tucked) for g in out["meshes"][1:])
    print("skin through the outfit without / with the body's targets:", counts)
    assert counts[0] >= 10 and counts[1] <= 0.2 * counts[0], counts


def test_body_tucks_hide_the_skin_showing_through_the_underwear(model, setup) -> None:
    """The heavy man in the casual jacket alone, over the look's trunks (``outfit.glb`` with pose
    targets). Under the loose jacket the trunks are skinned like it, so in the walking step the
    forward thigh came up through their front: in the page a patch of skin flickered through
    them. The trunks are among what the body's targets tuck the skin under (measured: 12 body
    vertices through them without the body's targets, 0 with them; 12 with them too before the
    trunks were among what they tuck under)."""
    from service.application import look as LK

    bases, body, poses = setup
    out = read_glb(scenes.outfit_glb(model, body, [(record("jacket", 0), bases["casual-jacket"])], None,
                                     with_avatar=True, look=LK.resolve("male"), poses=poses))
    trunks = next(m for m in out["meshes"] if m["name"] == "underwear")
    counts = [drawn_pokes(model, body, out, trunks, poses["walking"], "walking", tucked) for tucked in (False, True)]
    assert counts[0] >= 5 and counts[1] == 0, counts


@pytest.mark.slow
def test_poking_through_prefilter_misses_nothing(model, setup) -> None:
    """``poking_through``'s prefilter (body points near ``garment_index``'s samples: the
    vertices plus barycentric grids on long triangles) finds the same pokes, depths and faces
    as testing every body point, for the blouse and the jacket in every page pose (the jacket's
    longest edge is ~10 cm; the samples' reach is at most 6.5 cm)."""
    from scipy.spatial import cKDTree

    bases, body, poses = setup
    found = 0
    for gid, b in bases.items():
        v = T.try_on(b, body)[0].astype(np.float64)
        for name, pose in poses.items():
            posed = C.posed_body(model, body.vertices, pose)
            pv = L.skin(v, posed.transforms, b.skin_idx, b.skin_w)
            X, N = posed.vertices[posed.ids], posed.normals[posed.ids]
            for trigger in (0.0, C.TRIGGER, 0.01):
                fast = C.poking_through(pv, b.faces, X, N, trigger)
                tree = cKDTree(pv)
                every = C.poking_through(pv, b.faces, X, N, trigger, (tree, tree, np.inf))
                assert all(np.array_equal(a, e) for a, e in zip(fast, every)), (gid, name, trigger)
                found += len(fast[0])
            assert C.garment_index(pv, b.faces)[2] < 0.07, gid
    assert found > 100

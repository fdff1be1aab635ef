"""Clothes that move like clothes: skin-weight transfer by inpainting (against a slow reference
on a tiny mesh; a skirt in the walking step no longer tears), the page's pose presets as body
poses (segments point where poses.json says; arms never inside the torso on five bodies), and
garment layering (inner garments pushed inside outer ones)."""
from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.model.garments import demo_garments as D
from service.model.garments import layering as LY
from service.model.body import lbs as L
from service.model.body import poses as P
from service.model.body import shape as S
from service.model.garments import skin_weights as SW
from service.model.garments import tryon as T
from service.model.body.model import BONES
from service.model.geometry.mesh import closest_point_on_triangles, barycentric, mesh_edges, vertex_normals

SHOW_THROUGH_TORN = 0.03  # share of the body under the skirt showing through: the slit of issue 11
SHOW_THROUGH_CLOSED = 0.015
FIVE_BODIES = {
    "160/55 woman": {"gender": "female", "height_cm": 160, "weight_kg": 55},
    "185/80 man": {"gender": "male", "height_cm": 185, "weight_kg": 80},
    "165/105 woman": {"gender": "female", "height_cm": 165, "weight_kg": 105},
    "200/130 man": {"gender": "male", "height_cm": 200, "weight_kg": 130},
    "150/45 man": {"gender": "male", "height_cm": 150, "weight_kg": 45},
}


# -- skin weights ------------------------------------------------------------------------------------
def grid(nx: int, ny: int, z: float = 0.0, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    xs, ys = np.meshgrid(np.linspace(0, size, nx), np.linspace(0, size, ny), indexing="ij")
    V = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    idx = np.arange(nx * ny).reshape(nx, ny)
    F = np.concatenate([np.stack([idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()], 1),
                        np.stack([idx[:-1, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()], 1)])
    return V, F


def reference_transfer(G, GF, B, BF, idx, w, J, max_distance, max_angle_deg, k, screening=SW.SCREENING):
    """Slow and obvious: closest point over every body triangle in a loop, a dense solve of the
    constrained (and screened) Dirichlet problem (KKT, edges weighted 1 / length^2), top-k by
    sorting each row."""
    Wb = np.zeros((len(B), J))
    for i in range(len(B)):
        for j, x in zip(idx[i], w[i]):
            Wb[i, j] += x
    nb = vertex_normals(B, BF).astype(np.float64)
    ng = vertex_normals(G, GF).astype(np.float64)
    W = np.zeros((len(G), J))
    rel = np.zeros(len(G), bool)
    for i, p in enumerate(G):
        best = None
        for f in BF:
            q = closest_point_on_triangles(p, B[f[0]], B[f[1]], B[f[2]])
            d = np.linalg.norm(p - q)
            if best is None or d < best[0] - 1e-12:
                best = (d, f, q)
        d, f, q = best
        bc = barycentric(q, B[f[0]], B[f[1]], B[f[2]])
        W[i] = bc @ Wb[f]
        n = bc @ nb[f]
        n /= np.linalg.norm(n)
        rel[i] = d < max_distance and abs(n @ ng[i]) >= np.cos(np.radians(max_angle_deg))
    rel &= ~SW.weight_jumps(G, GF, W, rel)
    M = len(G)
    Lap = np.zeros((M, M))
    for a, b in mesh_edges(GF):  # the Dirichlet energy sum ((w_a - w_b) / l_ab)^2
        c = 1.0 / np.sum((G[a] - G[b]) ** 2)
        Lap[a, a] += c
        Lap[b, b] += c
        Lap[a, b] -= c
        Lap[b, a] -= c
    kn = np.flatnonzero(rel)
    C = np.zeros((len(kn), M))
    C[np.arange(len(kn)), kn] = 1
    # screened toward the closest-point matches on the unknown rows: + s d sum_u |W_u - W0_u|^2
    Pu = np.diag((~np.isin(np.arange(M), kn)).astype(float)) * screening * np.abs(np.diag(Lap)).mean()
    K = np.block([[2 * Lap + 2 * Pu, C.T], [C, np.zeros((len(kn), len(kn)))]])
    sol = np.linalg.solve(K, np.vstack([2 * Pu @ W, W[kn]]))[:M]
    out_i, out_w = [], []
    for row in sol:
        order = sorted(range(J), key=lambda j: -row[j])[:k]
        ww = np.array([max(row[j], 0) for j in order])
        out_i.append(order)
        out_w.append(ww / ww.sum())
    return np.array(out_i), np.array(out_w)


def test_transfer_matches_slow_reference() -> None:
    # body: a 6x6 sheet in z = 0 whose weights go from joint 0 (x = 0) to joint 2 (x = 1);
    # garment: a finer sheet above it, near (reliable) on the left, lifted 10 cm on the right
    B, BF = grid(6, 6)
    x = B[:, 0]
    w01 = np.clip(1 - 2 * x, 0, 1)
    w2 = np.clip(2 * x - 1, 0, 1)
    Wb = np.stack([w01, 1 - w01 - w2, w2], 1)
    idx = np.tile(np.arange(3), (len(B), 1))
    G, GF = grid(9, 7, z=0.005)
    G[:, 2] += np.where(G[:, 0] > 0.55, 0.1 * (G[:, 0] - 0.55) / 0.45, 0.0)
    G[:, 1] = 0.05 + 0.9 * G[:, 1]
    kw = dict(max_distance=0.02, max_angle_deg=35.0, k=3)  # no truncation: top_k has its own test
    got_i, got_w = SW.transfer_skin_weights(G, GF, B, BF, idx, Wb, 3, **kw)
    ref_i, ref_w = reference_transfer(G, GF, B, BF, idx, Wb, 3, kw["max_distance"], kw["max_angle_deg"], kw["k"])
    dense = lambda i, w: SW.dense_weights(i, w, 3)  # noqa: E731
    assert np.allclose(dense(got_i, got_w), dense(ref_i, ref_w), atol=1e-5)
    assert np.allclose(got_w.sum(1), 1, atol=1e-6)
    # unreliable vertices (lifted) got inpainted values strictly between their neighbours'
    lifted = G[:, 2] > 0.03
    assert lifted.any() and (~lifted).any()


def test_top_k_and_inpaint_constraints() -> None:
    W = np.array([[0.1, 0.5, 0.2, 0.15, 0.05], [0, 0, 0, 0, 0.0]])
    i, w = SW.top_k(W, 4)
    assert i[0].tolist() == [1, 2, 3, 0] and np.isclose(w[0].sum(), 1)
    assert w[1].tolist() == [1, 0, 0, 0] and i[1].tolist() == [0, 0, 0, 0]
    # a path 0-1-2-3-4 with ends fixed: harmonic = linear interpolation
    F = np.array([[0, 1, 1], [1, 2, 2], [2, 3, 3], [3, 4, 4]])
    Lap = SW.uniform_laplacian(F, 5)
    X = np.zeros((5, 1))
    X[4] = 1
    out = SW.inpaint(X, np.array([1, 0, 0, 0, 1], bool), Lap)
    assert np.allclose(out[:, 0], [0, 0.25, 0.5, 0.75, 1], atol=1e-6)


def tube(radius: float, x0: float, x1: float, n_around: int, n_along: int) -> tuple[np.ndarray, np.ndarray]:
    """A cylinder around the x axis (no caps)."""
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    x = np.linspace(x0, x1, n_along)
    V = np.stack([np.repeat(x, n_around), np.tile(radius * np.cos(a), n_along), np.tile(radius * np.sin(a), n_along)], 1)
    idx = np.arange(n_along * n_around).reshape(n_along, n_around)
    nxt = np.roll(idx, -1, axis=1)
    F = np.concatenate([np.stack([idx[:-1].ravel(), nxt[:-1].ravel(), nxt[1:].ravel()], 1),
                        np.stack([idx[:-1].ravel(), nxt[1:].ravel(), idx[1:].ravel()], 1)])
    return V, F


def elbow_bend(degrees: float, elbow: float) -> np.ndarray:
    """Bone transforms (2, 4, 4): bone 0 (upper arm) still, bone 1 (forearm) turned about z at x = elbow."""
    R = L.axis_angle_to_matrix(np.array([0.0, 0.0, np.radians(degrees)]))
    T = np.tile(np.eye(4), (2, 1, 1))
    T[1, :3, :3] = R
    T[1, :3, 3] = np.array([elbow, 0, 0]) - R @ np.array([elbow, 0, 0])
    return T


def test_sleeve_on_a_two_bone_arm_stretches_less_than_nearest_vertex() -> None:
    # an arm: a coarse tube (2 cm rings) whose weights step from bone 0 to bone 1 at the elbow;
    # a sleeve: a fine tube (5 mm rings) 1 cm off it (every vertex reliable); elbow bent 60 degrees
    from scipy.spatial import cKDTree

    B, BF = tube(0.05, 0.0, 0.6, 24, 31)
    step = (B[:, 0] > 0.3).astype(np.float64)
    idx, Wb = np.tile([0, 1], (len(B), 1)), np.stack([1 - step, step], 1)
    G, GF = tube(0.06, 0.02, 0.58, 48, 113)
    T = elbow_bend(60.0, 0.3)[None]
    e = mesh_edges(GF)
    p = lambda i, w: np.percentile(SW.pose_stretch(G, e, T, i, w), 99.9)  # noqa: E731
    near = cKDTree(B).query(G)[1]
    assert p(idx[near], Wb[near]) > 5.0  # the nearest vertex copies the step: the sleeve tears
    assert np.percentile(SW.pose_stretch(B, mesh_edges(BF), T, idx, Wb), 99.9) > 3.0  # so does the arm
    i0, w0 = SW.transfer_skin_weights(G, GF, B, BF, idx, Wb, 2)  # jump released, inpainted
    assert p(i0, w0) < 2.0
    i1, w1 = SW.transfer_skin_weights(G, GF, B, BF, idx, Wb, 2, test_transforms=T)  # + released where it stretches
    assert p(i1, w1) < 1.5 and p(i1, w1) < p(i0, w0)
    assert np.allclose(w1.sum(1), 1, atol=1e-6)
    # far from the elbow the sleeve still follows its bone
    assert (i1[G[:, 0] < 0.1, 0] == 0).all() and (i1[G[:, 0] > 0.5, 0] == 1).all()
    assert (w1[G[:, 0] < 0.1, 0] > 0.99).all() and (w1[G[:, 0] > 0.5, 0] > 0.99).all()


def test_metric_laplacian_is_the_squared_gradient_energy() -> None:
    V, F = grid(4, 3, size=0.2)
    V[:, 0] *= np.linspace(0.5, 1.5, len(V))  # uneven edges
    W = np.random.default_rng(0).random((len(V), 2))
    e = mesh_edges(F)
    want = sum(np.sum((W[a] - W[b]) ** 2) / np.sum((V[a] - V[b]) ** 2) for a, b in e)
    Lap = SW.metric_laplacian(V, F)
    assert np.isclose(np.trace(W.T @ (Lap @ W)), want)


@pytest.fixture(scope="module")
def skirt(model):
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    g = D.make_demo_garments(model)["skirt"]
    basis = T.build_garment_basis(model, np.stack([g.fit(model, E) for E in EX]), g.faces, ex)
    return basis


def test_skirt_does_not_tear_in_walking_step(model, skirt) -> None:
    X = model.mean
    body = T.customer_body(model, np.zeros(model.n_components))
    v, _ = T.try_on(skirt, body)
    pose = P.preset_poses(model, X)["walking"]
    G = model.forward(pose=pose, vertices=X).transforms
    near = skirt.binding[:, 0]
    before = P.edge_stretch(v, L.skin(v, G, model.lbs_indices[near], model.lbs_weights[near]), skirt.faces)
    after = P.edge_stretch(v, L.skin(v, G, skirt.skin_idx, skirt.skin_w), skirt.faces)
    assert np.percentile(before, 99.9) > 4.0  # nearest-vertex weights tear it
    # 1.51 with the left/right ramp below the crotch (the cloth between the parted legs stretches
    # instead of the forward thigh coming through the front; 1.39 without it)
    assert np.percentile(after, 99.9) < 1.6
    assert skirt.skin_idx.shape == (skirt.n_vertices, 4) and np.allclose(skirt.skin_w.sum(1), 1, atol=1e-5)


def test_leg_ramp_splits_the_legs_by_side_below_the_crotch(model) -> None:
    """Step 4 on hand-made weights: below the crotch a vertex left of the ramp follows the left
    leg only, one on the midplane half and half, the pelvis share untouched; above the crotch
    nothing changes; a wider ramp (skirts) blends further out; the enclosure depth is where a
    garment's edges cross the midplane."""
    nb = model.n_body_vertices
    legs = SW.leg_frame(model.mean[:nb], model.joints(model.mean), list(BONES))
    assert 0.7 < legs.crotch < 0.9 and legs.lateral[0] > 0.99
    J = len(BONES)
    th_l, th_r, pelvis = BONES.index("thigh_l"), BONES.index("thigh_r"), BONES.index("pelvis")
    y = legs.crotch / legs.up[1]
    X = np.array([[0.1, y - 0.2, 0.1], [0.0, y - 0.2, 0.1], [-0.1, y - 0.2, 0.1], [0.1, y + 0.1, 0.1]])
    W = np.zeros((4, J))
    W[:, th_l], W[:, th_r], W[:, pelvis] = 0.2, 0.6, 0.2
    out = SW.leg_ramp(X, W, legs)
    assert np.allclose(out.sum(1), 1) and np.allclose(out[:, pelvis], 0.2)
    assert np.allclose(out[0, [th_l, th_r]], [0.8, 0.0]) and np.allclose(out[2, [th_l, th_r]], [0.0, 0.8])
    assert np.allclose(out[1, [th_l, th_r]], [0.4, 0.4]) and np.allclose(out[3], W[3])
    assert abs(SW.enclosure_depth(X, np.array([[0, 2, 3]]), legs) - 0.2 * legs.up[1]) < 0.02  # crosses the midplane
    assert SW.enclosure_depth(X, np.array([[0, 1, 3]]), legs) == 0.0  # the left side only (s = 0 counts as left)
    wide = SW.leg_ramp(X, W, legs, widening=1.0)  # half width 0.03 + 0.2 at the vertices below
    assert 0.4 < wide[0, th_l] < 0.8 and 0.0 < wide[0, th_r] < 0.4


def test_screened_inpainting_matches_the_dense_minimiser() -> None:
    """``inpaint(..., screening=s)`` solves min tr(W^T L W) + s d sum_u |W_u - W0_u|^2 over the
    unknown rows (d the mean diagonal of L): checked against the normal equations solved dense
    on a 6-vertex path, and between the two limits (s = 0: the harmonic interpolation; large s:
    the closest-point matches W0 themselves)."""
    F = np.array([[i, i + 1, i + 1] for i in range(5)])
    Lap = SW.uniform_laplacian(F, 6).toarray()
    W = np.array([[1.0, 0.0], [0.2, 0.8], [0.1, 0.9], [0.0, 1.0], [0.5, 0.5], [0.0, 1.0]])  # rows 1-4: W0
    known = np.array([1, 0, 0, 0, 0, 1], bool)
    u, k = np.flatnonzero(~known), np.flatnonzero(known)
    d = np.abs(np.diag(Lap)).mean()
    for s in (0.0, 0.05, 0.5):
        got = SW.inpaint(W, known, Lap, screening=s)
        A = Lap[np.ix_(u, u)] + s * d * np.eye(len(u))
        ref = np.linalg.solve(A, -Lap[np.ix_(u, k)] @ W[k] + s * d * W[u])
        assert np.allclose(got[u], ref, atol=1e-6) and np.array_equal(got[k], W[k]), s
    harmonic = SW.inpaint(W, known, Lap)
    assert np.allclose(harmonic[:, 0], [1, 0.8, 0.6, 0.4, 0.2, 0], atol=1e-6)
    assert np.allclose(SW.inpaint(W, known, Lap, screening=1e6)[u], W[u], atol=1e-4)


def test_a_loose_jackets_front_does_not_follow_the_arms(model) -> None:
    """The casual jacket hangs 3-4 cm off the torso, so few of its torso vertices have a
    reliable closest-point match, and plain inpainting spread the sleeves' arm weight over its
    front (0.17 on average over the cloth whose closest body point has no arm weight): in the
    page's arms-down pose its hem rose with the arms and the trunks under it, skinned like it,
    were pulled into the thighs. Screened inpainting (``SW.SCREENING``) keeps that cloth on the
    torso's bones."""
    old, new = _catalogue_basis_without(model, "casual-jacket", "SKIN_SCREENING")
    nb = model.n_body_vertices
    arm = [i for i, n in enumerate(BONES) if n.startswith(("upper_arm", "forearm", "hand"))]
    Wb = SW.dense_weights(model.lbs_indices[:nb], model.lbs_weights[:nb], len(BONES))
    g = np.asarray(new.g, np.float64)
    Wcp = SW._closest_point_match(g, np.asarray(new.faces, np.int64), model.mean[:nb], model.body_faces, Wb,
                                  SW.MAX_DISTANCE, SW.MAX_ANGLE_DEG)[0]
    torso = Wcp[:, arm].sum(1) < 0.02

    def arm_weight(b):
        W = np.zeros((b.n_vertices, len(BONES)))
        np.add.at(W, (np.arange(b.n_vertices)[:, None], np.asarray(b.skin_idx)), np.asarray(b.skin_w))
        return W[torso][:, arm].sum(1)

    before, after = arm_weight(old), arm_weight(new)
    print("torso cloth arm weight, mean / > 0.1:", before.mean(), (before > 0.1).sum(), after.mean(), (after > 0.1).sum())
    assert torso.sum() > 500 and before.mean() > 0.1, before.mean()
    assert after.mean() < 0.04 and (after > 0.1).sum() < 0.1 * torso.sum(), (after.mean(), (after > 0.1).sum())


def _catalogue_basis_without(model, garment_id: str, switch: str | tuple[str, ...]):
    """A catalogue garment's basis built with the ``tryon`` skinning switch ``switch`` (or each
    of several) off, and with them as they are: (old, new)."""
    from service.model.garments.catalogue import load_catalogue

    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    it = {i.id: i for i in load_catalogue().garments()}[garment_id]
    fits = np.stack([it.fit_to(E) for E in EX])
    switches = (switch,) if isinstance(switch, str) else switch
    keep = {k: getattr(T, k) for k in switches}
    try:
        for k in switches:
            setattr(T, k, False)
        old = T.build_garment_basis(model, fits, it.faces, ex)
    finally:
        for k, v in keep.items():
            setattr(T, k, v)
    return old, T.build_garment_basis(model, fits, it.faces, ex)


@pytest.fixture(scope="module")
def pencil_skirt(model):
    return _catalogue_basis_without(model, "pencil-skirt", ("SKIN_LEG_RAMP", "SKIN_SCREENING"))


def test_pencil_skirt_stays_closed_in_the_walking_step(model, pencil_skirt) -> None:
    """Issue 11 (a): on the 160 cm / 55 kg woman in the page's walking step the pencil skirt's
    front opened over the forward thigh (the inpainted weights mixed the thighs over the thighs
    themselves): the body showed through at 3.9 % of the body vertices under it (outside the
    skirt, the skirt's rest points followed through the pose). With the left/right ramp below
    the crotch 0.0 %; and no edge of it tears (largest stretch 1.67; the pose correctives'
    strain limiting brings it to 1.4)."""
    from tests.bench.tryon import covered_points, show_through

    X = S.avatar_from_measurements(model, FIVE_BODIES["160/55 woman"]).vertices
    body = T.customer_body(model, model.project(X))
    nb = model.n_body_vertices
    rest = body.vertices[:nb].astype(np.float64)
    posed = model.forward(pose=P.preset_poses(model, body.vertices)["walking"], vertices=body.vertices)
    pb = posed.vertices[:nb].astype(np.float64)
    pn = vertex_normals(pb, model.body_faces).astype(np.float64)
    share = []
    for basis in pencil_skirt:
        v = T.try_on(basis, body)[0].astype(np.float64)
        pv = L.skin(v, posed.transforms, basis.skin_idx, basis.skin_w)
        share.append(show_through(covered_points(rest, model.body_faces, v, basis.faces), pv, basis.faces, pb, pn))
        stretch = P.edge_stretch(v, pv, basis.faces)
    assert share[0] > SHOW_THROUGH_TORN  # the measure sees the slit of the previous weights
    assert share[1] < SHOW_THROUGH_CLOSED, share
    assert stretch.max() < 1.7  # 1.57 before the screening (skin_weights.SCREENING), 1.67 with it


@pytest.fixture(scope="module")
def cropped_tee(model):
    """The catalogue's cropped tee without and with the limb-side release (``T.SKIN_LIMB_SIDE``)."""
    return _catalogue_basis_without(model, "cropped-tee", "SKIN_LIMB_SIDE")


@pytest.mark.slow
def test_cropped_tee_armpits_stretch_less_in_hands_on_hips(model, cropped_tee) -> None:
    """Issue 11 (b): on the 165 cm / 105 kg woman in the page's hands-on-hips pose (adapted to
    her) the cropped tee's armpit seams stretched 5.2x (p99.9 of its edges): a seam vertex with
    no reliable match sat between a sleeve vertex pinned to the arm and a torso vertex pinned to
    the torso. Releasing the sleeve's side (``skin_weights.release_limb_side``): 3.3x, with
    about as much of the tee inside her posed body over the four poses (vertices > 3 mm inside:
    1.40 -> 1.56 %; an earlier ramp giving the torso side arm weight pushed the five bodies'
    1.3 % to 6.6 %)."""
    from scipy.spatial import cKDTree

    from service.model.geometry.mesh import vertex_faces
    from tests.bench.tryon import INSIDE_DEPTH, penetration_depths

    X = S.avatar_from_measurements(model, FIVE_BODIES["165/105 woman"]).vertices
    body = T.customer_body(model, model.project(X))
    nb = model.n_body_vertices
    vf = vertex_faces(model.body_faces, nb)
    stretch, inside = np.ones(2), np.zeros(2)
    for name, pose in P.adapted_poses(model, body.vertices).items():
        posed = model.forward(pose=pose, vertices=body.vertices)
        pb = posed.vertices[:nb].astype(np.float64)
        tree = cKDTree(pb)
        for i, basis in enumerate(cropped_tee):
            v = T.try_on(basis, body)[0].astype(np.float64)
            pv = L.skin(v, posed.transforms, basis.skin_idx, basis.skin_w)
            if name == "hands-on-hips":
                stretch[i] = np.percentile(P.edge_stretch(v, pv, basis.faces), 99.9)
            inside[i] += np.mean(penetration_depths(pv, pb, model.body_faces, tree, vf) > INSIDE_DEPTH) / 4
    assert stretch[0] > 4.5  # the torn armpit seam of the previous weights
    assert stretch[1] < 3.8, stretch
    assert inside[1] < inside[0] + 0.003, inside


def test_stale_skin_weights_are_recomputed(model, pencil_skirt) -> None:
    """A basis stored by an older service (skinning version 1: no leg ramp) gets the current
    weights (``refresh_skinning``, from the basis's own example fits) and a new ETag; a current
    one is left alone."""
    old, new = pencil_skirt
    assert new.meta["skinning"] == T.SKINNING_VERSION and T.refresh_skinning(model, new) is None
    stale = T.GarmentBasis(g=old.g, B=old.B, faces=old.faces, binding=old.binding, skin_idx=old.skin_idx,
                           skin_w=old.skin_w, gn=old.gn, Bn=old.Bn, meta={**old.meta, "skinning": 1})
    fresh = T.refresh_skinning(model, stale)
    assert fresh is not None and fresh.meta["skinning"] == T.SKINNING_VERSION and fresh.etag() != old.etag()

    def dense(b):
        W = np.zeros((b.n_vertices, len(model.bone_parents)))
        np.add.at(W, (np.arange(b.n_vertices)[:, None], np.asarray(b.skin_idx)), np.asarray(b.skin_w))
        return W

    assert np.abs(dense(fresh) - dense(new)).max() < 0.02  # as if built today
    assert np.abs(dense(stale) - dense(new)).max() > 0.2  # (the stale weights were not)


def test_stale_garment_served_with_current_weights(client: TestClient, model, pencil_skirt) -> None:
    """Through the API: a stored garment whose basis has version-1 weights is refreshed when it
    is first tried on (files and record ETag rewritten once), and its try-on carries the new weights."""
    from service.model.formats.gltf_read import read_glb

    ctx = client.app.state.context
    old, new = pencil_skirt
    rec = next(g for g in ctx.garments.repo.list() if g.catalogue_id == "pencil-skirt")
    stale = T.GarmentBasis(g=old.g, B=old.B, faces=old.faces, binding=old.binding, skin_idx=old.skin_idx,
                           skin_w=old.skin_w, gn=old.gn, Bn=old.Bn, meta={**old.meta, "skinning": 1, "etag": "stale"})
    stale.render_vertex, stale.render_uv, stale.render_faces = new.render_vertex, new.render_uv, new.render_faces
    ctx.garments.bases.save(rec.id, stale)
    ctx.garments.repo.put(rec.model_copy(update={"etag": "stale"}))
    c = client.post("/v1/customers", json={"measurements": {"gender": "female"}}).json()
    r = client.get(f"/v1/customers/{c['id']}/garments/{rec.id}.glb", headers={"Authorization": f"Bearer {c['token']}"})
    assert r.status_code == 200, r.text
    after = ctx.garments.repo.get(rec.id)
    assert after.etag not in ("stale", "") and T.GarmentBasis.load(ctx.garments.bases.path(rec.id)).meta["skinning"] == T.SKINNING_VERSION
    served = read_glb(r.content)
    assert served["json"]["skins"]  # skinned, with the refreshed weights (checked on the stored basis above)
    assert ctx.garments.require_ready(after, rec.id)[0].etag == after.etag  # no second refresh


# -- poses -------------------------------------------------------------------------------------------
def test_presets_point_segments_at_targets(model) -> None:
    spec = P.presets()
    assert set(spec["poses"]) == {"a-pose", "arms-down", "walking", "hands-on-hips"}
    X = model.mean
    for name, pose in P.preset_poses(model, X).items():
        posed = model.forward(pose=pose, vertices=X)
        for bone, d in P.targets(spec["poses"][name]).items():
            seg = posed.joints[BONES.index(spec["child"][bone])] - posed.joints[BONES.index(bone)]
            assert np.degrees(np.arccos(np.clip(seg @ d / np.linalg.norm(seg), -1, 1))) < 0.01, (name, bone)
        if name == "a-pose":
            assert np.allclose(pose, 0)


@pytest.mark.slow
@pytest.mark.parametrize("body", list(FIVE_BODIES))
def test_adapted_poses_keep_arms_out_of_the_torso(model, body) -> None:
    X = S.avatar_from_measurements(model, FIVE_BODIES[body]).vertices
    poses = P.adapted_poses(model, X)
    for name, pose in poses.items():
        posed = model.forward(pose=pose, vertices=X).vertices
        for side in "lr":
            pts = P.arm_points(model, X, side)[::5]  # exhaustive winding numbers on every 5th arm vertex
            inside = P.arm_vertices_inside(model, posed, pts, side, exhaustive=True)
            assert len(inside) == 0, (body, name, side, len(inside))


@pytest.mark.slow
@pytest.mark.parametrize("body", ["165/105 woman", "200/130 man"])
def test_the_fast_arm_check_agrees_with_the_exhaustive_one(model, body) -> None:
    """``arm_vertices_inside`` without ``exhaustive`` (arm points near the torso searched,
    deepest first, stopping at the first confirmed batch) finds an arm vertex inside the torso
    or thighs exactly when the exhaustive winding-number check over the same points does, for
    every page pose at the extra abductions the adaptation tries (colliding and not)."""
    X = S.avatar_from_measurements(model, FIVE_BODIES[body]).vertices
    spec = P.presets()
    J = model.joints(X)
    outcomes = set()
    for name, p in spec["poses"].items():
        for side in "lr":
            pts = P.arm_points(model, X, side)[::3]
            for extra in (0.0, 6.0, 12.0, 30.0):
                tg = P.abducted(P.targets(p), side, extra)
                pose = P.pose_from_directions(J, model.bone_parents, tg, spec["order"], spec["child"])
                posed = model.forward(pose=pose, vertices=X).vertices
                fast = P.arm_vertices_inside(model, posed, pts, side)
                slow = P.arm_vertices_inside(model, posed, pts, side, exhaustive=True)
                assert (len(fast) > 0) == (len(slow) > 0), (body, name, side, extra, len(fast), len(slow))
                assert set(fast) <= set(slow)
                outcomes.add(len(slow) > 0)
    assert outcomes == {True, False}  # both kinds of case were checked


@pytest.mark.slow
def test_the_estimated_arm_inside_share_follows_the_exhaustive_one(model) -> None:
    """``arm_inside_share`` (candidates near the torso, a sample of them confirmed by winding
    number) against the exhaustive winding-number share over the same arm points, on a heavy
    body with the left arm swung down and across into the torso by 0-100 degrees and the
    forearm bent into the hip: within 0.05 of it (measured within 0.01), 0 when the arm is out,
    and growing while the arm goes in (at 100 degrees it comes out through the other side)."""
    from service.model.body.lbs import matrix_to_axis_angle

    X = S.avatar_from_measurements(model, FIVE_BODIES["165/105 woman"]).vertices
    pts = P.arm_points(model, X, "l")
    up, fore = BONES.index("upper_arm_l"), BONES.index("forearm_l")
    shares = []
    for deg in (0.0, 40.0, 70.0, 100.0):
        pose = np.zeros((len(BONES), 3))
        pose[up] = np.radians([0.0, 0.0, -deg])  # adduction: the arm down and into the torso
        pose[fore] = matrix_to_axis_angle(L.axis_angle_to_matrix(np.radians([0.0, 0.0, -0.5 * deg])[None]))[0]
        posed = model.forward(pose=pose, vertices=X).vertices
        est = P.arm_inside_share(model, posed, pts, "l")
        exact = len(P.arm_vertices_inside(model, posed, pts, "l", exhaustive=True)) / len(pts)
        assert abs(est - exact) < 0.05, (deg, est, exact)
        assert P.arm_inside_share(model, posed, P.arm_points(model, X, "r"), "r") == 0.0  # the other arm out
        shares.append(est)
    assert shares[0] == 0.0 and shares[1] > 0.05 and shares[2] > shares[1] + 0.03, shares


# -- layering ----------------------------------------------------------------------------------------
def cylinder(radius, y0, y1, n_around=40, n_up=20):
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    y = np.linspace(y0, y1, n_up)
    if callable(radius):
        r = radius(y)[:, None]
    else:
        r = np.full((n_up, 1), radius)
    V = np.stack([(r * np.cos(a)).ravel(), np.repeat(y, n_around), (r * np.sin(a)).ravel()], 1)
    idx = np.arange(n_up * n_around).reshape(n_up, n_around)
    nxt = np.roll(idx, -1, axis=1)
    F = np.concatenate([np.stack([idx[:-1].ravel(), nxt[:-1].ravel(), nxt[1:].ravel()], 1),
                        np.stack([idx[:-1].ravel(), nxt[1:].ravel(), idx[1:].ravel()], 1)])
    return V, F


def test_push_inside_only_where_covered() -> None:
    body, _ = cylinder(0.10, -0.5, 0.5, 60, 40)
    bn = body * np.array([1, 0, 1])
    bn /= np.linalg.norm(bn, axis=1, keepdims=True)
    outer, OF = cylinder(0.13, 0.0, 0.4)  # a "T-shirt" from y = 0 up
    inner, IF = cylinder(lambda y: 0.12 + 0.03 * np.exp(-((y - 0.05) / 0.05) ** 2), -0.4, 0.2, 40, 61)  # a "waistband" bulge
    out = LY.push_inside(inner, IF, outer, OF, body, bn)
    r_in, r_out = np.linalg.norm(inner[:, [0, 2]], axis=1), np.linalg.norm(out[:, [0, 2]], axis=1)
    covered = (inner[:, 1] > 0.02) & (inner[:, 1] < 0.38)
    assert (r_out[covered] <= 0.13 - LY.GAP + 2e-4).all()
    far = inner[:, 1] < -0.2  # nowhere near the outer garment: untouched
    assert np.allclose(r_out[far], r_in[far], atol=5e-4)
    # smooth: neighbours along a column move by similar amounts
    moved = (r_in - r_out).reshape(-1, 40)[:, 0]
    assert np.abs(np.diff(moved)).max() < 0.015
    both, outside = LY.inner_outside_share(out, outer, OF, IF, body, bn, None)
    assert both > 0 and outside == 0
    _, outside0 = LY.inner_outside_share(inner, outer, OF, IF, body, bn, None)
    assert outside0 > 0


def _grid(n: int, size: float, z: float, x0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """A flat n x n grid of side ``size`` at height z (vertices (n*n, 3), faces facing +z)."""
    t = np.linspace(0, size, n)
    X, Y = np.meshgrid(t + x0, t, indexing="ij")
    V = np.stack([X.ravel(), Y.ravel(), np.full(n * n, z)], 1)
    i = np.arange(n * n).reshape(n, n)
    F = np.concatenate([np.stack([i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()], 1),
                        np.stack([i[:-1, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()], 1)])
    return V, F


def test_the_layering_figure_leaves_out_a_hand_resting_on_the_clothes() -> None:
    """A "hip" of skin (joint 0) under two sheets of cloth that move with it, the inner one
    inside, and a "hand" (joint 1) resting on the outer sheet, palm down: seen from the palm the
    inner sheet is farther out than the outer one, so without the skin test the hand counts as
    covered by both with the inner one outside; with it, neither sheet covers the hand."""
    hip, _ = _grid(11, 0.2, 0.0)
    hand, _ = _grid(5, 0.06, 0.03, x0=0.07)
    body = np.concatenate([hip, hand])
    bn = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(hip), 1)), np.tile([0.0, 0.0, -1.0], (len(hand), 1))])
    inner, IF = _grid(21, 0.24, 0.006)
    outer, OF = _grid(21, 0.24, 0.012)
    inner -= [0.02, 0.02, 0.0]
    outer -= [0.02, 0.02, 0.0]

    def skin(n: int, joint: int) -> tuple[np.ndarray, np.ndarray]:
        idx = np.zeros((n, 2), np.int64)
        idx[:, 0] = joint
        return idx, np.tile([1.0, 0.0], (n, 1))

    body_skin = tuple(np.concatenate(p) for p in zip(skin(len(hip), 0), skin(len(hand), 1)))
    skins = (body_skin, skin(len(inner), 0), skin(len(outer), 0))
    both, outside = LY.inner_outside_share(inner, outer, OF, IF, body, bn, None)
    assert both == len(body) and outside == len(hand)  # the hand counted against the layering
    both, outside = LY.inner_outside_share(inner, outer, OF, IF, body, bn, None, skins=skins)
    assert both == len(hip) and outside == 0
    # cloth that moves with the hip and is in the wrong order there still counts
    both, outside = LY.inner_outside_share(outer, inner, IF, OF, body, bn, None, skins=skins)
    assert both == len(hip) and outside == len(hip)
    # a garment weighted partly (>= MOVES_WITH) on the hand's joint covers it
    def partly_on_the_hand(n: int) -> tuple[np.ndarray, np.ndarray]:
        return np.tile([0, 1], (n, 1)), np.tile([1 - LY.MOVES_WITH, LY.MOVES_WITH], (n, 1))

    half, outer_half = partly_on_the_hand(len(inner)), partly_on_the_hand(len(outer))
    both, outside = LY.inner_outside_share(inner, outer, OF, IF, body, bn, None, skins=(body_skin, half, outer_half))
    assert both == len(body) and outside == len(hand)


@pytest.fixture(scope="module")
def shirt_and_jacket(model):
    """The catalogue's striped shirt (layer 2) and casual jacket (layer 3) as clothing bases with
    their records, inner first."""
    from service.model.garments.catalogue import load_catalogue
    from service.records import Garment

    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    cat = load_catalogue()
    out = []
    for gid in ("striped-shirt", "casual-jacket"):
        it = cat.items[gid]
        basis = T.build_garment_basis(model, np.stack([it.fit_to(E) for E in EX]), it.faces, ex)
        out.append((Garment(id=gid, body_model=model.version, owner="test", name=gid, source="demo",
                            color=[0.5, 0.5, 0.5, 1.0], layer=it.layer), basis))
    return out


@pytest.mark.slow
def test_outfit_keeps_the_shirt_inside_the_jacket(model, shirt_and_jacket) -> None:
    """``outfit.glb`` on a held-out body, shirt under open jacket: of the body vertices covered
    by both, few have the shirt outside the jacket, in the rest pose and once the GLB's meshes
    are skinned (their own joints and weights, as the browser does) into the page's walking and
    hands-on-hips poses (the covered points followed through the pose: ``layering.posed_outside``).
    Held-out body 3, shirt outside by more than 2 mm: rest 64 -> 3 of ~2,200; walking 249 ->
    33, hands on hips 120 -> 28, before -> after the rim checks (``layering.violations``,
    ``layering.rim_violations``) and skinning the shirt like the jacket where covered
    (``layering.covered_skin``)."""
    from service.application import scenes
    from service.model.formats.gltf_read import read_glb
    from tests.bench.common import heldout_avatars

    nb = model.n_body_vertices
    body = T.customer_body(model, model.project(heldout_avatars(model)[3]))
    meshes = {m["name"]: m for m in read_glb(scenes.outfit_glb(model, body, shirt_and_jacket, None))["meshes"]}
    shirt, jacket = meshes["striped-shirt"], meshes["casual-jacket"]
    Bv, Bn = body.vertices[:nb].astype(np.float64), body.normals.astype(np.float64)
    pairs = LY.layered_pairs(shirt["positions"], shirt["indices"], jacket["positions"], jacket["indices"], Bv, Bn)
    both = len(pairs[0])
    assert both > 1000  # the jacket covers the shirt's body and sleeves
    rest = LY.posed_outside(pairs, shirt["positions"], shirt["indices"], jacket["positions"], jacket["indices"],
                            Bv, Bn, tolerance=OUTSIDE_TOLERANCE)
    poses = P.preset_poses(model, body.vertices)
    posed = []
    for name in ("walking", "hands-on-hips"):
        G = model.forward(pose=poses[name], vertices=body.vertices).transforms
        PB = L.skin(Bv, G, model.lbs_indices[:nb], model.lbs_weights[:nb])
        PN = vertex_normals(PB, model.body_faces).astype(np.float64)
        s, j = (L.skin(m["positions"], G, m["joints"], m["weights"]) for m in (shirt, jacket))
        posed.append(LY.posed_outside(pairs, s, shirt["indices"], j, jacket["indices"], PB, PN,
                                      tolerance=OUTSIDE_TOLERANCE))
    print(f"shirt outside the jacket by > {OUTSIDE_TOLERANCE * 1000:.0f} mm: rest {rest} of {both}, posed {posed}")
    assert rest <= 0.01 * both, rest  # 0.029 * both before
    assert max(posed) <= 0.03 * both, posed  # 0.11 * both before (goal 1 %: not met yet, see README)


OUTSIDE_TOLERANCE = 0.002  # metres: the shirt showing through the jacket by more than this


# -- the route -----------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    from service.app import create_app
    from service.settings import Settings
    from tests.harness import redis_db, redis_url

    with redis_db() as db:
        settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("poses"), REDIS_URL=redis_url(db),
                            TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="pencil-skirt")
        with TestClient(create_app(settings), raise_server_exceptions=True) as c:
            yield c


def test_poses_route(client: TestClient) -> None:
    c = client.post("/v1/customers", json={"measurements": {"gender": "female", "height_cm": 165,
                                                             "weight_kg": 105}}).json()
    assert client.get(f"/v1/customers/{c['id']}/poses").status_code == 404  # no token
    assert client.get("/v1/customers/nope/poses", headers={"Authorization": f"Bearer {c['token']}"}).status_code == 404
    r = client.get(f"/v1/customers/{c['id']}/poses", headers={"Authorization": f"Bearer {c['token']}"})
    assert r.status_code == 200
    poses = r.json()
    assert set(poses) == {"a-pose", "arms-down", "walking", "hands-on-hips"}
    assert all(set(p) == set(BONES) and all(len(v) == 3 for v in p.values()) for p in poses.values())
    # a heavy body: arms down needs more abduction than the preset's direction
    arm = np.array(poses["arms-down"]["upper_arm_l"])
    assert np.linalg.norm(arm) > 0


@pytest.mark.slow
def test_adapted_poses_are_computed_once_for_every_process(client: TestClient, monkeypatch) -> None:
    """The poses' adaptation (~0.5 s of CPU per body) runs once per body for the whole service:
    its result is stored (a process with an empty LRU -- another server process, or this one
    after a restart -- reads it), concurrent first requests compute it once (a cross-process
    lock), a malformed stored entry is computed again, and deleting the customer drops it."""
    import json
    import threading

    from service.application import poses as AP

    ctx = client.app.state.context
    calls = []
    real = AP.adapted_poses

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(AP, "adapted_poses", counted)
    c = client.post("/v1/customers", json={"measurements": {"gender": "male", "height_cm": 178,
                                                             "weight_kg": 92}}).json()
    auth = {"Authorization": f"Bearer {c['token']}"}
    record = ctx.customers.repo.get(c["id"])
    key = AP.store_key(ctx.customers.repo.prefix, ctx.model.version, record.weights)
    conn = ctx.customers.repo.conn

    def other_process() -> None:
        AP._cache.clear()  # what another server process (or a restarted one) has in memory

    other_process()
    first = client.get(f"/v1/customers/{c['id']}/poses", headers=auth).json()
    assert len(calls) == 1
    assert json.loads(conn.get(key)) == first and 0 < conn.ttl(key) <= AP.POSES_TTL_S
    other_process()
    assert client.get(f"/v1/customers/{c['id']}/poses", headers=auth).json() == first
    assert len(calls) == 1  # read from the store, the same values

    # concurrent first requests in two "processes" (threads with no LRU hit): computed once
    conn.delete(key)
    other_process()
    got: list = []
    threads = [threading.Thread(target=lambda: got.append(ctx.poses.record_poses(record))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(calls) == 2 and got == [first, first]

    # a malformed entry is not served: computed again and replaced
    for bad in (b"{not json", json.dumps({"walking": {"pelvis": [0.0, 0.0]}}).encode()):
        conn.set(key, bad)
        other_process()
        assert client.get(f"/v1/customers/{c['id']}/poses", headers=auth).json() == first
        assert json.loads(conn.get(key)) == first
    assert len(calls) == 4

    assert client.delete(f"/v1/customers/{c['id']}", headers=auth).status_code == 204
    assert conn.get(key) is None


# -- step 6: the legs' weights refined in strides -------------------------------------------------------
@pytest.fixture(scope="module")
def mens_jeans(model):
    """The catalogue's men's jeans without and with the refinement in strides (``T.SKIN_STRIDES``)."""
    return _catalogue_basis_without(model, "mens-jeans", "SKIN_STRIDES")


def test_stride_operators_match_skinning(model, mens_jeans) -> None:
    """The linear operators the refinement solves with, checked against LBS itself on other
    weights than those they were built from: the posed edge vectors (D w + fx), each refined
    vertex's height over its rest body point along the posed normal (Pn w + pfix) and each
    covered body vertex's garment point's height over it (Q w + qfix)."""
    from service.model.geometry.mesh import closest_points_on_mesh

    _, basis = mens_jeans
    nb = model.n_body_vertices
    case = T.stride_cases(model, basis.g, None)[0]
    W0 = SW.dense_weights(basis.skin_idx, basis.skin_w, len(BONES))
    legs = [BONES.index(b) for c in SW.LEG_BONES for b in c]
    act = np.flatnonzero(W0[:, legs].sum(1) >= SW.STRIDE_MIN_LEG_WEIGHT)
    joints = np.flatnonzero(W0[act].max(0) >= SW.STRIDE_MIN_LEG_WEIGHT)
    e = mesh_edges(basis.faces)
    faces = np.asarray(basis.faces, np.int64)
    terms = SW._stride_terms(case, faces, model.body_faces, W0, act, joints, e)
    rng = np.random.default_rng(3)
    W = W0.copy()
    W[np.ix_(act, joints)] = np.clip(W0[np.ix_(act, joints)] + 0.1 * rng.random((len(act), len(joints))), 0, None)
    w = W[np.ix_(act, joints)].ravel()
    X = np.asarray(basis.g, np.float64)
    f, _, bary = closest_points_on_mesh(X[act], case.body, model.body_faces)
    for t, G, pb in zip(terms, case.transforms, case.posed):
        idx = np.repeat(np.arange(len(BONES))[None], len(X), 0)
        x = L.skin(X, G, idx, W)  # every bone, these weights (rows need not sum to 1)
        assert np.allclose((t["D"] @ w).reshape(-1, 3) + t["fx"], x[e[:, 0]] - x[e[:, 1]], atol=1e-9)
        n = vertex_normals(pb, model.body_faces).astype(np.float64)
        q = np.einsum("mk,mkj->mj", bary, pb[model.body_faces[f]])
        nq = np.einsum("mk,mkj->mj", bary, n[model.body_faces[f]])
        nq /= np.linalg.norm(nq, axis=1, keepdims=True)
        assert np.allclose(t["Pn"] @ w + t["pfix"], np.einsum("ij,ij->i", x[act] - q, nq), atol=1e-9)
        assert t["Q"].shape[0] > 100  # the jeans cover the thighs
    assert nb == len(case.body)


def test_strides_keep_the_crotch_from_stretching_in_a_walking_step(model, mens_jeans) -> None:
    """Issue 43's walking step on the plain GLB: the men's jeans on the 165 cm / 105 kg woman
    (none of the bodies the refinement used) in the page's walking step and in the mirrored one
    (the other leg forward): the 99.9th-percentile edge stretch was 1.9 (the crotch's front)
    and is under 1.5 with the refined weights, and no slit opens: the covered skin showing
    through stays within half a point of before (0.85 -> 1.06 % and 0.99 -> 0.85 % when
    written; the pencil skirt's slit of issue 11 was 3.9 %)."""
    from tests.bench.tryon import covered_points, show_through

    old, new = mens_jeans
    X = S.avatar_from_measurements(model, FIVE_BODIES["165/105 woman"]).vertices
    body = T.customer_body(model, model.project(X))
    nb = model.n_body_vertices
    rest = body.vertices[:nb].astype(np.float64)
    poses = [P.preset_poses(model, body.vertices)["walking"], *P.stride_poses(model, body.vertices, (1.0,))[1:]]
    stretch, shown = {}, {}
    for name, basis in (("old", old), ("new", new)):
        v = T.try_on(basis, body)[0].astype(np.float64)
        cov = covered_points(rest, model.body_faces, v, basis.faces)
        for i, pose in enumerate(poses):
            posed = model.forward(pose=pose, vertices=body.vertices)
            pb = posed.vertices[:nb].astype(np.float64)
            pv = L.skin(v, posed.transforms, basis.skin_idx, basis.skin_w)
            stretch[name, i] = np.percentile(P.edge_stretch(v, pv, basis.faces), 99.9)
            shown[name, i] = show_through(cov, pv, basis.faces, pb, vertex_normals(pb, model.body_faces))
    assert max(stretch["old", i] for i in range(2)) > 1.8, stretch
    assert max(stretch["new", i] for i in range(2)) < 1.5, stretch
    for i in range(2):
        assert shown["new", i] <= shown["old", i] + 0.005, shown
    assert np.allclose(new.skin_w.sum(1), 1, atol=1e-5) and (new.skin_w >= 0).all()


def test_strides_leave_the_cloth_off_the_legs_alone(model) -> None:
    """The refinement changes only the weights of vertices with some weight on the leg bones (the
    demo T-shirt's hem over the hips), and its cases are the mean avatar and the population's
    four extremes, each in both strides at every amplitude."""
    ex = T.example_set(model)
    EX = T.example_vertices(model, ex)
    g = D.make_demo_garments(model)["tshirt"]
    fits = np.stack([g.fit(model, E) for E in EX]).astype(np.float64)
    idx, w = T._transferred_skin_weights(model, fits[0], g.faces, fits)
    W = SW.dense_weights(idx, w, len(BONES))
    legs = [BONES.index(b) for c in SW.LEG_BONES for b in c]
    off = W[:, legs].sum(1) < SW.STRIDE_MIN_LEG_WEIGHT
    assert 0 < off.sum() < len(W)
    W2 = SW.dense_weights(*T.garment_skin_weights(model, fits[0], g.faces, fits), len(BONES))
    assert np.allclose(W2[off], W[off], atol=1e-6) and np.abs(W2[~off] - W[~off]).max() > 0.01
    B = fits[1::2] - fits[2::2]
    cases = T.stride_cases(model, fits[0], B)
    assert len(cases) == 5 and all(c.transforms.shape[0] == 2 * len(T.STRIDE_AMPLITUDES) for c in cases)
    heights = [float(np.ptp(c.body[:, 1])) for c in cases]
    assert min(heights[1:]) < 1.55 < 1.85 < max(heights[1:])  # the smallest and the largest bodies


def test_stride_poses_are_the_walking_step_and_its_mirror(model) -> None:
    """At amplitude 1 the stride is the page's walking preset; its mirror puts the other leg
    forward as far; a shorter stride parts the knees less."""
    X = model.mean
    short, full, m_short, m_full = P.stride_poses(model, X, (0.5, 1.0))
    assert np.allclose(full, P.preset_poses(model, X)["walking"])
    knee_l, knee_r = BONES.index("shin_l"), BONES.index("shin_r")

    def knees_z(pose):
        j = model.forward(pose=pose, vertices=X).joints
        return j[knee_l, 2], j[knee_r, 2]

    (lz, rz), (mlz, mrz) = knees_z(full), knees_z(m_full)
    assert lz - rz > 0.15 and abs((lz - rz) - (mrz - mlz)) < 0.01  # left forward; mirrored, right as far
    sl, sr = knees_z(short)
    assert 0.2 * (lz - rz) < sl - sr < 0.8 * (lz - rz)

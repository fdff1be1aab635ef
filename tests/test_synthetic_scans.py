"""Synthetic clothed scans (``tests/bench/synthetic_scans.py``), the ground truth of
``tryon bench fitting``: hidden skin removed, frames and units as recorded, readable files,
determinism. Needs the MakeHuman garments of ``../shared/data`` (or ``TRYON_SHARED_DATA``)."""
from __future__ import annotations

import io

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from tests.bench.common import HELDOUT_AVATARS, shared_data_dir
from tests.bench.tryon import penetration_depths
from tests.bench.fitting import BodySurface
from service.model.fitting import rig as F_rig
from service.model.body.model import BONES
from service.model.body import measurements as M
from tests.bench import synthetic_scans as SS
from service.model.geometry.mesh import vertex_faces, vertex_normals

CLOTHES = shared_data_dir() / "makehuman_clothes"
pytestmark = [pytest.mark.slow, pytest.mark.skipif(not CLOTHES.is_dir(), reason=f"no MakeHuman garments at {CLOTHES}")]


@pytest.fixture(scope="module")
def person(model):
    """A held-out avatar's shape (projected on the PCA basis) and gender."""
    z = np.load(HELDOUT_AVATARS)
    i = int(np.flatnonzero(z["gender"] == "female")[0])
    X = model.mean.astype(np.float64) + z["offsets"][i].astype(np.float64) * float(z["scale"])
    return model.project(X), str(z["gender"][i])


@pytest.fixture(scope="module")
def scans(model, person):
    """The same person, pose and frame clothed and unclothed (noise-free meshes), and a noisy
    clothed point cloud."""
    w, g = person
    kw = dict(n_points=5000, clothes_dir=CLOTHES)
    return {
        "clothed": SS.make_scan(model, np.random.default_rng(5), w, g, clothed=True, point_cloud=False,
                                noise_mm=0.0, garments=["female_casualsuit01", "shoes01"], **kw),
        "naked": SS.make_scan(model, np.random.default_rng(5), w, g, clothed=False, point_cloud=False,
                              noise_mm=0.0, **kw),
        "cloud": SS.make_scan(model, np.random.default_rng(6), w, g, clothed=True, point_cloud=True, **kw),
    }


def test_same_person_pose_and_frame_with_and_without_clothes(scans):
    c, n = scans["clothed"], scans["naked"]
    np.testing.assert_array_equal(c.rotvecs, n.rotvecs)
    np.testing.assert_array_equal(c.to_model, n.to_model)
    np.testing.assert_array_equal(c.true_posed, n.true_posed)
    assert (c.unit, c.up, c.clothed, n.clothed) == (n.unit, n.up, True, False)
    assert c.garments == ["female_casualsuit01", "shoes01"] and n.garments == []
    assert set(M.ATTRIBUTES) <= set(c.measurements) and c.measurements["gender"] == "female"


def test_hidden_skin_is_removed_visible_skin_kept(model, scans):
    c, n = scans["clothed"], scans["naked"]
    assert n.point_is_body.all()
    # the suit covers torso and legs, the shoes the feet: most skin is gone
    assert c.point_is_body.sum() < 0.4 * n.point_is_body.sum()
    # ... but head and hands are still there
    P = c.points_in_model_frame()[c.point_is_body]
    head, hand_l, hand_r = (c.true_joints[BONES.index(b)] for b in ("head", "hand_l", "hand_r"))
    for j in (head, hand_l, hand_r):
        assert (np.linalg.norm(P - j, axis=1) < 0.12).sum() > 20
    # no skin under the shirt and the trousers: count skin points by their body vertex's
    # dominant bone
    nb = model.n_body_vertices
    dom = model.lbs_indices[np.arange(nb), np.argmax(model.lbs_weights[:nb], axis=1)]

    def per_bone(scan):
        _, nn = cKDTree(scan.true_posed[:nb]).query(scan.points_in_model_frame()[scan.point_is_body])
        return np.bincount(dom[nn], minlength=len(BONES))

    pc, pn = per_bone(c), per_bone(n)
    covered = [BONES.index(b) for b in ("pelvis", "spine", "thigh_l", "thigh_r", "shin_l", "shin_r")]
    assert pc[covered].sum() < 0.05 * pn[covered].sum()
    for b in ("head", "hand_l", "hand_r"):
        assert pc[BONES.index(b)] > 0.8 * pn[BONES.index(b)], b


def test_no_scan_point_deep_inside_the_true_body(model, scans):
    nb = model.n_body_vertices
    for key in ("clothed", "cloud"):
        s = scans[key]
        P = s.points_in_model_frame()
        idx = np.random.default_rng(0).choice(len(P), 250, replace=False)
        B = s.true_posed[:nb]
        depth = penetration_depths(P[idx], B, model.body_faces, cKDTree(B), vertex_faces(model.body_faces, nb))
        assert depth.max() < (0.02 if key == "clothed" else 0.02 + 4 * 0.002), key  # cloud: 2 mm noise


def test_to_model_maps_the_scan_onto_the_true_body(model, scans):
    s = scans["naked"]  # noise-free, unclothed: every vertex lies on the true posed body
    d = BodySurface(model.body_faces, model.n_body_vertices).distances(s.points_in_model_frame(), s.true_posed)
    assert d.max() < 1e-6
    # a similarity: rotation times 1/scale of the unit
    A = s.to_model[:3, :3] * SS.UNIT_SCALE[s.unit]
    np.testing.assert_allclose(A @ A.T, np.eye(3), atol=1e-9)
    assert np.linalg.det(A) > 0
    np.testing.assert_array_equal(s.to_model[3], [0, 0, 0, 1])
    # the true joints of the posed body are the ones its skeleton gives
    assert s.true_joints.shape == (17, 3) and s.true_posed.shape == (model.mean.shape[0], 3)
    assert abs(s.true_posed[: model.n_body_vertices, 1].min()) < 1e-9  # standing on y = 0


@pytest.mark.parametrize("unit,up", [("m", "+y"), ("cm", "+z"), ("mm", "+y"), ("mm", "+z")])
def test_units_and_up_axes_are_what_they_claim(model, person, unit, up):
    w, g = person
    s = SS.make_scan(model, np.random.default_rng(1), w, g, clothed=False, point_cloud=True, n_points=1500,
                     max_pose_deg=0.0, unit=unit, up=up, clothes_dir=CLOTHES)
    assert (s.unit, s.up) == (unit, up)
    axis = {"+y": 1, "+z": 2}[up]
    ext = np.ptp(s.points, axis=0) / SS.UNIT_SCALE[unit]  # metres
    height = s.measurements["height_cm"] / 100
    assert abs(ext[axis] - height) < 0.05
    assert np.argmax(ext) == axis
    # the scan's up axis maps to the model's +Y
    e = np.zeros(3)
    e[axis] = 1.0
    up_model = s.to_model[:3, :3] @ e
    np.testing.assert_allclose(up_model / np.linalg.norm(up_model), [0, 1, 0], atol=1e-9)
    assert abs(s.points_in_model_frame()[:, 1].min()) < 0.01  # feet on the floor (2 mm noise)


def test_point_clouds_have_unit_outward_normals(model, scans):
    s = scans["cloud"]
    assert s.faces is None and s.point_cloud
    assert s.points.shape == s.normals.shape == (5000, 3)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, atol=1e-9)
    # skin points: normals agree with the true body's vertex normals
    from service.model.geometry.mesh import vertex_normals

    nb = model.n_body_vertices
    B = s.true_posed[:nb]
    bn = vertex_normals(B, model.body_faces)
    P = s.points_in_model_frame()[s.point_is_body]
    N = (s.normals @ s.to_model[:3, :3].T)[s.point_is_body]
    N /= np.linalg.norm(N, axis=1, keepdims=True)
    _, nn = cKDTree(B).query(P)
    assert np.median(np.einsum("ij,ij->i", N, bn[nn])) > 0.9


def test_meshes_are_remeshed_to_about_n_points(model, scans):
    for key in ("clothed", "naked"):
        s = scans[key]
        assert 0.9 * 5000 <= len(s.points) <= 1.1 * 5000
        assert s.faces.min() >= 0 and s.faces.max() < len(s.points)
        assert len(np.unique(s.faces)) == len(s.points)  # no unreferenced vertex
        assert s.normals.shape == s.points.shape
    assert len(scans["naked"].points) != model.n_body_vertices


@pytest.mark.parametrize("fmt", SS.FORMATS)
def test_files_are_readable_with_the_right_counts(scans, fmt):
    for key in ("naked", "cloud"):
        s = scans[key]
        if s.point_cloud and fmt not in SS.POINT_CLOUD_FORMATS:
            with pytest.raises(ValueError):
                SS.scan_file_bytes(s, fmt)
            continue
        data = SS.scan_file_bytes(s, fmt)
        if fmt == "xyz":
            arr = np.loadtxt(io.BytesIO(data))
            assert arr.shape == (len(s.points), 6)
            np.testing.assert_allclose(arr[:, :3], s.points, atol=1e-5)
            continue
        got = trimesh.load(io.BytesIO(data), file_type=fmt, process=False)
        if isinstance(got, trimesh.Scene):
            got = got.to_geometry()
        if s.point_cloud:
            assert isinstance(got, trimesh.PointCloud) and len(got.vertices) == len(s.points)
        else:
            assert len(got.faces) == len(s.faces)
            if fmt != "stl":  # STL is a triangle soup
                assert len(got.vertices) == len(s.points)
        scale = np.abs(s.points).max()
        np.testing.assert_allclose(np.ptp(got.vertices, axis=0), np.ptp(s.points, axis=0), rtol=1e-5,
                                   atol=1e-6 * scale)


def test_deterministic_for_a_seed(model, person):
    w, g = person
    a, b, c = (SS.make_scan(model, np.random.default_rng(seed), w, g, clothed=True, point_cloud=False,
                            n_points=2000, clothes_dir=CLOTHES) for seed in (9, 9, 10))
    for f in ("points", "normals", "faces", "to_model", "rotvecs", "true_posed", "point_is_body"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert (a.unit, a.up, a.garments) == (b.unit, b.up, b.garments)
    assert not np.array_equal(a.rotvecs, c.rotvecs)
    d, e = (SS.make_scan(model, np.random.default_rng(9), w, g, clothed=True, point_cloud=True, n_points=2000,
                         clothes_dir=CLOTHES) for _ in range(2))
    np.testing.assert_array_equal(d.points, e.points)
    np.testing.assert_array_equal(d.normals, e.normals)


def test_random_pose_angles():
    rng = np.random.default_rng(0)
    for _ in range(50):
        rv = SS.random_pose(rng, 45.0)
        assert rv.shape == (17, 3)
        assert np.degrees(np.linalg.norm(rv[1:], axis=1)).max() <= 45.0 + 1e-9
        # the root: any yaw about +Y, tilted at most 10 degrees
        R = SS.lbs.axis_angle_to_matrix(rv[0])
        assert np.degrees(np.arccos(np.clip(R[1, 1], -1, 1))) <= SS.ROOT_MAX_TILT_DEG + 1e-6
    assert np.allclose(SS.random_pose(rng, 0.0)[1:], 0.0)


def test_anatomical_random_pose_redraws_only_the_bones_outside_the_joint_limits():
    """``random_pose(anatomical=True)``: every bone inside the fitter's joint limits, within the
    angle bound; the bones that were inside, the root and the caller's next draws are the same
    as without (the redraws come from a spawned child generator)."""
    from service.model.fitting.rig import limit_violation

    redrawn = 0
    for seed in range(40):
        a, b = np.random.default_rng([7, seed]), np.random.default_rng([7, seed])
        free, anat = SS.random_pose(a, 45.0), SS.random_pose(b, 45.0, anatomical=True)
        assert a.uniform() == b.uniform()  # the caller's stream goes on unchanged
        assert not limit_violation(anat).any()
        assert np.degrees(np.linalg.norm(anat[1:], axis=1)).max() <= 45.0 + 1e-9
        outside = limit_violation(free).any(axis=1)
        np.testing.assert_array_equal(anat[~outside], free[~outside])
        assert not np.any(np.all(anat[outside] == free[outside], axis=1))
        redrawn += int(outside.sum())
    assert redrawn >= 10  # the free poses do leave the limits (a knee bent sideways)


def test_leg_gap_on_known_lines():
    """``leg_gap``: the least distance between the two legs' centre lines (hip -> knee -> ankle)."""
    J = np.zeros((17, 3))
    J[11], J[12], J[13] = [0.1, 1.0, 0.0], [0.1, 0.5, 0.0], [0.1, 0.0, 0.0]  # left leg, straight
    J[14], J[15], J[16] = [-0.1, 1.0, 0.0], [-0.1, 0.5, 0.0], [-0.1, 0.0, 0.0]
    assert abs(SS.leg_gap(J) - 0.2) < 1e-9
    J[15], J[16] = [0.0, 0.5, 0.05], [0.3, 0.0, 0.0]  # the right shin crosses over to the left
    assert SS.leg_gap(J) < 0.06


def test_anatomical_scans_do_not_cross_the_legs_through_each_other(model):
    """An anatomical random pose can keep every bone inside its limits and still pass one leg
    through the other: held-out avatar 5 at 45 degrees (the fitting bench's seed) had the
    legs' centre lines 4 cm apart, the ankles crossed over by 22 cm. ``make_scan(anatomical=True)``
    draws the thighs and shins again until the legs are apart; the frame and everything drawn
    after the pose are the same as without that redraw."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    person = heldout_people(model, 11)[10]
    X = model.vertices(person["weights"]).astype(np.float64)
    rv = SS.random_pose(np.random.default_rng([BF.SEED, person["index"]]), 45.0, anatomical=True)
    assert SS.leg_gap(model.forward(pose=rv, vertices=X).joints) < 0.05  # crossed before
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=False, point_cloud=True, n_points=2000, max_pose_deg=45.0,
                        anatomical=True)
    assert SS.leg_gap(scan.true_joints) >= SS.LEG_CLEARANCE_M
    changed = np.any(scan.rotvecs != rv, axis=1)
    assert set(np.nonzero(changed)[0]) <= set(SS.LEG_BONES) and changed.any()
    free = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=False, point_cloud=True, n_points=2000, max_pose_deg=45.0)
    assert free.unit == scan.unit and free.up == scan.up
    R = lambda s: s.to_model[:3, :3]  # noqa: E731 - the random yaw and up axis
    np.testing.assert_allclose(R(free), R(scan))


def test_individual_detail_moves_soft_tissue_not_the_skull_hands_or_soles(model, person):
    """The off-model person of the fitting bench (``make_scan(detail_mm=...)``): the skin moves
    by the RMS asked for where there is soft tissue; the head, hands and feet keep their shape,
    so the stature is the person's; the body model cannot reproduce it."""
    w, g = person
    kw = dict(clothed=False, point_cloud=False, n_points=5000, max_pose_deg=10.0)
    plain = SS.make_scan(model, np.random.default_rng(5), w, g, **kw)
    off = SS.make_scan(model, np.random.default_rng(5), w, g, detail_mm=4.0, detail_rng=np.random.default_rng(9), **kw)
    nb = model.n_body_vertices
    X, Y = plain.true_rest[:nb], off.true_rest[:nb]
    rigid = np.isin(model.lbs_indices[:nb], SS.DETAIL_RIGID_BONES)
    mask = 1.0 - np.where(rigid, model.lbs_weights[:nb], 0.0).sum(axis=1)
    moved = np.einsum("ij,ij->i", Y - X, vertex_normals(X, model.body_faces))
    assert np.sqrt(np.mean(moved[mask > 0.5] ** 2)) == pytest.approx(0.004, rel=1e-3)
    assert np.abs(Y - X)[mask < 1e-6].max() < 1e-9  # the skull, hands and soles as they were
    assert off.measurements["height_cm"] == pytest.approx(plain.measurements["height_cm"], abs=1e-6)
    assert off.measurements["waist_cm"] != pytest.approx(plain.measurements["waist_cm"], abs=0.05)
    Z = model.vertices(model.project(off.true_rest))[:nb]
    assert np.linalg.norm(Z - Y, axis=1).mean() > 0.001  # off the model's space
    np.testing.assert_allclose(off.rotvecs, plain.rotvecs)  # the same pose and draws otherwise


def test_relaxed_hands_curl_the_fingers_towards_the_palms(model, person):
    """The fitting bench's relaxed hands (``make_scan(finger_curl_deg=...)``, ``curl_fingers``):
    only the hands' vertices beyond the knuckles move, the fingertips come nearer the wrist and
    the thigh beside them (the palms face the body), both hands alike; the measurements and
    every draw are the person's own."""
    w, g = person
    kw = dict(clothed=False, point_cloud=False, n_points=5000, max_pose_deg=0.0)
    plain = SS.make_scan(model, np.random.default_rng(5), w, g, **kw)
    relaxed = SS.make_scan(model, np.random.default_rng(5), w, g, finger_curl_deg=70.0, **kw)
    X, Y = plain.true_rest, relaxed.true_rest
    bone = np.argmax(F_rig._rig(model).W, axis=1)
    nb = model.n_body_vertices
    moved = np.linalg.norm(Y[:nb] - X[:nb], axis=1) > 1e-9
    assert moved.any() and np.isin(bone[moved], [BONES.index("hand_l"), BONES.index("hand_r")]).all()
    J = model.forward(pose=np.zeros((len(BONES), 3)), vertices=X).joints
    for name in ("hand_l", "hand_r"):
        b = BONES.index(name)
        hand = np.flatnonzero(bone == b)
        tip = hand[np.argmax(np.linalg.norm(X[hand] - J[b], axis=1))]
        assert np.linalg.norm(Y[tip] - J[b]) < 0.85 * np.linalg.norm(X[tip] - J[b])  # curled in
        assert abs(Y[tip, 0] - J[0, 0]) < abs(X[tip, 0] - J[0, 0])  # towards the body (the palm's side)
        assert 0.3 < moved[hand].mean() < 0.95
    assert (moved & (bone == BONES.index("hand_l"))).sum() == (moved & (bone == BONES.index("hand_r"))).sum()
    assert relaxed.measurements == plain.measurements
    np.testing.assert_allclose(relaxed.rotvecs, plain.rotvecs)


def test_raw_scanner_artifacts_offset_views_fly_pixels_and_cut_the_soles(model, person):
    """The fitting bench's raw scanner errors (``with_raw_artifacts``, ``cut_soles``): every
    point moves, most by its view's calibration offset (a few millimetres), a few percent fly
    off away from a camera by up to RAW_FLYING_MAX_M; a mesh keeps its faces and gets its
    normals from them again; the truth is untouched; the soles' cut drops exactly the points
    within its height of the floor (the true body's lowest point; 3 cm here: the virtual
    scanner hardly sees the soles, so the bench's 1 cm drops few)."""
    w, g = person
    scan = SS.make_scan(model, np.random.default_rng(5), w, g, clothed=False, point_cloud=False, n_points=5000,
                        max_pose_deg=10.0)
    raw = SS.with_raw_artifacts(scan, np.random.default_rng(6))
    P, Q = scan.points_in_model_frame(), raw.points_in_model_frame()
    d = np.linalg.norm(Q - P, axis=1)
    assert len(Q) == len(P) and np.array_equal(raw.faces, scan.faces) and (d > 0).all()
    assert np.median(d) < 4 * SS.RAW_MISREGISTRATION_M and d.max() < SS.RAW_FLYING_MAX_M + 6 * SS.RAW_MISREGISTRATION_M
    flown = d > 0.01
    assert 0.01 < flown.mean() < 0.1, flown.mean()
    np.testing.assert_allclose(raw.normals, vertex_normals(raw.points, raw.faces), atol=1e-6)
    assert np.array_equal(raw.true_posed, scan.true_posed) and raw.measurements == scan.measurements
    floor = scan.true_posed[:, 1].min()
    cut = SS.cut_soles(raw, 0.03)
    C = cut.points_in_model_frame()
    assert len(C) == int((Q[:, 1] > floor + 0.03).sum()) < len(Q) and C[:, 1].min() > floor + 0.03
    assert cut.faces.max() < len(C)
    cloud = SS.make_scan(model, np.random.default_rng(5), w, g, clothed=False, point_cloud=True, n_points=5000,
                         max_pose_deg=10.0)
    raw_cloud = SS.with_raw_artifacts(cloud, np.random.default_rng(6))
    assert raw_cloud.faces is None and np.array_equal(raw_cloud.normals, cloud.normals)

"""Parametric body fitting (service/model/fitting/fit.py): Jacobians against finite differences,
the prefactored Eq. 2 solve against a dense reference on both sparse back ends, and whole fits
of synthetic scans with a known body (tests/bench/synthetic_scans.py)."""
from __future__ import annotations

import numpy as np
import pytest

from service.model.fitting import fit as F
from service.model.fitting import alg1 as F_alg1
from service.model.fitting import checks as F_checks
from service.model.fitting import initialise as F_initialise
from service.model.fitting import params as F_params
from service.model.fitting import prepare as F_prepare
from service.model.fitting import regions as F_regions
from service.model.fitting import rig as F_rig
from service.model.body.model import BONES
from tests.bench import synthetic_scans as SS
from tests.bench.fitting import v2v_mm
from service.model.body.lbs import axis_angle_to_matrix, bone_hops
from service.model.geometry import kernels
from service.model.geometry.mesh import vertex_normals
from scipy.spatial import cKDTree


@pytest.fixture(scope="module")
def rig(model):
    return F_rig._rig(model)


def _random_state(model, rig, seed=1):
    rng = np.random.default_rng(seed)
    return F_rig._State(rng.normal(size=len(rig.U)) * np.sqrt(model.variances) * 0.5,
                    axis_angle_to_matrix(rng.normal(size=(17, 3)) * 0.3), rng.normal(size=3) * 0.1)


def test_pose_model_matches_skinning(model, rig):
    s = _random_state(model, rig)
    sub = F_rig._subset(rig, np.arange(0, model.n_body_vertices, 53))
    ref = model.forward(s.beta, s.rot, s.trans).vertices[: model.n_body_vertices][sub.idx]
    assert np.abs(F_rig._pose_model(rig, s, sub).v - ref).max() < 1e-6


def test_jacobians_match_finite_differences(model, rig):
    s = _random_state(model, rig, 2)
    sub = F_rig._subset(rig, np.arange(0, model.n_body_vertices, 97))
    p = F_rig._pose_model(rig, s, sub)
    J = F_rig._pose_jacobian(rig, p, F_rig.ALL_BONES)
    eps = 1e-6
    for k in range(J.shape[2]):  # translation and every bone's rotation
        d = np.zeros(J.shape[2])
        d[k] = eps
        s2 = s.copy()
        F_rig._apply_pose(rig, s2, p, F_rig.ALL_BONES, d)
        fd = (F_rig._pose_model(rig, s2, sub).v - p.v) / eps
        assert np.abs(fd - J[:, :, k]).max() < 1e-4 * max(1.0, np.abs(J[:, :, k]).max()), k
    comps = np.array([0, 3, 17, 75])
    Jb = F_rig._shape_jacobian(rig, p, comps)
    for c, k in enumerate(comps):
        s2 = s.copy()
        s2.beta[k] += eps
        fd = (F_rig._pose_model(rig, s2, sub).v - p.v) / eps
        assert np.abs(fd - Jb[:, :, c]).max() < 1e-6
    # both in one array, the shape's columns written in place after the pose's
    assert np.array_equal(F_rig._pose_jacobian(rig, p, F_rig.ALL_BONES, comps), np.concatenate([J, Jb], axis=2))


@pytest.mark.skipif(not kernels.AVAILABLE, reason="the compiled kernels are off (numba missing, or TRYON_NO_KERNELS)")
@pytest.mark.parametrize("bones", [F_rig.ALL_BONES, F_rig.ROOT_ONLY, np.array([BONES.index("thigh_l"), BONES.index("shin_l"),
                                                                       BONES.index("upper_arm_r")])])
def test_compiled_pose_jacobian_equals_the_numpy_reference(model, rig, bones):
    """The compiled pose Jacobian (kernels.pose_jacobian_into) is the numpy path's, with and
    without the shape's columns, on every vertex of a posed random body."""
    s = _random_state(model, rig, 5)
    sub = F_rig._subset(rig, np.arange(0, model.n_body_vertices, 41))
    p = F_rig._pose_model(rig, s, sub)
    for comps in (None, np.arange(10)):
        fast = F_rig._pose_jacobian(rig, p, bones, comps, compiled=True)
        ref = F_rig._pose_jacobian(rig, p, bones, comps, compiled=False)
        assert fast.shape == ref.shape
        assert np.abs(fast - ref).max() <= 1e-13 * np.abs(ref).max()
        assert np.abs(ref).max() > 0.1  # not an all-zero comparison


@pytest.mark.skipif(not kernels.AVAILABLE, reason="the compiled kernels are off (numba missing, or TRYON_NO_KERNELS)")
def test_compiled_pair_rows_equal_the_numpy_reference():
    """The point-to-plane normal equations with the compiled rows (kernels.pair_rows) are the
    numpy path's, with and without the per-region stand-off unknowns, and a slow sum pair by pair."""
    from service.model.geometry.solvers import point_to_plane_normal_equations

    rng = np.random.default_rng(3)
    m, k, P = 40, 90, 11
    J = rng.normal(size=(m, 3, P))
    vi = rng.integers(0, m, k)
    nn = rng.normal(size=(k, 3))
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    w, r = rng.uniform(0.1, 1.0, k), rng.normal(size=k)
    region = rng.integers(0, 4, k)
    for extra in ((), (region, 4)):
        H1, g1 = point_to_plane_normal_equations(J, vi, nn, w, r, *extra, compiled=True)
        H0, g0 = point_to_plane_normal_equations(J, vi, nn, w, r, *extra, compiled=False)
        assert np.allclose(H1, H0, rtol=1e-13, atol=1e-12) and np.allclose(g1, g0, rtol=1e-13, atol=1e-12)
    H = sum(w[t] * np.outer(nn[t] @ J[vi[t]], nn[t] @ J[vi[t]]) for t in range(k))
    g = sum(w[t] * r[t] * (nn[t] @ J[vi[t]]) for t in range(k))
    H1, g1 = point_to_plane_normal_equations(J, vi, nn, w, r, compiled=True)
    assert np.allclose(H1, H, rtol=1e-12, atol=1e-12) and np.allclose(g1, g, rtol=1e-12, atol=1e-12)


def test_unit_detection_errors_are_fit_errors():
    pts = np.random.default_rng(0).normal(size=(500, 3)) * [0.2, 0.5, 0.1]
    pts[:, 1] = np.linspace(0, 1.75, 500)
    assert F_prepare.detect_scan_unit(pts * 100)[0] == "cm"
    with pytest.raises(F_checks.FitError, match="units"):
        F_prepare.detect_scan_unit(pts * 10)




def _person(model):
    from tests.bench.common import heldout_people

    return heldout_people(model, 1)[0]


@pytest.mark.slow
def test_fit_unclothed_scan(model):
    """A posed, noisy, re-meshed body in cm with Z up: the fit recovers units, the up axis,
    the body (vertex-to-vertex) and the measurements. BLAS runs with ``blas_threads`` (1)
    threads during the fit, and as before after it."""
    from threadpoolctl import threadpool_info

    def blas_threads():
        return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]

    person = _person(model)
    scan = SS.make_scan(model, np.random.default_rng(11), person["weights"], person["gender"], clothed=False,
                        point_cloud=False, n_points=8000, max_pose_deg=20, unit="cm", up="+z")
    progress, threads, before = [], [], blas_threads()

    def report(f, m):
        progress.append(f)
        threads.extend(blas_threads())

    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False, progress=report)
    assert (fit.unit, fit.up) == ("cm", "+z")
    assert progress[-1] == 1.0 and progress == sorted(progress)
    assert threads and set(threads) == {F_params.DEFAULT_PARAMS.blas_threads}, threads
    assert blas_threads() == before
    err = v2v_mm(model, scan, fit)
    assert err < 8.0, err
    height = model.measure(model.vertices(fit.weights), person["gender"])["height_cm"]
    assert abs(height - scan.measurements["height_cm"]) < 4.0
    assert fit.outer_iterations >= 1 and fit.inner_iterations >= 1
    assert fit.residual_mm < 10


@pytest.mark.slow
def test_fit_clothed_point_cloud_stays_inside_clothes(model):
    """A clothed point cloud without normals (estimated) in mm: the body is recovered and sits
    inside the clothes, not inflated to them."""
    from service.model.geometry.mesh import winding_numbers

    person = _person(model)
    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    scan = SS.make_scan(model, np.random.default_rng(12), person["weights"], person["gender"], clothed=True,
                        point_cloud=True, n_points=8000, max_pose_deg=20, unit="mm", up="+y")
    fit = F.fit_body(model, scan.points, None, None, clothed=True)
    assert fit.unit == "mm"
    err = v2v_mm(model, scan, fit)
    assert err < 20.0, err
    body = fit.posed_vertices[: model.n_body_vertices]
    P = scan.points @ fit.to_model[:3, :3].T + fit.to_model[:3, 3]
    covered = ~scan.point_is_body
    inside = winding_numbers(P[covered][::10], body, model.body_faces) > 0.5
    assert inside.mean() < 0.2  # cloth points inside the fitted body: the body pokes through


def _rest_stature_error_cm(model, person, scan, fit) -> float:
    return model.measure(model.vertices(fit.weights), person["gender"])["height_cm"] - scan.measurements["height_cm"]


@pytest.mark.slow
def test_fit_recovers_rest_pose_stature_of_posed_scan(model):
    """Shape and posture decoupled (issue 12): the rest-pose body of a posed scan (every bone
    turned up to 20 degrees) has the person's stature within 1 cm, and the rest body itself
    (vertex to vertex) is close: the fit does not trade a longer bone for a bent one.
    With the refinement damped like the coarse stage (``refine_levenberg`` 1e-3) this scan's
    stature comes out 1.8 cm short (rest body 17 mm off); now 0.1 cm (2 mm)."""
    person = _person(model)
    scan = SS.make_scan(model, np.random.default_rng(14), person["weights"], person["gender"], clothed=False,
                        point_cloud=False, n_points=8000, max_pose_deg=20)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    err = _rest_stature_error_cm(model, person, scan, fit)
    assert abs(err) < 1.0, err
    rest = np.linalg.norm(model.vertices(fit.weights) - model.vertices(person["weights"]), axis=1)
    assert 1000 * rest[: model.n_body_vertices].mean() < 5.0


def test_fit_rejects_non_person(model):
    with pytest.raises(F_checks.FitError):
        F.fit_body(model, np.random.default_rng(0).normal(size=(50, 3)))
    with pytest.raises(F_checks.FitError, match="units"):
        F.fit_body(model, np.random.default_rng(0).uniform(0, 5, size=(2000, 3)))


# -- the person check (service/model/fitting/person_check.py) ----------------------------------------
@pytest.mark.parametrize("kind", ["box", "ellipsoid", "two_people"])
def test_person_check_before_the_fit_rejects_shapes(model, kind):
    """A box and an ellipsoid are convex solids; two people apart are two person-sized
    components: refused before any fitting, 'not a person: <reason>'."""
    from service.model.fitting import person_check as PC

    pts, nrm, unit, up = SS.non_person_scan(model, kind, np.random.default_rng(3), n_points=4000)
    P = pts / SS.UNIT_SCALE[unit]
    assert (PC.convex_solid(P) is None) == (kind == "two_people")
    assert (PC.separate_bodies(P) is None) == (kind != "two_people")
    with pytest.raises(F_checks.FitError, match="^not a person: "):
        F_checks.check_person_before(P)
    with pytest.raises(F_checks.FitError, match="^not a person: "):  # in the file's unit, before any fitting
        F.fit_body(model, pts, nrm)


@pytest.mark.slow
def test_a_stick_figure_is_not_a_bare_person(model):
    """A mannequin-like figure of capsules and a ball, person-sized (synthetic_scans'
    "stick_figure"): fitted as bare it used to come back ready, a 167 cm, 84 kg woman near the
    population's limits (Mahalanobis 56 of 60), the scan's median point 8.4 mm off the body's
    surface. Bare people are 1.5-2.1 mm off it (``person_check.bare_surface``): refused. Declared
    clothed, the population check refuses it (hips and thighs out of range)."""
    pts, nrm, unit, up = SS.non_person_scan(model, "stick_figure", np.random.default_rng(3), n_points=6000)
    with pytest.raises(F_checks.FitError, match="^not a person: the best-fitting body is .* from the scan's surface"):
        F.fit_body(model, pts, nrm, clothed=False)
    with pytest.raises(F_checks.FitError):
        F.fit_body(model, pts, nrm, clothed=True)


@pytest.mark.parametrize("clothed,cloud", [(False, True), (True, False)])
def test_person_check_before_the_fit_passes_people(model, clothed, cloud):
    """Posed people, bare or clothed, mesh or cloud, pass the checks before the fit."""
    from service.model.fitting import person_check as PC

    if clothed and not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = _person(model)
    scan = SS.make_scan(model, np.random.default_rng(4), person["weights"], person["gender"], clothed=clothed,
                        point_cloud=cloud, n_points=4000, max_pose_deg=30)
    P = scan.points_in_model_frame()
    assert PC.concave_share(P) > 2 * PC.CONCAVE_SHARE_MIN
    F_checks.check_person_before(P)


def test_population_check(model):
    """The accepted measurement ranges and the shape prior: the mean body passes; a shape with
    an attribute out of range, or far from the population, fails saying which."""
    from service.model.fitting import person_check as PC

    w = np.zeros(model.n_components)
    assert F_checks.check_population(model, w)["mahalanobis"] == 0.0
    attrs = model.attributes
    reason, _ = PC.population_check(w, model.variances, {"waist_cm": 37.0, "height_cm": 158.0}, attrs)
    assert reason.startswith("waist_cm 37.0 outside the accepted 48.6")
    w[5] = 1.5 * PC.COMPONENT_Z_MAX * np.sqrt(model.variances[5])
    reason, fig = PC.population_check(w, model.variances, {}, attrs)
    assert "standard deviations" in reason and fig["max_component_sd"] > PC.COMPONENT_Z_MAX
    with pytest.raises(F_checks.FitError, match="^the fitted body is outside the population: "):
        F_checks.check_population(model, w * 3)


def test_a_part_of_the_scan_far_from_the_body_is_unexplained(model):
    """``person_check.unexplained_part``: a scan that is the body plus an arm-sized rod of
    points reaching 50 cm out from the chest (a limb the fit left elsewhere, or an object held)
    is refused saying how much of the scan is left out; the body alone, or with the rod only
    15 cm long (loose clothes, hair), passes."""
    from service.model.fitting import person_check as PC

    body = model.vertices(np.zeros(model.n_components))[: model.n_body_vertices].astype(np.float64)
    chest = body[np.argmax(body[:, 2] * (np.abs(body[:, 1] - 1.3) < 0.05))]  # the front of the chest

    def rod(length):  # a 4 cm thick rod along +Z from the chest, ~2 % of the scan's points
        rng = np.random.default_rng(0)
        t = rng.uniform(0.0, length, 300)
        return chest + np.c_[rng.normal(0, 0.02, 300), rng.normal(0, 0.02, 300), t]

    assert PC.unexplained_part(body, body)[0] is None
    assert PC.unexplained_part(np.vstack([body, rod(0.15)]), body)[0] is None
    reason, fig = PC.unexplained_part(np.vstack([body, rod(0.5)]), body)
    assert reason is not None and "not explained" in reason, reason
    assert fig["unexplained_share"] >= PC.UNEXPLAINED_SHARE and fig["farthest_scan_point_mm"] > 450, fig


def _bench_clothed_scan_at_45(model):
    """Held-out avatar 2 (a man in a work suit) as the fitting bench scans it in the clothed
    conditions at 45 degrees: (person, scan); skips without the MakeHuman clothes."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = heldout_people(model, 5)[4]
    return person, SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                                person["gender"], clothed=True, point_cloud=False, n_points=BF.N_POINTS,
                                noise_mm=BF.NOISE_MM, max_pose_deg=45, clothes_dir=SS.default_clothes_dir())


@pytest.mark.slow
def test_a_wrong_fit_of_a_scanner_scan_at_45_degrees_is_refused(model):
    """Issue 12: a wrong minimum is refused, never returned. Held-out avatar 2 in a work suit,
    scanned with holes, a cut head top and a floor, in a pose up to 45 degrees per bone (the
    fitting bench's scanner condition): the fit puts the left arm over the head where the scan's
    points forward. Before ``person_check.unexplained_part`` it was returned as a customer's
    body 120.9 mm off (point to surface), the stature 32 cm short; now the fit either comes
    within 10 mm or fails saying that part of the scan is not explained (with the
    initialisation's distances per area and the clothed posture anchored it is fitted: 4.6 mm
    on the bench, where it was refused)."""
    from tests.bench import fitting as BF

    person, scan = _bench_clothed_scan_at_45(model)
    scan = SS.degrade(scan, ("holes", "cut_head", "scanner_floor"), np.random.default_rng([BF.SEED, 11, person["index"]]))
    try:
        fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    except F_checks.FitError as exc:
        assert str(exc).startswith(F_checks.NOT_FITTED) and "not explained" in str(exc), exc
        return
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert ev["p2s_mm"] < 10.0, ev["p2s_mm"]


@pytest.mark.slow
def test_front_only_scan_is_flagged_partial(model):
    """A single-view front scan (bare point cloud) is fitted from what is visible and flagged
    ``partial``; the whole scan of the same person is not."""
    person = _person(model)
    scan = SS.make_scan(model, np.random.default_rng(13), person["weights"], person["gender"], clothed=False,
                        point_cloud=True, n_points=6000, max_pose_deg=15, unit="m", up="+y")
    whole = F.fit_body(model, scan.points, scan.normals, None, clothed=False)
    front = F.fit_body(model, *(lambda s: (s.points, s.normals))(SS.front_only(scan)), None, clothed=False)
    assert not whole.partial and min(whole.coverage.values()) > 0.9, whole.coverage
    assert front.partial and front.coverage["back"] < 0.5 and front.coverage["front"] > 0.9, front.coverage


def test_joint_limits_data_and_penalty_gradient(model, rig):
    """Every bone but the pelvis has hand-set limits with lo < 0 < hi (the rest pose inside);
    the penalty's gradient over the world-frame pose parameters matches finite differences of
    weight/2 sum ||violation||^2."""
    from service.model.body.model import BONES
    from service.model.body.lbs import matrix_to_axis_angle

    assert set(F_rig.JOINT_LIMITS_DEG) == set(BONES) - {"pelvis"}
    lo, hi = F_rig.joint_limits()
    assert np.all(lo[1:] < 0) and np.all(hi[1:] > 0) and np.isinf(lo[0]).all()
    assert not F_rig.limit_violation(np.zeros((17, 3))).any()
    s = _random_state(model, rig, 5)
    s.rot = axis_angle_to_matrix(np.random.default_rng(5).normal(size=(17, 3)) * 1.2)  # many outside
    sub = F_rig._subset(rig, np.arange(0, model.n_body_vertices, 97))
    p = F_rig._pose_model(rig, s, sub)
    w = 3.0

    def energy(st):
        return 0.5 * w * float((F_rig.limit_violation(matrix_to_axis_angle(st.rot)) ** 2).sum())

    assert energy(s) > 0
    H, g = F_rig._joint_limit_terms(rig, s, p, F_rig.ALL_BONES, w)
    eps = 1e-6
    for k in range(3, g.size):
        d = np.zeros(g.size)
        d[k] = eps
        s2 = s.copy()
        F_rig._apply_pose(rig, s2, p, F_rig.ALL_BONES, d)
        assert abs((energy(s2) - energy(s)) / eps - g[k]) < 1e-3 * max(1.0, abs(g[k])), k
    assert np.all(np.linalg.eigvalsh(H) > -1e-9)


def test_loose_region_weight_against_a_per_pair_reference():
    """``loose_region_weight``: per region, the median inside depth (pairs outside counted as
    0) sets one multiplier for the region's inside pairs, 1 / (1 + (median / depth)^2); pairs
    outside keep 1. Checked against a pair-by-pair loop on random pairs, and on a snug and a
    loose region: a shirt 2-4 mm off keeps ~all its weight, a jacket 2-3 cm off ~1/7."""
    rng = np.random.default_rng(5)
    signed = rng.normal(-0.01, 0.012, size=300)
    region = rng.integers(0, 5, size=300)
    got = F_regions.loose_region_weight(signed, region, 0.01)
    for k in range(len(signed)):
        same = region == region[k]
        med = np.median([max(-x, 0.0) for x in signed[same]])
        want = 1.0 / (1.0 + (med / 0.01) ** 2) if signed[k] < 0 else 1.0
        assert abs(got[k] - want) < 1e-12
    snug, loose = -rng.uniform(0.002, 0.004, 50), -rng.uniform(0.02, 0.03, 50)
    w = F_regions.loose_region_weight(np.r_[snug, loose, 0.001], np.r_[np.zeros(50, int), np.ones(50, int), 1], 0.01)
    assert np.all(w[:50] > 0.85) and np.all(w[50:100] < 0.2) and w[100] == 1.0


def test_cloth_offset_normal_equations_against_a_per_pair_reference():
    """``point_to_plane_normal_equations`` with regions: point-to-plane rows n_k^T J_{vi_k} with a
    one-hot column per region (the residual r_k + o_{region_k}), summed pair by pair."""
    from service.model.geometry.solvers import point_to_plane_normal_equations

    rng = np.random.default_rng(8)
    m, P, R, k = 7, 5, 4, 30
    J = rng.normal(size=(m, 3, P))
    vi, region = rng.integers(0, m, k), rng.integers(0, R, k)
    nn = rng.normal(size=(k, 3))
    nn /= np.linalg.norm(nn, axis=1, keepdims=True)
    w, r = rng.uniform(0.1, 2.0, k), rng.normal(size=k)
    H, g = point_to_plane_normal_equations(J, vi, nn, w, r, region, R)
    Hr, gr = np.zeros((P + R, P + R)), np.zeros(P + R)
    for q in range(k):
        row = np.r_[nn[q] @ J[vi[q]], np.eye(R)[region[q]]]
        Hr += w[q] * np.outer(row, row)
        gr += w[q] * row * r[q]
    assert np.allclose(H, Hr) and np.allclose(g, gr)
    H0, g0 = point_to_plane_normal_equations(J, vi, nn, w, r)  # the same without the regions
    assert np.allclose(H[:P, :P], H0) and np.allclose(g[:P], g0)


def test_offset_step_is_the_bounded_least_squares_step():
    """``_offset_step``: the Gauss-Newton step with the clothes' stand-offs kept >= 0 is the
    minimiser of the quadratic model under those bounds (checked against L-BFGS-B on random
    problems where some bounds are active and some are not)."""
    from scipy.optimize import minimize

    params = F_params.FitParams(damping=1e-12, levenberg=0.0)
    rng = np.random.default_rng(3)
    active = 0
    for _ in range(20):
        n, R = 6, 5
        A = rng.normal(size=(40, n + R))
        H, g = A.T @ A, rng.normal(size=n + R) * 3
        offsets = rng.uniform(0.0, 1.0, R) * (rng.uniform(size=R) < 0.6)
        d = F_initialise._offset_step(H, g, offsets, params)
        bounds = [(None, None)] * n + [(-o, None) for o in offsets]
        ref = minimize(lambda x: 0.5 * x @ H @ x + g @ x, np.zeros(n + R), jac=lambda x: H @ x + g,
                       bounds=bounds, method="L-BFGS-B", options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 10000}).x
        assert np.all(offsets + d[n:] >= -1e-12)
        assert np.allclose(d, ref, atol=1e-5)
        active += int(np.sum(np.isclose(offsets + d[n:], 0.0)))
    assert active > 5  # the bounds did bind


def test_clothing_weight_is_asymmetric_and_redescending():
    """Issue 12, loose clothes: a body point outside the clothes keeps the full weight, one
    touching them from inside (within the contact depth) nearly so, one deep under a loose
    jacket almost none -- far less than the constant ``inside_weight`` -- and the pull
    (weight x depth) falls again beyond the contact depth (redescending)."""
    p = F_params.FitParams()
    signed = np.array([0.01, 0.0, -0.001, -0.004, -0.03, -0.06])
    w = F_regions._clothing_weight(signed, True, p, p.clothing_contact)
    assert w[0] == w[1] == 1.0 and w[2] > 0.9
    assert abs(w[3] - 0.5) < 1e-12  # half weight at the contact depth
    assert w[4] < 0.1 * p.inside_weight + 0.01 and w[5] < w[4]
    pull = w * np.abs(signed)
    assert pull[3] > pull[4] > pull[5]
    assert np.all(F_regions._clothing_weight(signed, False, p, p.clothing_contact) == 1.0)
    assert np.all(F_regions._clothing_weight(signed[2:], True, p, None) == p.inside_weight)


@pytest.mark.slow
def test_fit_scanner_scan_in_clothes_keeps_stature(model):
    """Issue 12, scanner output (a clothed mesh with holes, the head top cut off, a noisy tilted
    floor): the body sits snug inside the clothes and its rest-pose stature is right. With the
    refinement's constant 10 % weight for body points inside the clothes (``clothing_contact``
    None) this scan (a woman in a sports suit) came out 6.4 mm off (point to surface) with the
    stature 3.1 cm short; with the contact weight 2.7 mm and 0.5 cm."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = heldout_people(model, 2)[1]
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=True, point_cloud=False, n_points=BF.N_POINTS,
                        noise_mm=BF.NOISE_MM, max_pose_deg=20)
    scan = SS.degrade(scan, ("holes", "cut_head", "scanner_floor"), np.random.default_rng([BF.SEED, 11, person["index"]]))
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert ev["p2s_mm"] < 4.0, ev["p2s_mm"]
    assert abs(ev["stature_err_cm"]) < 1.0, ev["stature_err_cm"]


@pytest.mark.slow
def test_fit_clothed_mesh_in_a_45_degree_pose(model):
    """Issue 12, clothed scans in poses up to 45 degrees per bone: the coarse initialisation
    leaves the posture 15-50 degrees off per bone under loose clothes (here a man in a work suit,
    trousers 2-4 cm off the legs: feet turned, the rest-pose body 16 cm short), and with the
    clothing weights from the start the refinement cannot pull the limbs out of that: body
    points deep inside the clothes hardly count. Before the posture-first refinement on the
    clothes' outer surface (``refine_bare_iterations`` 0) this scan came out 7.0 mm off (point
    to surface), the stature 5.0 cm short; with it 3.7 mm and 2.7 cm. With the pull of each bone
    towards its parent's rotation (Eq. 3's smoothness, also a pull towards the rest pose) at 0.1
    the knee's bend inside the trouser leg was underestimated and the legs came out short
    (clothed prior on: 3.24 mm, stature -2.16 cm); at 0.02 after the posture-first stage
    (``FitParams.bone_smoothness``, ``bare_smoothness``): 2.94 mm and -1.73 cm; with the loose
    regions' weights (``FitParams.loose_region_depth``, the body deeper in the work suit's loose
    trousers) 3.15 mm and -1.95 cm; with the clothes' stand-offs per region instead
    (``FitParams.cloth_offset_mean``) and the clothed posture anchor at 0.1 (the knee free to
    bend inside the trouser leg), 2.25 mm and -0.7 cm."""
    from tests.bench import fitting as BF

    person, scan = _bench_clothed_scan_at_45(model)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    print("avatar 2, clothed mesh, 45 degrees:", round(ev["p2s_mm"], 2), "mm,", round(ev["stature_err_cm"], 2), "cm")
    assert ev["p2s_mm"] < 2.7, ev["p2s_mm"]
    assert abs(ev["stature_err_cm"]) < 1.2, ev["stature_err_cm"]



@pytest.mark.slow
def test_the_body_does_not_fill_a_loose_suit(model):
    """Issue 12, loose clothes: under a suit the scan's residuals are the cloth's stand-off, not
    the scanner's noise, and with the bare scans' shape prior (5 mm) the body grows into the
    jacket. Held-out avatar 0 (a man in a casual suit, 45 degrees, the clothed-mesh condition of
    the fitting bench): with the clothed scans' prior (``FitParams.clothed_shape_prior``, 2 cm,
    once the posture is found) the waist came out +14.5 cm against +16.4 cm, 15.6 -> 14.7 kg too
    heavy, 3.20 -> 3.02 mm off (point to surface), measured with the bone smoothness 0.02 in every
    stage. Since the clothes' stand-off per region (``FitParams.cloth_offset_mean``) the body no
    longer fills the jacket either way, and the clothed prior is the better fit: 2.03 -> 1.53 mm,
    waist +6.6 -> +4.7 cm (weight +0.9 -> +2.6 kg; with the clothed posture anchor at 1.0, 2.07 ->
    1.64 mm)."""
    from dataclasses import replace

    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = heldout_people(model, 1)[0]
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=True, point_cloud=False, n_points=BF.N_POINTS,
                        noise_mm=BF.NOISE_MM, max_pose_deg=45, clothes_dir=SS.default_clothes_dir())
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    ev = {}
    for name, params in (("prior", F_params.FitParams()), ("none", replace(F_params.FitParams(), clothed_shape_prior=None))):
        fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True, params=params)
        ev[name] = BF.evaluate(model, scan, fit, surface)
    print({k: (round(v["p2s_mm"], 2), round(v["measurements"]["weight_kg"], 1), round(v["measurements"]["waist_cm"], 1))
           for k, v in ev.items()})
    assert ev["prior"]["measurements"]["waist_cm"] < ev["none"]["measurements"]["waist_cm"], ev
    assert ev["prior"]["p2s_mm"] < ev["none"]["p2s_mm"] - 0.2, ev


def _bench_scan(model, k: int, condition: str = "clothed_mesh", deg: float = 45.0, draw: int = 0):
    """The fitting bench's scan of held-out person ``k`` (its order) in ``condition``, anatomical
    poses, degraded as the condition says: (person, scan). ``draw`` > 0: another random draw of
    the raw scanner's errors (the degradations from ``raw_artifacts`` on; the holes kept)."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    cond = {c.name: c for c in BF.CONDITIONS}[condition]
    person = heldout_people(model, k + 1)[k]
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=cond.clothed, point_cloud=cond.cloud, n_points=BF.N_POINTS,
                        noise_mm=BF.NOISE_MM, max_pose_deg=deg, clothes_dir=SS.default_clothes_dir(),
                        garments=None if cond.garments is None else cond.garments[person["gender"]],
                        anatomical=True, detail_mm=cond.detail_mm,
                        detail_rng=np.random.default_rng([BF.SEED, 13, person["index"]]),
                        finger_curl_deg=cond.finger_curl_deg)
    if cond.degrade:
        rng = np.random.default_rng([BF.SEED, 11, person["index"]])
        kinds = list(cond.degrade)
        cut = kinds.index("raw_artifacts") if draw and "raw_artifacts" in kinds else len(kinds)
        scan = SS.degrade(scan, kinds[:cut], rng)
        scan = SS.degrade(scan, kinds[cut:], np.random.default_rng([BF.SEED, 11, person["index"], draw]))
    return person, scan


def _fits(model, scan, **variants) -> dict:
    """{name: the bench's evaluation of the clothed fit with FitParams(**kwargs)} per variant."""
    from tests.bench import fitting as BF

    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    return {name: BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True,
                                                      params=F_params.FitParams(**kw)), surface)
            for name, kw in variants.items()}


@pytest.mark.slow
def test_a_man_in_a_t_shirt_is_not_fitted_as_filling_it(model):
    """Issue 12, clothed men too heavy: held-out avatar 0 in the men's T-shirt and jeans (the
    fitting bench's tight clothes, 45 degrees). The shirt hangs 1-1.5 cm off his belly and back;
    fitted pair by pair, thousands of body points inside it each pulled the body out a little
    against a shape prior that counts once, and the body filled the shirt: +11.5 kg, waist +12.4
    cm, 2.78 mm off (point to surface). With the clothes' stand-off one unknown per body region
    (``FitParams.cloth_offset_mean``): +1.0 kg, waist +4.7 cm, 1.83 mm; with the clothed posture
    anchor at 0.1 too, +1.3 kg, +5.1 cm, 1.71 mm (pair by pair then +11.7 kg, 2.63 mm)."""
    _, scan = _bench_scan(model, 0, "tight_clothes")
    ev = _fits(model, scan, offsets={}, pairs={"cloth_offset_mean": None})
    print({k: (round(v["p2s_mm"], 2), round(v["measurements"]["weight_kg"], 1), round(v["measurements"]["waist_cm"], 1))
           for k, v in ev.items()})
    m = ev["offsets"]["measurements"]
    assert abs(m["weight_kg"]) < 4.0 and abs(m["waist_cm"]) < 7.0, m
    assert ev["offsets"]["p2s_mm"] < 2.0, ev["offsets"]["p2s_mm"]
    assert ev["pairs"]["measurements"]["weight_kg"] > 8.0, ev["pairs"]["measurements"]  # the mechanism


@pytest.mark.slow
def test_a_heavy_man_in_a_snug_suit_is_not_shrunk_inside_it(model):
    """Issue 12: held-out avatar 3 (a 115 kg man in a casual suit, 45 degrees, the bench's
    clothed mesh). Pair by pair, the body filled the jacket (+26.1 kg, waist +22.7 cm, 4.78 mm
    off). The stand-offs per region (``FitParams.cloth_offset_mean``) must not swing the other
    way: combined with the loose regions' weights (``FitParams.loose_region_depth`` 1 cm), which
    all but drop a region whose body sits deep in the clothes, the trousers' stand-off let the
    whole body shrink towards the population's mean (-29.4 kg, waist -23.6 cm, 6.11 mm off; with
    a 2 cm mean stand-off -25.7 kg). With the stand-offs alone: -1.4 kg, waist +1.8 cm, 2.80 mm;
    with the clothed posture anchor at 0.1 too, +2.3 kg, +5.0 cm, 2.73 mm (pair by pair then
    +24.7 kg, both -24.9 kg)."""
    _, scan = _bench_scan(model, 6, "clothed_mesh")
    ev = _fits(model, scan, offsets={}, pairs={"cloth_offset_mean": None},
               both={"loose_region_depth": 0.01})
    print({k: (round(v["p2s_mm"], 2), round(v["measurements"]["weight_kg"], 1), round(v["measurements"]["waist_cm"], 1))
           for k, v in ev.items()})
    m = ev["offsets"]["measurements"]
    assert abs(m["weight_kg"]) < 6.0 and abs(m["waist_cm"]) < 6.0, m
    assert ev["offsets"]["p2s_mm"] < 3.2, ev["offsets"]["p2s_mm"]
    assert ev["pairs"]["measurements"]["weight_kg"] > 15.0, ev["pairs"]["measurements"]  # filled
    assert ev["both"]["measurements"]["weight_kg"] < -15.0, ev["both"]["measurements"]  # shrunk


@pytest.mark.slow
def test_a_bent_forward_clothed_cloud_is_not_folded(model):
    """Issue 12: held-out avatar 1 (bent forward ~70 degrees, an arm up, a casual suit and
    shoes) as the fitting bench's clothed point cloud at 45 degrees. With the bone smoothness
    0.02 in the posture-first stage too, the fit folded into a wrong minimum the person check
    does not see: 28.4 mm off (point to surface), the head 13 cm from the truth, the rest body
    17.7 cm short. With 0.1 in that stage (``FitParams.bare_smoothness``): 6.2 mm."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = next(p for p in heldout_people(model, 12) if p["index"] == 1)
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=True, point_cloud=True, n_points=BF.N_POINTS,
                        noise_mm=BF.NOISE_MM, max_pose_deg=45, clothes_dir=SS.default_clothes_dir())
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert ev["p2s_mm"] < 9.0 and ev["worst_joint"][1] < 80.0, ev
    assert abs(ev["stature_err_cm"]) < 4.0, ev["stature_err_cm"]

def test_vertex_areas_and_area_weighted_trimmed_mean(model, rig):
    """The template's vertex areas sum to its surface area and are far from uniform (the hands'
    and the head's vertices are dense: per vertex they would outweigh the legs); the weighted
    trimmed mean keeps the smallest values holding ``keep`` of the weight."""
    from service.model.geometry.solvers import trimmed_mean

    faces = rig.faces
    v = rig.mean[faces]
    total = 0.5 * np.linalg.norm(np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0]), axis=1).sum()
    assert abs(rig.area.sum() - total) < 1e-9 * total
    hand = rig.W[:, 7] > 0.5  # hand_l
    thigh = rig.W[:, 11] > 0.5  # thigh_l
    assert hand.sum() > thigh.sum() and rig.area[hand].sum() < 0.5 * rig.area[thigh].sum()
    d = np.array([1.0, 2.0, 3.0, 100.0])
    assert trimmed_mean(d, 0.75) == 2.0 == trimmed_mean(d, 0.75, weights=np.ones(4))
    w = np.array([1.0, 1.0, 8.0, 1.0])
    assert trimmed_mean(d, 0.95, weights=w) == (1 + 2 + 24) / 10  # 10 of 11 within 95 %
    assert trimmed_mean(d, 0.9, weights=w) == 1.5  # the heavy 3 would pass 90 %: left out


def test_posture_anchor_pulls_each_bone_back(model, rig):
    """``_anchor_terms``: Gauss-Newton steps on the anchor term alone bring every bone's local
    rotation (the root's too) back to the anchored posture; at the anchor the gradient is 0."""
    s = _random_state(model, rig, 7)
    anchor = s.rot.copy()
    sub = F_rig._subset(rig, np.arange(0, model.n_body_vertices, 97))
    p = F_rig._pose_model(rig, s, sub)
    H, g = F_rig._anchor_terms(rig, s, p, F_rig.ALL_BONES, anchor, 2.0)
    assert np.abs(g).max() < 1e-9
    s.rot = axis_angle_to_matrix(np.random.default_rng(8).normal(size=(17, 3)) * 0.3) @ anchor
    for _ in range(6):
        p = F_rig._pose_model(rig, s, sub)
        H, g = F_rig._anchor_terms(rig, s, p, F_rig.ALL_BONES, anchor, 2.0)
        H[:3, :3] += np.eye(3)  # the translation is free of the term
        F_rig._apply_pose(rig, s, p, F_rig.ALL_BONES, -np.linalg.solve(H, g))
    from service.model.body.lbs import matrix_to_axis_angle

    left = np.linalg.norm(matrix_to_axis_angle(np.einsum("bji,bjk->bik", anchor, s.rot)), axis=1)
    assert left.max() < 1e-4, left


def _bench_scanner_scan(model, index: int, max_pose_deg: float, clothed: bool = True):
    """Held-out avatar ``index`` as the fitting bench scans it in the "scanner" condition (a
    random MakeHuman suit, holes, a cut head top, a scanner's floor), or with ``clothed`` False
    in the "scanner_minimal" one (the same bare): (person, scan)."""
    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    if not SS.default_clothes_dir().is_dir():
        pytest.skip("MakeHuman clothes (../shared/data/makehuman_clothes) not available")
    person = next(p for p in heldout_people(model, 12) if p["index"] == index)
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"],
                        person["gender"], clothed=clothed, point_cloud=False, n_points=BF.N_POINTS,
                        noise_mm=BF.NOISE_MM, max_pose_deg=max_pose_deg, clothes_dir=SS.default_clothes_dir())
    return person, SS.degrade(scan, ("holes", "cut_head", "scanner_floor"),
                              np.random.default_rng([BF.SEED, 11, person["index"]]))


@pytest.mark.slow
def test_a_face_in_a_hole_does_not_tip_the_head_back(model):
    """Issue 12, a body scanner's output (bare, 8 holes, the head top cut 4 cm down, a floor):
    held-out avatar 41 at 20 degrees, her face in a hole. The refinement pulled the template's
    face to the hole's rim and paired surfaces whose normals were up to 60 degrees apart; the
    head tipped back 34-41 degrees and grew, and the rest-pose body came out 3.8 cm taller
    (5.5 mm off), even when started at the truth. With no pull into holes and the normals held
    to 30 degrees in the refinement: +0.96 cm, 3.6 mm."""
    from tests.bench import fitting as BF

    _, scan = _bench_scanner_scan(model, 41, 20, clothed=False)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert abs(ev["stature_err_cm"]) < 1.5, ev
    assert ev["p2s_mm"] < 4.5, ev


@pytest.mark.slow
def test_a_hand_over_a_hole_is_not_folded_onto_the_hip(model):
    """Issue 12, a wrong fit the person check does not see: held-out avatar 39 (a woman in a
    sports suit), scanner output, a pose up to 20 degrees, a hole over part of her right hand.
    Scored per template vertex (the hands hold 12 % of them each, 2 % of the area), the hand off
    the scan cost more than the scan's own hand left unexplained, and the limb search folded the
    forearm onto the hip: 27.7 mm off (point to surface), the hand 20 cm from the truth, no scan
    point 0.22 m from the body (not refused). With the initialisation's distances per area and
    the clothed refinement held to the posture of the clothes' outer surface: 4.9 mm."""
    from tests.bench import fitting as BF

    _, scan = _bench_scanner_scan(model, 39, 20)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert ev["p2s_mm"] < 8.0, ev
    assert ev["worst_joint"][1] < 60.0, ev["worst_joint"]


@pytest.mark.slow
def test_a_scanner_scan_bent_forward_is_fitted_facing_the_right_way(model):
    """Issue 12, a wrong fit the person check does not see: held-out avatar 1 (a man in a casual
    suit), scanner output, a pose up to 45 degrees (bent forward ~70 degrees, an arm up). The
    fit came back facing the wrong way, 48 mm off (point to surface), a hand 1.2 m from the truth
    and yet no scan point 0.15 m from the body. Now it faces the scan's way and comes within
    8 mm (7.3 mm measured; 6.3 mm with the lower bone smoothness after the posture-first
    stage): the right facing wins the initialisation once its distances count per area, and the
    clothed refinement and Alg. 1 keep the posture of the clothes' outer surface where the
    clothing weights leave a limb without data (a hand drifted 10 cm)."""
    from tests.bench import fitting as BF

    _, scan = _bench_scanner_scan(model, 1, 45)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=True)
    ev = BF.evaluate(model, scan, fit, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert ev["p2s_mm"] < 8.0 and ev["joints_mm"] < 25.0, ev
    assert ev["worst_joint"][1] < 80.0, ev["worst_joint"]


@pytest.mark.slow
def test_a_hand_in_a_hole_is_neither_hidden_in_the_thigh_nor_crossed_over(model):
    """Issue 12, a body scanner's output of a person in minimal clothing (holes, a cut head top,
    a floor): held-out avatar 40 at 45 degrees, a hole over her left hand. The initialisation's
    symmetric distance is a trimmed mean, and a limb hidden inside the body costs little there:
    the landmark hypotheses crossed both arms through the chest (each arm 78 cm long, refused as
    outside the population), and the ICP pulled the hand into the thigh beside the hole. Alg. 1
    then spun the hand, which no scan point holds (131 mm mean error on the hand). Now: the
    arm's adduction limited to 75 degrees, the arms' share inside the torso or thighs costed in
    the initialisation, no pair whose scan point belongs to a body part three bones away, and
    Alg. 1's pose and shape fitted to the matched template vertices only: 1.74 mm (point to
    surface), every joint within 5 mm."""
    from dataclasses import replace

    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 7, "scanner_minimal")
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    ev = BF.evaluate(model, scan, fit, surface)
    assert ev["p2s_mm"] < 3.0 and ev["worst_joint"][1] < 30.0, ev
    assert abs(ev["stature_err_cm"]) < 1.0, ev
    # the mechanism: without the three (the limit stays), the hand ends up in the thigh (since
    # the fingers are weighted by their residuals, FitParams.finger_scale, it does so without
    # that too: 4.3 mm worst joint with the three off)
    before = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                        params=replace(BF.BEFORE_PARAMS("hidden_limbs"), finger_scale=None))
    assert BF.evaluate(model, scan, before, surface)["worst_joint"][1] > 150.0


@pytest.mark.slow
def test_a_scan_with_holes_does_not_drift_in_alg1(model):
    """Issue 12, a body scanner's mesh with holes (bare): held-out avatar 41 at 45 degrees. Alg.
    1's later outer iterations moved the fit away from the truth, each re-matching near the
    holes (10 outer iterations: 2.19 mm point to surface); with at most 3 (``FitParams.max_outer``)
    1.20 mm. Both measured without the holes' rims (``FitParams.rim_reject``, added since), which
    keep those re-matchings off the rims by themselves: with them, 10 outer iterations end at
    1.43 mm, as do 3. Measured without the unseen bones' prior (``FitParams.unseen_prior``, added
    since), which pulls this scan's right hand, 8 % seen and turned 45 degrees, towards its
    rest posture: 1.97 mm."""
    from dataclasses import replace

    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 9, "holes")
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)

    def error(params):
        fit = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False, params=params)
        return BF.evaluate(model, scan, fit, surface)["p2s_mm"], fit.outer_iterations

    p2s, outer = error(F_params.FitParams(unseen_prior=0.0))
    assert p2s < 1.6 and outer <= 3
    p2s, outer = error(F_params.FitParams(rim_reject=False, unseen_prior=0.0))
    assert p2s < 1.6 and outer <= 3
    # (since FitParams.finger_scale the drift needs the fingers weighted as any vertex too: 1.33 mm)
    p2s, outer = error(replace(BF.BEFORE_PARAMS("alg1_outer"), rim_reject=False, unseen_prior=0.0, finger_scale=None))
    assert p2s > 1.8 and outer > 3


@pytest.mark.slow
def test_a_face_in_a_hole_does_not_nod_the_head(model):
    """Issue 12, a body scanner's mesh with 8 holes (bare), held-out avatar 40 at 10 degrees:
    one hole takes her face, another her right hand. The nose and chin jut out over the hole's
    rim, so ``over_hole`` (the offset's direction) kept their pairs with the neck and cheeks, and
    the fit nodded the head 45 degrees (6.2 mm, joints 14 mm off). With the rims found on the scan
    (``FitParams.rim_reject``): 1.15 mm, joints 1.4 mm."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 7, "holes", deg=10.0)
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    fit = BF.evaluate(model, scan, result, surface)
    assert fit["p2s_mm"] < 1.5 and fit["joints_mm"] < 4.0, fit
    # the right hand in its hole is left to the prior (FitParams.unseen_prior); the face's
    # hole leaves most of the head seen (its scalp)
    assert result.unseen == ["hand_r"] and result.stats["hair_region"] is True
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=BF.BEFORE_PARAMS("rim_reject")), surface)
    assert before["p2s_mm"] > 4.0 and before["worst_joint"][0] == "head", before


def test_seen_shares_find_a_hand_in_a_hole(model):
    """``fitting.seen_shares`` on the template itself as the scan, the left hand's points taken
    out: the hand unseen, every bone away from it wholly seen."""
    rig = F_rig._rig(model)
    state = F_rig._State(np.zeros(len(rig.U)), np.broadcast_to(np.eye(3), (len(BONES), 3, 3)).copy(), np.zeros(3))
    bone = np.argmax(rig.W, axis=1)
    hand = BONES.index("hand_l")
    wrist = rig.mean[bone == hand].mean(0)
    P = rig.mean[np.linalg.norm(rig.mean - wrist, axis=1) > 0.12]
    seen = F_prepare.seen_shares(rig, state, P, None)
    assert seen.shape == (len(BONES),)
    assert seen[hand] < F_params.TUNING.unseen_share
    far = [b for b in range(len(BONES)) if b not in (hand, BONES.index("forearm_l"))]
    assert np.all(seen[far] == 1.0), dict(zip(BONES, seen.round(2)))
    assert np.all(F_prepare.seen_shares(rig, state, rig.mean, None) == 1.0)


def test_the_scalp_region_holds_the_scalp_not_the_face(model):
    """``fitting.scalp_region`` on the template: the head above the hairline and the whole neck
    in it, the nose tip (the head's most forward vertex) and everything off the head and neck out
    of it, and MakeHuman's bob (the catalogue's hair, fitted to the mean body) within 3 cm of most
    of it."""
    from scipy.spatial import cKDTree

    from service.model.garments.catalogue import load_catalogue

    rig = F_rig._rig(model)
    bone = np.argmax(rig.W, axis=1)
    head, neck = bone == BONES.index("head"), bone == BONES.index("neck")
    scalp = rig.scalp
    assert not (scalp & ~(head | neck)).any() and scalp[neck].all()
    y = rig.mean[:, 1]
    assert scalp[head & (y > y[head].max() - F_params.TUNING.scalp_hairline_m)].all()
    hv = np.flatnonzero(head)
    assert not scalp[hv[np.argmax(rig.mean[hv, 2])]]  # the nose tip
    assert 0.1 < 1 - scalp[head].mean() < 0.3  # the face's front is out (~19 % of the head)
    bob = load_catalogue().items["hair-bob02"].fit_to(model.mean.astype(np.float64))
    d, _ = cKDTree(bob).query(rig.mean[scalp])
    assert (d < 0.03).mean() > 0.75


def _hair_fit(model, k: int, condition: str, **params) -> tuple:
    """The bench's evaluation of held-out person ``k``'s bare scan with hair in ``condition``
    (20 degrees) fitted bare with FitParams(**params), and the fit's stats."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, k, condition, deg=20.0)
    result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False, params=F_params.FitParams(**params))
    stats = dict(result.stats, unseen=result.unseen)
    return BF.evaluate(model, scan, result, BF.BodySurface(model.body_faces, model.n_body_vertices)), stats


@pytest.mark.slow
def test_a_hand_in_a_hole_is_left_to_the_prior(model):
    """Issue 12, a body scanner's output with hair, fitted bare: held-out avatar 39 (bob) at 20
    degrees, her left hand in a hole (17 % of it near a scan point). Its few stray pairs turned
    it over: 83 mm mean error on the hand, 7.4 mm overall. Pulled towards its rest posture
    (``FitParams.unseen_prior``): 2.1 mm. (Since the upper back is also treated as possibly
    hair, ``FitParams.hair_back``, this scan keeps the hand without the prior too: 1.84 mm, and
    since the fingers are weighted by their residuals, ``FitParams.finger_scale``, without both:
    1.54 mm; the failure is reproduced without the three, and without the initial stature from
    the scan's height, ``FitParams.init_stature_max``, from which it is right without all four.)"""
    fit, stats = _hair_fit(model, 5, "scanner_hair")
    assert stats["unseen"] == ["hand_l"], stats
    assert fit["p2s_mm"] < 3.0 and abs(fit["stature_err_cm"]) < 0.6, fit
    before, _ = _hair_fit(model, 5, "scanner_hair", unseen_prior=0.0, hair_back=False, finger_scale=None,
                          init_stature_max=None)
    assert before["p2s_mm"] > 5.0, before


@pytest.mark.slow
def test_a_neck_in_a_hole_does_not_grow_into_the_hair(model):
    """Issue 12, the same person off the body model's space (4 mm of individual detail): her
    neck in a hole (18 % seen), the top of the head cut. The head nodded and grew into the bob,
    +3.2 cm of stature, 4.5 mm. The neck pulled towards its rest posture: +0.4 cm, 2.5 mm.
    (Started from the stature her scan's height gives, ``FitParams.init_stature_max``, the head
    stays down without the pull too; the failure is reproduced without both.)"""
    fit, stats = _hair_fit(model, 5, "off_model_scanner_hair")
    assert "neck" in stats["unseen"], stats
    assert abs(fit["stature_err_cm"]) < 1.0 and fit["p2s_mm"] < 3.0, fit
    before, _ = _hair_fit(model, 5, "off_model_scanner_hair", unseen_prior=0.0, init_stature_max=None)
    assert before["stature_err_cm"] > 2.0, before


@pytest.mark.slow
def test_a_face_in_a_hole_under_short_hair_keeps_the_head_upright(model):
    """Issue 12: held-out avatar 1 (short hair) in a scanner's output at 20 degrees, his face in a
    hole. The fit used to pair his scalp as skin when the face was unseen, and his head turned
    51 degrees inside the hair (58 mm mean error on the head, 4.07 mm overall). The scalp
    weighted as hair either way (``FitParams.hair_region``): under 1 mm."""
    fit, stats = _hair_fit(model, 2, "scanner_hair")
    assert stats["hair_region"] is True
    assert fit["p2s_mm"] < 1.2 and fit["worst_joint"][1] < 10.0, fit


@pytest.mark.slow
def test_a_scan_without_its_head_leaves_the_head_to_the_prior(model):
    """Issue 12, a scanner's output with no head at all (bench condition ``headless``: holes, the
    scanner's floor): held-out avatar 37 at 20 degrees. The template's head, a quarter of its
    vertices, was paired with the neck and shoulders, bent and shrank into them: 36 mm off and
    the stature 20 cm short, yet "ready". The coarse fit again with the head absent
    (``FitParams.headless_check``, ``absent_bones``) finds no scan where its head is: kept, the
    head is the prior's (``unseen``), ~2.2 mm and -0.3 cm. (The initial stature from the
    scan's height, ``FitParams.init_stature_max``, now avoids the fold on this scan without
    the check too: the failure is reproduced without both.)"""
    from dataclasses import replace

    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 1, "headless", deg=20.0)
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    assert result.stats["headless"]["adopted"] is True and "head" in result.unseen, result.stats["headless"]
    fit = BF.evaluate(model, scan, result, surface)
    assert fit["p2s_mm"] < 3.0 and abs(fit["stature_err_cm"]) < 1.0, fit
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=replace(BF.BEFORE_PARAMS("headless"), init_stature_max=None)),
                        surface)
    assert before["p2s_mm"] > 10.0 and before["stature_err_cm"] < -10.0, before


@pytest.mark.slow
def test_a_scan_without_its_head_is_not_fitted_upside_down(model):
    """Issue 12, bench condition ``headless`` at 45 degrees, held-out avatar 4. The screen of the
    16 facings (the root alone, 5 iterations) ranked the body upside down first (93 against 109
    mm), so only upside-down facings went through the coarse stage, and the fit was refused as
    "not a person" (13 mm from the scan). The best facing of each up-axis sign now goes through
    it (``FitParams.coarse_each_up``): the right way up wins (23 against 40 mm), ~2.5 mm."""
    from dataclasses import replace

    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 8, "headless", deg=45.0)
    result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    fit = BF.evaluate(model, scan, result, BF.BodySurface(model.body_faces, model.n_body_vertices))
    assert result.up == scan.up and fit["p2s_mm"] < 4.0 and abs(fit["stature_err_cm"]) < 1.0, fit
    before = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                        params=replace(BF.BEFORE_PARAMS("coarse_each_up"), person_check=False, min_accepted=0.0))
    assert before.up != scan.up, before.up


@pytest.mark.slow
def test_long_hair_down_the_back_is_not_taken_for_skin(model):
    """Issue 12, a bare scanner scan with long hair down the back to the shoulder blades (bench
    condition ``long_hair``): held-out avatar 37 at 20 degrees. With only the head and neck
    treated as possibly hair, the upper back grew out into the hair (0.95 mm); with the upper
    back among where hair may hang (``FitParams.hair_back``) the fit is as good as without
    hair (0.44 mm; the same scan without hair 0.40 mm)."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 1, "long_hair", deg=20.0)
    assert (~scan.point_is_body).sum() > 300  # the hair is there
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    fit = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False), surface)
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=BF.BEFORE_PARAMS("hair_back")), surface)
    assert fit["p2s_mm"] < 0.7 and abs(fit["stature_err_cm"]) < 0.5, fit
    assert before["p2s_mm"] > 1.5 * fit["p2s_mm"], (before["p2s_mm"], fit["p2s_mm"])


def test_hair_back_region_is_the_upper_back(model):
    """``fitting.hair_back_region`` on the rest template: vertices on the back of the torso
    (facing backwards, behind the torso's middle), between the shoulders, above the middle of
    the back, none of the scalp's."""
    rig = F_rig._rig(model)
    m = rig.hair_back
    V = rig.mean
    head = rig.jmean[BONES.index("head")]
    assert 100 < m.sum() < 0.05 * len(m) and not (m & rig.scalp).any()
    torso = np.isin(np.argmax(rig.W, axis=1), [BONES.index("spine"), BONES.index("chest")])
    assert (V[m, 2] < np.median(V[torso, 2])).all() and (vertex_normals(V, rig.faces)[m, 2] < 0).all()
    assert (V[m, 1] > head[1] - F_params.TUNING.hair_back_below_m).all() and V[m, 1].max() < head[1]


@pytest.mark.slow
def test_relaxed_fingers_do_not_pull_the_body(model):
    """Issue 12, real hands: a scanned person's fingers are curled (bench condition
    ``relaxed_hands``: 70 degrees towards the palm, bare scanner output, 20 degrees; held-out
    avatar 37), which the model's bones cannot follow, and the hands hold 24 % of the template's
    vertices. With every vertex alike (``finger_scale`` None) the fingers pulled the arms short
    and the body off elsewhere (0.91 mm without the hands, arm -0.9 cm); with the fingers' pairs
    weighted by their residuals (``FitParams.finger_scale``) 0.52 mm and -0.3 cm."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 1, "relaxed_hands", deg=20.0)
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    fit = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False), surface)
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=BF.BEFORE_PARAMS("finger_weight")), surface)
    assert fit["p2s_no_hands_mm"] < 0.7 and abs(fit["measurements"]["arm_length_cm"]) < 0.6, fit
    assert before["p2s_no_hands_mm"] > 1.4 * fit["p2s_no_hands_mm"], (before["p2s_no_hands_mm"], fit["p2s_no_hands_mm"])
    assert before["measurements"]["arm_length_cm"] < -0.7, before["measurements"]


def test_finger_region_is_the_fingers(model):
    """``fitting.finger_region`` on the rest template: on the hands only, beyond the wrist,
    most of each hand's vertices (the fingers are dense), the same count on both hands, and
    farther along the hand than any of the hand's vertices it leaves out."""
    rig = F_rig._rig(model)
    bone = np.argmax(rig.W, axis=1)
    for name in ("hand_l", "hand_r"):
        hand = bone == BONES.index(name)
        fingers = rig.fingers & hand
        assert 0.6 * hand.sum() < fingers.sum() < 0.95 * hand.sum()
        wrist = rig.jmean[BONES.index(name)]
        tip = rig.mean[hand][np.argmax(np.linalg.norm(rig.mean[hand] - wrist, axis=1))]
        axis = (tip - wrist) / np.linalg.norm(tip - wrist)
        along = (rig.mean - wrist) @ axis
        assert along[fingers].min() > 0.3 * along[hand].max()
        assert np.median(along[fingers]) > np.percentile(along[hand & ~fingers], 90)
    assert not (rig.fingers & ~np.isin(bone, [BONES.index("hand_l"), BONES.index("hand_r")])).any()
    assert (rig.fingers & (bone == BONES.index("hand_l"))).sum() == (rig.fingers & (bone == BONES.index("hand_r"))).sum()


@pytest.mark.slow
def test_a_dense_scan_is_fitted_on_a_random_share_of_its_points(model):
    """A body scanner's mesh has 100k-1M vertices; the fit takes ``FitParams.max_points`` of
    them at random once the floor is gone (a 450k-point mesh: 14.4 s -> 8.0 s). Here a
    36k-point bare scanner mesh fitted on 12k of its points is as good as fitted on all; as a
    point cloud without normals, they are estimated on the 12k."""
    import dataclasses

    from tests.bench import fitting as BF
    from tests.bench.common import heldout_people

    person = heldout_people(model, 1)[0]
    scan = SS.make_scan(model, np.random.default_rng([BF.SEED, person["index"]]), person["weights"], person["gender"],
                        clothed=False, point_cloud=False, n_points=36_000, noise_mm=1.0, max_pose_deg=20, anatomical=True)
    scan = SS.degrade(scan, ("holes", "cut_head", "scanner_floor"), np.random.default_rng(3))
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    out = {}
    for cap in (12_000, None):
        result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                            params=dataclasses.replace(F_params.FitParams(), max_points=cap))
        out[cap] = (BF.evaluate(model, scan, result, surface), result.stats["points"], result.kept)
    (few, p_few, kept_few), (full, p_full, kept_full) = out[12_000], out[None]
    assert p_few["fitted"] == 12_000 and p_full["fitted"] == p_few["scan"] == p_full["scan"] > 30_000
    assert np.array_equal(kept_few, kept_full) and (~kept_few).sum() > 1000  # the floor, dropped either way
    assert few["p2s_mm"] < 1.0 and abs(few["p2s_mm"] - full["p2s_mm"]) < 0.3, (few["p2s_mm"], full["p2s_mm"])
    assert abs(few["stature_err_cm"]) < 0.6, few
    # the same points as a bare cloud (no faces, no normals): the normals estimated on the share
    result = F.fit_body(model, scan.points, None, None, clothed=False,
                        params=dataclasses.replace(F_params.FitParams(), max_points=12_000))
    cloud = BF.evaluate(model, scan, result, surface)
    assert result.stats["points"]["fitted"] == 12_000 and cloud["p2s_mm"] < 1.5, (result.stats["points"], cloud)


def test_absent_bones_take_no_pairs(model):
    """``FitParams.absent_bones``: Alg. 1's pairs (``_correspondences``) leave out every template
    vertex the absent bone moves most, and only those."""
    rig = F_rig._rig(model)
    T = rig.mean
    tree = cKDTree(T)
    N = vertex_normals(T, rig.faces)
    head = np.argmax(rig.W, axis=1) == BONES.index("head")
    _, _, w_all = F_prepare._correspondences(T, rig, tree, T, N, False, F_params.FitParams())
    _, _, w = F_prepare._correspondences(T, rig, tree, T, N, False, F_params.FitParams(absent_bones=("head",)))
    assert w_all[head].all() and not w[head].any() and np.array_equal(w[~head], w_all[~head])


@pytest.mark.slow
def test_hair_on_a_bare_scan_does_not_make_the_body_taller(model):
    """Issue 12, a body scanner's customer in minimal clothing, with hair: held-out avatar 0
    (short hair) at 10 degrees, fitted bare. Paired as skin, the hair made the head grow: +0.91 cm
    of stature, 0.92 mm; with the head (but the face's front) and neck weighted as clothing
    (``FitParams.hair_region``) +0.32 cm, 0.56 mm."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 0, "bare_hair", deg=10.0)
    assert scan.garments == ["hair-short02"]
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    result = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    assert result.stats["hair_region"] is True
    fit = BF.evaluate(model, scan, result, surface)
    assert abs(fit["stature_err_cm"]) < 0.5 and fit["p2s_mm"] < 0.8, fit
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=BF.BEFORE_PARAMS("hair_region")), surface)
    assert before["stature_err_cm"] > 0.7, before


@pytest.mark.slow
def test_a_person_off_the_body_models_space_is_fitted_as_near_as_it_allows(model):
    """Real people are not in the body model's space (the bench's held-out people are, to 0.02
    mm). Held-out avatar 0 with 4 mm RMS of individual soft-tissue detail (condition
    ``off_model``), 20 degrees, bare: the fit comes within 0.3 mm of the model's own best (the
    true rest body's projection on its space, 0.77 mm), with the stature kept (0.93 mm, -0.06 cm
    when measured)."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 0, "off_model", deg=20.0)
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    floor = BF.model_floor_mm(model, scan, surface)
    assert floor > 0.5  # the detail is off the model's space
    fit = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False), surface)
    assert fit["p2s_mm"] < floor + 0.3 and abs(fit["stature_err_cm"]) < 0.3, (fit, floor)


def test_known_terms_against_finite_differences(model):
    """``fitting.known_terms``: the residuals (in sigmas) are the measurements' misses, the
    gradient g is J^T r and H = J^T J, with J the finite differences of the body model's own
    measurements of float64 vertices (the slow, obvious reference)."""
    from service.model.body import measurements as M

    rng = np.random.default_rng(5)
    beta = rng.normal(size=model.n_components) * np.sqrt(model.variances) * 0.5
    mean = model.mean.astype(np.float64)
    comps = model.components.astype(np.float64)
    measure = lambda b: model.measure(mean + np.tensordot(b, comps, axes=1), "male")  # noqa: E731
    true = measure(beta)
    known = {"height_cm": true["height_cm"] + 1.0, "weight_kg": true["weight_kg"] - 2.0, "waist_cm": true["waist_cm"]}
    names = [n for n in M.ATTRIBUTES if n in known]
    sigma = np.array([F_params.TUNING.known_sigma.get(n, F_params.TUNING.known_sigma_cm) for n in names])
    H, g, r = F_alg1.known_terms(model, known, "male")(beta)
    np.testing.assert_allclose(r, [(true[n] - known[n]) / s for n, s in zip(names, sigma)], atol=0.02)
    J = np.zeros((len(names), len(beta)))
    for k in range(len(beta)):
        h = 0.1 * np.sqrt(model.variances[k])
        up, down = measure(beta + h * np.eye(len(beta))[k]), measure(beta - h * np.eye(len(beta))[k])
        J[:, k] = [(up[n] - down[n]) / (2 * h) for n in names] / sigma
    np.testing.assert_allclose(g, J.T @ r, rtol=0.02, atol=0.01 * np.abs(J.T @ r).max())
    np.testing.assert_allclose(H, J.T @ J, rtol=0.02, atol=0.01 * np.abs(J.T @ J).max())
    with pytest.raises(ValueError, match="not a body measurement"):
        F_alg1.known_terms(model, {"shoe_size": 42.0}, "male")


@pytest.mark.slow
def test_measurements_given_with_a_loose_suit_scan_are_kept(model):
    """Issue 12: a man in a loose business suit (held-out avatar 2, 20 degrees) comes back ~11 kg
    heavy, the suit's stand-off taken for girth. With his height, weight, chest, waist and hips
    given (``fit_body(known=...)``), the rest body keeps them and the body error goes down."""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 4, "loose_clothes", deg=20.0)
    assert "business-suit" in scan.garments
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    plain = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces), surface)
    names = ("height_cm", "weight_kg", "chest_cm", "waist_cm", "hip_cm")
    known = {n: scan.measurements[n] for n in names}
    given = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, known=known,
                                                gender=scan.gender), surface)
    assert plain["measurements"]["weight_kg"] > 5.0, plain
    for n in names:
        assert abs(given["measurements"][n]) < (1.0 if n == "weight_kg" else 0.5), (n, given)
    assert given["p2s_mm"] < plain["p2s_mm"], (given, plain)


def test_bone_hops_against_a_breadth_first_search(model):
    """``lbs.bone_hops`` against a breadth-first search per bone on the
    body model's skeleton."""
    parents = np.asarray(model.bone_parents)
    hops = bone_hops(parents)
    J = len(parents)
    nbrs = [[p for p in (parents[j],) if p >= 0] + [c for c in range(J) if parents[c] == j] for j in range(J)]
    for a in range(J):
        dist, frontier = {a: 0}, [a]
        while frontier:
            nxt = []
            for u in frontier:
                for v in nbrs[u]:
                    if v not in dist:
                        dist[v] = dist[u] + 1
                        nxt.append(v)
            frontier = nxt
        assert [dist[b] for b in range(J)] == hops[a].tolist()
    assert hops[BONES.index("hand_l"), BONES.index("thigh_l")] > 2 >= hops[BONES.index("forearm_l"), BONES.index("chest")]


def test_bench_fit_params_overrides():
    """``tryon bench fitting --fit-params``: 'name=value,...' parsed as Python literals and
    checked against FitParams; applied to a "before" kind's params except where that kind
    changed the field itself."""
    from tests.bench import fitting as BF

    got = BF.parse_fit_params("cloth_offset_mean=None, loose_region_depth=0.02,max_outer=3")
    assert got == {"cloth_offset_mean": None, "loose_region_depth": 0.02, "max_outer": 3}
    assert BF.parse_fit_params("") == {} and BF.parse_fit_params(None) == {}
    with pytest.raises(ValueError, match="unknown FitParams field"):
        BF.parse_fit_params("no_such_field=1")
    before = BF.BEFORE_PARAMS("cloth_offsets")  # its own cloth_offset_mean=None, anchor 1.0
    p = BF.with_overrides(before, {"cloth_offset_mean": 0.1, "max_outer": 3, "clothed_posture_anchor": 0.5})
    assert p.cloth_offset_mean is None and p.clothed_posture_anchor == 1.0  # the kind's own changes win
    assert p.max_outer == 3 and p.loose_region_depth == 0.01


@pytest.mark.slow
def test_a_poorly_seen_face_does_not_shape_the_body(model):
    """Issue 12, bare scanner output at 20 degrees with the face in a hole and the head's top
    cut: held-out avatar 40 from a raw scanner (bench condition ``scanner_raw``: misregistered
    views, flying pixels, the soles cut; the head 58 % seen). On the scalp a bare fit lets the
    body lie inside the scan (hair), so a head grown up into the cut top fitted as well as the
    true one, and the face's few pairs, on the hole's edges, grew the neck: +2.7 cm (3.2 mm).
    With the face's pairs moving the pose but not the shape (``FitParams.face_shape_min_seen``)
    she is her height (+0.16 cm on the bench). The long-haired avatar 41 it also takes to her
    height in the bench (+4.8 -> +0.05 cm) is not asserted: read from a file she was still a
    wrong fit (+7.5 cm; +1.96 cm since the second head hypothesis, README, **A poorly seen head
    fitted twice**; -0.12 cm since ``test_a_long_haired_scan_starts_from_its_own_height``).
    Started from the stature her scan's height gives (``FitParams.init_stature_max``), she is
    right without it too: the failure is reproduced without both."""
    from dataclasses import replace

    k, condition = 7, "scanner_raw"
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, k, condition, deg=20.0)
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    after = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False)
    fit = BF.evaluate(model, scan, after, surface)
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=replace(BF.BEFORE_PARAMS("face_shape"), init_stature_max=None)),
                        surface)
    assert after.stats["face_shape_from_body"] and after.stats["seen"]["head"] < F_params.FitParams().face_shape_min_seen
    assert abs(fit["stature_err_cm"]) < 0.5 and fit["p2s_mm"] < 1.5, fit
    assert before["stature_err_cm"] > 2.0 and before["p2s_mm"] > 2.5, before


def test_scan_to_surface_mm_against_brute_force():
    """``fitting.scan_to_surface_mm`` (the head hypotheses' score): the mean over points of the
    distance to the nearest of every triangle, each clipped, as a loop over all triangles."""
    from service.model.geometry.mesh import closest_point_on_triangles

    rng = np.random.default_rng(3)
    g = np.stack(np.meshgrid(np.linspace(0, 0.3, 7), np.linspace(0, 0.3, 7)), -1).reshape(-1, 2)
    V = np.c_[g, 0.03 * np.sin(13 * g[:, 0]) * np.cos(10 * g[:, 1])]  # a bumpy sheet, 30 cm square
    idx = np.arange(49).reshape(7, 7)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    Fc = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    P = rng.uniform([-0.03, -0.03, -0.08], [0.33, 0.33, 0.08], (200, 3))
    best = np.full(len(P), np.inf)
    for f in Fc:
        q = closest_point_on_triangles(P, V[f[0]][None], V[f[1]][None], V[f[2]][None])
        best = np.minimum(best, np.linalg.norm(P - q, axis=1))
    for clip in (0.05, 0.01, 1.0):
        ref = 1000 * np.minimum(best, clip).mean()
        assert F.scan_to_surface_mm(P, V, Fc, clip=clip) == pytest.approx(ref, rel=1e-9, abs=1e-9)
    assert F.scan_to_surface_mm(V[Fc[:, 0]], V, Fc) == pytest.approx(0.0, abs=1e-9)  # points on it


@pytest.mark.slow
def test_bench_fits_the_scan_as_uploaded(model):
    """``tryon bench fitting --via-file``: the scan as the fitting job gets it from an upload
    (``as_uploaded``: the file read by ``uploads.read_body_upload``, stored as the queue
    does) is the generated scan to float32 precision, in the file's units and axes; a point
    cloud keeps its normals; a non-person upload is refused with the upload's reason."""
    from service.application.errors import Invalid
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 0, "unclothed_mesh", deg=20.0)
    got = BF.as_uploaded(model, scan, "ply")
    assert got.faces is not None and len(got.faces) == len(scan.faces)
    used = np.unique(scan.faces)  # vertices on no face are dropped by the upload
    assert got.points.shape == (len(used), 3)
    scale = np.abs(scan.points).max()
    assert np.abs(got.points - scan.points[used]).max() <= 1e-6 * scale
    _, cloud = _bench_scan(model, 0, "clothed_cloud", deg=20.0)
    got = BF.as_uploaded(model, cloud, "ply")
    assert got.faces is None and got.normals is not None and len(got.points) == len(cloud.points)
    assert np.abs(got.points - cloud.points).max() <= 1e-6 * np.abs(cloud.points).max()
    assert np.einsum("ij,ij->i", got.normals, cloud.normals).min() > 0.999
    from dataclasses import replace

    tiny = replace(cloud, points=cloud.points * 1e-4, faces=None)  # 0.2 mm tall in any unit
    with pytest.raises(Invalid):
        BF.as_uploaded(model, tiny, "ply")


@pytest.mark.slow
def test_a_poorly_seen_head_is_fitted_twice_and_the_better_kept(model):
    """Issue 12, bare scanner output at 20 degrees with the head poorly seen. Held-out avatar 40
    from a raw scanner (``scanner_raw``, another draw of its errors; the face in a hole, the top
    cut): her head fitted once grows up into the cut top (+2.1 cm, 2.8 mm); fitted again with
    the head and neck shaped by the body (``FitParams.head_hypothesis_seen``), the second fit
    leaves less of the scan unexplained and is kept. Held-out avatar 41's capped head
    (``scanner_capped``), whose face is seen, keeps the first: shaped by her body alone her head
    would be 2.4 cm too tall. Started from the stature her scan's height gives
    (``FitParams.init_stature_max``), avatar 40's first fit is right and kept: the two
    hypotheses are shown from the coarse stage's stature, and the default fit is checked too."""
    from dataclasses import replace

    from tests.bench import fitting as BF

    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    _, scan = _bench_scan(model, 7, "scanner_raw", deg=20.0, draw=11)
    default = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False), surface)
    assert abs(default["stature_err_cm"]) < 0.5 and default["p2s_mm"] < 1.5, default
    coarse = F_params.FitParams(init_stature_max=None)
    after = F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False, params=coarse)
    fit = BF.evaluate(model, scan, after, surface)
    before = BF.evaluate(model, scan, F.fit_body(model, scan.points, scan.normals, scan.faces, clothed=False,
                                                 params=replace(BF.BEFORE_PARAMS("head_hypothesis"),
                                                                init_stature_max=None)), surface)
    tried = after.stats["head_hypotheses"]
    assert [h["head_from_body"] for h in tried] == [False, True] and tried[1]["chosen"], tried
    assert tried[1]["scan_to_surface_mm"] < tried[0]["scan_to_surface_mm"]
    assert after.stats["head_shape_from_body"] and after.stats["face_shape_from_body"]
    assert abs(fit["stature_err_cm"]) < 0.5 and fit["p2s_mm"] < 1.5, fit
    assert before["stature_err_cm"] > 1.5 and before["p2s_mm"] > 2.0, before

    _, capped = _bench_scan(model, 9, "scanner_capped", deg=20.0)
    kept = F.fit_body(model, capped.points, capped.normals, capped.faces, clothed=False)
    tried = kept.stats["head_hypotheses"]
    assert len(tried) == 2 and tried[0]["chosen"] and not kept.stats["head_shape_from_body"], tried
    assert abs(BF.evaluate(model, capped, kept, surface)["stature_err_cm"]) < 0.5


@pytest.mark.slow
def test_a_clothed_scans_hand_in_a_hole_is_left_to_the_prior(model):
    """Issue 12, a clothed scanner scan (bench ``scanner``: a work suit, holes, a cut head top,
    the scanner's floor; 20 degrees) of held-out avatar 2 as the service reads it from a PLY
    file: his left hand is in a hole (8 % seen). Held by the clothed anchors to the posture the
    scan's few points there gave it, it turned over (51 mm mean error on the hand, 8.2 mm on the
    body); pulled to its rest posture (``FitParams.clothed_unseen_bones``) it is near the truth
    and said in ``unseen``. (A hand cut away entirely, 10-12 cm around it, is a guess either
    way: 21 -> 39 mm on this scan, 34 -> 27 mm on avatar 0's clothed mesh; not asserted.)"""
    from tests.bench import fitting as BF

    _, scan = _bench_scan(model, 4, "scanner", deg=20.0)
    up = BF.as_uploaded(model, scan, "ply")
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    hand = (np.argmax(F_rig._rig(model).W, axis=1) == BONES.index("hand_l"))[:model.n_body_vertices]

    def hand_mm(fit) -> float:
        C = scan.to_model @ np.linalg.inv(np.asarray(fit.to_model, np.float64))
        Pf = BF._apply(C, np.asarray(fit.posed_vertices, np.float64))
        return 1000 * float(surface.distances(scan.true_posed[:model.n_body_vertices][hand], Pf).mean())

    after = F.fit_body(model, up.points, up.normals, up.faces, clothed=True)
    before = F.fit_body(model, up.points, up.normals, up.faces, clothed=True,
                        params=BF.BEFORE_PARAMS("clothed_hands"))
    assert after.unseen == ["hand_l"] and before.unseen == [], (after.unseen, before.unseen)
    assert hand_mm(after) < 20.0 and BF.evaluate(model, scan, after, surface)["p2s_mm"] < 4.5
    assert hand_mm(before) > 30.0, hand_mm(before)


@pytest.mark.slow
def test_bench_fitting_via_file_end_to_end(capsys):
    """``tryon bench fitting --via-file ply --before head_hypothesis --json`` on one held-out
    person (a bare scan with the head's top cut, 20 degrees): the scan is fitted as read back
    from its PLY file, both fits land in the JSON with what the fit said."""
    import json

    from tests.bench.__main__ import main

    assert main(["fitting", "--limit", "1", "--max-pose-deg", "20", "--no-kill", "--no-person-check",
                 "--conditions", "cut_head", "--before", "head_hypothesis", "--via-file", "ply", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)["accuracy"]
    cond = res["conditions"]["cut_head"]
    assert res["via_file"] == "ply" and cond["fits"] == 1 and cond["failures"] == 0, cond["failure_examples"]
    row = cond["per_scan"][0]
    assert row["p2s_mm"] < 1.5 and "p2s_mm" in row["before"], row
    assert row["head_hypotheses"] in (1, 2) and isinstance(row["unseen"], list)


@pytest.mark.slow
def test_a_long_haired_scan_starts_from_its_own_height(model):
    """Issue 12, bench ``long_hair`` at 20 degrees (holes, hair down the back, the face poorly
    seen), held-out avatar 41 as the service reads her scan from a PLY file: the coarse stage
    left her 5.8 cm tall and the refinement stopped with her head risen into the hair, +1.96 cm
    (both head hypotheses wrong). Started from the stature her scan's height gives
    (``FitParams.init_stature_max``), she is fitted within 0.5 cm."""
    from tests.bench import fitting as BF

    person, scan = _bench_scan(model, 9, "long_hair", deg=20.0)
    assert person["index"] == 41
    up = BF.as_uploaded(model, scan, "ply")
    surface = BF.BodySurface(model.body_faces, model.n_body_vertices)
    after = BF.evaluate(model, scan, F.fit_body(model, up.points, up.normals, up.faces, clothed=False), surface)
    before = BF.evaluate(model, scan, F.fit_body(model, up.points, up.normals, up.faces, clothed=False,
                                                 params=BF.BEFORE_PARAMS("init_stature")), surface)
    assert abs(after["stature_err_cm"]) < 0.5 and after["p2s_mm"] < 1.0, after["stature_err_cm"]
    assert before["stature_err_cm"] > 1.5, before["stature_err_cm"]


@pytest.mark.parametrize("avatar", [2, 40])
def test_the_initial_stature_follows_the_scans_height(model, rig, avatar):
    """Issue 12: the coarse initialisation's rest stature stayed near the population's (12
    held-out bare scans at 20 degrees: -16.0 to +11.7 cm), and the refinement had to find the
    rest on its own. ``_stature_from_extent`` scales it by the scan's height over the posed
    body's. Here the posture is the person's own, the shape the population mean (171 cm): the
    tallest held-out man (196 cm) and the shortest woman (153 cm) come within a third of the
    mean's error (with the ratio's bound widened to 20 %: the mean is 11-14 % off them); by
    default a scan more than ``init_stature_max`` off (these, half a body) leaves the state
    alone."""
    from tests.bench.common import heldout_people

    person = next(p for p in heldout_people(model, 12) if p["index"] == avatar)
    rot = axis_angle_to_matrix(np.random.default_rng(avatar).normal(size=(17, 3)) * 0.15)
    truth = F_rig._State(np.asarray(person["weights"], np.float64), rot, np.zeros(3))
    V = F_rig._pose_model(rig, truth, F_rig._subset(rig, np.arange(model.n_body_vertices))).v
    scan = F_prepare._make_scan(V, vertex_normals(V, rig.faces), np.eye(3), np.zeros(3), 500, np.random.default_rng(0))
    start = F_rig._State(np.zeros(len(rig.U)), rot.copy(), np.zeros(3))

    def stature(s):
        return model.measure(model.vertices(s.beta), person["gender"])["height_cm"]

    target = stature(truth)
    from dataclasses import replace

    got = F_initialise._stature_from_extent(rig, scan, start, replace(F_params.DEFAULT_PARAMS, init_stature_max=0.2))
    assert got is not None and np.array_equal(got.rot, start.rot)
    assert F_initialise._stature_from_extent(rig, scan, start, F_params.DEFAULT_PARAMS) is None
    assert abs(stature(start) - target) > 10.0
    assert abs(stature(got) - target) < abs(stature(start) - target) / 3
    half = F_prepare._make_scan(V[V[:, 1] < np.median(V[:, 1])], vertex_normals(V, rig.faces)[V[:, 1] < np.median(V[:, 1])],
                        np.eye(3), np.zeros(3), 500, np.random.default_rng(0))
    assert F_initialise._stature_from_extent(rig, half, start, replace(F_params.DEFAULT_PARAMS, init_stature_max=0.2)) is None


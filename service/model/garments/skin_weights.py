"""Skin weights for garments: robust transfer from the body by weight inpainting.

Abdrashitov, Raichstat, Monsen, Hill, "Robust Skin Weights Transfer via Weight Inpainting"
(SIGGRAPH Asia 2023):

1. closest-point matching (Sec. 3.1): each garment vertex takes the body's weights
   interpolated (barycentric) at its closest point on the body surface; the match is *reliable*
   when the distance is below ``MAX_DISTANCE`` and the normals agree within ``MAX_ANGLE_DEG``
   (Eq. 1 and 2; garments are double-sided cloth, so a flipped normal counts as agreeing).
   Our addition: where neighbouring reliable matches jump (the garment bridges a crease such as
   the armpit, its vertices matched to the arm on one side and the torso on the other), the
   matches within ``JUMP_RADIUS`` are dropped too (:func:`weight_jumps`). Where the inpainted
   weights still change faster than ``MAX_WEIGHT_GRADIENT`` along an edge (a seam vertex with no
   reliable match between a sleeve vertex pinned to the arm and a torso vertex pinned to the
   torso: :func:`weight_jumps` compares reliable neighbours only), the matches within
   ``STEEP_RADIUS`` on the limb side of the edge are dropped as well (:func:`release_limb_side`):
   the sleeve's underside takes the change, the torso side keeps the body's weights (torso cloth
   given arm weight went into the torso when the arm came down). Catalogue, p99.9 pose stretch
   (5 bodies x 4 poses): cropped tee 5.25 -> 3.34, women's T-shirt 2.40 -> 2.22, casual jacket
   1.92 -> 1.65, dungarees 1.75 -> 1.61, share of vertices > 3 mm inside the posed body within
   +0.07 points of before (releasing both sides of the edge: cropped tee 2.92, but the jacket's
   1.83 -> 2.66 % inside);
2. inpainting (Sec. 3.2, Eq. 3-4): the other vertices' weights W_u minimise the Dirichlet energy
   tr(W^T L W) of the garment mesh with the reliable weights W_k as constraints, i.e.
   L_uu W_u = -L_uk W_k, one factorisation for all bones. L is the paper's discrete Dirichlet
   energy in the garment's metric: here each edge weighs 1 / length^2
   (:func:`metric_laplacian`, sum over edges of ((w_a - w_b) / l_ab)^2, the squared weight
   gradient along the edge), not the uniform graph Laplacian: garment meshes have mm-long edges
   at seams (armpits, crotch) where a uniform Laplacian spends as much of the weight change as on
   a 3 cm edge, and those edges stretched 3-16x in the page's poses. The paper's cotangent
   Laplacian (its negative weights on seam slivers clamped to 1e-3) did less well on the demo
   catalogue: p99.9 pose stretch median garment 2.43, worst 5.75, vs 1.92 and 5.25 with
   1 / length^2, both without step 3;
   our addition, screening (:func:`inpaint`, ``SCREENING``): the inpainted weights are also
   pulled a little toward the closest-point matches, so cloth far from every reliable match
   takes the weights of the body under it: the casual jacket's front, 3-4 cm off the torso with
   only 160 of its 1070 torso vertices within ``MAX_DISTANCE``, carried 0.17 arm weight on
   average (639 vertices over 0.1) diffused from the sleeves, and its hem rose with the arms in
   the arms-down pose; 0.022 (42) with screening 0.005 (0.02: 0.010 but the pencil skirt's
   p99.9 stretch on the mean body 1.40 -> 1.54);
3. our addition, release where the page's poses stretch (:func:`release_stretched`): the
   garment is posed in a few test poses (the page's presets on the mean body) with the inpainted
   weights; reliable vertices within ``RELEASE_RADIUS`` of an edge stretched over
   ``STRETCH_TARGET`` (its rest length taken as the shortest over the example fits, where a
   heavy body squeezes the armpit) are left to inpainting too, for up to
   ``MAX_RELEASE_ROUNDS`` rounds, keeping the round with the least p99.9 stretch: the weight
   change from torso to arm, or from one leg to the other, is spread over more cloth;
4. our addition, below the crotch (:func:`ramp_legs`): the left/right split of the leg bones'
   weight is a smooth ramp across the body's midplane (:func:`leg_ramp`), not the inpainted
   mix; how much of the weight is on the legs (vs the pelvis) stays the inpainted one. The
   paper's inpainting leaves a skirt's front and back, far from the body, to a harmonic mix of
   the two thighs that reaches over the thighs themselves (a vertex in front of the left thigh
   0.8 left / 0.2 right): in a walking step the forward thigh came through the pencil skirt's
   front (a slit of skin from hip to hem). With the ramp, cloth over a thigh follows it and only
   the cloth near the midplane blends the two: ``LEG_RAMP_HALF_WIDTH`` either side (trousers:
   the inner legs where the thighs touch), widened towards the hem by ``LEG_RAMP_WIDENING`` x
   the depth below the crotch for garments that enclose both legs (:func:`enclosure_depth`),
   which spreads the cloth's stretch between the parted legs; faded in over ``LEG_RAMP_FADE``
   below the crotch;
5. the 4 largest weights per vertex are kept and renormalised (the GLB's JOINTS_0/WEIGHTS_0,
   like ``BodyModel.lbs_indices`` / ``lbs_weights``).

Nearest-vertex copying (the previous rule) makes neighbouring skirt vertices follow different
legs; the inpainted weights vary smoothly over the garment, so it stretches instead of tearing.

Shapes: garment vertices (M, 3), faces (F, 3); body vertices (V, 3), body faces (Fb, 3);
body lbs_indices / lbs_weights (V, 4); dense weights (n, J); bone transforms (P, J, 4, 4) of P
test poses; edges (E, 2) in ``mesh_edges`` order.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, dijkstra

from service.model.geometry.mesh import closest_points_on_mesh, edge_length_graph, mesh_edges, vertex_normals
from service.model.body.lbs import skin
from service.model.geometry.solvers import factor_spd

MAX_DISTANCE = 0.02  # metres: a closest-point match farther than this is not reliable (Eq. 1)
MAX_ANGLE_DEG = 35.0  # normals must agree within this angle, up to sign (Eq. 2)
MAX_WEIGHT_GRADIENT = 40.0  # per metre: reliable matches that jump faster than this along a garment
# edge (the garment bridging a crease, e.g. the armpit, between arm and torso) are not reliable
JUMP_RADIUS = 0.04  # metres (geodesic over the garment edges) around such jumps also left to inpainting
STEEP_RADIUS = 0.02  # metres (geodesic) on the limb side of a steep inpainted edge left to inpainting
# (0.01: only the cropped tee gains, 5.25 -> 4.30, inside 1.29 -> 1.27 %, vs 3.34 and 1.36 %; 0.015: no gain
# on the jacket; 0.03: women's T-shirt 0.57 -> 0.69 % of its vertices > 3 mm inside the posed body)
TOP_K = 4  # joints per vertex in the GLB
SCREENING = 0.005  # the closest-point matches' weight where inpainted (x the mean diagonal of L): see inpaint
REGULARISATION = 1e-9  # added to L_uu's diagonal (x the mean diagonal): keeps the factorisation SPD
MIN_EDGE_LENGTH = 1e-4  # metres: shorter edges weigh as much as this in the metric Laplacian
STRETCH_TARGET = 1.4  # edge length ratio in a test pose above which nearby constraints are released
# (1.3: a little less stretch, 2.1 vs 2.3 at worst, but the sleeves lag the arms more: see README)
RELEASE_RADIUS = 0.03  # metres (geodesic over the garment edges) of reliable vertices released around it
MAX_RELEASE_ROUNDS = 6
LEG_RAMP_HALF_WIDTH = 0.03  # metres either side of the midplane over which a skirt blends the two legs
LEG_RAMP_FADE = 0.05  # metres over which the ramp fades in, from LEG_RAMP_START above the crotch down
LEG_RAMP_START = 0.04  # metres above the crotch where the fade starts
LEG_RAMP_WIDENING = 0.25  # a skirt's ramp half width grows by this x the depth below the crotch
# (0.35: pencil skirt p99.9 stretch 1.54 vs 1.68 but its walking show-through 1.1 vs 0.4 %; 0.15: 1.82, 0.4 %)
ENCLOSE_DEPTH = 0.15  # metres: a garment crossing the midplane lower than this below the crotch is a skirt
LEG_BONES = (("thigh_l", "shin_l", "foot_l"), ("thigh_r", "shin_r", "foot_r"))  # left, right chains
MIDPLANE_BAND = 0.005  # metres: body vertices this close to the midplane find the crotch (the lowest)
STRETCH_PERCENTILE = 99.9  # the round kept is the one with the least stretch at this percentile


def dense_weights(indices: np.ndarray, weights: np.ndarray, n_joints: int) -> np.ndarray:
    """Sparse-by-rows skin weights (n, k) + (n, k) -> dense (n, J) float64."""
    n = len(indices)
    W = np.zeros((n, n_joints))
    np.add.at(W, (np.repeat(np.arange(n), indices.shape[1]), np.asarray(indices).reshape(-1)),
              np.asarray(weights, np.float64).reshape(-1))
    return W


def top_k(W: np.ndarray, k: int = TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """Dense weights (n, J) -> the k largest per row: indices (n, k) int32 (descending weight;
    index 0 where the weight is 0, as the glTF validator wants) and weights (n, k) float32
    summing to 1."""
    W = np.clip(np.asarray(W, np.float64), 0.0, None)
    idx = np.argsort(-W, axis=1, kind="stable")[:, :k]
    w = np.take_along_axis(W, idx, axis=1)
    s = w.sum(axis=1, keepdims=True)
    empty = s[:, 0] <= 0
    w[empty] = 0.0
    w[empty, 0] = 1.0
    s[empty] = 1.0
    w = w / s
    idx = np.where(w > 0, idx, 0)
    return idx.astype(np.int32), w.astype(np.float32)


def uniform_laplacian(faces: np.ndarray, n: int) -> sp.csr_matrix:
    """The graph Laplacian L = D - A (n, n) of the mesh edges (positive semi-definite)."""
    e = mesh_edges(faces)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


def metric_laplacian(vertices: np.ndarray, faces: np.ndarray, lengths: np.ndarray | None = None) -> sp.csr_matrix:
    """L = D - A (n, n) with A_ab = 1 / l_ab^2 on every mesh edge: tr(W^T L W) = sum over edges of
    |W_a - W_b|^2 / l_ab^2, the squared weight gradient along the edges (the Dirichlet energy of
    Eq. 3 in the garment's metric). ``lengths`` (E,) in ``mesh_edges`` order: the edge lengths to
    use (default: those of ``vertices`` (n, 3)), floored at ``MIN_EDGE_LENGTH``."""
    X = np.asarray(vertices, np.float64)
    n = len(X)
    e = mesh_edges(faces)
    if lengths is None:
        lengths = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    a = 1.0 / np.maximum(np.asarray(lengths, np.float64), MIN_EDGE_LENGTH) ** 2
    A = sp.coo_matrix((np.r_[a, a], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    return (sp.diags(np.asarray(A.sum(axis=1)).ravel()) - A).tocsr()


def closest_point_weights(vertices: np.ndarray, faces: np.ndarray, body_vertices: np.ndarray,
                          body_faces: np.ndarray, body_weights: np.ndarray, *,
                          max_distance: float = MAX_DISTANCE,
                          max_angle_deg: float = MAX_ANGLE_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Step 1: the body's dense weights (Vb, J) interpolated at each garment vertex's closest
    body point -> (weights (M, J) float64, reliable (M,) bool)."""
    W, reliable, _ = _closest_point_match(vertices, faces, body_vertices, body_faces, body_weights,
                                          max_distance, max_angle_deg)
    return W, reliable


def _closest_point_match(vertices, faces, body_vertices, body_faces, body_weights, max_distance: float,
                         max_angle_deg: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`closest_point_weights` and the distance (M,) of each vertex to the body."""
    X = np.asarray(vertices, np.float64)
    Vb = np.asarray(body_vertices, np.float64)
    Fb = np.asarray(body_faces, np.int64)
    face, q, bary = closest_points_on_mesh(X, Vb, Fb)
    W = np.einsum("mk,mkj->mj", bary, np.asarray(body_weights, np.float64)[Fb[face]])
    nb = vertex_normals(Vb, Fb).astype(np.float64)
    nq = np.einsum("mk,mkj->mj", bary, nb[Fb[face]])
    nq /= np.maximum(np.linalg.norm(nq, axis=1, keepdims=True), 1e-12)
    ng = vertex_normals(X, faces).astype(np.float64)
    dist = np.linalg.norm(X - q, axis=1)
    cos = np.abs(np.einsum("ij,ij->i", ng, nq))
    reliable = (dist < max_distance) & (cos >= np.cos(np.radians(max_angle_deg)))
    return W, reliable, dist


def weight_jumps(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, reliable: np.ndarray, *,
                 max_gradient: float = MAX_WEIGHT_GRADIENT, radius: float = JUMP_RADIUS) -> np.ndarray:
    """(M,) bool: vertices within ``radius`` (geodesic along the garment edges) of an edge
    between two reliable vertices whose weights (M, J) differ by more than ``max_gradient`` x the
    edge length (L1 norm): there the closest-point matches disagree (the garment spans a crease
    the body's weights cross over a longer path) and inpainting must decide instead."""
    X = np.asarray(vertices, np.float64)
    e = mesh_edges(faces)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    jump = np.abs(W[e[:, 0]] - W[e[:, 1]]).sum(axis=1) > max_gradient * length
    jump &= reliable[e[:, 0]] & reliable[e[:, 1]]
    seeds = np.unique(e[jump])
    if not len(seeds):
        return np.zeros(len(X), bool)
    d = dijkstra(edge_length_graph(X, faces), directed=False, indices=seeds, min_only=True, limit=radius)
    return np.isfinite(d)


def inpaint(W: np.ndarray, known: np.ndarray, laplacian: sp.spmatrix, screening: float = 0.0) -> np.ndarray:
    """Step 2 (Eq. 3-4): weights (n, J) with rows ``known`` (n,) bool kept and the others the
    minimiser of tr(W^T L W): L_uu W_u = -L_uk W_k (factored once, J right-hand sides). Every
    connected component needs a known vertex (see :func:`transfer_skin_weights`). With
    ``screening`` s > 0 (our addition), the minimiser of tr(W^T L W) + s d sum_u |W_u - W0_u|^2,
    W0 the closest-point matches W has in the unknown rows and d the mean diagonal of L:
    (L_uu + s d I) W_u = -L_uk W_k + s d W0_u. Far from every reliable match, cloth takes the
    weights of the body under it rather than whatever diffuses from the nearest constraint (a
    loose jacket's front, 3-4 cm off the torso, took the sleeves' arm weight: its hem rose with
    the arms)."""
    L = sp.csr_matrix(laplacian)
    u = np.flatnonzero(~known)
    k = np.flatnonzero(known)
    out = np.array(W, np.float64)
    if len(u) == 0:
        return out
    d = float(np.abs(L.diagonal()).mean() or 1.0)
    Luu = L[u][:, u] + sp.identity(len(u)) * ((REGULARISATION + screening) * d)
    rhs = -(L[u][:, k] @ out[k]) + screening * d * out[u]
    out[u] = factor_spd(Luu).solve(rhs)
    return out


def pose_stretch(vertices: np.ndarray, edges: np.ndarray, transforms: np.ndarray, indices: np.ndarray,
                 weights: np.ndarray, rest_lengths: np.ndarray | None = None) -> np.ndarray:
    """(E,) the largest edge length ratio posed / rest of ``edges`` (E, 2) of ``vertices`` (n, 3)
    skinned by ``indices`` / ``weights`` (n, k) over the test poses ``transforms`` (P, J, 4, 4).
    With ``rest_lengths`` (E,) (shorter than the edges of ``vertices``: the garment on another
    body) the ratio is extrapolated: the length an edge gains in a pose comes from the weight
    difference of its ends (nearly the same on both bodies), so ratio - 1 grows as l / rest."""
    X = np.asarray(vertices, np.float64)
    length = np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1)
    ok = length > 0
    s = np.ones(len(edges))
    for G in np.asarray(transforms, np.float64):
        P = skin(X, G, indices, weights)
        s[ok] = np.maximum(s[ok], np.linalg.norm(P[edges[ok, 0]] - P[edges[ok, 1]], axis=1) / length[ok])
    if rest_lengths is not None:
        s[ok] = 1.0 + (s[ok] - 1.0) * length[ok] / np.maximum(np.minimum(rest_lengths[ok], length[ok]), MIN_EDGE_LENGTH)
    return s


def _keep_one_per_component(reliable: np.ndarray, labels: np.ndarray, n_comp: int, distance: np.ndarray) -> np.ndarray:
    """A connected piece of the garment with no reliable vertex gets its vertex nearest the body
    (``distance`` (M,)) back as reliable (inpainting needs one per component)."""
    reliable = reliable.copy()
    has = np.bincount(labels, weights=reliable.astype(np.float64), minlength=n_comp) > 0
    for c in np.flatnonzero(~has):
        members = np.flatnonzero(labels == c)
        reliable[members[np.argmin(distance[members])]] = True
    return reliable


def release_stretched(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, reliable: np.ndarray,
                      laplacian: sp.spmatrix, transforms: np.ndarray, distance: np.ndarray, *,
                      rest_lengths: np.ndarray | None = None, k: int = TOP_K,
                      target: float = STRETCH_TARGET, radius: float = RELEASE_RADIUS,
                      rounds: int = MAX_RELEASE_ROUNDS, legs: LegFrame | None = None,
                      screening: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Step 3: inpaint (Eq. 3-4), pose the garment in the test poses ``transforms`` (P, J, 4, 4),
    release the reliable vertices within ``radius`` (geodesic) of every edge stretched over
    ``target`` (:func:`pose_stretch`), inpaint again; at most ``rounds`` times. Returns the top-k
    weights (indices (M, k) int32, weights (M, k) float32) of the round with the least
    ``STRETCH_PERCENTILE`` stretch. W (M, J) closest-point weights, reliable (M,) bool,
    distance (M,) to the body (a component never loses its nearest reliable vertex); ``legs``:
    step 4 after each inpainting (:func:`ramp_legs`)."""
    X = np.asarray(vertices, np.float64)
    M = len(X)
    e = mesh_edges(faces)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    graph = sp.coo_matrix((np.r_[length, length], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                          shape=(M, M)).tocsr()
    n_comp, labels = connected_components(graph, directed=False)
    best: tuple[float, np.ndarray, np.ndarray] | None = None
    for _ in range(rounds + 1):
        Wi = inpaint(W, reliable, laplacian, screening)
        idx, w = top_k(Wi if legs is None else ramp_legs(X, faces, Wi, legs), k)
        s = pose_stretch(X, e, transforms, idx, w, rest_lengths)
        score = float(np.percentile(s, STRETCH_PERCENTILE)) if len(s) else 1.0
        if best is None or score < best[0]:
            best = (score, idx, w)
        bad = s > target
        if not bad.any():
            break
        d = dijkstra(graph, directed=False, indices=np.unique(e[bad]), min_only=True, limit=radius)
        released = reliable & np.isfinite(d)
        if not released.any():
            break
        reliable = _keep_one_per_component(reliable & ~released, labels, n_comp, distance)
    assert best is not None
    return best[1], best[2]


def bone_depths(parents: np.ndarray) -> np.ndarray:
    """(J,) float: each bone's number of ancestors (the root 0) from its parent index (J,)
    (-1 for the root; parents listed before their children)."""
    depth = np.zeros(len(parents))
    for j, p in enumerate(parents):
        if p >= 0:
            depth[j] = depth[p] + 1
    return depth


def release_limb_side(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, reliable: np.ndarray,
                      laplacian: sp.spmatrix, parents: np.ndarray, *, max_gradient: float = MAX_WEIGHT_GRADIENT,
                      radius: float = STEEP_RADIUS, screening: float = 0.0) -> np.ndarray:
    """Reliable (M,) bool less the matches on the limb side of steep inpainted edges: inpaint W
    (M, J) from ``reliable`` (Eq. 3-4), find the edges whose weights differ by more than
    ``max_gradient`` x their length (L1), take each one's end nearer the root (the smaller
    weighted bone depth d = W_i . depth, :func:`bone_depths` of ``parents`` (J,)) as a seed,
    and release the reliable vertices within ``radius`` (geodesic over the garment edges) of
    their nearest seed that lie deeper than it (the sleeve's side of an armpit seam)."""
    X = np.asarray(vertices, np.float64)
    e = mesh_edges(faces)
    length = np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1)
    Wi = inpaint(W, reliable, laplacian, screening)
    steep = np.abs(Wi[e[:, 0]] - Wi[e[:, 1]]).sum(axis=1) > max_gradient * length
    if not steep.any():
        return reliable
    depth = Wi @ bone_depths(np.asarray(parents))
    a, b = e[steep, 0], e[steep, 1]
    seeds = np.unique(np.where(depth[a] <= depth[b], a, b))
    n = len(X)
    graph = sp.coo_matrix((np.r_[length, length], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                          shape=(n, n)).tocsr()
    d, _, src = dijkstra(graph, directed=False, indices=seeds, min_only=True, limit=radius,
                         return_predecessors=True)
    near = np.isfinite(d)
    limb = np.zeros(n, bool)
    limb[near] = depth[near] > depth[src[near]]
    return reliable & ~limb


@dataclass(frozen=True)
class LegFrame:
    """Where the legs are on the body the weights are transferred from: ``left`` / ``right``
    (3,) int joint indices of the leg chains (thigh, shin, foot, paired), ``origin`` (3,) a point
    of the midplane, ``lateral`` (3,) its unit normal towards the left leg, ``up`` (3,) unit, and
    ``crotch`` the height (along ``up``) of the crotch."""

    left: np.ndarray
    right: np.ndarray
    origin: np.ndarray
    lateral: np.ndarray
    up: np.ndarray
    crotch: float


def leg_frame(body_vertices: np.ndarray, joints: np.ndarray, bone_names: list[str]) -> LegFrame:
    """The :class:`LegFrame` of a body (Vb, 3) with joint positions (J, 3) named ``bone_names``:
    the midplane halfway between the hips, normal to hip-to-hip; up from the knees to the hips;
    the crotch the lowest body vertex within ``MIDPLANE_BAND`` of the midplane between knee and
    hip height."""
    name = {n: i for i, n in enumerate(bone_names)}
    left = np.array([name[b] for b in LEG_BONES[0]])
    right = np.array([name[b] for b in LEG_BONES[1]])
    J = np.asarray(joints, np.float64)
    hip_l, hip_r = J[left[0]], J[right[0]]
    lateral = (hip_l - hip_r) / np.linalg.norm(hip_l - hip_r)
    origin = (hip_l + hip_r) / 2
    knees = (J[left[1]] + J[right[1]]) / 2
    up = origin - knees
    up -= lateral * (up @ lateral)
    up /= np.linalg.norm(up)
    X = np.asarray(body_vertices, np.float64) - origin
    h = X @ up
    mid = (np.abs(X @ lateral) < MIDPLANE_BAND) & (h < 0) & (h > (knees - origin) @ up)
    crotch = float(h[mid].min()) if mid.any() else 0.0
    return LegFrame(left, right, origin, lateral, up, crotch + float(origin @ up))


def enclosure_depth(vertices: np.ndarray, faces: np.ndarray, legs: LegFrame) -> float:
    """How far (metres) below the crotch a garment (M, 3) / (F, 3) still crosses the midplane
    (the lowest garment edge with ends on either side of it; 0 when none does below the crotch):
    a skirt's hem, a trouser's crotch seam."""
    X = np.asarray(vertices, np.float64)
    e = mesh_edges(faces)
    left = (X - legs.origin) @ legs.lateral >= 0
    cross = left[e[:, 0]] != left[e[:, 1]]
    if not cross.any():
        return 0.0
    h = (X @ legs.up)[e[cross]].max(axis=1)
    return max(0.0, legs.crotch - float(h.min()))


def leg_ramp(vertices: np.ndarray, W: np.ndarray, legs: LegFrame, *, half_width: float = LEG_RAMP_HALF_WIDTH,
             fade: float = LEG_RAMP_FADE, widening: float = 0.0) -> np.ndarray:
    """Step 4: dense weights (M, J) with the legs' share split left/right by position below the
    crotch. Per vertex the two chains' weights are summed bone by bone (thigh with thigh, ...)
    into one chain profile P, then given to the left chain x r and the right x (1 - r), with
    r = clip(1/2 + s / (2 w), 0, 1) of the signed distance s (m) to the midplane and the ramp's
    half width w = ``half_width`` + ``widening`` x (depth below the crotch) (a skirt: the legs
    part more towards the hem, the cloth between them spreads over more of it); blended with W
    by f = clip((depth + ``LEG_RAMP_START``) / ``fade``, 0, 1). The pelvis / spine weights are kept, so rows still sum
    as before."""
    X = np.asarray(vertices, np.float64)
    out = np.array(W, np.float64)
    s = (X - legs.origin) @ legs.lateral
    depth = np.maximum(legs.crotch - X @ legs.up, 0.0)
    r = np.clip(0.5 + s / (2 * (half_width + widening * depth)), 0.0, 1.0)
    f = np.clip((legs.crotch + LEG_RAMP_START - X @ legs.up) / fade, 0.0, 1.0)
    P = out[:, legs.left] + out[:, legs.right]
    out[:, legs.left] = (1 - f)[:, None] * out[:, legs.left] + (f * r)[:, None] * P
    out[:, legs.right] = (1 - f)[:, None] * out[:, legs.right] + (f * (1 - r))[:, None] * P
    return out


def ramp_legs(vertices: np.ndarray, faces: np.ndarray, W: np.ndarray, legs: LegFrame) -> np.ndarray:
    """Step 4 for any garment (M, 3) / (F, 3), dense weights (M, J): the narrow ramp, widened by
    ``LEG_RAMP_WIDENING`` where the garment encloses both legs (crosses the midplane more than
    ``ENCLOSE_DEPTH`` below the crotch: skirts, dresses, long coats)."""
    skirt = enclosure_depth(vertices, faces, legs) > ENCLOSE_DEPTH
    return leg_ramp(vertices, W, legs, widening=LEG_RAMP_WIDENING if skirt else 0.0)


def transfer_skin_weights(vertices: np.ndarray, faces: np.ndarray, body_vertices: np.ndarray,
                          body_faces: np.ndarray, lbs_indices: np.ndarray, lbs_weights: np.ndarray,
                          n_joints: int, *, max_distance: float = MAX_DISTANCE,
                          max_angle_deg: float = MAX_ANGLE_DEG, k: int = TOP_K,
                          test_transforms: np.ndarray | None = None,
                          rest_lengths: np.ndarray | None = None,
                          legs: LegFrame | None = None,
                          parents: np.ndarray | None = None,
                          screening: float = SCREENING) -> tuple[np.ndarray, np.ndarray]:
    """Garment skin weights from the body's: closest-point matches on reliable vertices,
    less those on the limb side of steep inpainted edges (``parents`` (J,): the bones' parent
    indices; None: none released), inpainted over the rest (metric Laplacian), released around
    edges that the test poses stretch, the legs' share ramped left/right below the crotch when the garment encloses both
    legs (``legs``: the body's :class:`LegFrame`; None: no ramp), top-k renormalised.

    vertices (M, 3), faces (F, 3): the garment on ``body_vertices`` (Vb, 3) / ``body_faces``;
    lbs_indices / lbs_weights (Vb, 4) the body's; test_transforms (P, J, 4, 4): bone transforms
    of test poses of that body (None: no release step); rest_lengths (E,) in ``mesh_edges``
    order: the shortest length of each edge on the bodies the garment is worn on (the example
    fits). Returns (indices (M, k) int32, weights (M, k) float32). A connected piece of the
    garment with no reliable vertex keeps the match of its vertex nearest the body."""
    faces = np.asarray(faces, np.int64)
    X = np.asarray(vertices, np.float64)
    Wb = dense_weights(lbs_indices, lbs_weights, n_joints)
    W, reliable, distance = _closest_point_match(X, faces, body_vertices, body_faces, Wb, max_distance, max_angle_deg)
    reliable &= ~weight_jumps(X, faces, W, reliable)
    L = metric_laplacian(X, faces)
    n_comp, labels = connected_components(L, directed=False)
    reliable = _keep_one_per_component(reliable, labels, n_comp, distance)
    if parents is not None:
        released = release_limb_side(X, faces, W, reliable, L, parents, screening=screening)
        reliable = _keep_one_per_component(released, labels, n_comp, distance)
    if test_transforms is None or len(test_transforms) == 0:
        Wi = inpaint(W, reliable, L, screening)
        return top_k(Wi if legs is None else ramp_legs(X, faces, Wi, legs), k)
    return release_stretched(X, faces, W, reliable, L, test_transforms, distance, rest_lengths=rest_lengths, k=k,
                             legs=legs, screening=screening)


# -- step 6: the legs' weights refined in strides --------------------------------------------------
STRIDE_STRETCH = 1.1  # an edge posed longer than this x its length on that body is pulled back to it
STRIDE_FIDELITY = 1e-4  # pull toward the transferred weights (x the mean diagonal of the stretch term)
STRIDE_CONTACT = 100.0  # weight of the one-sided contact rows (x that diagonal, x 4 / the cases' count)
STRIDE_SUM = 10.0  # weight of each vertex's weights summing to 1 (x that diagonal)
STRIDE_GAP = 0.003  # metres: a garment vertex keeps min(its gap at rest, this) off its body point ...
STRIDE_SLACK = 0.0005  # ... unless the transferred weights already took it closer (and inside: this deeper at most)
STRIDE_COVER = 0.002  # metres: a covered body vertex keeps its garment point this far out (or as far as before)
STRIDE_COVER_DISTANCE = 0.05  # metres: a body vertex is covered when the garment's closest point is this close ...
STRIDE_ROUNDS = 10  # local-global rounds, then as many again within each vertex's top-k joints
STRIDE_MIN_LEG_WEIGHT = 1e-3  # the refined vertices: those with at least this much weight on the leg bones
STRIDE_MAX_VERTICES = 4000  # a garment with more of them keeps its transferred weights: the refinement holds
# 6 poses x 5 bodies of operators over (vertices x joints) unknowns (men's jeans, 886 vertices: 4 s on 2 cores,
# 112 MB at peak; the dungarees, 3,763: 133 MB)


def covered_points(body: np.ndarray, body_faces: np.ndarray, garment: np.ndarray, faces: np.ndarray,
                   body_normals: np.ndarray | None = None,
                   max_distance: float = STRIDE_COVER_DISTANCE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The body's (V, 3) vertices covered by the garment (M, 3) / faces (F, 3): its closest point
    within ``max_distance`` and over the vertex (the offset within 45 degrees of the body normal,
    ``body_normals`` (V, 3) or computed). Returns (body vertex ids (K,), garment face (K,),
    barycentric (K, 3)): garment points that follow the vertex through a pose."""
    B = np.asarray(body, np.float64)
    n = vertex_normals(B, body_faces).astype(np.float64) if body_normals is None else body_normals
    face, q, bary = closest_points_on_mesh(B, np.asarray(garment, np.float64), np.asarray(faces))
    d = q - B
    dist = np.linalg.norm(d, axis=1)
    ok = (dist < max_distance) & (np.einsum("ij,ij->i", d, n) > np.cos(np.pi / 4) * dist)
    return np.flatnonzero(ok), face[ok], bary[ok]


@dataclass(frozen=True)
class StrideCase:
    """One body the garment is refined on: the garment on it (M, 3), the rest body (Vb, 3), and
    test poses of that body: bone transforms (P, J, 4, 4) and the posed body (P, Vb, 3)."""

    garment: np.ndarray
    body: np.ndarray
    transforms: np.ndarray
    posed: np.ndarray


def _stride_terms(case: StrideCase, faces: np.ndarray, body_faces: np.ndarray, W0: np.ndarray, act: np.ndarray,
                  joints: np.ndarray, e: np.ndarray) -> list[dict]:
    """The linear operators of :func:`refine_in_strides` for one body, per pose: with w the
    refined weights (A x S, flattened; A = ``act`` vertices, S = ``joints``) and the other
    weights those of W0 (M, J), the posed edge vectors are ``D w + fx`` (3E,), the garment
    vertices' heights along their body points' normals ``Pn w + pfix`` (A,), and the covered
    body vertices' garment points' heights over them ``Q w + qfix`` (K,)."""
    X = np.asarray(case.garment, np.float64)
    body = np.asarray(case.body, np.float64)
    M, nA, nS = len(X), len(act), len(joints)
    pos = -np.ones(M, np.int64)
    pos[act] = np.arange(nA)
    nvar = nA * nS

    def lin(vid: np.ndarray, coef: np.ndarray, Y: np.ndarray, rows: np.ndarray):
        """COO parts of sum over points of coef (n, 3) . sum_s w_(vid, s) Y_(vid, s) into ``rows``
        (n,), and the fixed part (n,) from W0's other weights."""
        a = pos[vid] >= 0
        r = np.repeat(rows[a], nS)
        c = (pos[vid[a]][:, None] * nS + np.arange(nS)[None]).ravel()
        v = np.einsum("asj,aj->as", Y[vid[a]][:, joints, :], coef[a]).ravel()
        Wf = W0[vid].copy()
        Wf[np.ix_(a, joints)] = 0.0
        fixed = np.einsum("nj,nj->n", np.einsum("nsj,ns->nj", Y[vid], Wf), coef)
        return r, c, v, fixed

    le = np.maximum(np.linalg.norm(X[e[:, 0]] - X[e[:, 1]], axis=1), MIN_EDGE_LENGTH)
    face, q, bary = closest_points_on_mesh(X[act], body, body_faces)
    n0 = vertex_normals(body, body_faces).astype(np.float64)
    nq = np.einsum("mk,mkj->mj", bary, n0[body_faces[face]])
    nq /= np.maximum(np.linalg.norm(nq, axis=1, keepdims=True), 1e-12)
    gap = np.clip(np.minimum(np.einsum("ij,ij->i", X[act] - q, nq), STRIDE_GAP), 0.0, None)
    cid, cface, cbary = covered_points(body, body_faces, X, faces, n0)
    cv = faces[cface]
    mine = (pos[cv] >= 0).any(axis=1)
    cid, cv, cbary = cid[mine], cv[mine], cbary[mine]
    Xh = np.c_[X, np.ones(M)]
    out = []
    for G, pb in zip(np.asarray(case.transforms, np.float64), np.asarray(case.posed, np.float64)):
        Y = np.einsum("jab,mb->mja", G[:, :3, :], Xh)  # (M, J, 3): each vertex moved by each bone
        npb = vertex_normals(pb, body_faces).astype(np.float64)
        qp = np.einsum("mk,mkj->mj", bary, pb[body_faces[face]])
        nqp = np.einsum("mk,mkj->mj", bary, npb[body_faces[face]])
        nqp /= np.maximum(np.linalg.norm(nqp, axis=1, keepdims=True), 1e-12)
        parts, fx = [], np.zeros((len(e), 3))
        for sign, end in ((1.0, 0), (-1.0, 1)):
            for k in range(3):
                coef = np.zeros((len(e), 3))
                coef[:, k] = sign
                r, c, v, f = lin(e[:, end], coef, Y, 3 * np.arange(len(e)) + k)
                parts.append((r, c, v))
                fx[:, k] += f
        D = sp.csr_matrix((np.concatenate([p[2] for p in parts]), (np.concatenate([p[0] for p in parts]),
                                                                  np.concatenate([p[1] for p in parts]))),
                          shape=(3 * len(e), nvar))
        r, c, v, f = lin(act, nqp, Y, np.arange(nA))
        Pn = sp.csr_matrix((v, (r, c)), shape=(nA, nvar))
        pfix = f - np.einsum("aj,aj->a", qp, nqp)
        nrm = npb[cid]
        parts, qfix = [], -np.einsum("kj,kj->k", pb[cid], nrm)
        for corner in range(3):
            r, c, v, f = lin(cv[:, corner], cbary[:, corner, None] * nrm, Y, np.arange(len(cid)))
            parts.append((r, c, v))
            qfix += f
        Q = sp.csr_matrix((np.concatenate([p[2] for p in parts]), (np.concatenate([p[0] for p in parts]),
                                                                  np.concatenate([p[1] for p in parts]))),
                          shape=(len(cid), nvar))
        out.append({"D": D, "fx": fx, "le": le, "Pn": Pn, "pfix": pfix, "gap": gap, "Q": Q, "qfix": qfix})
    return out


def refine_in_strides(W: np.ndarray, faces: np.ndarray, body_faces: np.ndarray, cases: list[StrideCase],
                      leg_joints: np.ndarray, *, k: int = TOP_K) -> tuple[np.ndarray, np.ndarray]:
    """Step 6 (our addition): the weights (M, J) of the garment's vertices on the legs (at least
    ``STRIDE_MIN_LEG_WEIGHT`` on ``leg_joints``) re-solved so that the test poses of ``cases``
    (strides, on a few bodies) stretch no edge past ``STRIDE_STRETCH`` while the cloth keeps
    off the body where the transferred weights kept it. A posed vertex is linear in its weights,
    x_i = sum_j w_ij G_j [x_i; 1], so every condition is a linear one: local-global rounds
    (as ARAP's) alternate (local) each posed edge projected to its allowed length, and each
    garment vertex (body point under it, along its normal) or covered body vertex (its garment
    point over it) that went inside its floor as a one-sided row, with (global) the least
    squares of those targets, ``STRIDE_FIDELITY`` x |W - W0|^2 and rows summing to 1; then the
    same within each vertex's ``k`` largest joints, which the GLB keeps. The floors: a garment
    vertex at least min(its gap at rest, ``STRIDE_GAP``) off the body, a covered body vertex
    under its garment point by ``STRIDE_COVER``, each relaxed to where W0 already took it.
    Without this, the weight change between the legs, spread over the few centimetres the leg
    ramp gives it, stretches the crotch's front in a walking step up to 1.9x on a heavy body;
    spreading it wider by a fixed rule lets the forward thigh through the cloth (docs/drape.md).
    A garment with more than ``STRIDE_MAX_VERTICES`` such vertices keeps the weights W.
    Returns the top-k (indices (M, k) int32, weights (M, k) float32)."""
    W0 = np.clip(np.asarray(W, np.float64), 0.0, None)
    faces = np.asarray(faces, np.int64)
    body_faces = np.asarray(body_faces, np.int64)
    act = np.flatnonzero(W0[:, np.asarray(leg_joints)].sum(axis=1) >= STRIDE_MIN_LEG_WEIGHT)
    if not len(act) or not cases or len(act) > STRIDE_MAX_VERTICES:
        return top_k(W0, k)
    joints = np.flatnonzero(W0[act].max(axis=0) >= STRIDE_MIN_LEG_WEIGHT)
    nA, nS = len(act), len(joints)
    nvar = nA * nS
    on = np.zeros(len(W0), bool)
    on[act] = True
    e = mesh_edges(faces)
    e = e[on[e[:, 0]] | on[e[:, 1]]]
    terms = [t for case in cases for t in _stride_terms(case, faces, body_faces, W0, act, joints, e)]
    # all bodies and poses as one system: edges (3E rows each), contacts (garment side, body side)
    D = sp.vstack([t["D"] for t in terms]).tocsr()
    fx = np.concatenate([t["fx"] for t in terms])
    le = np.concatenate([t["le"] for t in terms])
    cw = np.repeat(1.0 / le ** 2, 3)
    C = sp.vstack([t[a] for t in terms for a in ("Pn", "Q")]).tocsr()
    cfix = np.concatenate([t[a] for t in terms for a in ("pfix", "qfix")])
    H0 = (D.T @ sp.diags(cw) @ D).tocsr()
    scale = float(H0.diagonal().mean()) or 1.0
    mu, kap, nu = STRIDE_FIDELITY * scale, STRIDE_SUM * scale, STRIDE_CONTACT * scale * 4 / len(terms)
    rows = sp.csr_matrix((np.ones(nvar), (np.repeat(np.arange(nA), nS), np.arange(nvar))), shape=(nA, nvar))
    w0 = W0[act][:, joints].ravel()
    H = (H0 + mu * sp.identity(nvar) + kap * (rows.T @ rows)).tocsr()
    base = mu * w0 + kap * (rows.T @ np.ones(nA))
    # floors: a garment vertex min(its gap at rest, STRIDE_GAP) off its body point, a covered body vertex's
    # garment point STRIDE_COVER over it, or only as far as W0 already kept them (less STRIDE_SLACK once inside)
    c0 = C @ w0 + cfix
    limit = np.concatenate([t["gap"] if a == "Pn" else np.full(t["Q"].shape[0], STRIDE_COVER)
                            for t in terms for a in ("Pn", "Q")])
    floor = np.where(c0 >= limit, limit, np.where(c0 >= 0, c0, c0 - STRIDE_SLACK))
    w = w0.copy()
    kk = np.arange(nvar)
    factor = None  # H's (a round without contact rows)
    for it in range(2 * STRIDE_ROUNDS):
        if it == STRIDE_ROUNDS:  # within each vertex's k largest joints from here on
            top = np.argsort(-w.reshape(nA, nS), axis=1)[:, :k]
            mask = np.zeros((nA, nS), bool)
            np.put_along_axis(mask, top, True, axis=1)
            kk = np.flatnonzero(mask.ravel())
            w = np.where(mask.ravel(), w, 0.0)
            H = H[kk][:, kk].tocsr()
            factor = None
        ev = (D @ w).reshape(-1, 3) + fx
        length = np.linalg.norm(ev, axis=1)
        target = ev * np.minimum(1.0, STRIDE_STRETCH * le / np.maximum(length, 1e-12))[:, None]
        rhs = base + D.T @ (cw * (target - fx).ravel())
        inside = np.flatnonzero(C @ w + cfix < floor)  # the contact rows of this round
        if not len(inside):
            factor = factor or factor_spd(H)
            w[kk] = factor.solve(rhs[kk])
            continue
        A = C[inside][:, kk].tocsr()
        rhs = (rhs + nu * (C[inside].T @ (floor[inside] - cfix[inside])))[kk]
        w[kk] = factor_spd((H + nu * (A.T @ A)).tocsc()).solve(rhs)
    out = W0.copy()
    out[np.ix_(act, joints)] = w.reshape(nA, nS)
    return top_k(out, k)

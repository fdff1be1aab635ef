"""Shared helpers of the benchmarks: the shared data directory (ANSUR II, MakeHuman garments),
held-out avatars (never seen by any build step), timing, and the body model."""
from __future__ import annotations

import csv
import os
import time
from pathlib import Path

import numpy as np

from service.model.body import measurements as M
from service.model.formats import mhclo

DATA_DIR = Path(__file__).resolve().parent.parent / "data"
HELDOUT_AVATARS = DATA_DIR / "heldout_avatars.npz"


def heldout_avatars(model) -> np.ndarray:
    """(n, V, 3) held-out evaluation avatars (``tests/data/heldout_avatars.npz``: avatars of
    held-out ANSUR II subjects, fitted by the body-model build, never used by it)."""
    z = np.load(HELDOUT_AVATARS)
    return model.mean[None].astype(np.float64) + z["offsets"].astype(np.float64) * float(z["scale"])


def heldout_genders() -> list[str]:
    """The gender of each of :func:`heldout_avatars`, in the same order."""
    return [str(g) for g in np.load(HELDOUT_AVATARS)["gender"]]


def surface_distances(a: np.ndarray, b: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(2M,) metres: each vertex of mesh a (M, 3) to the surface of mesh b (M, 3), then each of b
    to a's, both with ``faces`` (F, 3): how far apart the two shapes are, whatever the cloth's
    sliding along itself (which the vertex-to-vertex distance counts too)."""
    from service.model.geometry.mesh import closest_points_on_mesh

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    _, qa, _ = closest_points_on_mesh(a, b, faces)
    _, qb, _ = closest_points_on_mesh(b, a, faces)
    return np.r_[np.linalg.norm(a - qa, axis=1), np.linalg.norm(b - qb, axis=1)]


def shared_data_dir() -> Path:
    env = os.environ.get("TRYON_SHARED_DATA")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "shared" / "data"


def read_ansur(heldout: bool) -> list[dict]:
    """ANSUR II subjects in API units: {"row", "measurements": {12 attributes}}."""
    base = shared_data_dir() / "anthropometry" / "ansur2"
    out = []
    for fname, gender, enc in (("ANSUR_II_MALE_Public.csv", "male", "latin-1"),
                               ("ANSUR_II_FEMALE_Public.csv", "female", "ascii")):
        with open(base / fname, encoding=enc, newline="") as f:
            for i, r in enumerate(csv.DictReader(f)):
                if (i % 5 == 0) != heldout:
                    continue
                m = {"gender": gender}
                for name in M.ATTRIBUTES[1:]:
                    v = float(r[M.ANSUR_COLUMNS[name]])
                    m[name] = v / 10.0  # mm -> cm, and weightkg is in 0.1 kg
                out.append({"row": i, "measurements": m})
    return out


def median_ms(fn, repeats: int) -> float:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return 1000.0 * float(np.median(ts))




def makehuman_garments(model) -> dict:
    """The MakeHuman CC0 garments of ../shared/data (tests and benchmarks only): name ->
    (fit function avatar -> (M, 3), faces)."""
    out = {}
    base = shared_data_dir() / "makehuman_clothes"
    for f in sorted(base.glob("*/*.mhclo")):
        b = mhclo.parse_mhclo(f.read_text(encoding="utf-8", errors="replace"), model.mean.shape[0])
        _, faces = mhclo.parse_obj_faces(f.with_suffix(".obj").read_text(encoding="utf-8", errors="replace"))
        out[f.stem] = (b.fit, faces)
    return out




def heldout_people(model, n: int) -> list[dict]:
    """n held-out avatars, alternately male and female: {"index", "weights", "gender"}."""
    z = np.load(HELDOUT_AVATARS)
    genders = [str(g) for g in z["gender"]]
    lists = [[i for i, g in enumerate(genders) if g == "male"], [i for i, g in enumerate(genders) if g == "female"]]
    order = []
    while len(order) < min(n, len(genders)):
        for lst in lists:
            if lst and len(order) < n:
                order.append(lst.pop(0))
    out = []
    for i in order:
        X = model.mean.astype(np.float64) + z["offsets"][i].astype(np.float64) * float(z["scale"])
        out.append({"index": int(i), "weights": model.project(X), "gender": genders[i]})
    return out

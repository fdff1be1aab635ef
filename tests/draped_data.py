"""Test data for garments draped on one body (issue 10): a MakeHuman CC0 garment fitted by its
binding to an avatar, written as a design tool would export it."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.application.scenes import obj_text
from service.model.formats import mhclo
from tests.bench import synthetic_scans as SS
from tests.bench.common import heldout_people, shared_data_dir

GARMENT = "female_casualsuit01"


@dataclass
class Draped:
    garment_obj: bytes  # the garment, in the frame of the body it was draped on
    avatar: bytes | None  # that body as a file (None: the example avatar `mean`)
    avatar_name: str | None
    reference: np.ndarray  # (M, 3) the garment fitted by its own binding to the source body, model frame


def binding(model, name: str = GARMENT) -> tuple[mhclo.Binding, np.ndarray]:
    d = shared_data_dir() / "makehuman_clothes" / name
    b = mhclo.parse_mhclo((d / f"{name}.mhclo").read_text(errors="replace"), model.mean.shape[0])
    _, faces = mhclo.parse_obj_faces((d / f"{name}.obj").read_text(errors="replace"))
    return b, faces


def on_mean(model, scale: float = 1.0, name: str = GARMENT) -> Draped:
    """The garment draped on the example avatar `mean`, written in metres x ``scale`` (cm: 100)."""
    b, faces = binding(model, name)
    G = b.fit(model.mean)
    return Draped(obj_text(G * scale, faces).encode(), None, None, G)


def on_foreign_avatar(model, seed: int = 3, name: str = GARMENT) -> Draped:
    """The garment draped on a held-out person's body, both given in the body scan's own frame:
    a remeshed unclothed scan (~12k vertices, cm, Z up, any yaw), standing (no bone bent)."""
    person = heldout_people(model, 4)[seed % 4]
    scan = SS.make_scan(model, np.random.default_rng([seed, 10]), person["weights"], person["gender"], clothed=False,
                        point_cloud=False, n_points=12_000, noise_mm=0.5, max_pose_deg=0.0, unit="cm", up="+z")
    b, faces = binding(model, name)
    X = model.vertices(person["weights"]).astype(np.float64)
    posed = model.forward(vertices=X, pose=scan.rotvecs)
    T = posed.transforms[0].copy()  # no bone bent: the whole body moves rigidly with the root
    T[:3, 3] += scan.translation
    G = b.fit(X) @ T[:3, :3].T + T[:3, 3]  # model frame, where the scan's truth is
    to_scan = np.linalg.inv(scan.to_model)
    G_scan = G @ to_scan[:3, :3].T + to_scan[:3, 3]
    return Draped(obj_text(G_scan, faces).encode(), SS.scan_file_bytes(scan, "ply"), "avatar.ply", G)

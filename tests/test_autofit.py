"""The garment auto-fit (service/model/garments/autofit.py, issue 10): a draped garment carried onto
other bodies stays off them (exact closest-point test), keeps its shape on its own body, follows
a body that grows, and reports progress."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from service.model.garments import autofit as AF
from service.model.garments import tryon as T
from service.model.geometry.mesh import vertex_faces, vertex_normals, winding_numbers


@pytest.fixture(scope="module")
def tee(model):
    """A loose-ish top: the torso and upper arms pushed 8 mm off the mean body."""
    nb = model.n_body_vertices
    X = model.mean.astype(np.float64)[:nb]
    y = X[:, 1]
    keep = (y > 0.95) & (y < 1.45) & (np.abs(X[:, 0]) < 0.35)
    F = model.body_faces[keep[model.body_faces].all(axis=1)]
    used = np.unique(F)
    remap = np.full(nb, -1)
    remap[used] = np.arange(len(used))
    n = vertex_normals(X, model.body_faces).astype(np.float64)
    return X[used] + 0.008 * n[used], remap[F]


@pytest.mark.slow
def test_autofit_stays_off_every_target_and_keeps_its_own_fit(model, tee):
    g, faces = tee
    nb = model.n_body_vertices
    ex = T.example_set(model, n=2)
    EX = T.example_vertices(model, ex)
    seen = []
    res = AF.autofit(g, faces, model.mean, EX, model.body_faces, progress=lambda f, m: seen.append(f))
    assert res.fits.shape == (5, len(g), 3) and res.fits.dtype == np.float32
    assert seen[0] >= 0.0 and seen[-1] == 1.0 and all(a <= b + 1e-12 for a, b in zip(seen, seen[1:]))
    # on its own body (E0 = mean) the garment is where it was draped
    np.testing.assert_allclose(res.fits[0], g, atol=2e-4)
    vf = vertex_faces(model.body_faces, nb)
    for E, fit in zip(EX, res.fits):
        body = AF.BodyCollider(E[:nb], model.body_faces, vf)
        s, _, _ = body.signed_distance(fit.astype(np.float64))
        assert s.min() > 0.0009  # nothing inside, nothing closer than the least clearance
        inside = winding_numbers(fit[:200].astype(np.float64), E[:nb], model.body_faces)
        assert np.all(inside < 0.5)
    assert res.stats["strain"]["within_10pct"] > 0.99


def test_autofit_follows_a_bigger_body_and_pushes_out(model, tee):
    g, faces = tee
    nb = model.n_body_vertices
    X = model.mean.astype(np.float64)
    centre = X[:nb].mean(axis=0) * np.array([1.0, 0.0, 1.0]) + np.array([0.0, 1.2, 0.0])
    bigger = X.copy()
    bigger[:, [0, 2]] = centre[[0, 2]] + 1.05 * (X[:, [0, 2]] - centre[[0, 2]])  # 5 % wider and deeper
    res = AF.autofit(g, faces, X, bigger[None], model.body_faces)
    fit = res.fits[0].astype(np.float64)
    d_before = cKDTree(X[:nb]).query(g)[0]
    d_after = cKDTree(bigger[:nb]).query(fit)[0]
    assert abs(np.median(d_after) - np.median(d_before)) < 0.003  # the ease is carried along
    assert np.abs(fit - g).max() > 0.005  # and it did move
    s, _, _ = AF.BodyCollider(bigger[:nb], model.body_faces, vertex_faces(model.body_faces, nb)).signed_distance(fit)
    assert s.min() > 0.0009


def test_resolve_collisions_moves_inside_vertices_out(model, tee):
    g, faces = tee
    nb = model.n_body_vertices
    X = model.mean.astype(np.float64)[:nb]
    body = AF.BodyCollider(X, model.body_faces, vertex_faces(model.body_faces, nb))
    n = vertex_normals(X, model.body_faces).astype(np.float64)
    dented = g.copy()
    i = np.arange(0, len(g), 7)
    nn = body.tree.query(g[i])[1]
    dented[i] -= 0.015 * n[nn]  # 7 mm inside the skin
    from service.model.garments.garment import laplacian_smoother
    gap = np.full(len(g), 0.0015)
    out, moved = AF.resolve_collisions(dented, body, gap, laplacian_smoother(faces, len(g)).tocsc(), AF.AutofitParams())
    assert moved >= len(i)
    s, _, _ = body.signed_distance(out)
    assert s.min() > 0.0015 - 1e-4

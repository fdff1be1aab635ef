"""A dense garment draped through its simulation mesh (``service.model.drape.proxy``): the
simplification keeps a manifold cloth of the garment's own vertices with its topology and open
edges, the embedding carries the garment exactly at rest and through rigid motions, and a dense
tube drapes through its simulation mesh as analytic cases and the direct drape say."""
from __future__ import annotations

import numpy as np
import pytest

from service.model.drape import Config, precompute
from service.model.drape.proxy import COLLAPSE_MIN_PIECE, ProxyDraper, collapse_edges, simulation_mesh
from service.model.geometry import mesh as geometry
from tests.drape_cases import cylinder, ring_girth, tube


def _sheet(n: int = 40, size: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """A gently curved n x n grid (V, 3) with faces (F, 3), facing +z."""
    u, v = np.meshgrid(np.linspace(0, size, n), np.linspace(0, size, n), indexing="ij")
    V = np.stack([u.ravel(), v.ravel(), 0.05 * np.sin(3 * u.ravel()) * np.cos(2 * v.ravel())], 1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def _euler(faces: np.ndarray, n: int) -> int:
    return n - len(geometry.mesh_edges(faces)) + len(faces)


@pytest.mark.parametrize("shape", ["sheet", "tube"])
def test_collapse_edges_keeps_a_manifold_cloth_of_the_garments_own_vertices(shape: str) -> None:
    V, F = _sheet() if shape == "sheet" else tube(0.12, 0.3, 96, 24)
    # a button beside it: a piece too small to simplify
    B, BF = tube(0.01, 0.01, 8, 2, y0=0.5)
    F = np.vstack([F, BF + len(V)])
    V = np.vstack([V, B])
    n = len(V)
    keep, Q, owner = collapse_edges(V, F, n // 4)
    assert len(keep) <= n // 4 and np.all(np.diff(keep) > 0)
    X = V[keep]  # the simulation mesh's vertices are the garment's own, where they were
    assert Q.min() >= 0 and Q.max() < len(keep)
    _, count = geometry.edge_counts(Q)
    assert count.max() <= 2  # manifold
    tri = X[Q]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-8
    # same topology: the Euler characteristic of each piece (sheet 1, open tube 0, button 0)
    assert _euler(Q, len(keep)) == _euler(F, n)
    assert len(np.unique(geometry.vertex_components(Q, len(keep)))) == 2
    # no face turned over: each faces as the garment under it does
    fi, _, _ = geometry.closest_points_on_mesh(tri.mean(1), V, F)
    t0 = V[F[fi]]
    n0 = np.cross(t0[:, 1] - t0[:, 0], t0[:, 2] - t0[:, 0])
    n1 = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    assert ((n0 * n1).sum(1) > 0).all()
    # open edges stay on the garment's open edges, corners kept; the button is whole
    open_before = geometry.boundary_vertices(F, n)
    assert open_before[keep[geometry.boundary_vertices(Q, len(keep))]].all()
    if shape == "sheet":
        corners = [0, 39, 40 * 39, 40 * 40 - 1]
        assert np.isin(corners, keep).all()
    assert np.isin(np.arange(n - len(B), n), keep).all() and len(B) < COLLAPSE_MIN_PIECE
    # each vertex went into a kept vertex near it
    assert (owner[keep] == np.arange(len(keep))).all()
    edge = np.median(np.linalg.norm(V[F[:, 0]] - V[F[:, 1]], axis=1))
    assert np.linalg.norm(V - X[owner], axis=1).max() < 8 * edge


def test_the_embedding_carries_the_garment_exactly_at_rest_and_through_rigid_motions() -> None:
    V, F = _sheet()
    sim = simulation_mesh(V, F, 300)
    assert sim is not None and len(sim.keep) <= 300
    assert np.abs(sim.garment.place(V[sim.keep]) - V).max() < 1e-12
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]) @ np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    t = np.array([0.3, -1.0, 2.0])
    assert np.abs(sim.garment.place(V[sim.keep] @ R.T + t) - (V @ R.T + t)).max() < 1e-12
    assert simulation_mesh(V, F, len(V)) is None  # not denser than the limit: draped as it is


def test_a_dense_tube_drapes_through_its_simulation_mesh_as_directly() -> None:
    """A dense tube (girth Cg, 3,072 vertices) on a wider cylinder (girth Cb) through a
    simulation mesh of 1,600 vertices: its hoop strain at every ring within 0.3 percentage
    points of the direct drape's (itself Cb / Cg - 1 and the clearance's 0.5 %), 0.2 mm from the
    direct drape on average, outside the body and not through itself. (Coarser, the simulation
    mesh's flat triangles meet a curved body at their middles, and the body-vertex / cloth-face
    contact holds them off it: 800 vertices here, ~33 around, add up to 0.7 points.)"""
    Rg, Rb, na, nh = 0.10, 0.104, 128, 23
    V, F = tube(Rg, 0.3, na, nh)
    BV, BF = cylinder(Rb, -0.3, 0.6)
    init = V.copy()
    init[:, [0, 2]] *= (Rb + 0.002) / Rg  # the warp's guess: around the body
    proxy = precompute(V, F, "knit", Config(proxy_max_vertices=1600))
    assert isinstance(proxy, ProxyDraper) and proxy.n == len(V)
    r = proxy.solve(BV, BF, init)
    assert r.vertices.shape == V.shape and r.stats["simulation_vertices"] <= 1600
    x = r.vertices.astype(np.float64)
    direct = precompute(V, F, "knit", Config(proxy_max_vertices=None)).solve(BV, BF, init)
    d = direct.vertices.astype(np.float64)
    for ring in range(1, nh):
        hoop, hoop_direct = (ring_girth(y, ring, na) / ring_girth(V, ring, na) - 1 for y in (x, d))
        assert abs(100 * hoop_direct - 100 * (Rb / Rg - 1) - 0.5) < 0.1, (ring, hoop_direct)
        assert abs(100 * hoop - 100 * hoop_direct) < 0.3, (ring, hoop, hoop_direct)
    assert np.linalg.norm(x - d, axis=1).mean() < 2e-4
    assert (geometry.winding_numbers(x, BV, BF) < 0.5).all()
    assert r.stats["self_intersections"] == 0 and not len(geometry.intersecting_face_pairs(x, F))


def test_precompute_chooses_the_simulation_mesh_only_for_a_dense_garment_and_refuses_as_alone() -> None:
    from service.model.drape import DrapeError, Draper

    V, F = _sheet()  # 1,600 vertices
    assert isinstance(precompute(V, F, "knit", Config(proxy_max_vertices=400)), ProxyDraper)
    assert isinstance(precompute(V, F, "knit", Config(proxy_max_vertices=len(V))), Draper)
    assert isinstance(precompute(V, F, "knit", Config(proxy_max_vertices=None)), Draper)
    # pinned vertices are the garment's: it is draped as it is
    assert isinstance(precompute(V, F, "knit", Config(proxy_max_vertices=400), pinned=np.array([0, 39])), Draper)
    with pytest.raises(DrapeError, match="unknown fabric|fabric"):
        precompute(V, F, "silk", Config(proxy_max_vertices=400))
    bad = V.copy()
    bad[F[0, 1]] = bad[F[0, 0]]  # a zero-area face: refused as it would be alone
    with pytest.raises(DrapeError, match="zero-area"):
        precompute(bad, F, "knit", Config(proxy_max_vertices=400))
    # a start of the wrong shape is refused readably
    with pytest.raises(DrapeError, match="start shape"):
        precompute(V, F, "knit", Config(proxy_max_vertices=400)).solve(None, None, V[:-1])

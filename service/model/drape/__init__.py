"""Cloth drape engine: a garment at its own size settled on a body under gravity, with body
contact, friction and self-contact (projective dynamics, factored once per garment).

    draper = precompute(rest_vertices, faces, fabric="woven", config=Config())
    result = draper.solve(body_vertices, body_faces, init_vertices)   # DrapeResult
    edge_strain(rest_vertices, faces, result.vertices)                # (N,) stretch - 1

A garment of more than ``Config.proxy_max_vertices`` vertices is draped as a simulation mesh of
about that many and carried on it (``proxy``: ``precompute`` gives a ``ProxyDraper``; the
solver's own ``solver.precompute`` drapes any garment as it is).
"""
from .fabrics import FABRICS, Fabric
from .solver import Config, DrapeError, DrapeResult, Draper, edge_strain, start_outside
from .proxy import ProxyDraper, precompute
from .examples import drape_examples

__all__ = ["Config", "DrapeError", "DrapeResult", "Draper", "FABRICS", "Fabric", "ProxyDraper", "drape_examples", "edge_strain", "precompute",
           "start_outside"]

"""The reference cloth solver of ``tryon bench drape``: NVIDIA Newton's VBD solver (Apache-2.0,
``pip install newton``; bench only, never imported by the service). The pinned square of the
bench settled by a damped simulation on CPU (Warp compiles its kernels on the first run, ~3
minutes, cached in ``~/.cache/warp`` or ``WARP_CACHE_PATH``)."""
from __future__ import annotations

import time

import numpy as np


def available() -> str | None:
    """None if Newton imports, else why not."""
    try:
        import newton  # noqa: F401
        import warp  # noqa: F401
    except Exception as exc:  # pragma: no cover - depends on the install
        return f"newton not installed ({type(exc).__name__}: {exc}); pip install -e '.[bench-cloth]'"
    return None


def square_sag(V: np.ndarray, F: np.ndarray, pinned: list[int], density_kg_m2: float, stretch_n_m: float,
               bending_nm: float, seconds: float = 4.0, fps: int = 60, substeps: int = 10,
               device: str = "cpu") -> dict:
    """Settle the sheet (V (N, 3) m, Y up; F (F, 3)) pinned at ``pinned`` under gravity with
    Newton's VBD solver; returns the final vertices, the sag (pin height - lowest point), the
    largest speed at the end (m/s; settled when small) and the wall time."""
    import contextlib
    import io

    import warp as wp

    wp.config.quiet = True  # Warp's banner and module loads go to stdout: keep --json clean
    with contextlib.redirect_stdout(io.StringIO()):
        return _square_sag(V, F, pinned, density_kg_m2, stretch_n_m, bending_nm, seconds, fps, substeps, device)


def _cloth_builder(V, F, density_kg_m2, stretch_n_m, bending_nm, radius_m):
    """A Newton model builder (Y up, gravity) with one cloth mesh (rest shape V (N, 3), F (F, 3)),
    its material matched to the drape engine's energy (``service.model.drape.solver``):

    - membrane: ours is k_s A / 2 ||F - R||^2, i.e. k_s / 2 ||eps||^2 for a small strain eps,
      linear elasticity with Lame mu = k_s / 2 and lambda = 0 (no Poisson effect); Newton's
      membrane is a stable neo-Hookean one with Lame ``tri_ke`` = mu and ``tri_ka`` = lambda,
      hence ``tri_ke = k_s / 2``, ``tri_ka = 0``;
    - bending: ours is B / 2 kappa^2 per unit area for a cylindrical bend of curvature kappa
      (plate stiffness B, N m); Newton's is 1/2 ke_e |e| (theta - theta0)^2 per edge, whose sum
      over a mesh bent to curvature kappa is B / 2 kappa^2 per unit area with ke_e = B |e| / (A1
      + A2), A1, A2 the rest areas of the edge's two triangles (checked on a triangulated
      cylinder: ratio 1.001), so each edge gets its own ``ke``."""
    import warp as wp

    import newton

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -9.81, 0.0))
    builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                           vertices=[wp.vec3(*map(float, p)) for p in V], indices=[int(i) for i in F.reshape(-1)],
                           density=float(density_kg_m2), tri_ke=0.5 * float(stretch_n_m), tri_ka=0.0,
                           tri_kd=0.5 * float(stretch_n_m) * 1e-3, edge_ke=float(bending_nm), edge_kd=0.0,
                           particle_radius=float(radius_m))
    X = np.asarray(V, np.float64)
    builder.edge_bending_properties = [(float(bending_nm) * _edge_bending_scale(X, i, j, k, l), 0.0)
                                       for i, j, k, l in builder.edge_indices]
    return builder


def _edge_bending_scale(X: np.ndarray, i: int, j: int, k: int, l: int) -> float:
    """|e| / (A1 + A2) (1/m) of the edge (k, l) between the triangles (i, k, l) and (j, k, l) of
    the rest shape X (N, 3); 0 on a boundary edge (i or j is -1)."""
    if i < 0 or j < 0:
        return 0.0
    e = X[l] - X[k]
    a = 0.5 * (np.linalg.norm(np.cross(e, X[i] - X[k])) + np.linalg.norm(np.cross(e, X[j] - X[k])))
    return float(np.linalg.norm(e) / max(a, 1e-12))


def _settle(builder, seconds, fps, substeps, device, start=None, contact=None, collide_every=1, self_contact_m=None):
    """The builder's model simulated by VBD with air damping (velocities scaled by 0.9 every frame:
    the quasi-static answer), from ``start`` (N, 3) if given (its first N particles); ``contact``:
    (ke, kd, mu) of the particle-shape contacts (and of the self-contacts); collisions found every
    ``collide_every`` substeps; ``self_contact_m``: VBD's self-contact on at that distance, found
    once a step. Returns the final positions (all particles, float64) and velocities."""
    import warp as wp

    import newton

    builder.color(include_bending=True)
    with wp.ScopedDevice(device):
        model = builder.finalize()
        if contact is not None:
            model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = map(float, contact)
        if self_contact_m is None:
            solver = newton.solvers.SolverVBD(model=model, iterations=10)
        else:
            slot = newton.solvers.SolverVBD.CollisionSlot.SOFT_SELF_CONTACT
            solver = newton.solvers.SolverVBD(
                model=model, iterations=10, particle_enable_self_contact=True,
                particle_self_contact_margin=float(self_contact_m), particle_self_contact_gap=SELF_CONTACT_GAP_M,
                collision_frequency_type={slot: newton.solvers.SolverVBD.CollisionFrequencyType.PRE_INIT})
        s0, s1 = model.state(), model.state()
        if start is not None:
            q = s0.particle_q.numpy()
            q[: len(start)] = np.asarray(start, np.float32)
            s0.particle_q.assign(q)
        control = model.control()
        pipeline = newton.CollisionPipeline(model)
        contacts = pipeline.contacts()
        dt = 1.0 / fps / substeps
        for k in range(int(seconds * fps * substeps)):
            s0.clear_forces()
            if k % substeps == 0:
                s0.particle_qd.assign(s0.particle_qd.numpy() * 0.9)
            if k % collide_every == 0:
                pipeline.collide(s0, contacts)
            solver.step(s0, s1, control, contacts, dt)
            s0, s1 = s1, s0
        return s0.particle_q.numpy().astype(np.float64), s0.particle_qd.numpy()


def _square_sag(V, F, pinned, density_kg_m2, stretch_n_m, bending_nm, seconds, fps, substeps, device) -> dict:
    t0 = time.perf_counter()
    builder = _cloth_builder(V, F, density_kg_m2, stretch_n_m, bending_nm, 0.002)
    for i in pinned:
        builder.particle_mass[i] = 0.0
    x, v = _settle(builder, seconds, fps, substeps, device)
    pin_y = float(V[pinned, 1].mean())
    return {"vertices": x, "sag_m": pin_y - float(x[:, 1].min()), "max_speed_m_s": float(np.linalg.norm(v, axis=1).max()),
            "seconds": time.perf_counter() - t0, "device": device}

def garment_on_body(rest: np.ndarray, F: np.ndarray, init: np.ndarray, BV: np.ndarray, BF: np.ndarray,
                    density_kg_m2: float, stretch_n_m: float, bending_nm: float, friction: float,
                    seconds: float = 2.0, fps: int = 60, substeps: int = 10, radius_m: float = 0.003,
                    device: str = "cpu", full_contact: bool = False) -> dict:
    """A garment (rest shape V (N, 3) m, Y up; F (F, 3)) started at ``init`` (N, 3) (e.g. the
    warp fit) and settled on a static body mesh (BV, BF) under gravity with Newton's VBD solver
    (rest lengths from ``rest``; body contact by Newton's collision pipeline with friction
    ``friction``, its contacts found every substep: found once a frame, a tight shirt on a large
    body sank through the belly (95 vertices up to 96 mm inside, 2 of 5 bench people); air
    damping as in :func:`square_sag`). Start it where the drape engine starts
    (``drape.start_outside``): Newton's one-sided contact pushes a vertex that starts inside the
    body further in.

    ``full_contact``: also VBD's self-contact (vertex-triangle and edge-edge, ``radius_m`` apart),
    with the body's faces within ``BODY_CLOTH_REACH_M`` of the start added as a fixed cloth (zero
    mass): the garment then keeps off itself and keeps the body's vertices out of its faces, as
    the drape engine does (its self-contact and its body-vertex / cloth-face pass); the plain
    particle-shape contact lets body vertices through the cloth's faces between its vertices and
    lets the cloth pass through itself. Self-contacts are found once a step; a step costs ~0.3 s
    on CPU (Warp runs the kernels on one core), 4-7 minutes a body on 2 cores. With 2 steps a frame
    instead of 10 (5 times fewer VBD iterations) its shirt had not converged: stretched 3-5 %
    and hanging 2-3 cm lower on the loose people. Returns the final vertices, the largest speed
    at the end and the wall time."""
    import contextlib
    import io

    import warp as wp

    wp.config.quiet = True
    with contextlib.redirect_stdout(io.StringIO()):
        return _garment_on_body(rest, F, init, BV, BF, density_kg_m2, stretch_n_m, bending_nm, friction, seconds,
                                fps, substeps, radius_m, device, full_contact)


BODY_CLOTH_REACH_M = 0.05  # metres: body faces (centroids) this near a start vertex join the full-contact model
SELF_CONTACT_GAP_M = 0.001  # metres of detection reach beyond the contact distance (Newton's default, 1.5 x
# the distance, took 2.4 times as long for the same ease within 0.2 mm on the one body tried, 2 steps a frame)


def _garment_on_body(rest, F, init, BV, BF, density_kg_m2, stretch_n_m, bending_nm, friction, seconds, fps,
                     substeps, radius_m, device, full_contact=False) -> dict:
    import warp as wp
    from scipy.spatial import cKDTree

    import newton

    t0 = time.perf_counter()
    builder = _cloth_builder(rest, F, density_kg_m2, stretch_n_m, bending_nm, radius_m)
    n = len(builder.particle_q)
    builder.add_shape_mesh(body=-1, mesh=newton.Mesh(np.asarray(BV, np.float32), np.asarray(BF, np.int32).reshape(-1)))
    self_contact = None
    if full_contact:
        BF = np.asarray(BF, np.int64)
        d, _ = cKDTree(np.asarray(init, np.float64)).query(np.asarray(BV, np.float64)[BF].mean(axis=1))
        near = BF[d < BODY_CLOTH_REACH_M]
        used = np.unique(near)
        index = np.full(len(BV), -1, np.int64)
        index[used] = np.arange(len(used))
        builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                               vertices=[wp.vec3(*map(float, p)) for p in np.asarray(BV)[used]],
                               indices=[int(i) for i in index[near].reshape(-1)], density=1.0, tri_ke=0.0, tri_ka=0.0,
                               tri_kd=0.0, edge_ke=0.0, edge_kd=0.0, particle_radius=float(radius_m))
        for i in range(n, len(builder.particle_q)):
            builder.particle_mass[i] = 0.0  # the body does not move
        self_contact = float(radius_m)
    x, v = _settle(builder, seconds, fps, substeps, device, start=init, contact=(1.0e4, 1.0e-2, friction),
                   self_contact_m=self_contact)
    return {"vertices": x[:n], "max_speed_m_s": float(np.linalg.norm(v[:n], axis=1).max()),
            "seconds": time.perf_counter() - t0, "device": device}

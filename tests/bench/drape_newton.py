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
    """A Newton model builder (Y up, gravity) with one cloth mesh (rest shape V (N, 3), F (F, 3))."""
    import warp as wp

    import newton

    builder = newton.ModelBuilder(up_axis=newton.Axis.Y, gravity=(0.0, -9.81, 0.0))
    builder.add_cloth_mesh(pos=wp.vec3(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=wp.vec3(0.0, 0.0, 0.0),
                           vertices=[wp.vec3(*map(float, p)) for p in V], indices=[int(i) for i in F.reshape(-1)],
                           density=float(density_kg_m2), tri_ke=float(stretch_n_m), tri_ka=float(stretch_n_m),
                           tri_kd=float(stretch_n_m) * 1e-3, edge_ke=float(bending_nm), edge_kd=0.0,
                           particle_radius=float(radius_m))
    return builder


def _settle(builder, seconds, fps, substeps, device, start=None, contact=None, collide_every=1):
    """The builder's model simulated by VBD with air damping (velocities scaled by 0.9 every frame:
    the quasi-static answer), from ``start`` (N, 3) if given; ``contact``: (ke, kd, mu) of the
    particle-shape contacts; collisions found every ``collide_every`` substeps. Returns the
    final positions (N, 3) float64 and velocities (N, 3)."""
    import warp as wp

    import newton

    builder.color(include_bending=True)
    with wp.ScopedDevice(device):
        model = builder.finalize()
        if contact is not None:
            model.soft_contact_ke, model.soft_contact_kd, model.soft_contact_mu = map(float, contact)
        solver = newton.solvers.SolverVBD(model=model, iterations=10)
        s0, s1 = model.state(), model.state()
        if start is not None:
            s0.particle_q.assign(np.asarray(start, np.float32))
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
                    device: str = "cpu") -> dict:
    """A garment (rest shape V (N, 3) m, Y up; F (F, 3)) started at ``init`` (N, 3) (e.g. the
    warp fit) and settled on a static body mesh (BV, BF) under gravity with Newton's VBD solver
    (rest lengths from ``rest``; body contact by Newton's collision pipeline with friction
    ``friction``; air damping as in :func:`square_sag`); returns the final vertices, the largest
    speed at the end and the wall time."""
    import contextlib
    import io

    import warp as wp

    wp.config.quiet = True
    with contextlib.redirect_stdout(io.StringIO()):
        return _garment_on_body(rest, F, init, BV, BF, density_kg_m2, stretch_n_m, bending_nm, friction, seconds,
                                fps, substeps, radius_m, device)


def _garment_on_body(rest, F, init, BV, BF, density_kg_m2, stretch_n_m, bending_nm, friction, seconds, fps,
                     substeps, radius_m, device) -> dict:
    import newton

    t0 = time.perf_counter()
    builder = _cloth_builder(rest, F, density_kg_m2, stretch_n_m, bending_nm, radius_m)
    builder.add_shape_mesh(body=-1, mesh=newton.Mesh(np.asarray(BV, np.float32), np.asarray(BF, np.int32).reshape(-1)))
    x, v = _settle(builder, seconds, fps, substeps, device, start=init, contact=(1.0e4, 1.0e-2, friction),
                   collide_every=substeps)
    return {"vertices": x, "max_speed_m_s": float(np.linalg.norm(v, axis=1).max()),
            "seconds": time.perf_counter() - t0, "device": device}

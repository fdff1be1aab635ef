"""tryon: an online 3D clothes try-on service (body model, avatars, GLB export)."""

__version__ = "0.1.0"

# Per-request numpy work is small (a try-on is ~0.5 M multiply-adds); BLAS threads only add
# spin-wait latency under concurrent requests. Must be set before numpy is first imported.
import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")

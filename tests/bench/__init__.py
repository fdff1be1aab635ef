"""The project's benchmarks (``tryon bench <suite> [--json]``): accuracy and performance figures,
kept beside the tests and out of the service package and its image. They read third-party data
(ANSUR II, MakeHuman garments) from ``../shared/data`` (or ``TRYON_SHARED_DATA``) and held-out
avatars from ``tests/data/``; a suite that needs a server runs its own (``tests/harness.py``)
with its own embedded Redis, never a database it did not create."""

# As under ``tryon bench``: the service package sets one BLAS thread (unless OPENBLAS_NUM_THREADS
# etc. say otherwise) before numpy is first imported; without it, ``python -m tests.bench`` timed
# OpenBLAS threads spin-waiting for a core on a loaded machine (a 0.06 ms synthesis took 10 ms).
import service  # noqa: E402,F401

"""The project's benchmarks (``tryon bench <suite> [--json]``): accuracy and performance figures,
kept beside the tests and out of the service package and its image. They read third-party data
(ANSUR II, MakeHuman garments) from ``../shared/data`` (or ``TRYON_SHARED_DATA``) and held-out
avatars from ``tests/data/``; a suite that needs a server runs its own (``tests/harness.py``)
with its own embedded Redis, never a database it did not create."""

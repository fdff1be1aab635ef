"""`tryon bench load`, `tryon bench page` and `tryon bench kernels` run (slow tier): short, light
runs (the first two against a default `tryon serve`, which uses one server process per core;
every request answered 2xx)."""
from __future__ import annotations

import os

import pytest

from tests.bench import load

pytestmark = pytest.mark.slow


def test_bench_load_smoke() -> None:
    r = load.bench_load(rate=20, seconds=4)
    text = load.format_result(r)
    assert r["requests"] == 80 and r["errors"] == 0, text
    assert r["server_processes"] == len(os.sched_getaffinity(0)), text  # tryon serve's default
    assert set(r["by_kind"]) == {"tryon", "avatar", "customer"} and r["p99_ms"] > 0
    assert "p50" in text and "memory" in text


def test_bench_page_smoke() -> None:
    """`tryon bench page` with two new customers: every request of the page's first dressed view
    answered 200, every step timed."""
    from tests.bench import page

    r = page.bench_page(customers=2)
    text = page.format_result(r)
    assert r["errors"] == [], text
    assert set(r["steps"]) == set(page.STEPS) and all(v["n"] == 2 for v in r["steps"].values()), text
    assert "first_view" in text


def test_bench_kernels_smoke() -> None:
    """`tryon bench kernels` on two customers (one of each gender): every row timed both ways,
    and every output of the compiled kernels equal to the numpy path's (closest points, adapted
    poses, both outfits' GLB bytes; winding numbers to 1e-12)."""
    from service.model.geometry import kernels as K
    from tests.bench import kernels

    if not K.AVAILABLE:
        pytest.skip("the compiled kernels are off (numba missing, or TRYON_NO_KERNELS)")
    r = kernels.run(limit=2)
    text = kernels.format_result(r)
    assert set(r["rows"]) == {"closest_points", "winding_numbers", "adapt_poses", "first_outfit", "second_outfit"}
    for k, v in r["rows"].items():
        assert v["compiled_ms"] > 0 and v["numpy_ms"] > 0, text
        assert v["identical"] is (None if k == "winding_numbers" else True), text
    assert r["rows"]["winding_numbers"]["max_abs_diff"] <= 1e-12, text

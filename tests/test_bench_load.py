"""`tryon bench load` and `tryon bench page` run (slow tier): short, light runs against a default
`tryon serve`, which uses one server process per core; every request answered 2xx."""
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

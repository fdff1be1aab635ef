"""`tryon bench load` runs (slow tier): a short, light run against a default `tryon serve`,
which uses one server process per core; every request answered 2xx."""
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

"""Shared pytest helpers: the test tiers, the Khronos glTF validator (node, ``npm ci``) as a
fixture, the body model, the end of the session's own redis-server.

Tiers: a plain ``pytest`` runs the quick tier (maths and the API in process, against the
session's own redis-server of tests/harness.py, under a minute); tests marked ``slow`` (real server and worker processes, worker kills, whole body fits,
Chromium, the body-model build) run with ``pytest --full``, which is what ``bash .ci/test`` (the
whole suite) does. ``-m`` selects by marker as usual and overrides the default."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parent.parent
# test apps build their demo garments in one size (seconds, not minutes) unless a test asks for
# sizes (``TRYON_DEMO_SIZES=True`` in its Settings, or in run_server's environment)
os.environ.setdefault("TRYON_DEMO_SIZES", "false")
# ... and through the warp: the drape (on by default, minutes a garment) only where a test turns it
# on (``TRYON_DRAPE=True``): CI does not spend its time draping
os.environ.setdefault("TRYON_DRAPE", "false")
VALIDATE_SCRIPT = REPO / "tests" / "gltf_validate.mjs"


def run_gltf_validator(glb: bytes, tmp_dir: Path) -> dict[str, Any]:
    """Validate GLB bytes with the Khronos validator; returns its report (``issues.numErrors``,
    ``issues.numWarnings``, ``issues.messages``...). Needs node and ``npm ci`` at the repo root."""
    node = shutil.which("node")
    if node is None:
        raise RuntimeError("node is required for the glTF validator (see .ci/run)")
    if not (REPO / "node_modules" / "gltf-validator").is_dir():
        raise RuntimeError("gltf-validator is not installed: run `npm ci` at the repo root")
    path = tmp_dir / "asset.glb"
    path.write_bytes(glb)
    proc = subprocess.run(
        [node, str(VALIDATE_SCRIPT), str(path)],
        cwd=REPO, capture_output=True, text=True, timeout=120, check=False,
    )
    if proc.returncode != 0:
        raise RuntimeError(f"glTF validator failed: {proc.stderr.strip()}")
    return json.loads(proc.stdout)


def format_issues(report: dict[str, Any]) -> str:
    """The report's messages, one per line, for assertion output."""
    return "\n".join(
        f"[{m.get('severity')}] {m.get('code')} {m.get('pointer', '')}: {m.get('message')}"
        for m in report.get("issues", {}).get("messages", [])
    )


def valid_glb(validate: Callable[[bytes], dict[str, Any]], data: bytes) -> dict[str, Any]:
    """Assert ``data`` is a GLB with 0 validator errors; return it read back (``read_glb``)."""
    from service.model.formats.gltf_read import read_glb

    assert data[:4] == b"glTF"
    report = validate(data)
    assert report["issues"]["numErrors"] == 0, format_issues(report)
    return read_glb(data)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--full", action="store_true", default=False,
                     help="run the whole suite, slow tests included (bash .ci/test does)")


# The service's variables that point at state outside the test's own: unset for the whole run,
# so that no test (nor a server or worker it starts) reaches a developer's Redis or data.
OUTSIDE_STATE_ENV = ("REDIS_URL", "TRYON_REDIS_PREFIX", "TRYON_DATA_DIR")


def _interrupt(signum: int, frame: Any) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def pytest_configure(config: pytest.Config) -> None:
    for var in OUTSIDE_STATE_ENV:
        os.environ.pop(var, None)
    # SIGTERM (a CI timeout, `timeout`) ends the run as Ctrl-C does: fixtures tear down (servers,
    # workers, redis-servers stopped) and the session's redis-server is shut down.
    if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
        signal.signal(signal.SIGTERM, _interrupt)
    config.addinivalue_line("markers", "slow: real processes, browsers, builds or whole fits (run with --full)")


def pytest_unconfigure(config: pytest.Config) -> None:
    """Stop the session's own redis-server (tests/harness.py), if a test started it: at the end
    of every run, failed or interrupted ones included."""
    harness = sys.modules.get("tests.harness")
    if harness is not None:
        harness.stop_session_redis()


# The full suite's longest test files, started first (docs/testing.md, "Figures measured": the
# seconds of each): xdist hands out one file at a time (``--dist loadfile``,
# ``--no-loadscope-reorder`` in .ci/test), and a long file handed out last runs alone at the end.
LONGEST_FILES_FIRST = ("test_fitting.py", "test_web_client.py", "test_drape_api.py", "test_fitting_jobs.py",
                       "test_faults.py", "test_build_smoke.py", "test_garments_draped_jobs.py", "test_bench_load.py",
                       "test_hostile.py")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--full"):
        rank = {name: i for i, name in enumerate(LONGEST_FILES_FIRST)}
        items.sort(key=lambda it: rank.get(it.path.name, len(rank)))  # stable: each file's order kept
    if config.getoption("--full") or config.getoption("-m"):
        return
    quick = [it for it in items if "slow" not in it.keywords]
    slow = [it for it in items if "slow" in it.keywords]
    if slow:
        config.hook.pytest_deselected(items=slow)
        items[:] = quick


@pytest.fixture
def validate_glb(tmp_path: Path) -> Callable[[bytes], dict[str, Any]]:
    """``validate_glb(bytes) -> report`` using the Khronos glTF validator."""
    return lambda glb: run_gltf_validator(glb, tmp_path)


@pytest.fixture(scope="session")
def model():
    """The packaged body model, loaded once for the whole test session."""
    from service.model.body.model import load_body_model

    return load_body_model()

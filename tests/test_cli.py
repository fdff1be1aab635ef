"""The `tryon` command line (commands that need no body model)."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service.cli import main

REPO = Path(__file__).resolve().parent.parent


def test_help_lists_commands() -> None:
    proc = subprocess.run([sys.executable, "-m", "service.cli", "--help"], cwd=REPO,
                          capture_output=True, text=True, check=True)
    for command in ("serve", "worker", "build-body-model", "bench", "openapi"):
        assert command in proc.stdout


def test_bench_needs_a_suite(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench"]) == 2
    assert "usage: tryon bench <suite>" in capsys.readouterr().err


def test_bench_only_is_a_tryon_option(capsys: pytest.CaptureFixture[str]) -> None:
    from tests.bench.__main__ import main as bench_main

    with pytest.raises(SystemExit) as exc:
        bench_main(["body", "--only", "latency"])
    assert exc.value.code == 2 and "--only is a tryon option" in capsys.readouterr().err


def test_openapi_to_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["openapi", "--out", "-"]) == 0
    out = capsys.readouterr().out
    assert out.endswith("}\n")
    assert json.loads(out) == json.loads((REPO / "openapi" / "openapi.json").read_text("utf-8"))


def test_unknown_command_fails() -> None:
    with pytest.raises(SystemExit) as exc:
        main(["frobnicate"])
    assert exc.value.code == 2

"""The committed OpenAPI document must match the app's (regenerate: `tryon openapi`)."""
from __future__ import annotations

import json
from pathlib import Path

from service.cli import main, openapi_document

COMMITTED = Path(__file__).resolve().parent.parent / "openapi" / "openapi.json"


def test_committed_openapi_is_current() -> None:
    committed = json.loads(COMMITTED.read_text(encoding="utf-8"))
    assert committed == openapi_document(), "openapi/openapi.json is stale: run `tryon openapi`"


def test_openapi_documents_the_contract() -> None:
    doc = openapi_document()
    paths = doc["paths"]
    assert {"/healthz", "/v1/body-model", "/v1/avatars"} <= set(paths)
    post = paths["/v1/avatars"]["post"]
    assert set(post["responses"]["200"]["content"]) == {"application/json", "model/gltf-binary"}
    assert "422" in post["responses"]


def test_cli_writes_sorted_document(tmp_path: Path) -> None:
    out = tmp_path / "sub" / "openapi.json"
    assert main(["openapi", "--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    assert text.endswith("}\n")
    assert text == json.dumps(json.loads(text), sort_keys=True, indent=2) + "\n"
    assert json.loads(text) == openapi_document()

"""App wiring that needs no body model: settings, content negotiation, request validation,
body-size limit and the static page (the lifespan, which loads the model, is not entered)."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from service.api.responses import wants_glb
from service.api.schemas import AvatarRequest
from service.app import create_app
from service.settings import Settings, get_settings


@pytest.fixture
def client(tmp_path: Path) -> TestClient:
    # No `with`: the lifespan (body model loading) does not run, routes not needing it work.
    app = create_app(Settings(data_dir=tmp_path, max_upload_bytes=1000))
    return TestClient(app, raise_server_exceptions=False)


def test_settings_from_env(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TRYON_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("REDIS_URL", "redis://redis.example:6379/0")
    monkeypatch.setenv("TRYON_BODY_MODEL", "/models/x.npz")
    s = Settings()
    assert s.data_dir == tmp_path and s.redis_url == "redis://redis.example:6379/0"
    assert s.body_model_path == Path("/models/x.npz")
    assert s.max_upload_bytes == 50 * 1024 * 1024


def test_pose_workers_setting_reaches_the_pose_threads(monkeypatch: pytest.MonkeyPatch, tmp_path: Path, model) -> None:
    from service.application import parallel
    from service.application.context import Context

    monkeypatch.setattr(parallel, "WORKERS", parallel.WORKERS)
    monkeypatch.setenv("TRYON_POSE_WORKERS", "3")
    assert Settings().pose_workers == 3
    ctx = Context.open(Settings(data_dir=tmp_path), model=model)
    try:
        assert parallel.WORKERS == 3
        assert parallel.per_pose(lambda x: x * x, range(7)) == [x * x for x in range(7)]
    finally:
        ctx.close()
    monkeypatch.setenv("TRYON_POSE_WORKERS", "0")
    with pytest.raises(ValueError):
        Settings()


def test_settings_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    for var in ("TRYON_DATA_DIR", "REDIS_URL", "TRYON_BODY_MODEL", "TRYON_MAX_UPLOAD_BYTES"):
        monkeypatch.delenv(var, raising=False)
    s = Settings()
    assert s.data_dir == Path("./tryon-data") and s.redis_url is None and s.body_model_path is None


@pytest.mark.parametrize(
    "accept, glb",
    [
        (None, False), ("", False), ("*/*", False), ("application/json", False),
        ("model/gltf-binary", True), ("model/*", True),
        ("model/gltf-binary;q=0.4, application/json", False),
        ("application/json;q=0.2, model/gltf-binary", True),
        ("text/html", False), ("model/gltf-binary;q=abc", False),
    ],
)
def test_content_negotiation(accept: str | None, glb: bool) -> None:
    assert wants_glb(accept) is glb


def test_measurement_values_validated() -> None:
    r = AvatarRequest.model_validate({"measurements": {"height_cm": 170, "gender": "male"}})
    assert r.measurements == {"height_cm": 170.0, "gender": "male"}
    assert isinstance(r.measurements["height_cm"], float)
    for bad in (True, None, [1], {"a": 1}, math.nan, math.inf, 10**400):
        with pytest.raises(ValidationError):
            AvatarRequest.model_validate({"measurements": {"height_cm": bad}})
    assert AvatarRequest.model_validate({}).measurements == {}


def test_healthz_and_index(client: TestClient) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    r = client.get("/")  # the customer page: three.js through an importmap, its app module
    assert r.status_code == 200 and '<script type="importmap">' in r.text and "app.js" in r.text


def test_malformed_json_is_422(client: TestClient) -> None:
    h = {"Content-Type": "application/json"}
    r = client.post("/v1/avatars", content=b'{"measurements": {', headers=h)
    assert r.status_code == 422 and r.json()["detail"][0]["type"] == "json_invalid"


def test_body_size_limit(client: TestClient) -> None:
    r = client.post("/v1/avatars", content=b"{" + b" " * 2000 + b"}",
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 413


def test_server_fault_gives_generic_500(tmp_path: Path) -> None:
    # A misconfigured model path is a server fault: logged, answered as a clean 500.
    app = create_app(Settings(data_dir=tmp_path, body_model_path=tmp_path / "missing.npz"))
    r = TestClient(app, raise_server_exceptions=False).get("/v1/body-model")
    assert r.status_code == 500 and r.json() == {"detail": "internal server error"}


def test_app_settings_are_the_dependency(tmp_path: Path) -> None:
    settings = Settings(data_dir=tmp_path)
    app = create_app(settings)
    assert app.state.settings is settings  # what the routes' settings dependency reads
    assert get_settings() is get_settings()  # cached process-wide default

"""End-to-end HTTP tests: a real `tryon serve` subprocess with the real body model."""
from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from service.model.body.model import BONES
from service.model.formats.gltf_read import read_glb
from tests.conftest import format_issues
from tests.harness import run_server

pytestmark = pytest.mark.slow  # real processes (see tests/conftest.py: tiers)

REPO = Path(__file__).resolve().parent.parent
GLB = "model/gltf-binary"


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[httpx.Client]:
    """An httpx client against `python -m service.cli serve` (embedded default) on a free port."""
    with run_server(tmp_path_factory.mktemp("tryon-data"), "embedded", TRYON_MAX_UPLOAD_BYTES="1000000") as s:
        assert s.data_dir.is_dir()
        yield s.client


@pytest.fixture(scope="module")
def spec(client: httpx.Client) -> dict[str, Any]:
    r = client.get("/v1/body-model")
    assert r.status_code == 200
    return r.json()


@pytest.fixture(scope="module")
def attrs(spec: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {a["name"]: a for a in spec["attributes"]}


def _post(client: httpx.Client, measurements: Any, **kw: Any) -> httpx.Response:
    return client.post("/v1/avatars", json={"measurements": measurements}, **kw)


def _assert_422(r: httpx.Response, field: str | None = None) -> list[dict[str, Any]]:
    assert r.status_code == 422, (r.status_code, r.text)
    detail = r.json()["detail"]
    assert isinstance(detail, list) and detail
    if field is not None:
        assert any(d["loc"] == ["body", "measurements", field] for d in detail), detail
    return detail


# -- happy paths -----------------------------------------------------------------------------
def test_healthz(client: httpx.Client) -> None:
    r = client.get("/healthz")
    assert r.status_code == 200 and r.json() == {"status": "ok"}


def test_index_page(client: httpx.Client) -> None:
    r = client.get("/")
    assert r.status_code == 200 and "coming" in r.text


def test_body_model_description(spec: dict[str, Any]) -> None:
    assert spec["bones"] == list(BONES) and len(spec["bones"]) == 17
    assert isinstance(spec["components"], int) and spec["components"] > 0
    assert len(spec["attributes"]) == 12
    names = {a["name"] for a in spec["attributes"]}
    assert {"gender", "height_cm"} <= names
    for a in spec["attributes"]:
        assert set(a) == {"name", "unit", "min", "max", "description"}
        if a["name"] == "gender":
            assert a["unit"] is None
        else:
            assert a["unit"] in ("cm", "kg")
            assert a["min"] < a["max"]


def test_avatar_from_a_few_measurements(client: httpx.Client, attrs: dict[str, Any], spec: dict[str, Any]) -> None:
    given = {"gender": "female", "height_cm": 165.0}
    if "weight_kg" in attrs:
        given["weight_kg"] = 62.0
    r = _post(client, given)
    assert r.status_code == 200, r.text
    body = r.json()
    assert set(body) == {"weights", "measurements", "estimated"}
    assert len(body["weights"]) == spec["components"]
    assert all(math.isfinite(w) for w in body["weights"])
    assert set(body["measurements"]) == set(attrs)
    assert body["measurements"]["gender"] == "female"
    assert abs(body["measurements"]["height_cm"] - 165.0) <= 0.5
    assert set(body["estimated"]) == set(attrs) - set(given)


def test_avatar_population_mean_and_all_twelve(client: httpx.Client, attrs: dict[str, Any]) -> None:
    r = _post(client, {})
    assert r.status_code == 200, r.text
    mean = r.json()
    assert set(mean["estimated"]) == set(attrs)
    # Feed the mean avatar's own 12 measurements back: a consistent, complete set.
    r = _post(client, mean["measurements"])
    assert r.status_code == 200, r.text
    full = r.json()
    assert full["estimated"] == []
    assert full["measurements"]["gender"] == mean["measurements"]["gender"]
    assert abs(full["measurements"]["height_cm"] - mean["measurements"]["height_cm"]) <= 0.5
    # A missing "measurements" key means "none given".
    r = client.post("/v1/avatars", json={})
    assert r.status_code == 200 and set(r.json()["estimated"]) == set(attrs)


def test_avatar_glb(client: httpx.Client, validate_glb: Callable[[bytes], dict[str, Any]]) -> None:
    r = _post(client, {"gender": "male", "height_cm": 180.0}, headers={"Accept": GLB})
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == GLB
    assert r.content[:4] == b"glTF"
    report = validate_glb(r.content)
    assert report["issues"]["numErrors"] == 0, format_issues(report)
    assert report["issues"]["numWarnings"] == 0, format_issues(report)
    glb = read_glb(r.content)
    pos, idx = glb["positions"], glb["indices"]
    assert pos.shape[0] > 1000 and idx.max() < pos.shape[0]
    assert abs((pos[:, 1].max() - pos[:, 1].min()) * 100 - 180.0) < 5.0  # metres, Y up
    doc = glb["json"]
    assert [doc["nodes"][j]["name"] for j in doc["skins"][0]["joints"]] == list(BONES)
    assert np.all(np.isfinite(pos))
    # compressed as the page asks for it (and as every GLB route takes it): the same avatar in
    # far fewer bytes, validator-clean; positions within the quantization grid of the plain ones
    mo = _post(client, {"gender": "male", "height_cm": 180.0}, headers={"Accept": GLB},
               params={"compression": "meshopt"})
    assert mo.status_code == 200 and mo.content[:4] == b"glTF", mo.text
    report = validate_glb(mo.content)
    assert report["issues"]["numErrors"] == 0, format_issues(report)
    assert "EXT_meshopt_compression" in read_glb(mo.content)["json"]["extensionsUsed"]
    assert len(mo.content) < 0.7 * len(r.content)
    assert np.abs(read_glb(mo.content)["positions"] - pos).max() < 1e-3
    assert _post(client, {"height_cm": 180.0}, headers={"Accept": GLB}, params={"compression": "zip"}).status_code == 422


def test_accept_json_preferred_or_default(client: httpx.Client) -> None:
    for accept in ("application/json", "*/*", f"application/json, {GLB};q=0.5"):
        r = _post(client, {"height_cm": 170}, headers={"Accept": accept})
        assert r.status_code == 200 and r.headers["content-type"] == "application/json", accept
    r = _post(client, {"height_cm": 170}, headers={"Accept": f"{GLB}, application/json;q=0.5"})
    assert r.status_code == 200 and r.content[:4] == b"glTF"


# -- errors ------------------------------------------------------------------------------------
def test_unknown_attribute(client: httpx.Client) -> None:
    _assert_422(_post(client, {"shoe_size_eu": 42}), "shoe_size_eu")


def test_string_height(client: httpx.Client) -> None:
    _assert_422(_post(client, {"height_cm": "170"}), "height_cm")


def test_non_finite_and_huge_numbers(client: httpx.Client) -> None:
    for raw in ("NaN", "Infinity", "-Infinity", "1e400", "1e300", "-1e300", "1" + "0" * 400):
        r = client.post(
            "/v1/avatars",
            content=f'{{"measurements": {{"height_cm": {raw}}}}}',
            headers={"Content-Type": "application/json"},
        )
        _assert_422(r, "height_cm")


def test_height_out_of_range_names_range(client: httpx.Client, attrs: dict[str, Any]) -> None:
    detail = _assert_422(_post(client, {"height_cm": 20}), "height_cm")
    entry = next(d for d in detail if d["loc"] == ["body", "measurements", "height_cm"])
    assert entry["type"] == "value_error"
    numbers = [float(x) for x in re.findall(r"(?<![\d.])-?\d+(?:\.\d+)?", entry["msg"])]
    lo, hi = attrs["height_cm"]["min"], attrs["height_cm"]["max"]
    assert any(abs(x - lo) < 0.51 for x in numbers), entry["msg"]
    assert any(abs(x - hi) < 0.51 for x in numbers), entry["msg"]


def test_bad_gender(client: httpx.Client) -> None:
    _assert_422(_post(client, {"gender": "other"}), "gender")


@pytest.mark.parametrize("measurements", [[1, 2], "height", 170, None, True])
def test_measurements_not_an_object(client: httpx.Client, measurements: Any) -> None:
    _assert_422(_post(client, measurements))


def test_empty_and_malformed_bodies(client: httpx.Client) -> None:
    json_h = {"Content-Type": "application/json"}
    _assert_422(client.post("/v1/avatars"))
    _assert_422(client.post("/v1/avatars", content=b"", headers=json_h))
    _assert_422(client.post("/v1/avatars", content=b'{"measurements": {', headers=json_h))
    # Bytes that are not UTF-8: FastAPI answers 400 ("error parsing the body").
    r = client.post("/v1/avatars", content=b"\xff\xfe\x00", headers=json_h)
    assert r.status_code in (400, 422), r.text


BAD_PAYLOADS: list[Any] = [
    None, [], 1, "x", {"measurements": {"height_cm": True}},
    {"measurements": {"height_cm": None}}, {"measurements": {"height_cm": [170]}},
    {"measurements": {"height_cm": {"v": 170}}}, {"measurements": {"gender": 1}},
    {"measurements": {"gender": ""}}, {"measurements": {"gender": "FEMALE "}},
    {"measurements": {"": 1}}, {"measurements": {"height_cm": -1e308}},
    {"measurements": {"height_cm": 1e-320}}, {"measurements": {"height_cm": 0}},
    {"measurements": {"height_cm": -170}}, {"measurements": {"weight_kg": 1e9}},
    {"measurements": {"gender": "female", "height_cm": 250}},
    {"measurements": {"x" * 10000: 1}}, {"measurements": {"height_cm": "NaN"}},
]


def test_no_request_gives_500(client: httpx.Client, attrs: dict[str, Any]) -> None:
    payloads = list(BAD_PAYLOADS)
    for name, a in attrs.items():  # each attribute just outside its range, and at its bounds
        if a["min"] is not None:
            payloads += [{"measurements": {name: a["min"] - 1}}, {"measurements": {name: a["max"] + 1}},
                         {"measurements": {name: a["min"]}}, {"measurements": {name: a["max"]}}]
    for p in payloads:
        r = client.post("/v1/avatars", json=p)
        assert r.status_code in (200, 422), (p, r.status_code, r.text)
        if r.status_code == 422:
            assert isinstance(r.json()["detail"], list)
    for raw, ctype in [(b"[", "application/json"), (b"a=1", "application/x-www-form-urlencoded"),
                       (b"\x00" * 10, "application/octet-stream"), (b"{}", "text/plain")]:
        r = client.post("/v1/avatars", content=raw, headers={"Content-Type": ctype})
        assert r.status_code < 500, (raw, ctype, r.status_code, r.text)
    for method in ("GET", "PUT", "DELETE"):  # the static page mount answers what the API does not
        assert client.request(method, "/v1/avatars").status_code in (404, 405)
    assert client.get("/v1/nope").status_code == 404


def test_oversized_body_is_413(client: httpx.Client) -> None:
    big = b'{"measurements": {"height_cm": 170}}' + b" " * 1_000_001
    r = client.post("/v1/avatars", content=big, headers={"Content-Type": "application/json"})
    assert r.status_code == 413

    def chunks() -> Iterator[bytes]:
        yield b'{"measurements": {}}'
        for _ in range(20):
            yield b" " * 100_000

    r = client.post("/v1/avatars", content=chunks(), headers={"Content-Type": "application/json"})
    assert r.status_code == 413

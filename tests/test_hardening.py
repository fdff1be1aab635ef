"""The service under misuse and faults, in process (quick tier): CORS preflights for the
configured origins only, OPTIONS and 405 with the right Allow, garment names cleaned, rate
limits (429 + Retry-After, per client and per retailer key), back-pressure (503 + Retry-After),
a Redis outage (503 + Retry-After, then recovery by itself), point counts refused before a
parse. The process-level faults (SIGKILL, concurrent uploads, outage under load) are in
tests/test_faults.py (slow tier)."""
from __future__ import annotations

import asyncio
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi.testclient import TestClient

from service.api.middleware import BackPressureMiddleware, allowed_methods
from service.app import create_app
from service.model.formats.mesh_io import ScanError, declared_size, read_mesh_file
from service.settings import Settings
from tests.bench.common import shared_data_dir
from tests.harness import RETAILERS, assert_422, own_redis, redis_db, redis_url

KEY = {"X-API-Key": RETAILERS["acme"]}
SHOES = shared_data_dir() / "makehuman_clothes" / "shoes01"
ORIGIN = "https://shop.example"


def _settings(tmp: Path, url: str, **kw: object) -> Settings:
    kw.setdefault("TRYON_DEMO_ITEMS", "mens-tshirt")  # one demo garment: all these tests try on
    return Settings(TRYON_DATA_DIR=tmp, REDIS_URL=url, TRYON_EMBEDDED_WORKER=False,
                    TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()), **kw)


@pytest.fixture(scope="module")
def db() -> Iterator[int]:
    with redis_db() as leased:
        yield leased


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory, db: int) -> Iterator[TestClient]:
    settings = _settings(tmp_path_factory.mktemp("hard"), redis_url(db),
                         TRYON_CORS_ORIGINS=f"{ORIGIN}, http://localhost:3000/")
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="module")
def limited(tmp_path_factory: pytest.TempPathFactory, db: int) -> Iterator[TestClient]:
    """An app with low rate limits: 0.5 requests/s per client and per retailer."""
    settings = _settings(tmp_path_factory.mktemp("limited"), redis_url(db), TRYON_REDIS_PREFIX="limited:",
                         TRYON_RATE_LIMIT_CLIENT=0.5, TRYON_RATE_LIMIT_RETAILER=0.5)
    with TestClient(create_app(settings)) as c:
        yield c


# -- CORS and methods -------------------------------------------------------------------------
def test_cors_preflight_for_configured_origins_only(client: TestClient) -> None:
    pre = {"Access-Control-Request-Method": "POST", "Access-Control-Request-Headers": "authorization,content-type"}
    for origin in (ORIGIN, "http://localhost:3000"):
        r = client.options("/v1/customers", headers={"Origin": origin, **pre})
        assert r.status_code == 200, r.text
        assert r.headers["access-control-allow-origin"] == origin
        assert "POST" in r.headers["access-control-allow-methods"]
        assert "authorization" in r.headers["access-control-allow-headers"].lower()
    r = client.options("/v1/customers", headers={"Origin": "https://evil.example", **pre})
    assert r.status_code == 400 and "access-control-allow-origin" not in r.headers
    # simple requests: the header for allowed origins only; ETag etc. readable by the page
    r = client.get("/v1/garments", headers={"Origin": ORIGIN})
    assert r.headers["access-control-allow-origin"] == ORIGIN
    assert "etag" in r.headers["access-control-expose-headers"].lower()
    assert "access-control-allow-origin" not in client.get("/v1/garments", headers={"Origin": "https://x.y"}).headers


def test_no_cors_by_default(tmp_path: Path) -> None:
    c = TestClient(create_app(Settings(data_dir=tmp_path)))  # no lifespan: no storage needed
    r = c.options("/v1/garments", headers={"Origin": ORIGIN, "Access-Control-Request-Method": "GET"})
    assert "access-control-allow-origin" not in r.headers


def test_options_and_405_name_every_method(tmp_path: Path) -> None:
    c = TestClient(create_app(Settings(data_dir=tmp_path)))
    for path, methods in (("/v1/garments", "GET, HEAD, OPTIONS, POST"),
                          ("/v1/customers/abc", "DELETE, GET, HEAD, OPTIONS"),
                          ("/v1/customers", "OPTIONS, POST"), ("/healthz", "GET, HEAD, OPTIONS"),
                          ("/index.html", "GET, HEAD, OPTIONS")):
        r = c.options(path)
        assert r.status_code == 204 and r.headers["allow"] == methods and r.content == b"", (path, r.headers)
    for method, path, allow in (("PATCH", "/v1/garments", "GET, HEAD, OPTIONS, POST"),
                                ("PUT", "/v1/customers/abc", "DELETE, GET, HEAD, OPTIONS"),
                                ("DELETE", "/v1/body-model", "GET, HEAD, OPTIONS")):
        r = c.request(method, path)
        assert r.status_code == 405 and r.headers["allow"] == allow, (method, path, r.headers)
    assert allowed_methods([], "/nowhere") is None


# -- garment names ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["", "   ", "\t\n", "Tee\x00", "Tee\nshirt", "a\x1bb", "x\u202ey", "\x7f"])
def test_garment_names_cleaned(client: TestClient, name: str) -> None:
    files = {"mhclo": ("shoes01.mhclo", (SHOES / "shoes01.mhclo").read_bytes()),
             "obj": ("shoes01.obj", (SHOES / "shoes01.obj").read_bytes())}
    r = client.post("/v1/garments", data={"name": name}, files=files, headers={"X-API-Key": RETAILERS["globex"]})
    assert_422(r, ["body", "name"])


def test_garment_name_stripped(client: TestClient) -> None:
    files = {"mhclo": ("shoes01.mhclo", (SHOES / "shoes01.mhclo").read_bytes()),
             "obj": ("shoes01.obj", (SHOES / "shoes01.obj").read_bytes())}
    r = client.post("/v1/garments", data={"name": "  Shoes  é "}, files=files,
                    headers={"X-API-Key": RETAILERS["globex"]})
    assert r.status_code == 201, r.text
    assert r.json()["name"] == "Shoes  é"
    assert client.delete(f"/v1/garments/{r.json()['id']}", headers={"X-API-Key": RETAILERS["globex"]}).status_code == 204


# -- rate limits and back-pressure ------------------------------------------------------------
@pytest.mark.slow
def test_rate_limit_per_client_and_retailer(limited: TestClient) -> None:
    """0.5 requests/s per client and per retailer key (bursts of 1): the next request within 2 s
    is answered 429 with Retry-After; a retailer's key has its own budget; 2 s later the
    budget is back."""
    client = limited
    body = {"measurements": {"height_cm": 170}}
    codes = [client.post("/v1/avatars", json=body).status_code for _ in range(3)]
    assert codes == [200, 429, 429], codes
    r = client.post("/v1/avatars", json=body)
    assert r.status_code == 429 and 1 <= int(r.headers["retry-after"]) <= 2 and "rate limit" in r.json()["detail"]
    other = client.post("/v1/avatars", json=body, headers={"X-Forwarded-For": "1.2.3.4"})
    assert other.status_code == 429  # the TestClient has no trusted proxy: still the same client
    codes = [client.post("/v1/customers", json=body, headers=KEY).status_code for _ in range(3)]
    assert codes == [201, 429, 429], codes
    time.sleep(2.1)
    assert client.post("/v1/avatars", json=body).status_code == 200  # refilled


def test_back_pressure_answers_503_at_once() -> None:
    """Beyond max_inflight requests (or max_uploads uploads) per process: 503 + Retry-After at
    once, the upload's body read and dropped; the others are served."""
    gate = asyncio.Event()

    async def slow_app(scope, receive, send) -> None:
        while (await receive()).get("more_body"):
            pass
        await gate.wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b"ok"})

    mw = BackPressureMiddleware(slow_app, max_inflight=3, max_uploads=1)

    async def run() -> list[tuple[int, str | None]]:
        transport = httpx.ASGITransport(app=mw)
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as c:
            up = {"files": {"mesh": ("a.obj", b"v 0 0 0\n" * 1000)}}
            tasks = [asyncio.create_task(c.post("/v1/customers", **up))]
            await asyncio.sleep(0.05)
            tasks.append(asyncio.create_task(c.post("/v1/customers", **up)))  # a second upload: 503
            await asyncio.sleep(0.05)  # (its body is read before it is refused: it counts meanwhile)
            tasks += [asyncio.create_task(c.get("/v1/garments")) for _ in range(3)]  # the 4th request: 503
            await asyncio.sleep(0.2)
            tasks.append(asyncio.create_task(c.get("/healthz")))  # not an API route: never shed
            await asyncio.sleep(0.05)
            gate.set()
            return [(r.status_code, r.headers.get("retry-after")) for r in await asyncio.gather(*tasks)]

    out = asyncio.run(run())
    assert out[1] == (503, "1") and out.count((503, "1")) == 2 and out.count((200, None)) == 4, out
    assert mw.inflight == 0 and mw.uploads == 0


# -- a Redis outage ---------------------------------------------------------------------------
@pytest.mark.slow
def test_redis_outage_is_503_then_recovers(tmp_path: Path) -> None:
    """Redis killed: every route that needs it answers 503 + Retry-After (never a 500); the
    routes that do not need it keep working; Redis back: the same client recovers by itself."""
    with own_redis(tmp_path / "redis") as rs:
        with TestClient(create_app(_settings(tmp_path / "data", rs.url)), raise_server_exceptions=False) as c:
            r = c.post("/v1/customers", json={"measurements": {"height_cm": 170}})
            cid, auth = r.json()["id"], {"Authorization": f"Bearer {r.json()['token']}"}
            gid = c.get("/v1/garments").json()[0]["id"]
            rs.stop()
            for method, path, kw in (("GET", "/v1/garments", {}), ("GET", f"/v1/customers/{cid}", {"headers": auth}),
                                     ("GET", f"/v1/customers/{cid}/garments/{gid}.glb", {"headers": auth}),
                                     ("POST", "/v1/customers", {"json": {"measurements": {}}}),
                                     ("POST", "/v1/avatars", {"json": {"measurements": {}}}),
                                     ("GET", "/v1/jobs/fit-x", {})):
                t0 = time.perf_counter()
                r = c.request(method, path, **kw)
                assert r.status_code == 503 and r.headers["retry-after"] == "1", (path, r.status_code, r.text)
                assert time.perf_counter() - t0 < 3, path  # fails fast, does not hang
            assert c.get("/v1/body-model").status_code == 200 and c.get("/healthz").status_code == 200
            rs.start()
            deadline = time.monotonic() + 10
            while c.get("/v1/garments").status_code != 200 and time.monotonic() < deadline:
                time.sleep(0.1)
            assert c.get(f"/v1/customers/{cid}", headers=auth).json()["id"] == cid  # AOF: nothing lost
            assert c.get(f"/v1/customers/{cid}/garments/{gid}.glb", headers=auth).status_code == 200


# -- point counts before parsing --------------------------------------------------------------
def test_point_counts_refused_before_parsing() -> None:
    n = 2_000_001
    xyz = b"0.1 0.2 0.3\n" * n
    assert declared_size(xyz, "xyz") == (n, 0)
    ply = (b"ply\nformat binary_little_endian 1.0\nelement vertex 3000000\nproperty float x\nproperty float y\n"
           b"property float z\nend_header\n")  # no data at all: refused on its header alone
    obj = b"v 0 0 0\n" * n
    for data, name in ((xyz, "a.xyz"), (ply, "a.ply"), (obj, "a.obj")):
        t0 = time.perf_counter()
        with pytest.raises(ScanError, match="at most 2000000"):
            read_mesh_file(data, name)
        assert time.perf_counter() - t0 < 0.5, name
    faces = b"v 0 0 0\nv 1 0 0\nv 0 1 0\n" + b"f 1 2 3\n" * 8_000_001
    with pytest.raises(ScanError, match="faces"):
        read_mesh_file(faces, "f.obj")

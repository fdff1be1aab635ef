"""The service tried as an attacker would (issue 42), beyond tests/test_hardening.py.

Quick tier, in process (a redis-server of the test's own): declared sizes of every format
checked before allocation (and legitimate compressed GLBs still accepted), textures decoded and
re-encoded, forwarded headers trusted from configured proxies only, body deadlines, log
redaction, bad JSON 422 on every JSON route, short error excerpts, the outfit CPU budget, the
memory budget (413), per-client expensive-request slots, unknown and forbidden job ids alike.

Slow tier (``--full``), a real `tryon serve` process: every hostile upload of
tests/hostile_cases.py within its time and server-memory budget (psutil RSS of the server
process), a forwarded-header burst, trickling bodies beside legitimate uploads, a job flood, a
stalled body, a client gone mid-upload, a binary WebSocket frame, and the log afterwards: no
token, no key, no stack trace, the server process never restarted."""
from __future__ import annotations

import asyncio
import io
import json
import logging
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient
from PIL import Image

from service.api.logs import RedactSecrets, redact
from service.api.middleware import BodyTimeout, TimedReceive, TrustedProxyMiddleware
from service.app import create_app
from service.application.errors import Invalid, TooManyRequests
from service.application.limits import Requester
from service.application.uploads import read_texture
from service.model.formats import gltf, gltf_read
from service.model.formats.declared_sizes import DeclaredSizeError, check_gltf, decode_budget
from service.model.formats.mesh_io import ScanError, read_mesh_file
from service.settings import Settings
from tests import hostile_cases as H
from tests.harness import RETAILERS, assert_422, bearer, own_redis, run_server

KEY = {"X-API-Key": RETAILERS["acme"]}


@pytest.fixture(scope="module")
def redis_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    with own_redis(tmp_path_factory.mktemp("redis")) as server:
        yield server.url


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory, redis_server: str) -> Iterator[TestClient]:
    settings = Settings(TRYON_DATA_DIR=tmp_path_factory.mktemp("hostile"), REDIS_URL=redis_server,
                        TRYON_EMBEDDED_WORKER=False, TRYON_DEMO_ITEMS="", TRYON_RATE_LIMIT_CLIENT=1000,
                        TRYON_MEMORY_BUDGET_MB=64,
                        TRYON_RETAILER_KEYS=",".join(f"{n}:{k}" for n, k in RETAILERS.items()))
    with TestClient(create_app(settings)) as c:
        yield c


@pytest.fixture(scope="module")
def customer(client: TestClient) -> dict[str, Any]:
    r = client.post("/v1/customers", json={"measurements": {"height_cm": 170}})
    assert r.status_code == 201, r.text
    return r.json()


# -- declared sizes ------------------------------------------------------------------------------
@pytest.mark.parametrize("make, name", [
    (H.glb_unused_accessor, "a.glb"), (H.glb_viewless_accessor, "a.glb"), (H.glb_sparse_bomb, "a.glb"),
    (H.glb_view_past_buffer, "a.glb"), (H.glb_meshopt_undeclared, "a.glb"), (H.glb_image_view_bomb, "a.glb"),
    (H.gltf_data_uri_bomb, "a.gltf"), (H.ply_element_bomb, "a.ply"), (H.ply_ascii_rows, "a.ply")])
def test_declared_size_bombs_refused_before_allocation(make, name: str) -> None:
    """Each bomb is refused on its declarations: in milliseconds, whether or not a node uses
    the accessor, whether or not the compression is declared."""
    data = make()
    t0 = time.perf_counter()
    with pytest.raises(ScanError, match="malformed or too large"):
        read_mesh_file(data, name)
    assert time.perf_counter() - t0 < 0.2


def test_legitimate_glbs_within_the_decode_budget() -> None:
    """The service's own GLBs (plain, quantized, meshopt-compressed, skinned, with morph
    targets) pass the declared-size check with their real sizes."""
    from tests.test_mesh_io import body

    m = body()
    targets = np.zeros((4, len(m.vertices), 3), np.float32)
    targets[:, :10] = 0.01
    for compression in (None, "quantize", "meshopt"):
        data = gltf.mesh_to_glb(m.vertices, m.faces, compression=compression)
        doc, blob = gltf_read._parse_glb(data)
        assert check_gltf(doc, len(blob), len(data)) <= decode_budget(len(data))
    with pytest.raises(DeclaredSizeError, match="more than"):
        doc, blob = gltf_read._parse_glb(H.glb_sparse_bomb())
        check_gltf(doc, len(blob), 852)


def test_glb_garment_meshopt_view_refused(client: TestClient) -> None:
    """The garment route's texture reader and the upload check agree: a meshopt view that
    decompresses to 3 GB (not declared in extensionsUsed) is a 422 before any decode."""
    r = H._garment(H.glb_meshopt_undeclared(), "g.glb")(client)
    assert_422(r, ["body", "garment"], ("too large", "MiB of data"))


def test_mhclo_lines_counted_before_parsing(client: TestClient) -> None:
    r = client.post("/v1/garments", data={"name": "x"}, headers=KEY,
                    files={"mhclo": ("g.mhclo", H.mhclo_lines()), "obj": ("g.obj", H.SMALL_OBJ)})
    assert_422(r, ["body", "mhclo"], ("lines",))


def test_memory_budget_refuses_413(client: TestClient) -> None:
    """An upload whose declared sizes need more than the process's budget (64 MiB here) is a
    413 before it is parsed."""
    obj = b"v 0 0 0\n" * 600_000
    r = client.post("/v1/customers", files={"mesh": ("big.obj", obj)})
    assert r.status_code == 413 and "MiB" in r.json()["detail"], r.text


# -- textures ------------------------------------------------------------------------------------
def _png(mode: str = "RGB", size: tuple[int, int] = (8, 8)) -> bytes:
    buf = io.BytesIO()
    Image.new(mode, size, (10, 200, 30) if mode == "RGB" else (10, 200, 30, 128)).save(buf, "PNG")
    return buf.getvalue()


def test_texture_decoded_and_reencoded() -> None:
    """Only the decoded image is stored: text appended after a real PNG is gone, the pixels are
    the same; a JPEG stays a JPEG."""
    data = _png() + b"<script>alert(1)</script>"
    tex = read_texture(data, "t.png")
    assert tex.mime == "image/png" and b"script" not in tex.data
    assert np.array_equal(np.asarray(Image.open(io.BytesIO(tex.data))), np.asarray(Image.open(io.BytesIO(_png()))))
    rgba = read_texture(_png("RGBA"), "a.png")
    assert Image.open(io.BytesIO(rgba.data)).mode == "RGBA"
    buf = io.BytesIO()
    Image.new("RGB", (16, 16), (200, 10, 10)).save(buf, "JPEG")
    assert read_texture(buf.getvalue(), "t.jpg").mime == "image/jpeg"


@pytest.mark.parametrize("make, words", [(H.png_script, ("not a readable PNG",)), (H.png_dimension_bomb, ("pixels",))])
def test_fake_and_bomb_images_refused(make, words: tuple[str, ...]) -> None:
    with pytest.raises(Invalid) as exc:
        read_texture(make(), "t.png")
    assert all(w in exc.value.message for w in words), exc.value.message


def test_png_inflate_bomb_decoded_to_its_size() -> None:
    """A 16x16 PNG whose data inflates to ~400 MB: only 16x16 pixels are decoded and stored."""
    bomb = H.png_inflate_bomb()
    t0 = time.perf_counter()
    tex = read_texture(bomb, "t.png")
    assert time.perf_counter() - t0 < 1.0
    assert Image.open(io.BytesIO(tex.data)).size == (16, 16) and len(tex.data) < 1000


# -- proxies, body deadlines, logs -----------------------------------------------------------------
def _client_of(proxies: list[str], peer: str, forwarded: str | None) -> str:
    seen: list[str] = []

    async def app(scope, receive, send) -> None:
        seen.append(scope["client"][0])

    headers = [(b"x-forwarded-for", forwarded.encode())] if forwarded else []
    scope = {"type": "http", "client": (peer, 5000), "headers": headers, "path": "/", "method": "GET"}
    asyncio.run(TrustedProxyMiddleware(app, proxies)(scope, None, None))
    return seen[0]


def test_forwarded_for_trusted_from_configured_proxies_only() -> None:
    assert _client_of([], "127.0.0.1", "1.2.3.4") == "127.0.0.1"  # the default: the socket's address
    assert _client_of(["10.0.0.0/8"], "127.0.0.1", "1.2.3.4") == "127.0.0.1"  # not from a proxy
    assert _client_of(["10.0.0.0/8"], "10.0.0.5", "1.2.3.4") == "1.2.3.4"
    # the right-most address that is not a proxy: a client cannot prepend its own choice
    assert _client_of(["10.0.0.0/8"], "10.0.0.5", "6.6.6.6, 1.2.3.4, 10.0.0.9") == "1.2.3.4"
    assert _client_of(["localhost"], "127.0.0.1", "1.2.3.4") == "1.2.3.4"  # a host name, resolved
    assert _client_of(["10.0.0.0/8"], "10.0.0.5", "not-an-ip") == "10.0.0.5"


def test_stalled_body_times_out() -> None:
    async def never() -> dict:
        await asyncio.sleep(60)
        return {}

    async def slow() -> dict:
        await asyncio.sleep(0.05)
        return {"type": "http.request", "body": b"x", "more_body": True}

    async def go(receive, timeout: float, rate: int) -> float:
        timed = TimedReceive(receive, timeout, rate)
        t0 = time.monotonic()
        with pytest.raises(BodyTimeout):
            while True:
                await timed()
        return time.monotonic() - t0

    assert 0.2 <= asyncio.run(go(never, 0.2, 0)) < 1.0  # no progress
    assert 0.3 <= asyncio.run(go(slow, 0.3, 1000)) < 1.5  # progress, but 20 bytes/s


def test_log_redaction() -> None:
    assert redact('GET /v1/customers/c1/edit/ws?token=s3cr3t&x=1') == "GET /v1/customers/c1/edit/ws?token=REDACTED&x=1"
    assert redact("/p?key=abc;api_key=def") == "/p?key=REDACTED;api_key=REDACTED"
    # uvicorn's access records: the formatter reads the arguments one by one
    rec = logging.LogRecord("uvicorn.access", logging.INFO, "", 0, '%s - "%s %s HTTP/%s" %d',
                            ("1.2.3.4:5", "GET", "/x?token=abc", "1.1", 200), None)
    assert RedactSecrets().filter(rec) and rec.getMessage() == '1.2.3.4:5 - "GET /x?token=REDACTED HTTP/1.1" 200'


# -- one status for one kind of error; short excerpts -------------------------------------------
def test_bad_json_is_422_on_every_json_route(client: TestClient, customer: dict[str, Any]) -> None:
    routes = ["/v1/avatars", "/v1/customers", f"/v1/customers/{customer['id']}/edit"]
    for body in (b"[" * 100_000 + b"]" * 100_000, b'{"measurements": ', b"\xff\xfe", b'{"a": [' * 5000):
        for path in routes:
            r = client.post(path, content=body, headers={"Content-Type": "application/json", **bearer(customer)})
            assert r.status_code == 422, (path, body[:20], r.status_code, r.text[:200])
            assert isinstance(r.json()["detail"], list)


def test_error_messages_echo_a_short_excerpt(client: TestClient) -> None:
    big = "k" * 1_000_000
    for path in ("/v1/customers", "/v1/avatars"):
        r = client.post(path, json={"measurements": {big: 1, "height_cm": 170}})
        assert r.status_code == 422 and len(r.content) < 2000, (path, len(r.content))


def test_unknown_and_forbidden_job_ids_alike(client: TestClient) -> None:
    """A job id that exists but is not the caller's and one that does not exist: the same 404."""
    from tests.bench.hostile import _scan_xyz

    xyz = _scan_xyz(client.get("/v1/body-model/template.obj").content)
    r = client.post("/v1/customers", files={"mesh": ("scan.xyz", xyz)})
    assert r.status_code == 202, r.text
    job = r.json()["job"]["id"]
    forbidden = client.get(f"/v1/jobs/{job}", headers={"Authorization": "Bearer wrong"})
    unknown = client.get(f"/v1/jobs/{job[:-4]}beef", headers={"Authorization": "Bearer wrong"})
    assert forbidden.status_code == unknown.status_code == 404
    assert forbidden.json()["detail"].replace(job, "ID") == unknown.json()["detail"].replace(job[:-4] + "beef", "ID")
    assert client.get(f"/v1/jobs/{job}", headers=bearer(r.json())).status_code == 200


# -- bounded work per request -----------------------------------------------------------------
def test_outfit_cpu_budget(client: TestClient, customer: dict[str, Any]) -> None:
    """12 garments with pose targets (~11 s of CPU) are refused before anything is loaded; the
    same outfit without them, or 6 with them, go on (here: to the unknown garments' 404)."""
    ids = ",".join(f"g{i}" for i in range(12))
    r = client.get(f"/v1/customers/{customer['id']}/outfit.glb?garments={ids}&pose_correctives=true",
                   headers=bearer(customer))
    assert_422(r, ["query", "garments"], ("CPU", "at most 6"))
    for garments, poses in ((ids, "false"), (",".join(f"g{i}" for i in range(6)), "true")):
        r = client.get(f"/v1/customers/{customer['id']}/outfit.glb?garments={garments}&pose_correctives={poses}",
                       headers=bearer(customer))
        assert r.status_code == 404, r.text


def test_expensive_requests_per_client_at_once(client: TestClient) -> None:
    """TRYON_MAX_EXPENSIVE_CLIENT (4) slots per client and process: the fifth is a 429; another
    client and the same client afterwards are served."""
    limits = client.app.state.context.limits
    a, b = Requester("1.2.3.4", None), Requester("5.6.7.8", None)
    with limits.slot(a), limits.slot(a), limits.slot(a), limits.slot(a):
        with pytest.raises(TooManyRequests) as exc:
            with limits.slot(a):
                pass
        assert exc.value.retry_after >= 1
        with limits.slot(b):
            pass
    with limits.slot(a), limits.slot(a), limits.slot(a), limits.slot(a):
        pass


def test_websocket_misuse_closes_with_a_code(client: TestClient, customer: dict[str, Any]) -> None:
    from starlette.websockets import WebSocketDisconnect

    with client.websocket_connect(f"/v1/customers/{customer['id']}/edit/ws?token={customer['token']}") as ws:
        ws.receive_json(), ws.receive_bytes(), ws.receive_bytes()
        ws.send_bytes(b"\x00binary")
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_text()
        assert exc.value.code == 1003
    with client.websocket_connect(f"/v1/customers/{customer['id']}/edit/ws?token={customer['token']}") as ws:
        ws.receive_json(), ws.receive_bytes(), ws.receive_bytes()
        ws.send_text("x" * 100_000)
        with pytest.raises(WebSocketDisconnect) as exc:
            ws.receive_text()
        assert exc.value.code == 1008


# -- a real server, as an attacker would ------------------------------------------------------
@pytest.fixture(scope="module")
def attacked() -> Iterator[dict[str, Any]]:
    from tests.bench import hostile

    with tempfile.TemporaryDirectory(prefix="tryon-hostile-") as tmp:
        with run_server(Path(tmp) / "data", "embedded", workers=1, **hostile.SERVER_ENV) as server:
            res = hostile.run_suite(server)
        res["log"] = hostile.scan_log(server.log_path, res.pop("secrets"))
        res["figures"] = hostile.figures(res)
        yield res


@pytest.mark.slow
def test_hostile_uploads_within_time_and_memory_budgets(attacked: dict[str, Any]) -> None:
    for row in attacked["uploads"]:
        assert row["ok"], row
        assert row["after_mib"] <= 50, row  # memory given back (malloc keeps a little)
        assert row["answer_bytes"] < 4000, row
    assert attacked["server"]["alive"]


@pytest.mark.slow
def test_forwarded_burst_limited(attacked: dict[str, Any]) -> None:
    assert attacked["figures"]["burst_limited_pct"] >= 50, attacked["burst"]


@pytest.mark.slow
def test_trickling_bodies_do_not_hold_upload_slots(attacked: dict[str, Any]) -> None:
    t = attacked["trickle"]
    assert t["legit_in_time"] >= 5, t
    assert [s for s, _ in t["tricklers"]] == [408] * 8, t


@pytest.mark.slow
def test_job_flood_capped_per_client(attacked: dict[str, Any]) -> None:
    f = attacked["flood"]
    assert f["accepted"] == 3 and f["limited"] == 3 and f["retry_after"] == ["10"], f


@pytest.mark.slow
def test_stalled_body_and_websocket_misuse(attacked: dict[str, Any]) -> None:
    assert attacked["stalled"]["status"] == 408 and attacked["stalled"]["seconds"] < 8, attacked["stalled"]
    assert attacked["websocket"]["binary_frame_close_code"] == 1003
    j = attacked["job_ids"]
    assert j["forbidden"] == j["unknown"], j


@pytest.mark.slow
def test_logs_hold_no_secrets_and_no_traces(attacked: dict[str, Any]) -> None:
    assert attacked["log"]["secrets_in_log"] == 0 and attacked["log"]["tracebacks_in_log"] == 0, attacked["log"]


def test_cases_are_small() -> None:
    """Every hostile upload is at most ~1 MB (the figures are for uploads of <= 1 MB)."""
    sizes = {"unused": len(H.glb_unused_accessor()), "meshopt": len(H.glb_meshopt_undeclared()),
             "obj": len(H.obj_points_1mb()), "xyz": len(H.xyz_1mb()), "mhclo": len(H.mhclo_lines()),
             "png": len(H.png_inflate_bomb()), "gltf": len(H.gltf_data_uri_bomb())}
    assert max(sizes.values()) <= 1_100_000, sizes
    assert json.loads(H.gltf_data_uri_bomb())["buffers"][0]["uri"].startswith("data:")

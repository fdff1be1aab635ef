"""``tryon bench page``: what the customer page waits for when a shopper dresses a new body, over
HTTP against a default `tryon serve` (one server process per core, embedded Redis), client on
the same machine.

Per new customer (held-out ANSUR people, the tailor measurements the page sends: gender,
height, weight, chest, waist, hip), the page's requests in its order:

1. ``create``: ``POST /v1/customers`` (the page saves the customer when it is first dressed);
2. ``first_view``: ``outfit.glb?garments=top,bottoms&pose_correctives=1`` and ``/poses`` sent
   together on two connections, as the page does (it poses the avatar while the outfit loads):
   the time until both are answered, and each alone (``first_outfit``, ``first_poses``);
3. ``again``: the same outfit asked again on a new connection (a reload; with several server
   processes it may land on another one); ``again_plain``: the same, uncompressed (the bytes
   the page saves);
4. ``second_outfit``: a shirt under a jacket, with the pose correctives;
5. the customer deleted.

Every GLB is asked for as the page asks for it, ``compression=meshopt`` (``COMPRESSION``).
Reported: median, p90 and max of each step (ms) and the median bytes of each GLB answer over the
customers, the server processes and the machine's load average (this machine is shared, so
compare runs made side by side).
"""
from __future__ import annotations

import os
import threading
import time

import httpx
import numpy as np

from service.cli import default_workers
from tests.bench.common import read_ansur
from tests.harness import GLB, run_server

CUSTOMERS = 12
SENT = ("height_cm", "weight_kg", "chest_cm", "waist_cm", "hip_cm")  # with gender
OUTFITS = {"female": ("womens-tshirt", "womens-jeans"), "male": ("mens-tshirt", "mens-jeans")}
SECOND_OUTFIT = ("striped-shirt", "casual-jacket")
CATALOGUE_WAIT_S = 600.0
STEPS = ("create", "first_view", "first_outfit", "first_poses", "again", "again_plain", "second_outfit")
COMPRESSION = "meshopt"  # what web_client/app.js asks for (GLB_COMPRESSION)


def _people(n: int, ranges: dict) -> list[dict]:
    """The first ``n`` held-out ANSUR people (a fixed shuffle) whose sent measurements are in the
    service's ranges, as the page's JSON."""
    held = read_ansur(heldout=True)
    order = np.random.default_rng(7).permutation(len(held))
    out = []
    for i in order:
        m = held[i]["measurements"]
        if all(ranges[k][0] <= m[k] <= ranges[k][1] for k in SENT):
            out.append({"gender": m["gender"], **{k: round(float(m[k]), 1) for k in SENT}})
        if len(out) == n:
            break
    return out


def _catalogue(client: httpx.Client) -> dict[str, str]:
    """catalogue id -> garment id, once the demo catalogue is built."""
    deadline = time.monotonic() + CATALOGUE_WAIT_S
    wanted = {*SECOND_OUTFIT, *[g for o in OUTFITS.values() for g in o]}
    while True:
        ids = {g.get("catalogue_id"): g["id"] for g in client.get("/v1/garments").json() if g["status"] == "ready"}
        if wanted <= set(ids):
            return ids
        if time.monotonic() > deadline:
            raise TimeoutError(f"the demo catalogue lacks {sorted(wanted - set(ids))}")
        time.sleep(1.0)


def _get(base: str, path: str, token: str, out: dict, key: str) -> None:
    """GET on a new connection (a browser's parallel one); ``out[key]`` = (seconds, status, bytes)."""
    t0 = time.perf_counter()
    with httpx.Client(base_url=base, timeout=120) as c:
        r = c.get(path, headers={"Authorization": f"Bearer {token}", "Accept": GLB})
        r.read()
    out[key] = (time.perf_counter() - t0, r.status_code, len(r.content))


def bench_page(customers: int = CUSTOMERS) -> dict:
    load0 = os.getloadavg()[0]
    with run_server(None, "embedded", workers=None, log_level="warning") as server:
        c, base = server.client, server.base_url
        ranges = {a["name"]: (a["min"], a["max"]) for a in c.get("/v1/body-model").json()["attributes"]}
        ids = _catalogue(c)
        times: dict[str, list[float]] = {k: [] for k in STEPS}
        sizes: dict[str, list[int]] = {}
        errors: list[str] = []
        for person in _people(customers, ranges):
            t0 = time.perf_counter()
            r = c.post("/v1/customers", json={"measurements": person})
            times["create"].append(time.perf_counter() - t0)
            if r.status_code != 201:
                errors.append(f"create {r.status_code}: {r.text[:200]}")
                continue
            cid, token = r.json()["id"], r.json()["token"]
            outfit = ",".join(ids[g] for g in OUTFITS[person["gender"]])
            plain = f"/v1/customers/{cid}/outfit.glb?garments={outfit}&pose_correctives=1"
            path = f"{plain}&compression={COMPRESSION}"
            got: dict = {}
            t0 = time.perf_counter()
            th = [threading.Thread(target=_get, args=(base, path, token, got, "first_outfit")),
                  threading.Thread(target=_get, args=(base, f"/v1/customers/{cid}/poses", token, got, "first_poses"))]
            for t in th:
                t.start()
            for t in th:
                t.join()
            times["first_view"].append(time.perf_counter() - t0)
            _get(base, path, token, got, "again")
            _get(base, plain, token, got, "again_plain")
            second = ",".join(ids[g] for g in SECOND_OUTFIT)
            _get(base, f"/v1/customers/{cid}/outfit.glb?garments={second}&pose_correctives=1&compression={COMPRESSION}",
                 token, got, "second_outfit")
            for k, (sec, status, size) in got.items():
                times[k].append(sec)
                if k != "first_poses":
                    sizes.setdefault(k, []).append(size)
                if status != 200:
                    errors.append(f"{k} {status}")
            c.delete(f"/v1/customers/{cid}", headers={"Authorization": f"Bearer {token}"})
        processes = default_workers()
    steps = {k: {"median_ms": 1000 * float(np.median(v)), "p90_ms": 1000 * float(np.percentile(v, 90)),
                 "max_ms": 1000 * float(np.max(v)), "n": len(v),
                 **({"bytes_median": int(np.median(sizes[k]))} if k in sizes else {})} for k, v in times.items() if v}
    return {"suite": "page", "customers": customers, "server_processes": processes, "steps": steps,
            "errors": errors, "machine_load_avg": [load0, os.getloadavg()[0]],
            "outfits": {"first": OUTFITS, "second": SECOND_OUTFIT}, "compression": COMPRESSION}


def run(limit: int = 0, repeats: int = 0) -> dict:
    """``limit``: new customers (default 12)."""
    return bench_page(customers=limit or CUSTOMERS)


def format_result(r: dict) -> str:
    lines = [(f"the page's first dressed view of a new customer over HTTP: {r['customers']} held-out people, "
              f"default `tryon serve` ({r['server_processes']} processes), client on the same machine; "
              f"load average {r['machine_load_avg'][0]:.1f} -> {r['machine_load_avg'][1]:.1f}"),
             f"  {'step':<15}{'median ms':>10}{'p90 ms':>10}{'max ms':>10}{'bytes':>11}"]
    for k, v in r["steps"].items():
        size = f"{v['bytes_median']:>11,}" if "bytes_median" in v else ""
        lines.append(f"  {k:<15}{v['median_ms']:>10.0f}{v['p90_ms']:>10.0f}{v['max_ms']:>10.0f}{size}")
    lines.append(f"  GLBs as the page asks for them (compression={r.get('compression')}); first_view: the outfit "
                 "(tee + jeans, pose correctives) and /poses sent together; again: the same outfit on a new "
                 "connection (again_plain: uncompressed); second_outfit: striped shirt under the casual jacket")
    lines.append(f"  errors: {len(r['errors'])} {r['errors'][:3]}")
    return "\n".join(lines)

"""A shop back end's use of the try-on service, complete and runnable (Python 3.9+, stdlib only).

    python3 docs/examples/shop_client.py http://127.0.0.1:8000

Creates a customer from measurements (keeping its token), lists the catalogue, tries a garment
on (then asks again with the ETag: 304, nothing sent), asks for an outfit compressed with
meshopt, and deletes the customer. Every call retries what is worth retrying: 429 and 503 after
their ``Retry-After``, a dropped connection after a short back-off; a 4xx other than those is
the caller's mistake and is raised with the service's message. Prints a JSON summary.
"""
from __future__ import annotations

import json
import sys
import time
import urllib.error
import urllib.request

RETRY_STATUSES = {429, 503}  # rate limit, overload or Redis outage: each comes with Retry-After
MAX_TRIES = 5


class ServiceError(RuntimeError):
    def __init__(self, status: int, detail: object):
        super().__init__(f"HTTP {status}: {detail}")
        self.status, self.detail = status, detail


class TryOnClient:
    def __init__(self, base: str, api_key: str | None = None):
        self.base = base.rstrip("/")
        self.api_key = api_key
        self.etags: dict[str, tuple[str, bytes]] = {}  # url -> (ETag, body): a tiny private cache

    def request(self, method: str, path: str, *, body: dict | None = None, token: str | None = None,
                accept: str = "application/json") -> tuple[int, object, bytes]:
        url = self.base + path
        headers = {"Accept": accept}
        if body is not None:
            headers["Content-Type"] = "application/json"
        if token:
            headers["Authorization"] = f"Bearer {token}"
        if self.api_key:
            headers["X-API-Key"] = self.api_key
        if method == "GET" and url in self.etags:
            headers["If-None-Match"] = self.etags[url][0]
        data = json.dumps(body).encode() if body is not None else None
        for attempt in range(1, MAX_TRIES + 1):
            req = urllib.request.Request(url, data=data, headers=headers, method=method)
            try:
                with urllib.request.urlopen(req, timeout=120) as r:
                    status, head, payload = r.status, r.headers, r.read()
                break
            except urllib.error.HTTPError as e:
                status, head, payload = e.code, e.headers, e.read()
                if status == 304:
                    break
                if status in RETRY_STATUSES and attempt < MAX_TRIES:
                    time.sleep(float(e.headers.get("Retry-After", "1")))
                    continue
                try:
                    detail = json.loads(payload)["detail"]
                except (ValueError, KeyError):
                    detail = payload[:200].decode(errors="replace")
                raise ServiceError(status, detail) from None
            except (urllib.error.URLError, ConnectionError, TimeoutError):
                if attempt == MAX_TRIES:
                    raise
                time.sleep(0.5 * 2 ** attempt)
        if status == 304:  # unchanged: the cached body is still right
            return status, head, self.etags[url][1]
        if method == "GET" and head.get("ETag"):
            self.etags[url] = (head["ETag"], payload)
        return status, head, payload

    def json(self, method: str, path: str, **kw) -> dict:
        return json.loads(self.request(method, path, **kw)[2] or b"null")


def main(base: str) -> dict:
    shop = TryOnClient(base)
    # 1. the shopper enters a few measurements: the shop keeps the customer's id and token
    customer = shop.json("POST", "/v1/customers",
                         body={"measurements": {"gender": "female", "height_cm": 168, "weight_kg": 62}})
    cid, token = customer["id"], customer["token"]
    # 2. the catalogue: garments still building are left out
    garments = [g for g in shop.json("GET", "/v1/garments") if g["status"] == "ready"]
    top = min(garments, key=lambda g: -g["layer"])  # the outermost garment
    # 3. a try-on, then the same again: the second answer is a 304 served from the cache
    path = f"/v1/customers/{cid}/garments/{top['id']}.glb?compression=meshopt"
    first = shop.request("GET", path, token=token, accept="model/gltf-binary")
    again = shop.request("GET", path, token=token, accept="model/gltf-binary")
    # 4. an outfit: every ready garment of two layers, inner first, with the avatar
    chosen = sorted(garments, key=lambda g: g["layer"])[:2]
    outfit = shop.request("GET", f"/v1/customers/{cid}/outfit.glb?garments="
                          + ",".join(g["id"] for g in chosen) + "&compression=meshopt",
                          token=token, accept="model/gltf-binary")
    # 5. a mistake is a clear 4xx, not retried
    try:
        shop.json("POST", "/v1/avatars", body={"measurements": {"height_cm": 500}})
        refused = None
    except ServiceError as e:
        refused = {"status": e.status, "message": e.detail[0]["msg"] if isinstance(e.detail, list) else e.detail}
    # 6. the shopper deletes their data
    deleted = shop.request("DELETE", f"/v1/customers/{cid}", token=token)[0]
    return {"customer": cid, "garments": len(garments),
            "tryon": {"status": first[0], "bytes": len(first[2]), "etag": first[1].get("ETag"),
                      "again_status": again[0], "again_bytes": len(again[2])},
            "outfit": {"status": outfit[0], "bytes": len(outfit[2]), "magic": outfit[2][:4].decode()},
            "refused": refused, "deleted": deleted}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1] if len(sys.argv) > 1 else "http://127.0.0.1:8000"), indent=2))

"""``tryon bench hostile``: a default `tryon serve` (one server process, embedded Redis, default
rate limits and caps; no embedded worker, so queued jobs stay queued) tried as an attacker
would, on loopback:

- every hostile upload of tests/hostile_cases.py (declared-size bombs in every format, fake and
  bomb images, deep and huge JSON): status, answer time, and the server process's peak RSS
  growth over the upload (psutil, sampled every ~2 ms) and its growth 1 s after;
- a burst of 40 concurrent expensive requests (new avatars) with a different
  ``X-Forwarded-For`` each (forwarded headers are not trusted by default);
- 6 legitimate uploads (the template avatar, 201) while 8 connections trickle bodies (1 byte
  every 0.5 s): how many are answered within 8 s, and what the tricklers get;
- a flood of 6 scan uploads from one client (cap: 3 queued jobs);
- a stalled body, a client gone mid-upload, a binary frame on the editing WebSocket opened with
  ``?token=``, unknown vs forbidden job ids (median time of each refusal);
- afterwards: the server process alive (the same pid, never restarted), the log scanned for
  tokens, API keys and stack traces.

The issue-42 figures are in ``figures``; ``--json`` for machines.
"""
from __future__ import annotations

import asyncio
import io
import re
import socket
import statistics
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import psutil

from tests.harness import RETAILERS, run_server
from tests.hostile_cases import Case, upload_cases

MIB = 1024 * 1024
BURST = 40
TRICKLERS = 8
LEGIT_UPLOADS = 6
LEGIT_WITHIN_S = 8.0
FLOOD = 6
SAMPLE_S = 0.002
SETTLE_S = 1.0  # the growth "after" is read this long after the answer
REFILL_S = 2.2  # default rate limit (10/s, bursts of 20): a full bucket again
SERVER_ENV = {"TRYON_RATE_LIMIT_CLIENT": "10", "TRYON_EMBEDDED_WORKER": "false", "TRYON_DEMO_ITEMS": ""}


class PeakRss:
    """Samples a process's RSS in a thread: ``peak - baseline`` in bytes over a ``with`` block."""

    def __init__(self, pid: int):
        self.proc = psutil.Process(pid)

    def rss(self) -> int:
        return self.proc.memory_info().rss

    def __enter__(self) -> "PeakRss":
        self.baseline = self.peak = self.rss()
        self.running = True
        self.thread = threading.Thread(target=self._sample, daemon=True)
        self.thread.start()
        return self

    def _sample(self) -> None:
        while self.running:
            try:
                self.peak = max(self.peak, self.rss())
            except psutil.Error:
                return
            time.sleep(SAMPLE_S)

    def __exit__(self, *exc: object) -> None:
        self.running = False
        self.thread.join()
        self.peak = max(self.peak, self.rss())


def _run_case(client: httpx.Client, pid: int, case: Case) -> dict[str, Any]:
    with PeakRss(pid) as mem:
        t0 = time.perf_counter()
        try:
            r = case.send(client)
            status, size = r.status_code, len(r.content)
        except httpx.TransportError as exc:  # the connection dropped: the server process died
            status, size = f"dropped ({type(exc).__name__})", 0
        seconds = time.perf_counter() - t0
    time.sleep(SETTLE_S)
    after = mem.rss() - mem.baseline
    peak = mem.peak - mem.baseline
    return {"case": case.name, "status": status, "expected": list(case.expect), "seconds": round(seconds, 3),
            "peak_mib": round(peak / MIB, 1), "after_mib": round(after / MIB, 1), "answer_bytes": size,
            "ok": status in case.expect and seconds <= case.seconds and peak <= case.mib * MIB}


def _raw_request(port: int, head: str, body: bytes = b"") -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    s.sendall(head.encode() + body)
    return s


def _read_status(s: socket.socket) -> int | None:
    try:
        data = s.recv(4096)
    except OSError:
        return None
    m = re.match(rb"HTTP/1\.1 (\d{3})", data)
    return int(m.group(1)) if m else None


MULTIPART_HEAD = ("POST /v1/customers HTTP/1.1\r\nHost: x\r\nContent-Type: multipart/form-data; boundary=B\r\n"
                  "Content-Length: {n}\r\n\r\n")


def _trickle(port: int, stop: threading.Event, out: list[Any]) -> None:
    """Send a multipart body one byte every 0.5 s until answered (or stopped)."""
    t0 = time.monotonic()
    s = _raw_request(port, MULTIPART_HEAD.format(n=200_000), b"--B\r\n")
    s.settimeout(0.5)
    status = None
    while not stop.is_set():
        try:
            s.sendall(b"x")
        except OSError:
            break
        try:
            data = s.recv(4096)
            if data:
                m = re.match(rb"HTTP/1\.1 (\d{3})", data)
                status = int(m.group(1)) if m else None
            break
        except socket.timeout:
            continue
        except OSError:
            break
    out.append((status, round(time.monotonic() - t0, 1)))
    s.close()


def _burst(base: str) -> list[int]:
    async def go() -> list[int]:
        async with httpx.AsyncClient(base_url=base, timeout=60) as c:
            body = {"measurements": {"height_cm": 170, "weight_kg": 70}}
            rs = await asyncio.gather(*[c.post("/v1/avatars", json=body,
                                               headers={"X-Forwarded-For": f"10.1.{i // 250}.{i % 250}"})
                                        for i in range(BURST)])
            return [r.status_code for r in rs]
    return asyncio.run(go())


def _scan_xyz(template_obj: bytes) -> bytes:
    """The template avatar's vertices, every third, as an XYZ point cloud: a scan to fit."""
    v = np.array([[float(x) for x in line.split()[1:4]] for line in template_obj.decode().splitlines()
                  if line.startswith("v ")])
    buf = io.StringIO()
    np.savetxt(buf, v[::3], fmt="%.5f")
    return buf.getvalue().encode()


def _median_ms(client: httpx.Client, path: str, n: int = 30) -> float:
    times = []
    for _ in range(n):
        t0 = time.perf_counter()
        client.get(path)
        times.append(1000 * (time.perf_counter() - t0))
    return round(statistics.median(times), 2)


def run_suite(server: Any) -> dict[str, Any]:
    """All the hostile cases against a running server (``tests.harness.Server``, one process)."""
    client: httpx.Client = server.client
    port, pid = server.port, server.proc.pid
    rows = [_run_case(client, pid, case) for case in upload_cases()]
    out: dict[str, Any] = {"uploads": rows}

    time.sleep(REFILL_S)
    codes = _burst(server.base_url)
    out["burst"] = {"requests": BURST, "limited": codes.count(429), "codes": sorted(set(codes))}

    time.sleep(REFILL_S)
    template = client.get("/v1/body-model/template.obj").content
    stop = threading.Event()
    trickled: list[Any] = []
    threads = [threading.Thread(target=_trickle, args=(port, stop, trickled), daemon=True) for _ in range(TRICKLERS)]
    for t in threads:
        t.start()
    time.sleep(0.5)
    legit = []
    for _ in range(LEGIT_UPLOADS):
        t0 = time.perf_counter()
        try:
            r = client.post("/v1/customers", files={"mesh": ("me.obj", template)}, timeout=LEGIT_WITHIN_S)
            status: Any = r.status_code
        except httpx.TimeoutException:
            status = "timeout"
        legit.append({"status": status, "seconds": round(time.perf_counter() - t0, 2)})
    for t in threads:
        t.join(timeout=15)
    stop.set()
    in_time = sum(1 for x in legit if x["status"] == 201 and x["seconds"] <= LEGIT_WITHIN_S)
    out["trickle"] = {"legit": legit, "legit_in_time": in_time, "tricklers": sorted(trickled, key=str)}

    time.sleep(REFILL_S)
    scan = _scan_xyz(template)
    flood = [client.post("/v1/customers", files={"mesh": ("scan.xyz", scan)}) for _ in range(FLOOD)]
    accepted = [r.json() for r in flood if r.status_code == 202]
    out["flood"] = {"uploads": FLOOD, "accepted": len(accepted), "limited": sum(r.status_code == 429 for r in flood),
                    "retry_after": sorted({r.headers.get("retry-after") for r in flood if r.status_code == 429})}

    # a stalled body, and a client gone mid-upload
    t0 = time.monotonic()
    s = _raw_request(port, "POST /v1/avatars HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                           "Content-Length: 1000\r\n\r\n", b'{"measurements"')
    out["stalled"] = {"status": _read_status(s), "seconds": round(time.monotonic() - t0, 1)}
    s.close()
    s = _raw_request(port, MULTIPART_HEAD.format(n=100_000), b"--B\r\n" + b"x" * 5000)
    s.close()

    # the editing WebSocket: opened with ?token= as the README tells browsers, then a binary frame
    from websockets.sync.client import connect

    created = client.post("/v1/customers", json={"measurements": {"height_cm": 172}}).json()
    token = created["token"]
    ws_code = None
    with connect(f"ws://127.0.0.1:{port}/v1/customers/{created['id']}/edit/ws?token={token}") as ws:
        ws.recv(), ws.recv(), ws.recv()
        ws.send(b"\x00\x01binary")
        try:
            while True:
                ws.recv(timeout=5)
        except Exception:
            ws_code = ws.protocol.close_code
    out["websocket"] = {"binary_frame_close_code": ws_code}

    # unknown and forbidden job ids: the same answer, about the same time
    tokens = [token, *(a["token"] for a in accepted)]
    if accepted:
        job = accepted[0]["job"]["id"]
        forbidden = client.get(f"/v1/jobs/{job}")
        unknown = client.get(f"/v1/jobs/{job[:-4]}beef")
        out["job_ids"] = {"forbidden": [forbidden.status_code, forbidden.json()["detail"].replace(job, "<id>")],
                          "unknown": [unknown.status_code, unknown.json()["detail"].replace(job[:-4] + "beef", "<id>")],
                          "forbidden_ms": _median_ms(client, f"/v1/jobs/{job}"),
                          "unknown_ms": _median_ms(client, f"/v1/jobs/{job[:-4]}beef")}

    alive = server.proc.poll() is None and client.get("/healthz").status_code == 200
    out["server"] = {"alive": alive, "pid": pid}
    out["secrets"] = tokens + list(RETAILERS.values())
    return out


def scan_log(log_path: Path, secrets: list[str]) -> dict[str, int]:
    text = log_path.read_text(errors="replace")
    return {"secrets_in_log": sum(text.count(s) for s in secrets if s),
            "tracebacks_in_log": text.count("Traceback"), "log_lines": text.count("\n")}


def figures(res: dict[str, Any]) -> dict[str, Any]:
    """The issue-42 figures from a run."""
    ups = res["uploads"]
    return {
        "max_peak_mib": max(r["peak_mib"] for r in ups),
        "max_after_mib": max(r["after_mib"] for r in ups),
        "processes_killed": 0 if res["server"]["alive"] else 1,
        "burst_limited_pct": round(100 * res["burst"]["limited"] / res["burst"]["requests"], 1),
        "legit_uploads_in_8s": res["trickle"]["legit_in_time"],
        "secrets_in_log": res["log"]["secrets_in_log"],
        "tracebacks_in_log": res["log"]["tracebacks_in_log"],
        "uploads_failed": sum(not r["ok"] for r in ups),
        "uploads": len(ups),
    }


def run(limit: int = 0, repeats: int = 0, **_: Any) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="tryon-hostile-") as tmp:
        with run_server(Path(tmp) / "data", "embedded", workers=1, check_log=False, **SERVER_ENV) as server:
            res = run_suite(server)
        res["log"] = scan_log(server.log_path, res.pop("secrets"))  # the server stopped: its whole log
    res["figures"] = figures(res)
    return res


GOALS = {"max_peak_mib": "<= 100", "max_after_mib": "<= 50 (back to baseline)", "processes_killed": "0",
         "burst_limited_pct": ">= 50", "legit_uploads_in_8s": ">= 5 of 6", "secrets_in_log": "0",
         "tracebacks_in_log": "0", "uploads_failed": "0"}


def format_result(res: dict[str, Any]) -> str:
    lines = [f"{'case':<46}{'status':>8}{'time s':>9}{'peak MiB':>10}{'after MiB':>10}  ok"]
    for r in res["uploads"]:
        lines.append(f"{r['case']:<46}{str(r['status']):>8}{r['seconds']:>9.3f}{r['peak_mib']:>10.1f}"
                     f"{r['after_mib']:>10.1f}  {'yes' if r['ok'] else 'NO'}")
    b, t, f = res["burst"], res["trickle"], res["flood"]
    lines += ["", f"burst of {b['requests']} with changing X-Forwarded-For: {b['limited']} limited (codes {b['codes']})",
              f"legit uploads while {TRICKLERS} trickle: " + ", ".join(f"{x['status']} {x['seconds']}s" for x in t["legit"]),
              f"  tricklers got: {t['tricklers']}",
              f"flood of {f['uploads']} scans: {f['accepted']} queued, {f['limited']} limited (Retry-After "
              f"{f['retry_after']})",
              f"stalled body: {res['stalled']}", f"websocket binary frame: close {res['websocket']}"]
    if "job_ids" in res:
        j = res["job_ids"]
        lines.append(f"job ids: forbidden {j['forbidden']} {j['forbidden_ms']} ms, unknown {j['unknown']} "
                     f"{j['unknown_ms']} ms")
    lines += ["", f"{'figure':<24}{'value':>14}  goal"]
    for k, v in res["figures"].items():
        lines.append(f"{k:<24}{str(v):>14}  {GOALS.get(k, '')}")
    return "\n".join(lines)

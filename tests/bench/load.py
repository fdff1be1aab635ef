"""``tryon bench load``: mixed traffic against a default `tryon serve` (one server process per
core, embedded Redis with AOF, default rate limits and back-pressure) on loopback, the load
generator on the same machine.

Open loop: requests are sent on a fixed schedule (``rate`` per second, evenly spaced, kinds
drawn at random: 70 % try-ons of a stored customer and a demo garment, 20 % avatars from
measurements as GLB, 10 % new customers), whether or not earlier ones were answered, so a
server that falls behind shows it as latency (measured from the scheduled send time) instead of
slowing the generator down. Each simulated shopper has its own address (``X-Forwarded-For``,
trusted from loopback, ``TRYON_TRUSTED_PROXIES=127.0.0.1``, as behind a local proxy), so
per-client rate limits apply per shopper.

Reported: p50/p99 latency (all, and per kind), errors (anything but 2xx, 429/503 included),
the achieved rate, the CPU the server and the generator spent per request, and the server's
memory (RSS of its process tree: API processes, uvicorn's supervisor, redis-server, the embedded
worker) at the start (after every stored customer was tried on a few times, so that the
processes' bounded caches are warm), after 10 s and at the end.
"""
from __future__ import annotations

import asyncio
import json
import random
import threading
import time
from collections import Counter

import numpy as np
import psutil

from tests.harness import GLB, run_server

MIX = (("tryon", 0.70), ("avatar", 0.20), ("customer", 0.10))
RATE = 80.0  # requests per second
SECONDS = 40.0
WARMUP_S = 10.0  # memory growth is also counted from here
CUSTOMERS = 40  # stored before the run, tried on
SHOPPERS = 500


def _measurements(rng: random.Random) -> dict:
    female = rng.random() < 0.5
    h = rng.gauss(163 if female else 176, 7)
    bmi = min(max(rng.gauss(25, 4), 17), 40)
    return {"measurements": {"gender": "female" if female else "male", "height_cm": round(h, 1),
                             "weight_kg": round(bmi * (h / 100) ** 2, 1)}}


def _cpu(pid: int) -> float:
    """CPU seconds (user + system) of a process tree, children that ended included."""
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0.0
    total = 0.0
    for p in procs:
        try:
            t = p.cpu_times()
            total += t.user + t.system + t.children_user + t.children_system
        except psutil.NoSuchProcess:
            pass
    return total


def _rss(pid: int) -> int:
    try:
        root = psutil.Process(pid)
        procs = [root, *root.children(recursive=True)]
    except psutil.NoSuchProcess:
        return 0
    total = 0
    for p in procs:
        try:
            total += p.memory_info().rss
        except psutil.NoSuchProcess:
            pass
    return total


class _Pool:
    """Keep-alive HTTP/1.1 connections on raw asyncio streams (a light client: the server
    should get the CPU, not the load generator); one request per connection at a time."""

    def __init__(self, port: int):
        self.port = port
        self.idle: list[tuple[asyncio.StreamReader, asyncio.StreamWriter]] = []

    async def request(self, raw: bytes) -> int:
        """The status (0: no answer). A kept-alive connection the server closed meanwhile (its
        keep-alive timeout) is retried once on a new one, as HTTP clients do."""
        reused = bool(self.idle)
        status = await self._send(self.idle.pop() if reused else None, raw)
        if status is None and reused:
            status = await self._send(None, raw)
        return status or 0

    async def _send(self, conn, raw: bytes) -> int | None:
        if conn is None:
            try:
                conn = await asyncio.open_connection("127.0.0.1", self.port)
            except OSError:
                return None
        reader, writer = conn
        try:
            writer.write(raw)
            head = await reader.readuntil(b"\r\n\r\n")
            length, close = 0, False
            for line in head.split(b"\r\n")[1:]:
                name, _, value = line.partition(b":")
                name = name.strip().lower()
                if name == b"content-length":
                    length = int(value)
                elif name == b"connection" and value.strip().lower() == b"close":
                    close = True
            await reader.readexactly(length)
        except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            writer.close()
            return None
        if close:
            writer.close()
        else:
            self.idle.append(conn)
        return int(head[9:12])

    def close(self) -> None:
        for _, writer in self.idle:
            writer.close()


def _raw(method: str, path: str, headers: dict[str, str], body: bytes = b"") -> bytes:
    lines = [f"{method} {path} HTTP/1.1", "Host: bench", *(f"{k}: {v}" for k, v in headers.items())]
    if method == "POST":
        lines += ["Content-Type: application/json", f"Content-Length: {len(body)}"]
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body


async def _drive(port: int, customers: list[tuple[str, str]], garments: list[str], rate: float, seconds: float,
                 seed: int) -> list[tuple[str, float, float, int]]:
    """Send the schedule; (kind, scheduled offset s, latency s, status) per request. The
    requests are built before the clock starts."""
    rng = random.Random(seed)
    kinds, weights = zip(*MIX)
    n = int(rate * seconds)
    plan = []
    for i in range(n):
        kind = rng.choices(kinds, weights)[0]
        headers = {"X-Forwarded-For": f"10.{rng.randrange(4)}.{rng.randrange(256)}.{i % SHOPPERS}"}
        if kind == "tryon":
            cid, token = customers[rng.randrange(len(customers))]
            raw = _raw("GET", f"/v1/customers/{cid}/garments/{rng.choice(garments)}.glb",
                       {**headers, "Authorization": f"Bearer {token}"})
        elif kind == "avatar":
            raw = _raw("POST", "/v1/avatars", {**headers, "Accept": GLB}, json.dumps(_measurements(rng)).encode())
        else:
            raw = _raw("POST", "/v1/customers", headers, json.dumps(_measurements(rng)).encode())
        plan.append((kind, i / rate, raw))
    out: list[tuple[str, float, float, int]] = []
    pool = _Pool(port)
    t0 = time.perf_counter() + 0.2

    async def one(kind: str, at: float, raw: bytes) -> None:
        delay = t0 + at - time.perf_counter()
        if delay > 0:
            await asyncio.sleep(delay)
        status = await pool.request(raw)
        out.append((kind, at, time.perf_counter() - (t0 + at), status))

    await asyncio.gather(*(one(*p) for p in plan))
    pool.close()
    return out


def bench_load(rate: float = RATE, seconds: float = SECONDS, seed: int = 0) -> dict:
    with run_server(None, "embedded", workers=None, log_level="warning", check_log=False,
                    TRYON_TRUSTED_PROXIES="127.0.0.1") as server:
        client = server.client
        garments = [g["id"] for g in client.get("/v1/garments").json()]
        rng = random.Random(seed + 1)
        customers = []
        for i in range(CUSTOMERS):
            r = client.post("/v1/customers", json=_measurements(rng), headers={"X-Forwarded-For": f"10.9.0.{i}"})
            r.raise_for_status()
            customers.append((r.json()["id"], r.json()["token"]))
        for _ in range(4):  # warm: every server process has (very likely) seen every try-on
            for cid, token in customers:
                for g in garments:
                    client.get(f"/v1/customers/{cid}/garments/{g}.glb", headers={"Authorization": f"Bearer {token}"})
        pid = server.proc.pid
        memory: list[tuple[float, int]] = []
        stop = threading.Event()

        def sample() -> None:
            t0 = time.monotonic()
            while not stop.is_set():
                memory.append((time.monotonic() - t0, _rss(pid)))
                time.sleep(0.5)

        sampler = threading.Thread(target=sample)
        sampler.start()
        cpu0, me0, load0 = _cpu(pid), time.process_time(), psutil.getloadavg()[0]
        t = time.perf_counter()
        results = asyncio.run(_drive(server.port, customers, garments, rate, seconds, seed))
        wall = time.perf_counter() - t
        server_cpu, client_cpu, load1 = _cpu(pid) - cpu0, time.process_time() - me0, psutil.getloadavg()[0]
        stop.set()
        sampler.join()
        workers = len([p for p in psutil.Process(pid).children() if "spawn_main" in " ".join(p.cmdline())]) or 1
    lat = np.array([r[2] for r in results]) * 1000
    statuses = Counter(r[3] for r in results)
    by_kind = {}
    for kind, _ in MIX:
        k = np.array([r[2] for r in results if r[0] == kind]) * 1000
        by_kind[kind] = {"requests": len(k), "p50_ms": float(np.percentile(k, 50)), "p99_ms": float(np.percentile(k, 99)),
                         "errors": sum(1 for r in results if r[0] == kind and not 200 <= r[3] < 300)}
    start = memory[0][1]
    warm = next((m for s, m in memory if s >= WARMUP_S), memory[-1][1])
    end = memory[-1][1]
    return {
        "rate": rate, "seconds": seconds, "achieved_rps": len(results) / wall, "requests": len(results),
        "server_processes": workers, "cores": psutil.cpu_count(),
        "p50_ms": float(np.percentile(lat, 50)), "p99_ms": float(np.percentile(lat, 99)),
        "max_ms": float(lat.max()),
        "errors": sum(n for s, n in statuses.items() if not 200 <= s < 300),
        "statuses": {str(k): v for k, v in sorted(statuses.items())}, "by_kind": by_kind,
        "memory_mb": {"start": start / 1e6, "after_warmup": warm / 1e6, "end": end / 1e6, "peak": max(m for _, m in memory) / 1e6},
        "memory_growth_after_warmup": (end - warm) / warm, "memory_growth_from_start": (end - start) / start,
        "server_cpu_ms_per_request": 1000 * server_cpu / len(results),
        "client_cpu_ms_per_request": 1000 * client_cpu / len(results),
        "server_cores_used": server_cpu / wall, "machine_load_avg": [load0, load1],
        "goal": {"p99_ms": 100, "errors": 0, "memory_growth": 0.10},
    }


def run(limit: int = 0, repeats: int = 0) -> dict:
    """``limit``: seconds of load (default 40)."""
    return bench_load(seconds=float(limit or SECONDS))


def format_result(r: dict) -> str:
    m = r["memory_mb"]
    lines = [f"mixed load: {r['rate']:.0f} req/s for {r['seconds']:.0f} s (achieved {r['achieved_rps']:.1f}), "
             f"{r['requests']} requests, default `tryon serve` ({r['server_processes']} processes on "
             f"{r['cores']} cores), client on the same machine",
             f"  all        p50 {r['p50_ms']:7.1f} ms  p99 {r['p99_ms']:7.1f} ms  max {r['max_ms']:.0f} ms  "
             f"errors {r['errors']} {r['statuses']}"]
    for kind, k in r["by_kind"].items():
        lines.append(f"  {kind:<10} p50 {k['p50_ms']:7.1f} ms  p99 {k['p99_ms']:7.1f} ms  "
                     f"({k['requests']} requests, {k['errors']} errors)")
    lines.append(f"  server memory: start {m['start']:.0f} MB, after {WARMUP_S:.0f} s warm-up {m['after_warmup']:.0f} MB, "
                 f"end {m['end']:.0f} MB (peak {m['peak']:.0f}): growth {100 * r['memory_growth_after_warmup']:+.1f} % "
                 f"after warm-up, {100 * r['memory_growth_from_start']:+.1f} % from start")
    lines.append(f"  CPU: server {r['server_cpu_ms_per_request']:.1f} ms/request ({r['server_cores_used']:.2f} cores "
                 f"used), load generator {r['client_cpu_ms_per_request']:.1f} ms/request; machine load average "
                 f"{r['machine_load_avg'][0]:.1f} -> {r['machine_load_avg'][1]:.1f} (shared with other developers)")
    g = r["goal"]
    lines.append(f"  goals: p99 <= {g['p99_ms']} ms, {g['errors']} errors, memory growth <= {100 * g['memory_growth']:.0f} %")
    return "\n".join(lines)

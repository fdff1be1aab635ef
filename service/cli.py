"""The ``tryon`` command line: serve, worker, drape-demo, build-body-model, build-catalogue, bench, bench-report,
openapi."""
from __future__ import annotations

import argparse
import json
import logging
import os
import runpy
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from service.settings import SERVE_PID_ENV, get_settings
from service.storage.queue import (
    JOB_MONITORING_INTERVAL,
    MAINTENANCE_INTERVAL,
    WORKER_TTL,
)

# The body model and the maths (numpy, scipy, numba) are imported only by the commands that use
# them: `tryon serve`'s supervising process (the parent of the server processes) stays ~50 MB.

# Subcommands whose arguments are handed, untouched, to another module's main(argv).
REPO_ROOT = Path(__file__).resolve().parent.parent
PASS_THROUGH = {
    "build-body-model": "Compile the body model (needs the `build` extra: torch, anny).",
    "build-catalogue": "Compile the demo catalogue and avatar assets from ../shared/data (Pillow).",
    "bench": "Run a benchmark suite: tryon bench <suite> [--json] [--save] [...].",
    "drape-demo": "Drape the stored demo catalogue, then exit (what `tryon serve` runs in the background).",
    "bench-report": "Write docs/benchmarks.md from the results saved by `tryon bench <suite> --save`.",
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tryon", description="Online 3D clothes try-on service.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = sub.add_parser("serve", help="Run the HTTP service (loads the body model once).")
    serve.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    serve.add_argument("--log-level", default="info", help="uvicorn log level (default info)")
    serve.add_argument("--workers", type=int, default=None,
                       help=f"server processes (default: the machine's cores, here {default_workers()}); each "
                       "loads the model once")

    worker = sub.add_parser(
        "worker",
        help="Run an rq worker on the 'tryon' queue (REDIS_URL, else the embedded redis-server "
        "of TRYON_DATA_DIR).",
    )
    worker.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    worker.add_argument("--worker-ttl", type=int, default=WORKER_TTL,
                        help="seconds after its last heartbeat at which a worker, and the job it ran, "
                        f"count as dead (default {WORKER_TTL})")
    worker.add_argument("--job-monitoring-interval", type=int, default=JOB_MONITORING_INTERVAL,
                        help=f"seconds between heartbeats of a running job (default {JOB_MONITORING_INTERVAL})")
    worker.add_argument("--maintenance-interval", type=int, default=MAINTENANCE_INTERVAL,
                        help="seconds between registry clean-ups, which re-enqueue the jobs of dead "
                        f"workers (default {MAINTENANCE_INTERVAL})")
    worker.add_argument("--parent-pid", type=int, default=None,
                        help="stop (after the current job) when this process exits (tryon serve's "
                        "embedded worker)")

    openapi = sub.add_parser("openapi", help="Write the OpenAPI document.")
    openapi.add_argument(
        "--out", type=Path, default=Path("openapi/openapi.json"),
        help="output file (default openapi/openapi.json); '-' for stdout",
    )

    for name, text in PASS_THROUGH.items():
        p = sub.add_parser(name, help=text, add_help=False)
        p.add_argument("args", nargs=argparse.REMAINDER)
    return parser


def openapi_document() -> dict[str, Any]:
    """The app's OpenAPI document (no body model needed)."""
    from service.app import create_app  # the app, only for this command

    return create_app().openapi()


def openapi_text() -> str:
    """The OpenAPI document as committed: sorted keys, indent 2, trailing newline."""
    return json.dumps(openapi_document(), sort_keys=True, indent=2) + "\n"


# Set for `tryon serve`'s server processes (unless already set), not for its embedded worker
# (whose fits use BLAS threads): one BLAS thread per process, two malloc arenas (the thread
# pool's threads would each grow their own).
SERVER_ONLY_ENV = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
                   "MALLOC_ARENA_MAX": "2"}
SERVER_SET_ENV = "TRYON_SERVE_SET_ENV"


def default_workers() -> int:
    """Server processes by default: the cores this process may run on."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except AttributeError:  # pragma: no cover - not Linux
        return max(os.cpu_count() or 1, 1)


def _serve(host: str, port: int, log_level: str, workers: int | None = None) -> int:
    """uvicorn with ``workers`` processes. With the embedded default, this process starts the
    redis-server first and owns it (a child that dies with it; restarted if it dies), so the
    server processes, which die with this one too, and the embedded worker share it."""
    import uvicorn  # only to serve

    from service.storage.redis import EmbeddedServer

    settings = get_settings()
    embedded = None
    if settings.redis_url is None:
        embedded = EmbeddedServer.for_dir(settings.data_dir)
        embedded.acquire()
    os.environ[SERVE_PID_ENV] = str(os.getpid())
    n = workers or default_workers()
    if n > 1:  # one process per core: BLAS threads would only oversubscribe the cores
        for var in SERVER_ONLY_ENV:
            if var not in os.environ:
                os.environ[var] = SERVER_ONLY_ENV[var]
                os.environ[SERVER_SET_ENV] = ",".join(filter(None, [os.environ.get(SERVER_SET_ENV), var]))
    try:
        # forwarded headers are the app's to trust (TRYON_TRUSTED_PROXIES), never uvicorn's defaults
        uvicorn.run("service.app:create_app", factory=True, host=host, port=port, log_level=log_level, workers=n,
                    proxy_headers=False)
    finally:
        if embedded is not None:
            embedded.release()
    return 0


def _run_module(module: str, prog: str, argv: list[str]) -> int:
    """Run an offline command's module as ``python -m module argv`` in this process. The service
    package never imports offline work (the body-model build under ``worker/build``, the
    benchmarks under ``tests/bench``): they are run by name."""
    sys.argv = [prog, *argv]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
    return 0


def _bench(argv: list[str], module: str = "tests.bench", prog: str = "tryon bench") -> int:
    """``tryon bench``: the benchmarks live beside the tests (``tests/bench``), not in the service
    package or its image; run them from a checkout."""
    if not (REPO_ROOT / "tests" / "bench" / "__main__.py").is_file():
        print("tryon bench: the benchmarks are in the repository's tests/bench (run from a checkout)",
              file=sys.stderr)
        return 2
    if str(REPO_ROOT) not in sys.path:
        sys.path.insert(0, str(REPO_ROOT))
    return _run_module(module, prog, argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``tryon`` console script; returns the exit status."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    if args_list and args_list[0] in PASS_THROUGH:
        command, rest = args_list[0], args_list[1:]
        if command == "build-body-model":
            return _run_module("worker.build.body_model", "tryon build-body-model", rest)
        if command == "drape-demo":
            return _run_module("worker.demo_drape", "tryon drape-demo", rest)
        if command == "build-catalogue":
            return _run_module("worker.build.catalogue", "tryon build-catalogue", rest)
        if command == "bench-report":
            return _bench(rest, "tests.bench.report", "tryon bench-report")
        if not rest or (rest[0].startswith("-") and rest[0] not in ("-h", "--help")):
            print("usage: tryon bench <suite> [--json] [...]", file=sys.stderr)
            return 2
        return _bench(rest)

    args = _parser().parse_args(args_list)
    if args.command == "serve":
        return _serve(args.host, args.port, args.log_level, args.workers)
    if args.command == "worker":
        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s", "%H:%M:%S"))
        logging.getLogger("tryon").addHandler(handler)  # rq configures its own loggers
        logging.getLogger("tryon").setLevel(logging.INFO)
        from service.model.body import shape
        from service.model.body.model import load_body_model
        from service.storage.supervise import run_worker

        settings = get_settings()
        shape.precompute(load_body_model(settings.body_model_path))  # once: every work-horse is a fork of this process
        return run_worker(settings, burst=args.burst, worker_ttl=args.worker_ttl,
                          job_monitoring_interval=args.job_monitoring_interval,
                          maintenance_interval=args.maintenance_interval, parent_pid=args.parent_pid)
    if args.command == "openapi":
        write_output(openapi_text(), args.out)
        return 0
    raise AssertionError(f"unhandled command {args.command}")  # pragma: no cover



def write_output(text: str, out: Path) -> None:
    """Write a generated document to ``out`` (``-``: standard output), saying where."""
    if str(out) == "-":
        sys.stdout.write(text)
    else:
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(text, encoding="utf-8")
        print(f"wrote {out}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())

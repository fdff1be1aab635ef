"""The ``tryon`` command line: serve, worker, build-body-model, bench, openapi."""
from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

# Subcommands whose arguments are handed, untouched, to another module's main(argv).
PASS_THROUGH = {
    "build-body-model": "Compile the body model (needs the `build` extra: torch, anny).",
    "bench": "Run a benchmark suite: tryon bench <suite> [--json] [...].",
}


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tryon", description="Online 3D clothes try-on service.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    serve = sub.add_parser("serve", help="Run the HTTP service (loads the body model once).")
    serve.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    serve.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    serve.add_argument("--log-level", default="info", help="uvicorn log level (default info)")
    serve.add_argument("--workers", type=int, default=1,
                       help="server processes (default 1); each loads the model once")

    worker = sub.add_parser(
        "worker",
        help="Run an rq worker on the 'tryon' queue (REDIS_URL, else the embedded redis-server "
        "of TRYON_DATA_DIR).",
    )
    worker.add_argument("--burst", action="store_true", help="exit when the queue is empty")
    worker.add_argument("--worker-ttl", type=int, default=30,
                        help="seconds after its last heartbeat at which a worker, and the job it ran, "
                        "count as dead (default 30)")
    worker.add_argument("--job-monitoring-interval", type=int, default=5,
                        help="seconds between heartbeats of a running job (default 5)")
    worker.add_argument("--maintenance-interval", type=int, default=15,
                        help="seconds between registry clean-ups, which re-enqueue the jobs of dead "
                        "workers (default 15)")
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
    from service.app import create_app

    return create_app().openapi()


def openapi_text() -> str:
    """The OpenAPI document as committed: sorted keys, indent 2, trailing newline."""
    return json.dumps(openapi_document(), sort_keys=True, indent=2) + "\n"


def _serve(host: str, port: int, log_level: str, workers: int = 1) -> int:
    import uvicorn

    uvicorn.run("service.app:create_app", factory=True, host=host, port=port, log_level=log_level,
                workers=workers)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``tryon`` console script; returns the exit status."""
    args_list = list(sys.argv[1:] if argv is None else argv)
    if args_list and args_list[0] in PASS_THROUGH:
        command, rest = args_list[0], args_list[1:]
        if command == "build-body-model":
            from worker.build.body_model import main as build_main

            return int(build_main(rest) or 0)
        if not rest or (rest[0].startswith("-") and rest[0] not in ("-h", "--help")):
            print("usage: tryon bench <suite> [--json] [...]", file=sys.stderr)
            return 2
        from service.bench import main as bench_main

        return int(bench_main(rest) or 0)

    args = _parser().parse_args(args_list)
    if args.command == "serve":
        return _serve(args.host, args.port, args.log_level, args.workers)
    if args.command == "worker":
        import logging

        from service.settings import get_settings
        from service.storage import run_worker
        from worker.fitting import body_model

        handler = logging.StreamHandler()
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s", "%H:%M:%S"))
        logging.getLogger("tryon").addHandler(handler)  # rq configures its own loggers
        logging.getLogger("tryon").setLevel(logging.INFO)
        body_model()  # loaded once: every work-horse is a fork of this process
        return run_worker(get_settings(), burst=args.burst, worker_ttl=args.worker_ttl,
                          job_monitoring_interval=args.job_monitoring_interval,
                          maintenance_interval=args.maintenance_interval, parent_pid=args.parent_pid)
    if args.command == "openapi":
        text = openapi_text()
        if str(args.out) == "-":
            sys.stdout.write(text)
        else:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text, encoding="utf-8")
            print(f"wrote {args.out}", file=sys.stderr)
        return 0
    raise AssertionError(f"unhandled command {args.command}")  # pragma: no cover


if __name__ == "__main__":
    sys.exit(main())

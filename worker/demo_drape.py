"""``tryon drape-demo``: the background process that ``tryon serve`` starts with the drape on
(``service.storage.supervise.DemoDrape``): the demo garments built through their binding at the
first start, draped one by one (``GarmentService.drape_demo``), then exit. Not a queued job: it
runs at the lowest CPU priority beside the worker, whose jobs (a customer's fit or drape) must
not wait hours behind it."""
from __future__ import annotations

import argparse
import logging
import sys

from service.application.context import worker_context
from service.storage.redis import die_with_parent


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tryon drape-demo", description=__doc__.split("\n\n")[0])
    parser.add_argument("--parent-pid", type=int, default=None,
                        help="stop when this process exits (tryon serve's background drape)")
    args = parser.parse_args(argv)
    if args.parent_pid is not None:
        die_with_parent(args.parent_pid)
    handler = logging.StreamHandler()
    handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s: %(message)s", "%H:%M:%S"))
    log = logging.getLogger("tryon")
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    done = worker_context().garments.drape_demo()
    log.info("demo catalogue: %d garments draped", len(done))
    return 0


if __name__ == "__main__":
    sys.exit(main())

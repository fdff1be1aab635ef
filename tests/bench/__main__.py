"""``tryon bench <suite> [--json] [options]`` (also ``python -m tests.bench``).

Each suite is a module of this package with ``run(limit, repeats, **options) -> dict`` (the
``--json`` output) and ``format_result(result) -> str`` (a table for people). Timings are medians
beside a baseline measured in the same run; these machines are noisy.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import time
from pathlib import Path

from tests.bench.report import SAVE_DIR, save_result

# suite -> (module, run function, format function, description)
SUITES: dict[str, tuple[str, str, str, str]] = {
    "body": ("tests.bench.body", "run", "format_result",
             "body model: PCA, ISO accuracy of measurements -> avatar, estimation, timings"),
    "avatar": ("tests.bench.avatar_speed", "run", "format_result",
               "measurements -> avatar: the fast path beside the reference algorithm, same run"),
    "look": ("tests.bench.look", "run", "format_result",
             "avatar.glb: the added latency of the avatar's look (eyes, eyebrows, hair, underwear)"),
    "tryon": ("tests.bench.tryon", "bench_tryon", "format_tryon",
              "try-on: garment accuracy, penetration, latency, GLB bytes, HTTP"),
    "examples": ("tests.bench.tryon", "bench_examples", "format_examples",
                 "garment accuracy for a grid of example sets (chooses N and c)"),
    "fitting": ("tests.bench.fitting", "run", "format_result",
                "body fitting of synthetic scans, then jobs under worker kills"),
    "autofit": ("tests.bench.autofit", "run", "format",
                "garments from one draped mesh: auto-fit to the examples vs .mhclo references"),
    "editing": ("tests.bench.editing", "run", "format",
                "clothed-avatar editing: forward error, update time, elbow-twist volume"),
    "page": ("tests.bench.page", "run", "format_result",
             "the page's first dressed view of new customers over HTTP (outfit with pose correctives, /poses)"),
    "kernels": ("tests.bench.kernels", "run", "format_result",
                "the compiled geometry kernels vs the numpy paths, same run: closest points, poses, outfits"),
    "sizes": ("tests.bench.sizes", "run", "format_result",
              "sizes and fit: chart round trip, ANSUR II held-out recommendation, monotonicity, timings"),
    "drape": ("tests.bench.drape", "run", "format_result",
              "cloth drape engine: analytic tubes, pinned square vs a dense solve and Newton VBD, two bodies, 10k timing"),
    "dense": ("tests.bench.dense", "run", "format_result",
              "dense garments (11k, 44k vertices) through their simulation mesh vs the direct drape; the 44k build"),
    "hostile": ("tests.bench.hostile", "run", "format_result",
                "a default tryon serve tried as an attacker would: size bombs, slow bodies, spoofing, floods, logs"),
    "load": ("tests.bench.load", "run", "format_result",
             "mixed traffic at 80 req/s against a default tryon serve: p50/p99, errors, memory (--limit: seconds)"),
}


def _without_save(argv: list[str], saved_to: str) -> list[str]:
    """The command's arguments less ``--save [DIR]`` (the command as the report shows it)."""
    out, i = [], 0
    while i < len(argv):
        if argv[i] == "--save":
            i += 2 if i + 1 < len(argv) and argv[i + 1] == saved_to else 1
            continue
        if not argv[i].startswith("--save="):
            out.append(argv[i])
        i += 1
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tryon bench", description=__doc__,
                                 epilog="suites:\n" + "\n".join(f"  {k:<10}{v[3]}" for k, v in SUITES.items()),
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("suite", choices=sorted(SUITES))
    ap.add_argument("--json", action="store_true", help="print JSON for machines")
    ap.add_argument("--save", nargs="?", const=str(SAVE_DIR), default=None, metavar="DIR",
                    help="also write the result with its date, machine and command to DIR/<suite>.json "
                         "(default DIR: docs/bench; `tryon bench-report` makes docs/benchmarks.md from them)")
    ap.add_argument("--limit", type=int, default=0, help="held-out subjects/avatars to use (0 = the suite's default)")
    ap.add_argument("--repeats", type=int, default=50, help="repetitions per timing")
    ap.add_argument("--no-kill", action="store_true", help="fitting: skip the jobs-under-worker-kills part")
    ap.add_argument("--max-pose-deg", type=float, default=45.0,
                    help="fitting: largest random rotation per bone of the synthetic scans (default 45)")
    ap.add_argument("--only", choices=["latency"], default=None,
                    help="tryon: only the in-process try-on latency rows (template fast path vs reference)")
    ap.add_argument("--poses", choices=("anatomical", "free"), default="anatomical",
                    help="fitting: the synthetic scans' poses within the joint limits (default) or any axis per bone")
    ap.add_argument("--no-build", action="store_true", help="dense: skip the whole build of the 44k garment")
    ap.add_argument("--no-newton", action="store_true", help="drape: skip the Newton VBD reference row")
    ap.add_argument("--newton-full-contact", type=int, default=0, metavar="N",
                    help="drape: also settle the T-shirt on the N of its 5 reference people with the largest chests, "
                         "and the compared bottoms on the N of theirs with the largest hips, with Newton's "
                         "self-contact and the body's faces in its contact (3-7 minutes a person on CPU)")
    ap.add_argument("--no-person-check", action="store_true", help="fitting: skip the person-check part (1b)")
    from tests.bench.fitting import before_kinds

    ap.add_argument("--before", choices=(*before_kinds(), "none"), default=None,
                    help="fitting: what every condition's 'before' refit leaves out (default: per condition)")
    ap.add_argument("--fit-params", default=None,
                    help="fitting: FitParams fields overridden in every fit (experiments), e.g. "
                         "'cloth_offset_mean=None,loose_region_depth=0.02'")
    ap.add_argument("--known", default=None,
                    help="fitting: the truth's measurements given to every fit, as a customer gives them with a "
                         "scan, e.g. 'height_cm,weight_kg' (with --before known: the same fits without them)")
    ap.add_argument("--conditions", default=None,
                    help="fitting: comma-separated scan conditions to run (default all; see tests/bench/fitting.py)")
    ap.add_argument("--via-file", default=None, choices=("ply", "obj", "glb", "stl", "xyz"),
                    help="fitting: fit each scan as the service reads it back from an upload in this format "
                         "(uploads.read_body_upload, then the queue's storage), not from the generated arrays")
    args = ap.parse_args(argv)
    module, run_name, fmt_name, _ = SUITES[args.suite]
    mod = importlib.import_module(module)
    extra = {"kill": not args.no_kill, "max_pose_deg": args.max_pose_deg,
             "conditions": args.conditions, "person_check": not args.no_person_check,
             "before": args.before, "poses": args.poses, "fit_params": args.fit_params, "known": args.known,
             "via_file": args.via_file} if args.suite == "fitting" else {}
    if args.suite == "drape":
        extra = {"newton": not args.no_newton, "newton_full": args.newton_full_contact}
    if args.suite == "dense":
        extra = {"build": not args.no_build}
    if args.only is not None:
        if args.suite != "tryon":
            ap.error("--only is a tryon option")
        extra = {"only": args.only}
    started = time.time()
    load_before = os.getloadavg()
    res = getattr(mod, run_name)(args.limit, args.repeats, **extra)
    if args.save is not None:
        path = save_result(Path(args.save), args.suite, res, "tryon bench " + " ".join(_without_save(
            list(sys.argv[1:] if argv is None else argv), args.save)), started, load_before)
        print(f"saved {path}", file=sys.stderr)
    print(json.dumps(res, indent=2) if args.json else getattr(mod, fmt_name)(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())

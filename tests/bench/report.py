"""``tryon bench-report``: docs/benchmarks.md from the saved results of ``tryon bench <suite> --save``.

A saved result (``docs/bench/<suite>.json``) is the suite's ``--json`` output with the date, the
machine and the command that made it. The report gives one section per suite: the goals of
``tests.bench.goals`` beside the measured figures (and whether each is met), then every number
of the result; suites with no saved result are listed as not measured yet. Nothing in it is
typed by hand: rerun a suite with ``--save``, then ``tryon bench-report``.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

from service.cli import write_output

from tests.bench.goals import GOALS

REPO = Path(__file__).resolve().parents[2]
SAVE_DIR = REPO / "docs" / "bench"
REPORT = REPO / "docs" / "benchmarks.md"
MAX_LIST = 12  # lists of numbers up to this long are shown inline; longer ones are left out


def machine() -> dict[str, Any]:
    """The machine a result was measured on: CPU model, cores this process may use, memory."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cores = os.cpu_count() or 1
    mem_gb = None
    try:
        mem_gb = round(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30, 1)
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        pass
    return {"cpu": cpu, "cores": cores, "memory_gb": mem_gb, "python": platform.python_version(),
            "system": f"{platform.system()} {platform.release()}"}


def save_result(directory: Path, suite: str, result: dict, command: str, started: float,
                load_before: tuple[float, float, float]) -> Path:
    """Write ``directory/<suite>.json``: the suite's result with date (UTC), machine, command,
    seconds taken and load averages."""
    doc = {"suite": suite,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime(started)),
           "machine": machine(),
           "load_average": {"before": round(load_before[0], 2), "after": round(os.getloadavg()[0], 2)},
           "seconds": round(time.time() - started, 1),
           "command": command,
           "result": result}
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / f"{suite}.json"
    path.write_text(json.dumps(doc, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    return path


def lookup(result: dict, path: str) -> Any:
    """The value at ``a/b/c`` in a result; KeyError naming the path when it is absent."""
    node: Any = result
    for key in path.split("/"):
        if not isinstance(node, dict) or key not in node:
            raise KeyError(f"{path!r}: no {key!r}")
        node = node[key]
    return node


def figures(node: Any, prefix: str = "") -> list[tuple[str, str]]:
    """Every number (and short list of numbers, and string) of a result as (path, text), in order."""
    out: list[tuple[str, str]] = []
    if isinstance(node, dict):
        for k, v in node.items():
            out += figures(v, f"{prefix}/{k}" if prefix else str(k))
    elif isinstance(node, bool) or node is None:
        out.append((prefix, str(node).lower()))
    elif isinstance(node, (int, float)):
        out.append((prefix, fmt(node)))
    elif isinstance(node, str):
        out.append((prefix, node.replace("|", "\\|")))
    elif isinstance(node, list) and len(node) <= MAX_LIST and all(
            isinstance(x, (int, float)) and not isinstance(x, bool) for x in node):
        out.append((prefix, "[" + ", ".join(fmt(x) for x in node) + "]"))
    return out


def fmt(x: float) -> str:
    if isinstance(x, int):
        return f"{x:,}"
    if x != x or x in (float("inf"), float("-inf")):
        return str(x)
    if x == 0:
        return "0"
    if abs(x) >= 1000:
        return f"{x:,.0f}"
    return f"{x:.4g}"


def goal_rows(suite: str, result: dict) -> tuple[list[str], list[str]]:
    """The goal table's rows and the lines of what falls short, for one suite."""
    rows, short = [], []
    for g in GOALS.get(suite, ()):
        try:
            value = lookup(result, g.path)
        except KeyError:
            rows.append(f"| {g.figure} | not in this result | {g.op} {fmt(g.target)} {g.unit} | - |")
            continue
        v = float(value) * g.scale
        ok = g.met(float(value))
        rows.append(f"| {g.figure} | {fmt(v)} {g.unit} | {g.op} {fmt(g.target)} {g.unit} | {'yes' if ok else '**no**'} |")
        if not ok:
            short.append(f"- `{suite}`: {g.figure}: {fmt(v)} {g.unit} (goal {g.op} {fmt(g.target)} {g.unit})")
    return rows, short


def render(saved: dict[str, dict], suites: dict[str, str]) -> str:
    """The whole of docs/benchmarks.md from the saved results (suite -> saved document) and the
    suites' descriptions (suite -> text)."""
    head = ["# Benchmarks", "",
            "<!-- Generated by `tryon bench-report` from docs/bench/*.json; do not edit by hand. -->", "",
            "The current figures of each `tryon bench` suite, with the goals (`tests/bench/goals.py`) beside",
            "them. To refresh a suite: `tryon bench <suite> --save [options]` (writes `docs/bench/<suite>.json`),",
            "then `tryon bench-report` (writes this file). Timings are medians on the machine named; the",
            "development machines are shared, so compare timings only within one run (each suite times a",
            "baseline in the same run). The suites live in `tests/bench/`; a suite that needs a server starts",
            "its own with its own embedded Redis. Held-out subjects (ANSUR II rows whose index is a multiple",
            "of 5) never enter a build step; the benches read ANSUR II and the MakeHuman garments from",
            "`../shared/data` (or `TRYON_SHARED_DATA`). Options: `tryon bench <suite> --help`.", ""]
    body, short_all = [], []
    for suite, desc in suites.items():
        body += [f"## {suite}", "", desc[:1].upper() + desc[1:] + ".", ""]
        doc = saved.get(suite)
        if doc is None:
            body += ["Not measured yet.", ""]
            if GOALS.get(suite):
                body += ["| figure | goal |", "| --- | --- |"]
                body += [f"| {g.figure} | {g.op} {fmt(g.target)} {g.unit} |" for g in GOALS[suite]]
                body.append("")
            continue
        m = doc.get("machine", {})
        la = doc.get("load_average", {})
        body += [f"- date: {doc.get('date', '?')}",
                 f"- machine: {m.get('cpu', '?')}, {m.get('cores', '?')} cores, {m.get('memory_gb', '?')} GB, "
                 f"Python {m.get('python', '?')}; load average {la.get('before', '?')} -> {la.get('after', '?')}",
                 f"- command: `{doc.get('command', '?')}` ({doc.get('seconds', '?')} s)", ""]
        rows, short = goal_rows(suite, doc["result"])
        if short and la.get("before") is not None:  # timings on a busy machine read long
            short = [f"{line}; measured at load average {la['before']} on {m.get('cores', '?')} cores"
                     for line in short]
        short_all += short
        if rows:
            body += ["| figure | measured | goal | met |", "| --- | --- | --- | --- |", *rows, ""]
        body += ["<details><summary>every figure of the result</summary>", "",
                 "| figure | value |", "| --- | --- |"]
        body += [f"| `{p}` | {v} |" for p, v in figures(doc["result"])]
        body += ["", "</details>", ""]
    measured = [s for s in suites if s in saved]
    summary = ["## What falls short", ""]
    summary += short_all or [f"Every goal of the measured suites ({', '.join(measured) or 'none'}) is met."]
    missing = [s for s in suites if s not in saved]
    if missing:
        summary += ["", "Not measured yet: " + ", ".join(f"`{s}`" for s in missing) + "."]
    return "\n".join(head + summary + [""] + body).rstrip() + "\n"


def load_saved(directory: Path) -> dict[str, dict]:
    out = {}
    for p in sorted(directory.glob("*.json")):
        doc = json.loads(p.read_text(encoding="utf-8"))
        out[doc.get("suite", p.stem)] = doc
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tryon bench-report", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", type=Path, default=SAVE_DIR, help="saved results (default docs/bench)")
    ap.add_argument("--out", type=Path, default=REPORT, help="report to write (default docs/benchmarks.md); '-': stdout")
    ap.add_argument("--check", action="store_true", help="write nothing; exit 1 if the report is not current")
    args = ap.parse_args(argv)
    from tests.bench.__main__ import SUITES

    saved = load_saved(args.dir)
    unknown = sorted(set(saved) - set(SUITES))
    if unknown:
        print(f"tryon bench-report: results of unknown suites: {', '.join(unknown)}", file=sys.stderr)
        return 2
    text = render(saved, {k: v[3] for k, v in SUITES.items()})
    if args.check:
        current = args.out.read_text(encoding="utf-8") if args.out.is_file() else ""
        if current != text:
            print(f"{args.out} is not current: run `tryon bench-report`", file=sys.stderr)
            return 1
        return 0
    write_output(text, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

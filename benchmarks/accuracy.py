"""Accuracy benchmark: every method on every condition, seeds 0-9, with the protocol written out.

Usage::

    python benchmarks/accuracy.py [--data ../shared/data] [--seeds 0 1 ... 9] [--jobs N]
                                  [--json FILE] [--markdown FILE] [--quick]
                                  [--views KEY ...] [--methods LABEL ...] [--list]
                                  [--merge EARLIER.json]

What it measures (the tables live in ``benchmarks/accuracy_setup.py``; adding a method is one
line in ``METHODS`` there):

* conditions: Nordland 64x32 summer -> winter windows 0-999, 1000-1999 and 1400-2399 at
  tolerance 20 (and 10 and 2 on the same runs), a held-out window 2000-2399 that tuned nothing,
  winter -> summer 0-999, FlyNet's 100-place subset summer -> fall and summer -> winter
  (tolerance 2), the windows at 1.5x, 2x and a random 1-1.5x speed, the built-in synthetic
  route's hardest conditions (night; viewpoint jitter 3), the drifting-viewpoint Nordland set
  0-999 and 1000-1999, FlyNet's subset through a fisheye disc, control rows (blank frames,
  shuffled queries, a query that starts part-way along the reference: winter 300-999 against
  summer 0-999, and a short 300-frame window); and the robot group (``r-...``, at tolerance 2
  and 20): 0.6x to 3.25x, a random 0.4-1.6x walk, stop-and-go, a 100-frame stop, uneven and
  dropped frames, camera noise, a detour off the map (its map's places keep their frame
  numbers: the CANN is given the break they show), a fisheye disc, shuffled and reversed,
  with and without odometry, on the dev window and on the held-out one (``--list`` shows all);
* methods: single frames (pixels, flyhash, flynet, kenyon), SeqSLAM at lengths 20/40/60 with
  OpenSeqSLAM's velocity grid (0.8-1.2) and, on the 1x windows and the speed rows, with the
  paper CANN's speed range (0.75-2), SeqSLAM-60 with the robot speeds (0.25-3 and 0.25-3.5),
  FlyNet + SeqSLAM / RNN (the route prior, and trained from scratch) / CANN / the paper's
  attractor CANN, kenyon+cann (the default), pixels+cann, flyhash+cann and netvlad+cann
  (first seed only: slow; skipped when its extra is not installed);
* per condition and method: AUC mean, worst seed and spread (max - min), R@1, R@100%P and
  VPR-Bench's extended precision (means), the largest share of frames on one place, and the
  bytes per reference place each method stores for matching;
* the kidnap test: on windows 0-999 and 1000-1999 the query stream jumps 200 places ahead at
  stream frames 100, 200, ..., 700; frames until every ``+cann`` method is back within
  tolerance, next to the front end's own evidence for the true place after each landing.

Deterministic methods run once (first seed).  Output: a terminal table, ``--json`` (machine,
versions, protocol per condition, every per-seed value) and ``--markdown``
(:func:`benchmarks.accuracy_report.render_markdown` of the same JSON).
"""

from __future__ import annotations

import argparse
import importlib.util
import platform
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import DEFAULT_DATA, machine  # noqa: E402
from benchmarks.accuracy_merge import load_previous, merge_runs  # noqa: E402
from benchmarks.accuracy_report import render_markdown, render_text, summarise  # noqa: E402
from benchmarks.accuracy_run import (  # noqa: E402
    EVIDENCE_FRAMES,
    KIDNAP_AT,
    KIDNAP_JUMP,
    Task,
    run_task,
)
from benchmarks.accuracy_setup import (  # noqa: E402
    DATASETS,
    METHODS,
    QUICK_METHODS,
    QUICK_VIEWS,
    VIEWS,
    check_tables,
)

__all__ = ["main", "render_markdown", "build_tasks"]

HERE = Path(__file__).resolve().parent

#: what each front end stores per place (see Encoder.bytes_per_place)
BYTES_NOTE = {
    "pixels": "patch-normalised image, 2048 float32",
    "flyhash": "64-bit code, bit-packed",
    "flynet": "one classifier column, 64 float32",
    "kenyon": "4096-bit Kenyon-cell code, bit-packed",
    "netvlad": "one classifier column, 64 float32",
}


def build_tasks(args, views, entries) -> list[Task]:
    """One task per (data set, seed) that some selected view needs."""
    seeds = list(args.seeds)
    tasks = []
    for dataset in DATASETS:
        dviews = tuple(v for v in views if v.dataset == dataset.key)
        if not dviews:
            continue
        for seed in seeds:
            wanted = tuple(
                e for e in entries if e.runs_with(seed, seeds[0]) and any(map(e.runs_on, dviews))
            )
            if wanted:
                tasks.append(
                    Task(dataset, seed, seeds[0], dviews, wanted, args.data, not args.no_kidnap)
                )
    return tasks


def _available(entries):
    ok, skipped = [], []
    for e in entries:
        missing = [m for m in e.requires() if importlib.util.find_spec(m) is None]
        if missing:
            extras = ", ".join(e.spec.extras)
            skipped.append({"method": e.label, "reason": f"needs {', '.join(missing)} ({extras})"})
        else:
            ok.append(e)
    return ok, skipped


def _versions() -> dict:
    out = {"python": platform.python_version()}
    for name in ("flyvpr", "numpy", "scipy", "numba", "torch", "joblib"):
        try:
            module = __import__(name)
        except ImportError:
            continue
        out[name] = getattr(module, "__version__", "?")
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            cwd=HERE,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=HERE,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
        if commit:
            out["git"] = commit + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def _conditions(views, protocols) -> list[dict]:
    datasets = {d.key: d for d in DATASETS}
    out = []
    for v in views:
        for tol in v.tolerances:
            out.append(
                {
                    "key": f"{v.key}@{tol}",
                    "view_key": v.key,
                    "label": f"{v.label} (±{tol})",
                    "group": v.group
                    if tol == v.tolerances[0] or v.group == "robot"
                    else "tolerance",
                    "tolerance": tol,
                    "tolerances": list(v.tolerances),
                    "dataset": v.dataset,
                    "tuning": datasets[v.dataset].tuning,
                    "view": v.protocol(),
                    "protocol": protocols.get(v.dataset, {}),
                }
            )
    return out


def _bytes_per_place(results) -> dict:
    values: dict[str, set] = {}
    for res in results:
        for f in res["fitted"]:
            if res["dataset"].startswith("n64"):  # the 64x32 Nordland images
                values.setdefault(f["method"], set()).add(f["bytes_per_place"])
    return {label: max(v) for label, v in values.items()}


def _parse(argv):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(10)))
    p.add_argument("--views", nargs="+", help="view keys to run (default: all; see --list)")
    p.add_argument("--methods", nargs="+", help="method labels to run (default: all)")
    p.add_argument("--quick", action="store_true", help="smoke run: seeds 0-1, few views")
    p.add_argument("--jobs", type=int, default=1, help="parallel tasks (joblib processes)")
    p.add_argument("--no-kidnap", action="store_true", help="skip the kidnap test")
    p.add_argument("--json", type=Path, help="write everything as JSON")
    p.add_argument("--markdown", type=Path, help="write the Markdown tables")
    p.add_argument(
        "--merge",
        type=Path,
        metavar="FILE",
        help="keep the methods this run does not run from an earlier JSON (same seeds)",
    )
    p.add_argument("--list", action="store_true", help="list the views and methods, then exit")
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    args = p.parse_args(argv)
    if args.jobs < 1:
        p.error(f"--jobs must be >= 1; got {args.jobs}")
    if any(s < 0 for s in args.seeds):
        p.error(f"--seeds must be >= 0; got {args.seeds}")
    if args.quick:
        args.seeds = args.seeds if "--seeds" in (argv or sys.argv) else [0, 1]
        args.views = args.views or list(QUICK_VIEWS)
        args.methods = args.methods or list(QUICK_METHODS)
    views = {v.key: v for v in VIEWS}
    methods = {m.label: m for m in METHODS}
    for name, chosen, known in (
        ("--views", args.views, views),
        ("--methods", args.methods, methods),
    ):
        unknown = [x for x in chosen or () if x not in known]
        if unknown:
            p.error(f"{name}: unknown {unknown}; known: {', '.join(known)}")
    return args, views, methods


def main(argv=None) -> int:
    args, views_by_key, methods_by_label = _parse(argv)
    check_tables()
    if args.list:
        for v in VIEWS:
            print(f"view   {v.key:22s} {v.group:10s} {v.label} tolerances {list(v.tolerances)}")
        for m in METHODS:
            print(f"method {m.label:22s} {m.describe()}")
        return 0
    if not args.data.is_dir():
        print(f"data folder not found: {args.data} (give --data)", file=sys.stderr)
        return 1
    views = [views_by_key[k] for k in (args.views or views_by_key)]
    entries, skipped = _available([methods_by_label[k] for k in (args.methods or methods_by_label)])
    previous = None
    if args.merge is not None:
        try:
            previous = load_previous(args.merge, list(args.seeds))
        except ValueError as exc:
            print(exc, file=sys.stderr)
            return 1
    tasks = build_tasks(args, views, entries)
    log = (lambda *_: None) if args.quiet else (lambda s: print(s, flush=True))
    log(f"{len(tasks)} tasks (data set x seed), {len(entries)} methods, {len(views)} views")
    t_start = time.perf_counter()
    results = []
    if args.jobs == 1:
        stream = map(run_task, tasks)
    else:
        from joblib import Parallel, delayed

        stream = Parallel(n_jobs=args.jobs, return_as="generator_unordered")(
            delayed(run_task)(t) for t in tasks
        )
    for i, res in enumerate(stream, 1):
        results.append(res)
        done = time.perf_counter() - t_start
        log(
            f"[{i}/{len(tasks)}] {res['dataset']} seed {res['seed']}: {len(res['rows'])} rows, "
            f"{res['seconds']:.1f} s, {res['cpu_seconds']:.1f} CPU s (elapsed {done:.0f} s, about "
            f"{done / i * (len(tasks) - i):.0f} s left)"
            + "".join(f"\n    ERROR {e['method']}: {e['error']}" for e in res["errors"])
        )
    results.sort(key=lambda r: ([d.key for d in DATASETS].index(r["dataset"]), r["seed"]))
    rows = [row for r in results for row in r["rows"]]
    protocols = {r["dataset"]: r["protocol"] for r in results}
    data = {
        "benchmark": "flyvpr accuracy",
        "command": [Path(sys.argv[0]).name, *(sys.argv[1:] if argv is None else argv)],
        "quick": bool(args.quick),
        "machine": machine(),
        "versions": _versions(),
        "seeds": list(args.seeds),
        "methods": [m.describe() for m in entries],
        "skipped": skipped,
        "conditions": _conditions(views, protocols),
        "rows": rows,
        "summary": summarise(rows),
        "bytes_per_place": _bytes_per_place(results),
        "bytes_note": {
            m.label: BYTES_NOTE.get(m.spec.frontend, "")
            + (" + the RNN's input and readout weights, float32" if m.spec.filter == "rnn" else "")
            for m in entries
        },
        "kidnap": [k for r in results for k in r["kidnap"]],
        "reliability": [x for r in results for x in r.get("reliability", [])],
        "evidence": [e for r in results for e in r["evidence"]],
        "kidnap_protocol": {
            "jump": KIDNAP_JUMP,
            "at": list(KIDNAP_AT),
            "evidence_frames": EVIDENCE_FRAMES,
        },
        "errors": [{**e, "dataset": r["dataset"]} for r in results for e in r["errors"]],
        "task_seconds": {f"{r['dataset']}/{r['seed']}": r["seconds"] for r in results},
        "task_cpu_seconds": {f"{r['dataset']}/{r['seed']}": r["cpu_seconds"] for r in results},
        "elapsed_s": time.perf_counter() - t_start,
    }
    if previous is not None:
        conditions = [c["key"] for c in _conditions(VIEWS, {})]
        data = merge_runs(previous, data, [m.label for m in METHODS], conditions)
        data["summary"] = summarise(data["rows"])
    print()
    print(render_text(data))
    if args.json:
        from flyvpr._io import write_json_atomic

        write_json_atomic(args.json, data)
    if args.markdown:
        from flyvpr._io import write_text_atomic

        write_text_atomic(args.markdown, render_markdown(data))
    return 1 if data["errors"] else 0


if __name__ == "__main__":
    sys.exit(main())

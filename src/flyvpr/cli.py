"""Command-line interface: ``flyvpr <command> ...``.

``main(argv) -> int`` returns 0 on success, 1 after a runtime error (one line on
stderr) and 2 for a usage error.  Nothing else in the package imports this
module.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import textwrap
import time
from pathlib import Path

import numpy as np

from . import __version__
from ._io import write_json_atomic, write_text_atomic
from .datasets import DATASETS, load_benchmark
from .evaluation import evaluate_method
from .images import DEFAULT_SIZE
from .methods import METHODS, method_names

__all__ = ["main"]

logger = logging.getLogger("flyvpr")


class UsageError(Exception):
    """Bad command-line usage detected after parsing (exit code 2)."""


# ---------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------
def format_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """Align ``rows`` under ``columns`` given as (key, header, format)."""
    cells = [[header for _, header, _ in columns]]
    for row in rows:
        line = []
        for key, _, fmt in columns:
            value = row.get(key)
            line.append("-" if value is None else format(value, fmt))
        cells.append(line)
    widths = [max(len(r[i]) for r in cells) for i in range(len(columns))]
    out = []
    for n, r in enumerate(cells):
        out.append(
            "  ".join(
                c.rjust(w) if n and i else c.ljust(w)
                for i, (c, w) in enumerate(zip(r, widths, strict=True))
            )
        )
        if n == 0:
            out.append("  ".join("-" * w for w in widths))
    return "\n".join(out)


RESULT_COLUMNS = [
    ("method", "method", ""),
    ("auc", "AUC", ".3f"),
    ("recall_at_1", "R@1", ".3f"),
    ("recall_at_5", "R@5", ".3f"),
    ("recall_at_10", "R@10", ".3f"),
    ("recall_at_100_precision", "R@100%P", ".3f"),
    ("train_accuracy", "train acc", ".3f"),
    ("per_query_ms", "ms/query", ".3f"),
]


def _table_rows(results):
    return [{**r, "per_query_ms": r["timing"]["per_query_ms"]} for r in results]


def _parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 32x64; got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive; got {text!r}")
    return h, w


def _parse_param(text: str) -> tuple[str, object]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE; got {text!r}")
    key, raw = text.split("=", 1)
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.strip(), value


def _split_params(method: str, params: list[tuple[str, object]]):
    """Route KEY=VALUE pairs to the front end or the filter by their constructor names."""
    from .frontends import FRONTENDS
    from .temporal import FILTERS

    spec = METHODS[method]
    front_names = set(FRONTENDS[spec.frontend]._param_names())
    filt_names = set(FILTERS[spec.filter]._param_names()) if spec.filter else set()
    front, filt = {}, {}
    for key, value in params:
        if key.startswith("filter.") and spec.filter:
            key = key[len("filter.") :]
            target = filt if key in filt_names else None
        elif key.startswith("frontend."):
            key = key[len("frontend.") :]
            target = front if key in front_names else None
        elif key in front_names:
            target = front
        elif key in filt_names:
            target = filt
        else:
            target = None
        if target is None:
            raise UsageError(
                f"--param {key}: not a parameter of method {method!r}; front end takes "
                f"{sorted(front_names)}"
                + (f", filter takes {sorted(filt_names)}" if filt_names else "")
            )
        target[key] = value
    return front, filt


def _add_common_data_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--size",
        type=_parse_size,
        default=DEFAULT_SIZE,
        metavar="HxW",
        help="image size after area-averaging resize (default: %(default)s as HxW = 32x64)",
    )
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the image cache")
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="image cache folder (default: $FLYVPR_CACHE_DIR or ~/.cache/flyvpr)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars")


#: CLI form of every dataset option a loader may declare in ``DatasetSpec.options``
DATASET_OPTIONS = {
    "root": (Path, "dataset root folder"),
    "reference": (str, "reference traverse (a season, a run folder or an image folder)"),
    "query": (str, "query traverse (e.g. winter)"),
    "first": (int, "first frame of the window (0-based position in the traverse)"),
    "count": (int, "number of consecutive frames in the window"),
    "tolerance": (int, "ground truth: a reference within this many frames is a match"),
    "tolerance_m": (float, "ground truth: a reference within this many metres is a match"),
    "radius": (float, "ground truth by positions CSV: match radius in metres"),
    "spacing": (float, "keep one frame every this many metres along the route"),
    "positions_csv": (Path, "CSV with header traverse,filename,x,y (metres)"),
    "trust_pickle": (
        bool,
        "allow unpickling the dataset's ground-truth file; pickles can execute code, so only "
        "for files you trust",
    ),
}


def _add_dataset_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("dataset (see `flyvpr datasets` for layouts and options)")
    g.add_argument("--dataset", required=True, choices=sorted(DATASETS), help="dataset layout")
    used = {opt for spec in DATASETS.values() for opt in spec.options}
    for opt in DATASET_OPTIONS:
        if opt not in used:
            continue
        kind, help_text = DATASET_OPTIONS[opt]
        flag = "--" + opt.replace("_", "-")
        if kind is bool:
            g.add_argument(flag, dest=opt, action="store_true", default=None, help=help_text)
        else:
            g.add_argument(flag, dest=opt, type=kind, default=None, help=help_text)


def _add_method_args(p, required: bool = False, default=None, note: str = "") -> None:
    """--method (choices from the registry), --seed and --param, shared by several commands."""
    p.add_argument(
        "--method",
        required=required,
        default=default,
        choices=list(METHODS),
        metavar="METHOD",
        help="one of: " + ", ".join(METHODS) + note,
    )
    p.add_argument(
        "--seed", type=int, default=0, help="random_state of every random part (default 0)"
    )
    p.add_argument(
        "--param",
        type=_parse_param,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="constructor parameter of the front end or filter (JSON value), e.g. epochs=100; "
        "prefix with frontend. or filter. to disambiguate",
    )


def _dataset_kwargs(args) -> dict:
    """Pass the given dataset options that the chosen loader accepts; reject the others."""
    spec = DATASETS[args.dataset]
    kwargs = {}
    for opt in DATASET_OPTIONS:
        value = getattr(args, opt, None)
        if value is None:
            continue
        if opt not in spec.options:
            raise UsageError(
                f"--{opt.replace('_', '-')} does not apply to dataset {args.dataset!r} "
                f"(it takes: {', '.join('--' + o.replace('_', '-') for o in spec.options)})"
            )
        kwargs[opt] = value
    return kwargs


# ---------------------------------------------------------------------------
# commands
# ---------------------------------------------------------------------------
def cmd_evaluate(args) -> int:
    if args.load is not None:
        if args.param:
            raise UsageError("--param cannot change a model loaded with --load")
        from .modelio import load_method

        model = load_method(args.load, size=args.size)
        if args.method is not None and args.method != model.name:
            raise UsageError(f"--method {args.method} but {args.load} holds {model.name}")
        args.method = model.name
        front_params = filt_params = None
    elif args.method is None:
        raise UsageError("give --method METHOD (or --load MODEL.npz)")
    else:
        model = args.method
        front_params, filt_params = _split_params(args.method, args.param)
    bench = load_benchmark(args.dataset, **_dataset_kwargs(args))
    cache = False if args.no_cache else (args.cache_dir or True)
    progress = False if args.quiet else None
    t0 = time.perf_counter()
    ref = bench.reference.load_images(size=args.size, cache=cache, progress=progress)
    qry = bench.query.load_images(size=args.size, cache=cache, progress=progress)
    load_s = time.perf_counter() - t0
    result = evaluate_method(
        model,
        ref,
        qry,
        bench.ground_truth,
        seed=args.seed,
        frontend_params=front_params,
        filter_params=filt_params,
        load_s=load_s,
    )
    protocol = bench.protocol()
    out = {
        "method": args.method,
        "dataset": args.dataset,
        "reference": protocol.get("reference"),
        "query": protocol.get("query"),
        "first": protocol.get("first"),
        "count": protocol.get("count"),
        "n_reference": result["n_reference"],
        "n_query": result["n_query"],
        "tolerance": _tolerance_value(protocol.get("tolerance")),
        "tolerance_unit": _tolerance_unit(protocol.get("tolerance")),
        "seed": args.seed,
        "image_size": list(args.size),
        **{
            k: v for k, v in result.items() if k not in ("method", "seed", "n_reference", "n_query")
        },
        "protocol": protocol,
        "flyvpr_version": __version__,
    }
    _print_protocol(protocol, args)
    print(format_table(_table_rows([result]), RESULT_COLUMNS))
    if args.out is not None:
        write_json_atomic(args.out, out)
        print(f"wrote {args.out}")
    return 0


def cmd_fit(args) -> int:
    from .methods import make_method
    from .modelio import save_method

    front_params, filt_params = _split_params(args.method, args.param)
    bench = load_benchmark(args.dataset, **_dataset_kwargs(args))
    cache = False if args.no_cache else (args.cache_dir or True)
    ref = bench.reference.load_images(
        size=args.size, cache=cache, progress=False if args.quiet else None
    )
    t0 = time.perf_counter()
    model = make_method(args.method, args.seed, front_params, filt_params).fit(ref)
    fit_s = time.perf_counter() - t0
    path = save_method(model, args.save, size=args.size)
    acc = model.train_accuracy
    print(
        f"{args.method}: fitted on {len(ref)} reference places ({bench.reference.name}) in "
        f"{fit_s:.2f} s" + (f", train accuracy {acc:.3f}" if acc is not None else "")
    )
    print(f"wrote {path} ({path.stat().st_size:,} bytes)")
    return 0


def _tolerance_value(tol):
    """The number of a loader's tolerance dict such as ``{"frames": 20}``."""
    if isinstance(tol, dict) and len(tol) == 1:
        return next(iter(tol.values()))
    return tol


def _tolerance_unit(tol):
    if isinstance(tol, dict) and len(tol) == 1:
        return next(iter(tol))
    return None


def _print_protocol(protocol: dict, args) -> None:
    keys = (
        "dataset",
        "reference",
        "query",
        "first",
        "count",
        "n_reference",
        "n_query",
        "tolerance",
    )
    parts = [f"{k}={protocol[k]}" for k in keys[:-1] if protocol.get(k) is not None]
    tol = protocol.get("tolerance")
    if tol is not None:
        parts.append(f"tolerance={_tolerance_value(tol)} {_tolerance_unit(tol) or ''}".rstrip())
    size = getattr(args, "size", DEFAULT_SIZE)
    print(" ".join(parts) + f" size={size[0]}x{size[1]} seed={args.seed}")


def cmd_datasets(args) -> int:
    for name, spec in DATASETS.items():
        print(f"{name}: {spec.description}")
        print(textwrap.indent(spec.layout.strip(), "    "))
        print(f"    options: {', '.join('--' + o.replace('_', '-') for o in spec.options)}")
        print()
    return 0


def cmd_methods(args) -> int:
    available = set(method_names(available_only=True))
    rows = []
    for name, spec in METHODS.items():
        extras = ", ".join(spec.extras)
        rows.append(
            {
                "name": name,
                "extra": f"[{extras}]" + ("" if name in available else " (not installed)")
                if extras
                else "",
                "description": spec.description,
            }
        )
    print(
        format_table(
            rows, [("name", "method", ""), ("extra", "needs", ""), ("description", "what", "")]
        )
    )
    return 0


def cmd_demo(args) -> int:
    from .synthetic import make_route

    t0 = time.perf_counter()
    route = make_route(n_places=args.places, random_state=args.seed)
    gt = route.ground_truth(tolerance=args.tolerance)
    load_s = time.perf_counter() - t0
    methods = args.method or [m for m in DEMO_METHODS if m in method_names(available_only=True)]
    print(
        f"synthetic route: {args.places} places, reference={route.conditions[0]} "
        f"query={route.conditions[1]}, tolerance={args.tolerance} frames, seed={args.seed}, "
        f"size={route.reference_images.shape[1]}x{route.reference_images.shape[2]}"
    )
    results = []
    for m in methods:
        if m not in METHODS:
            raise UsageError(f"--method: unknown method {m!r}")
        logger.info("evaluating %s", m)
        results.append(
            evaluate_method(
                m, route.reference_images, route.query_images, gt, seed=args.seed, load_s=load_s
            )
        )
    print(format_table(_table_rows(results), RESULT_COLUMNS))
    print(
        "\nReal data is one flag away, e.g.:\n"
        "  flyvpr evaluate --dataset nordland --root ../shared/data/nordland_64x32 "
        "--reference summer --query winter --first 0 --count 1000 --tolerance 20 "
        "--method flynet+cann --seed 0 --out result.json"
    )
    if args.out is not None:
        write_json_atomic(
            args.out, {"dataset": "synthetic", "places": args.places, "results": results}
        )
        print(f"wrote {args.out}")
    return 0


def _parse_speed(text: str):
    try:
        if "-" in text:
            low, high = (float(v) for v in text.split("-"))
            return (low, high)
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a speed such as 2 or 1-1.5; got {text!r}"
        ) from None


def cmd_localize(args) -> int:
    import csv
    import io

    from tqdm.auto import tqdm

    from .evaluation import speed_profile
    from .localizer import Localizer

    if args.method not in METHODS:
        raise UsageError(f"--method: unknown method {args.method!r}")
    front_params, filt_params = _split_params(args.method, args.param)
    bench = load_benchmark(args.dataset, **_dataset_kwargs(args))
    if args.speed is not None:
        keep = speed_profile(bench.n_query, args.speed, random_state=args.seed)
        bench = bench.subset_queries(keep)
    else:
        keep = np.arange(bench.n_query)
    cache = False if args.no_cache else (args.cache_dir or True)
    progress = False if args.quiet else None
    ref, qry = bench.load_images(size=args.size, cache=cache, progress=progress)
    loc = Localizer(args.method, args.seed, front_params, filt_params).fit(ref)
    gt = bench.ground_truth
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["frame", "source_frame", "place", "confidence", "correct"])
    correct = 0
    t0 = time.perf_counter()
    show = not args.quiet and sys.stderr.isatty()
    for i in tqdm(range(len(qry)), desc="localizing", unit="frame", disable=not show):
        velocity = None
        if args.odometry and i > 0:
            velocity = float(keep[i] - keep[i - 1])
        place, conf = loc.update(qry[i], velocity=velocity)
        ok = bool(gt[i, place])
        correct += ok
        writer.writerow([i, int(keep[i]), place, f"{conf:.6g}", int(ok)])
    elapsed = time.perf_counter() - t0
    if args.out is not None:
        write_text_atomic(args.out, buf.getvalue())
    _print_protocol(bench.protocol(), args)
    print(
        f"{args.method}: {len(qry)} frames streamed, {correct / len(qry):.3f} correct "
        f"(best place within tolerance), {1000 * elapsed / len(qry):.3f} ms/frame"
    )
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0


def cmd_experiment(args) -> int:
    from .experiments import run_experiment

    summary = run_experiment(
        args.config,
        args.out,
        n_jobs=args.jobs,
        backend=args.backend,
        progress=False if args.quiet else None,
    )
    print(
        f"{summary['n_runs']} runs: {summary['n_skipped']} already finished, "
        f"{len(summary['ran'])} ran now, {len(summary['errors'])} failed "
        f"({summary['elapsed_s']:.1f} s); results in {summary['out_dir']}"
    )
    for run_id, error in summary["errors"].items():
        print(f"  failed: {run_id}: {error}", file=sys.stderr)
    print(f"next: flyvpr report {args.out}")
    return 1 if summary["errors"] else 0


def cmd_report(args) -> int:
    from .experiments import write_report

    html_path, md_path = write_report(args.dir, figures=not args.no_figures)
    print(f"wrote {html_path}")
    print(f"wrote {md_path}")
    return 0


#: methods the demo runs by default, in table order
DEMO_METHODS = ("pixels", "flyhash", "flynet", "seqslam", "flynet+seqslam", "flynet+cann")


# ---------------------------------------------------------------------------
# parser
# ---------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="flyvpr",
        description=(
            "Visual place recognition with FlyNet+CANN. A reference traverse is learned; every "
            "query frame is matched to a reference place; results are scored with precision-"
            "recall AUC and Recall@K."
        ),
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="Run `flyvpr COMMAND --help` for the options of a command.",
    )
    parser.add_argument("--version", action="version", version=f"flyvpr {__version__}")
    parser.add_argument("--verbose", "-v", action="count", default=0, help="more log output")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    p = sub.add_parser(
        "evaluate",
        help="fit a method on a reference traverse and score a query traverse",
        description=(
            "Fit METHOD on the reference traverse, score every query frame against every "
            "reference place, and report PR-AUC, Recall@1/5/10 and recall at 100%% precision. "
            "Each query's best reference is its prediction, with that score as confidence."
        ),
    )
    _add_dataset_args(p)
    _add_method_args(p, required=False, note=" (required unless --load)")
    p.add_argument("--out", type=Path, help="write the result as JSON (atomically)")
    p.add_argument(
        "--load",
        type=Path,
        metavar="MODEL.npz",
        help="use a model saved by `flyvpr fit --save` instead of fitting",
    )
    _add_common_data_args(p)
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "fit",
        help="fit a method on a reference traverse and save it to a model file",
        description=(
            "Fit METHOD on the reference traverse of a dataset and save front end and filter to "
            "an .npz model file (no pickle: loading it cannot run code). Use it with "
            "`flyvpr evaluate --load MODEL.npz`."
        ),
    )
    _add_dataset_args(p)
    _add_method_args(p, required=True)
    p.add_argument(
        "--save",
        type=Path,
        required=True,
        metavar="MODEL.npz",
        help="model file to write (atomically)",
    )
    _add_common_data_args(p)
    p.set_defaults(func=cmd_fit)

    p = sub.add_parser(
        "localize",
        help="stream a query traverse frame by frame and write one CSV line per frame",
        description=(
            "Fit METHOD on the reference traverse, then feed the query frames one at a time to "
            "the streaming localizer (constant time and memory per frame) and write frame, "
            "place, confidence and correctness to CSV."
        ),
    )
    _add_dataset_args(p)
    _add_method_args(p, default="flynet+cann", note=" (an online filter; default flynet+cann)")
    p.add_argument(
        "--speed",
        type=_parse_speed,
        metavar="S",
        help="simulate another robot speed: keep query frames at S places per frame "
        "(e.g. 2) or a seeded random profile LOW-HIGH (e.g. 1-1.5)",
    )
    p.add_argument(
        "--odometry",
        action="store_true",
        help="pass the true places moved per frame to the filter as velocity input",
    )
    p.add_argument("--out", type=Path, help="CSV file to write (atomically)")
    _add_common_data_args(p)
    p.set_defaults(func=cmd_localize)

    p = sub.add_parser("datasets", help="list dataset layouts and their options")
    p.set_defaults(func=cmd_datasets)

    p = sub.add_parser("methods", help="list the methods and the extras they need")
    p.set_defaults(func=cmd_methods)

    p = sub.add_parser(
        "demo",
        help="run the methods on a built-in procedurally generated route (no data needed)",
        description=(
            "Generate a route of PLACES places seen under two appearance conditions (summer as "
            "reference, winter as query), evaluate the methods and print the table."
        ),
    )
    p.add_argument("--places", type=int, default=500, help="number of places (default 500)")
    p.add_argument(
        "--tolerance", type=int, default=2, help="ground-truth tolerance in frames (default 2)"
    )
    p.add_argument(
        "--seed", type=int, default=0, help="seed of the route and the methods (default 0)"
    )
    p.add_argument("--method", action="append", metavar="METHOD", help="method to run (repeatable)")
    p.add_argument("--out", type=Path, help="write all results as JSON (atomically)")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser(
        "experiment",
        help="run the grids of an experiment config (resumable, in parallel)",
        description=(
            "Expand CONFIG.toml (datasets x methods x seeds x parameters, see "
            "experiments/paper.toml) into runs and execute them in parallel, one JSON file per "
            "run in DIR/runs/. Finished runs are skipped, so an interrupted experiment resumes "
            "where it stopped; failed runs are recorded, reported and retried next time."
        ),
    )
    p.add_argument("config", type=Path, metavar="CONFIG.toml", help="experiment config file")
    p.add_argument("--out", type=Path, required=True, metavar="DIR", help="results folder")
    p.add_argument(
        "--jobs",
        "-j",
        type=int,
        default=1,
        metavar="N",
        help="parallel worker processes (-1: all cores; default 1)",
    )
    p.add_argument(
        "--backend",
        choices=["loky", "dask", "ray"],
        default="loky",
        help="joblib backend: loky (local processes, default), dask (DASK_SCHEDULER_ADDRESS or "
        "a local cluster; pip install 'dask[distributed]') or ray (RAY_ADDRESS; pip install ray)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_experiment)

    p = sub.add_parser(
        "report",
        help="write DIR/report.html and DIR/report.md from the results of `flyvpr experiment`",
        description=(
            "Write a self-contained HTML report (figures embedded) and a Markdown summary "
            "(figures in DIR/figures/) with the tables, figures and protocol of every number."
        ),
    )
    p.add_argument("dir", type=Path, metavar="DIR", help="the --out folder of `flyvpr experiment`")
    p.add_argument("--no-figures", action="store_true", help="tables only (needs no matplotlib)")
    p.set_defaults(func=cmd_report)
    return parser


def main(argv=None) -> int:
    """Run the CLI; returns the process exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse: --help/--version (0) or usage error (2)
        return int(exc.code or 0)
    logging.basicConfig(
        level=logging.WARNING - 10 * min(args.verbose, 2),
        format="%(levelname)s %(name)s: %(message)s",
    )
    try:
        return int(args.func(args))
    except UsageError as exc:
        print(f"flyvpr {args.command}: usage error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("flyvpr: interrupted", file=sys.stderr)
        return 130
    except (ValueError, TypeError, OSError, ImportError, RuntimeError) as exc:
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"flyvpr {args.command}: error: {message}", file=sys.stderr)
        logger.debug("traceback", exc_info=True)
        return 1

"""``flyvpr experiment`` and ``flyvpr report``: config-driven grids of runs and their report."""

from __future__ import annotations

import sys
from pathlib import Path

from ._common import parse_jobs


def cmd_experiment(args) -> int:
    from ..experiments import run_experiment

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
    from ..experiments import write_report

    html_path, md_path = write_report(args.dir, figures=not args.no_figures)
    print(f"wrote {html_path}")
    print(f"wrote {md_path}")
    return 0


def register(sub) -> None:
    """Add ``experiment`` and ``report`` to the subcommand parsers ``sub``."""
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
        type=parse_jobs,
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

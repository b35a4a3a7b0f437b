"""Helpers shared by the subcommands: usage errors, tables, and the shared options.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from ..datasets import DATASETS
from ..images import DEFAULT_SIZE
from ..methods import METHODS

logger = logging.getLogger("flyvpr")


class UsageError(Exception):
    """Bad command-line usage detected after parsing (exit code 2)."""


# ---------------------------------------------------------------------------
# small helpers
# ---------------------------------------------------------------------------
def format_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    """Align ``rows`` under ``columns`` given as (key, header, format).

    Columns with a format (numbers) are right-aligned, text columns left-aligned, and trailing
    blanks are stripped so no line is wider than its content.
    """
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
                c.rjust(w) if n and columns[i][2] else c.ljust(w)
                for i, (c, w) in enumerate(zip(r, widths, strict=True))
            ).rstrip()
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


def table_rows(results):
    return [{**r, "per_query_ms": r["timing"]["per_query_ms"]} for r in results]


def parse_size(text: str) -> tuple[int, int]:
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW such as 32x64; got {text!r}") from None
    if h < 1 or w < 1:
        raise argparse.ArgumentTypeError(f"size must be positive; got {text!r}")
    return h, w


def parse_param(text: str) -> tuple[str, object]:
    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE; got {text!r}")
    key, raw = text.split("=", 1)
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    return key.strip(), value


def split_params(method: str, params: list[tuple[str, object]]):
    """Route KEY=VALUE pairs to the front end or the filter by their constructor names."""
    from ..frontends import FRONTENDS
    from ..temporal import FILTERS

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


def add_image_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--size",
        type=parse_size,
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


def add_dataset_args(p: argparse.ArgumentParser) -> None:
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


def add_method_args(p, required: bool = False, default=None, note: str = "") -> None:
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
        type=parse_param,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="constructor parameter of the front end or filter (JSON value), e.g. epochs=100; "
        "prefix with frontend. or filter. to disambiguate",
    )


def dataset_kwargs(args) -> dict:
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


def tolerance_value(tol):
    """The number of a loader's tolerance dict such as ``{"frames": 20}``."""
    if isinstance(tol, dict) and len(tol) == 1:
        return next(iter(tol.values()))
    return tol


def tolerance_unit(tol):
    if isinstance(tol, dict) and len(tol) == 1:
        return next(iter(tol))
    return None


def print_protocol(protocol: dict, args) -> None:
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
        parts.append(f"tolerance={tolerance_value(tol)} {tolerance_unit(tol) or ''}".rstrip())
    size = getattr(args, "size", DEFAULT_SIZE)
    print(" ".join(parts) + f" size={size[0]}x{size[1]} seed={args.seed}")


def parse_speed(text: str):
    try:
        if "-" in text:
            low, high = (float(v) for v in text.split("-"))
            return (low, high)
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a speed such as 2 or 1-1.5; got {text!r}"
        ) from None


def image_options(args) -> dict:
    """``cache`` and ``progress`` keyword arguments of the image loaders from the shared options."""
    return {
        "cache": False if args.no_cache else (args.cache_dir or True),
        "progress": False if args.quiet else None,
    }

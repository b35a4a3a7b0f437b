"""Helpers shared by the subcommands: usage errors, tables, and the shared options.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import re
from pathlib import Path

import numpy as np

from .._io import OutputPathError, check_output_path
from .._validation import check_memory
from ..datasets import DATASETS
from ..images import DEFAULT_SIZE, IMAGE_EXTENSIONS
from ..methods import METHODS

logger = logging.getLogger("flyvpr")


class UsageError(Exception):
    """Bad command-line usage detected after parsing (exit code 2)."""


#: library parameters that are command-line options under another name
_OPTION_OF = {
    "every": "--every",
    "topic": "--topic",
    "positions": "--positions",
    "position_topic": "--position-topic",
}
_PARAMETER = re.compile(r"(?<![\w-])(" + "|".join(_OPTION_OF) + r")=")


def as_options(message: str) -> str:
    """A library message in the command line's words: the library names its parameters
    (``every=2m``, ``position_topic=TOPIC``), the command line shows the options that set
    them (``--every 2m``, ``--position-topic TOPIC``).

    >>> as_options("every=2m: keeping frames by distance needs positions (positions=CSV)")
    '--every 2m: keeping frames by distance needs positions (--positions CSV)'
    """
    return _PARAMETER.sub(lambda m: _OPTION_OF[m.group(1)] + " ", message)


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
    ("extended_precision", "EP", ".3f"),
    ("train_accuracy", "train acc", ".3f"),
    ("per_query_ms", "ms/query", ".3f"),
]


def table_rows(results):
    return [{**r, "per_query_ms": r["timing"]["per_query_ms"]} for r in results]


def _number(kind, low, strict: bool, expected: str):
    """An argparse type: ``kind`` (int or float), finite, ``> low`` (strict) or ``>= low``."""

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {expected}; got {text!r}") from None
        if not math.isfinite(value) or value < low or (strict and value == low):
            raise argparse.ArgumentTypeError(f"expected {expected}; got {text!r}")
        return value

    parse.__name__ = expected  # argparse shows the type's name in some messages
    return parse


#: argparse types of counts and distances: the option's name is in argparse's message
positive_int = _number(int, 1, False, "an integer >= 1")
nonnegative_int = _number(int, 0, False, "an integer >= 0")
positive_float = _number(float, 0.0, True, "a finite number > 0")
nonnegative_float = _number(float, 0.0, False, "a finite number >= 0")


def parse_jobs(text: str) -> int:
    """``--jobs``: a number of processes >= 1, or -1 for every core."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1 and value != -1:
        raise argparse.ArgumentTypeError(
            f"expected an integer >= 1 or -1 (all cores); got {text!r}"
        )
    return value


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
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{key.strip()}: expected a finite number; got {raw!r}")
    return key.strip(), value


def split_params(method: str, params: list[tuple[str, object]]):
    """Route KEY=VALUE pairs to the front end or the filter by their constructor names.

    A name both parts take (``epochs`` of ``flynet+rnn``) must say which part it is for,
    ``frontend.KEY`` or ``filter.KEY``: given to one part silently, it would leave the other
    at its default.
    """
    from ..frontends import FRONTENDS
    from ..temporal import FILTERS

    spec = METHODS[method]
    front_names = set(FRONTENDS[spec.frontend]._param_names())
    filt_names = set(FILTERS[spec.filter]._param_names()) if spec.filter else set()
    front: dict = {}
    filt: dict = {}
    for key, value in params:
        if key.startswith("filter.") and spec.filter:
            key = key[len("filter.") :]
            target = filt if key in filt_names else None
        elif key.startswith("frontend."):
            key = key[len("frontend.") :]
            target = front if key in front_names else None
        elif key in front_names and key in filt_names and key != "random_state":
            raise UsageError(
                f"--param {key}: both parts of {method!r} take {key!r} (front end "
                f"{spec.frontend!r}, filter {spec.filter!r}); write frontend.{key}=... or "
                f"filter.{key}=... (or both)"
            )
        elif key in front_names:
            target = front
        elif key in filt_names:
            target = filt
        else:
            target = None
        if key == "random_state":
            raise UsageError(
                "--param random_state: set the seed with --seed, which the results record "
                "(one seed drives every random part)"
            )
        if target is None:
            raise UsageError(
                f"--param {key}: not a parameter of method {method!r}; front end takes "
                f"{sorted(front_names)}"
                + (f", filter takes {sorted(filt_names)}" if filt_names else "")
            )
        if key in target:
            raise UsageError(
                f"--param {key}: given twice ({target[key]!r}, {value!r}); one per run"
            )
        target[key] = value
    return front, filt


def add_image_args(
    p: argparse.ArgumentParser, size_default=DEFAULT_SIZE, from_file: str = "--map"
) -> None:
    """--size, --no-cache, --cache-dir and --quiet.  ``size_default`` None: --size is None
    unless given, and the command takes the size of the file ``from_file`` names (a map's,
    a model's) when there is one, else 32x64."""
    what = {"--map": "the map's", "--load": "the model's"}.get(from_file, "the file's")
    p.add_argument(
        "--size",
        type=parse_size,
        default=size_default,
        metavar="HxW",
        help="image size after area-averaging resize (default: 32x64"
        + ("" if size_default else f"; with {from_file}: {what}")
        + ")",
    )
    p.add_argument("--no-cache", action="store_true", help="neither read nor write the image cache")
    p.add_argument(
        "--cache-dir",
        type=Path,
        default=None,
        help="image cache folder (default: $FLYVPR_CACHE_DIR, else $XDG_CACHE_HOME/flyvpr, else "
        "~/.cache/flyvpr)",
    )
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars")


#: CLI form of every dataset option a loader may declare in ``DatasetSpec.options``
DATASET_OPTIONS = {
    "root": (Path, "dataset root folder"),
    "reference": (str, "reference traverse (a season, a run folder or an image folder)"),
    "query": (str, "query traverse (e.g. winter)"),
    "first": (nonnegative_int, "first frame of the window (0-based position in the traverse)"),
    "count": (positive_int, "number of consecutive frames in the window"),
    "tolerance": (nonnegative_int, "ground truth: a reference within this many frames is a match"),
    "tolerance_m": (
        nonnegative_float,
        "ground truth: a reference within this many metres is a match",
    ),
    "radius": (nonnegative_float, "ground truth by positions CSV: match radius in metres"),
    "spacing": (positive_float, "keep one frame every this many metres along the route"),
    "positions_csv": (
        Path,
        "CSV with header traverse,filename,x,y (metres); a relative path is relative to --root",
    ),
    "trust_pickle": (
        bool,
        "allow unpickling the dataset's ground-truth file; pickles can execute code, so only "
        "for files you trust",
    ),
}


def add_dataset_args(p: argparse.ArgumentParser, required: bool = True) -> None:
    g = p.add_argument_group("dataset (run flyvpr datasets for the layouts and their options)")
    g.add_argument("--dataset", required=required, choices=sorted(DATASETS), help="dataset layout")
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


class _Once(argparse.Action):
    """An option that may be given once: a second value is a usage error (argparse would keep
    the last one silently, and a user listing several methods would get only that one)."""

    def __call__(self, parser, namespace, values, option_string=None):
        given = getattr(namespace, self.dest, None)
        if getattr(namespace, f"_{self.dest}_given", False):
            parser.error(
                f"{option_string} given twice ({given}, {values}): one per run"
                + (
                    "; `flyvpr experiment` runs several methods and tables them"
                    if self.dest == "method"
                    else ""
                )
            )
        setattr(namespace, f"_{self.dest}_given", True)
        setattr(namespace, self.dest, values)


def add_method_args(
    p, required: bool = False, default=None, note: str = "", seed_default: int | None = 0
) -> None:
    """--method (choices from the registry), --seed and --param, shared by several commands
    (``seed_default`` None: the command tells a given --seed from none, and sets 0 itself)."""
    p.add_argument(
        "--method",
        required=required,
        default=default,
        choices=list(METHODS),
        action=_Once,
        metavar="METHOD",
        help="one of: " + ", ".join(METHODS) + note,
    )
    p.add_argument(
        "--seed",
        type=nonnegative_int,
        default=seed_default,
        action=_Once,
        help="random_state of every random part, an integer >= 0 (default 0)",
    )
    p.add_argument(
        "--param",
        type=parse_param,
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="constructor parameter of the front end or filter (JSON value), e.g. epochs=100; "
        "a name both take (epochs of flynet+rnn) needs the prefix frontend. or filter.",
    )


def counted(n: int, noun: str) -> str:
    """``n`` and ``noun``, plural unless ``n`` is 1: ``counted(1, "frame") == "1 frame"``."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def positions_words(positions, origin) -> str:
    """A map's positions in a summary: with or without them, and how many of its places
    have none (frames the positions file or topic does not cover)."""
    if positions is None:
        return "without positions"
    unplaced = int(np.isnan(np.asarray(positions, np.float64)).any(axis=1).sum())
    if not unplaced:
        return "with positions"
    return f"with positions (none for {unplaced} of {len(positions)} places: not in {origin})"


def flag(option: str) -> str:
    """The command-line form of a loader option: ``positions_csv -> --positions-csv``."""
    return "--" + option.replace("_", "-")


def dataset_kwargs(args) -> dict:
    """The given dataset options, checked against the chosen layout's rules (usage errors)."""
    spec = DATASETS[args.dataset]
    kwargs = {o: getattr(args, o) for o in DATASET_OPTIONS if getattr(args, o, None) is not None}
    try:
        spec.check_options(kwargs, name=flag)
    except ValueError as exc:
        raise UsageError(f"dataset {args.dataset!r}: {exc}") from None
    return kwargs


def check_outputs(args, inputs=(), options=("out",)) -> None:
    """Before any work: each output option names a writable regular file that is no input.

    Raises
    ------
    UsageError
        Naming the option and what is wrong (see :func:`flyvpr._io.check_output_path`).
    """
    inputs = list(inputs)
    for option in options:
        value = getattr(args, option, None)
        if value is None:
            continue
        try:
            check_output_path(value, inputs, what=flag(option), image_extensions=IMAGE_EXTENSIONS)
        except OutputPathError as exc:
            raise UsageError(str(exc)) from None


def check_run_memory(args, n_reference: int, n_query: int, score_rows: int | None = None) -> None:
    """Refuse, before loading, a run whose images and score matrices cannot fit in memory.

    Counts the two image stacks (float32) and three score matrices of ``score_rows`` rows
    (default ``n_query``; float64: the front end's, the filter's output and the metrics'
    working copy); the run needs at least that.
    """
    h, w = args.size
    rows = n_query if score_rows is None else score_rows
    need = (n_reference + n_query) * h * w * 4 + 3 * n_reference * rows * 8
    check_memory(need, f"--size {h}x{w} with {n_reference} reference and {n_query} query frames")


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
    matchable = protocol.get("n_query_with_match")
    if matchable is not None and matchable != protocol.get("n_query"):
        parts.append(f"({matchable} with a true match)")
    tol = protocol.get("tolerance")
    if tol is not None:
        parts.append(f"tolerance={tolerance_value(tol)} {tolerance_unit(tol) or ''}".rstrip())
    size = getattr(args, "size", DEFAULT_SIZE)
    load = getattr(args, "load", None)
    fitted = f"model={load}" if load is not None else f"seed={args.seed}"
    print(" ".join(parts) + f" size={size[0]}x{size[1]} {fitted}")


def parse_speed(text: str):
    """``--speed``: places per frame, a finite number > 0, or a range LOW-HIGH with LOW <= HIGH."""
    expected = f"a speed > 0 such as 2, or a range LOW-HIGH such as 1-1.5; got {text!r}"
    try:
        values = [float(v) for v in text.split("-")] if "-" in text else [float(text)]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {expected}") from None
    if len(values) > 2 or not all(math.isfinite(v) and v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"expected {expected}")
    if len(values) == 2:
        if values[0] > values[1]:
            raise argparse.ArgumentTypeError(f"LOW must be <= HIGH: expected {expected}")
        return (values[0], values[1])
    return values[0]


def image_options(args) -> dict:
    """``cache`` and ``progress`` keyword arguments of the image loaders from the shared options."""
    return {
        "cache": False if args.no_cache else (args.cache_dir or True),
        "progress": False if args.quiet else None,
    }

"""``flyvpr evaluate`` and ``flyvpr fit``: score a benchmark, or fit and save a model file."""

from __future__ import annotations

import inspect
import logging
import time
from pathlib import Path

from .._io import write_json_atomic
from .._version import __version__
from ..datasets import load_benchmark
from ..evaluation import check_true_matches, evaluate_method, self_match_share
from ..images import DEFAULT_SIZE
from ._common import (
    RESULT_COLUMNS,
    UsageError,
    add_dataset_args,
    add_image_args,
    add_method_args,
    check_outputs,
    check_run_memory,
    dataset_kwargs,
    format_table,
    image_options,
    print_protocol,
    split_params,
    table_rows,
    tolerance_unit,
    tolerance_value,
)

logger = logging.getLogger(__name__)


def cmd_evaluate(args) -> int:
    kwargs = _resolved(dataset_kwargs(args))
    if args.load is not None:
        if args.param:
            raise UsageError("--param cannot change a model loaded with --load")
        if args.seed is not None:
            raise UsageError(
                "--seed: a model loaded with --load is fitted already (its seed was given to "
                "`flyvpr fit`)"
            )
        from ..modelio import load_method

        # a given --size must be the model's; without one, the model's is used
        model = load_method(args.load, size=args.size)
        if args.method is not None and args.method != model.name:
            raise UsageError(f"--method {args.method} but {args.load} holds {model.name}")
        args.method = model.name
        args.size = tuple(int(v) for v in model.frontend.image_shape_)
        front_params = filt_params = None
    elif args.method is None:
        raise UsageError("give --method METHOD (or --load MODEL.npz)")
    else:
        model = args.method
        front_params, filt_params = split_params(args.method, args.param)
        args.seed = 0 if args.seed is None else args.seed
        args.size = args.size or DEFAULT_SIZE
    bench = load_benchmark(args.dataset, **kwargs)
    check_true_matches(bench)  # before the work: every metric needs a query with a match
    loaded = [args.load] if args.load is not None else []
    check_outputs(args, [*bench.input_files(), *loaded], ("out",))
    check_run_memory(args, bench.n_reference, bench.n_query)
    t0 = time.perf_counter()
    ref, qry = bench.load_images(size=args.size, **image_options(args))
    load_s = time.perf_counter() - t0
    if args.load is not None:
        _check_fitted_here(model, ref, args.load)
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
        "tolerance": tolerance_value(protocol.get("tolerance")),
        "tolerance_unit": tolerance_unit(protocol.get("tolerance")),
        # a loaded model's: the seed `flyvpr fit` was given (None for a file without one)
        "seed": args.seed if args.load is None else model.seed,
        "model_file": None if args.load is None else str(args.load),
        "image_size": list(args.size),
        **{
            k: v for k, v in result.items() if k not in ("method", "seed", "n_reference", "n_query")
        },
        "protocol": protocol,
        "flyvpr_version": __version__,
    }
    print_protocol({**protocol, "n_query_with_match": result["n_query_with_match"]}, args)
    print(format_table(table_rows([result]), RESULT_COLUMNS))
    if args.out is not None:
        write_json_atomic(args.out, out)
        print(f"wrote {args.out}")
    return 0


def _resolved(kwargs: dict) -> dict:
    """The dataset options with their paths absolute, so that the protocol of ``--out`` names
    the files wherever it is read (as experiment run files do).

    The loaders read ``reference``, ``query`` and ``positions_csv`` under ``root``; the
    generic layout without ``--root`` reads them from the working directory.  A relative
    path is resolved, an absolute one kept as given (as a config's paths are).
    """

    def absolute(path) -> Path:
        path = Path(path)
        return path if path.is_absolute() else path.resolve()

    out = dict(kwargs)
    if out.get("root") is not None:
        out["root"] = absolute(out["root"])
    else:
        for key in ("reference", "query", "positions_csv"):
            if out.get(key) is not None:
                out[key] = absolute(out[key])
    return out


#: warn when fewer reference frames find their own place than this share of those expected
_SELF_MATCH_FRACTION = 0.5


def _check_fitted_here(model, ref, path) -> None:
    """Warn when a loaded model's front end does not recognise the reference window's own
    images (a model fitted on another window: the ground truth would not be its places).

    The images it was fitted on find their own place (within 2) about as often as its
    training accuracy says, or more; a front end that learns nothing finds nearly all of
    them.  So the warning comes when fewer than half as many as that find it: on another
    window of the route almost none do, while a model that fits its own places poorly (a
    training accuracy of 30%) is not taken for one fitted elsewhere.
    """
    if model.frontend.n_reference_ != len(ref):
        return  # refused by the evaluation itself, with the two numbers
    share = self_match_share(model, ref)
    trained = model.train_accuracy
    expected = 1.0 if trained is None else float(trained)
    if share < _SELF_MATCH_FRACTION * expected:
        own = (
            "on the frames it was fitted on nearly all do"
            if trained is None
            else f"its training accuracy on the frames it was fitted on: {100 * trained:.0f}%"
        )
        logger.warning(
            "%s: only %.0f%% of the reference frames (evenly sampled) find their own place "
            "within 2 places (%s): the model was likely fitted on other reference frames "
            "(check --reference, --first and --count against those given to `flyvpr fit`)",
            path, 100 * share, own,
        )  # fmt: skip


def _reference_only(args) -> dict:
    """The dataset options of ``fit``, which reads the reference traverse only: without
    ``--query``, the layout's query is the reference itself (so that a missing default query
    folder does not stop a fit), and the ground-truth options are not read."""
    from ..datasets import DATASETS

    kwargs = dataset_kwargs(args)
    spec = DATASETS[args.dataset]
    if "query" in spec.options and "query" not in kwargs:
        reference = kwargs.get("reference")
        if reference is None:
            reference = inspect.signature(spec.loader).parameters["reference"].default
        kwargs["query"] = reference
        if kwargs.pop("positions_csv", None) is not None:  # (its query rows name other images)
            kwargs.pop("radius", None)
    return kwargs


def cmd_fit(args) -> int:
    from ..methods import make_method
    from ..modelio import save_method

    front_params, filt_params = split_params(args.method, args.param)
    bench = load_benchmark(args.dataset, **_reference_only(args))
    check_outputs(args, bench.input_files(), ("save",))
    check_run_memory(args, bench.n_reference, 0)
    ref = bench.reference.load_images(size=args.size, **image_options(args))
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


def register(sub) -> None:
    """Add ``evaluate`` and ``fit`` to the subcommand parsers ``sub``."""
    p = sub.add_parser(
        "evaluate",
        help="fit a method on a reference traverse and score a query traverse",
        description=(
            "Fit METHOD on the reference traverse, score every query frame against every "
            "reference place, and report PR-AUC, Recall@1/5/10 and recall at 100% precision. "
            "Each query's best reference is its prediction, with that score as confidence."
        ),
    )
    add_dataset_args(p)
    add_method_args(p, required=False, note=" (required unless --load)", seed_default=None)
    p.add_argument("--out", type=Path, help="write the result as JSON (atomically)")
    p.add_argument(
        "--load",
        type=Path,
        metavar="MODEL.npz",
        help="use a model saved by `flyvpr fit --save` instead of fitting",
    )
    add_image_args(p, size_default=None, from_file="--load")
    p.set_defaults(func=cmd_evaluate)

    p = sub.add_parser(
        "fit",
        help="fit a method on a reference traverse and save it to a model file",
        description=(
            "Fit METHOD on the reference traverse of a dataset and save front end and filter to "
            "an .npz model file (no pickle: loading it cannot run code). Use it with "
            "`flyvpr evaluate --load MODEL.npz`. Only the reference traverse is read: without "
            "--query the layout's query folder need not exist, and ground-truth options "
            "(--positions-csv, --radius) are not read."
        ),
    )
    add_dataset_args(p)
    add_method_args(p, required=True)
    p.add_argument(
        "--save",
        type=Path,
        required=True,
        metavar="MODEL.npz",
        help="model file to write (atomically)",
    )
    add_image_args(p)
    p.set_defaults(func=cmd_fit)

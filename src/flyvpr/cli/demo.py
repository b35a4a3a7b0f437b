"""``flyvpr demo``: the main job on the built-in procedurally generated route."""

from __future__ import annotations

import logging
import time
from pathlib import Path

from .._io import write_json_atomic
from .._validation import check_memory
from ..evaluation import evaluate_method
from ..images import DEFAULT_SIZE
from ..methods import DEFAULT_METHOD, METHODS, method_names
from ._common import (
    RESULT_COLUMNS,
    UsageError,
    check_outputs,
    format_table,
    nonnegative_int,
    positive_int,
    table_rows,
)

logger = logging.getLogger("flyvpr")

#: methods the demo runs by default, in table order; the default method of `flyvpr map` and
#: `flyvpr localize` (``DEFAULT_METHOD``) is always among them
DEMO_METHODS = tuple(
    dict.fromkeys(
        (
            "pixels",
            "flyhash",
            "flynet",
            "seqslam",
            "flynet+seqslam",
            "flynet+cann",
            "pixels+cann",
            DEFAULT_METHOD,
        )
    )
)

#: frames of the untimed warm-up run before each method is timed
WARMUP_FRAMES = 50


def cmd_demo(args) -> int:
    from ..synthetic import make_route

    check_outputs(args, (), ("out",))
    n = args.places
    h, w = DEFAULT_SIZE
    # two traverses of images and three score matrices (front end, filter, metrics)
    check_memory(2 * n * h * w * 4 + 3 * n * n * 8, f"--places {n}")
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
        # First calls pay numba's JIT compilation (seconds on a fresh install) and lazy
        # imports; an untimed run on the first frames keeps them out of ms/query, as the
        # experiments' timing runs do, so the table shows the steady state.
        k = min(WARMUP_FRAMES, n)
        evaluate_method(
            m, route.reference_images[:k], route.query_images[:k], gt[:k, :k], seed=args.seed
        )
        results.append(
            evaluate_method(
                m, route.reference_images, route.query_images, gt, seed=args.seed, load_s=load_s
            )
        )
    print(format_table(table_rows(results), RESULT_COLUMNS))
    print("(ms/query leaves out first-call compilation: each method is timed after a warm-up)")
    print(
        "\nYour own images are one command away: two folders of the same route, DATA/REF and "
        "DATA/QUERY,\nwhere query frame i shows reference place i (give or take --tolerance "
        "frames):\n"
        "  flyvpr evaluate --dataset generic --root DATA --reference REF --query QUERY "
        "--tolerance 2 --method kenyon+cann --out result.json\n"
        "(`flyvpr datasets` lists the other layouts: Nordland, Oxford RobotCar, VPR-Bench)\n"
        "and so is your robot's own recording (a video, a ROS bag or an image folder):\n"
        "  flyvpr map drive1.mp4 --out route.map && "
        "flyvpr localize --map route.map drive2.mp4 --out where.csv --render trace.mp4"
    )
    if args.out is not None:
        write_json_atomic(
            args.out, {"dataset": "synthetic", "places": args.places, "results": results}
        )
        print(f"wrote {args.out}")
    return 0


def register(sub) -> None:
    """Add ``demo`` to the subcommand parsers ``sub``."""
    p = sub.add_parser(
        "demo",
        help="run the methods on a built-in procedurally generated route (no data needed)",
        description=(
            "Generate a route of PLACES places seen under two appearance conditions (summer as "
            "reference, winter as query), evaluate the methods and print the table."
        ),
    )
    p.add_argument(
        "--places", type=positive_int, default=500, help="number of places (default 500)"
    )
    p.add_argument(
        "--tolerance",
        type=nonnegative_int,
        default=2,
        help="ground-truth tolerance in frames (default 2)",
    )
    p.add_argument(
        "--seed",
        type=nonnegative_int,
        default=0,
        help="seed of the route and the methods (default 0)",
    )
    p.add_argument("--method", action="append", metavar="METHOD", help="method to run (repeatable)")
    p.add_argument("--out", type=Path, help="write all results as JSON (atomically)")
    p.set_defaults(func=cmd_demo)

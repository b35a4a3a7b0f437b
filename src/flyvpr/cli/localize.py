"""``flyvpr localize``: stream a query traverse frame by frame through the online localizer."""

from __future__ import annotations

import csv
import io
import sys
import time
import zipfile
from pathlib import Path

import numpy as np

from .._io import write_text_atomic
from ..datasets import load_benchmark
from ..images import DEFAULT_SIZE
from ..methods import DEFAULT_METHOD, METHODS
from ..sources.live import is_live
from ._common import (
    UsageError,
    add_dataset_args,
    add_image_args,
    add_method_args,
    check_outputs,
    check_run_memory,
    dataset_kwargs,
    flag,
    image_options,
    parse_speed,
    print_protocol,
    split_params,
)
from ._live import LIVE_OPTIONS, add_live_args, add_view_args
from ._records import csv_cell
from .map import add_recording_args


def cmd_localize(args) -> int:
    if args.map is not None or args.source is not None:
        return _cmd_recording(args)
    if args.dataset is None:
        raise UsageError("give --map MAP SOURCE (a recording) or --dataset (a benchmark layout)")
    for option in (
        "render", "ground_truth", "topic", "every", "positions", "position_topic", "no_odometry",
        "no_breaks", "mcap_thumbnails", "view", "view_save", "calibration", "fit_calibration",
        "index",
        *LIVE_OPTIONS,
    ):  # fmt: skip
        if getattr(args, option):
            raise UsageError(f"{flag(option)} needs --map MAP SOURCE")
    if args.out is not None and args.out.suffix.lower() in (".jsonl", ".mcap"):
        raise UsageError(
            f"--out {args.out}: with --dataset the records are CSV; .jsonl and .mcap need "
            "--map MAP SOURCE"
        )
    if args.realtime:
        raise UsageError("--realtime needs --map MAP SOURCE")
    args.size = args.size or DEFAULT_SIZE
    args.method = args.method or DEFAULT_METHOD
    args.seed = 0 if args.seed is None else args.seed
    return _cmd_benchmark(args)


#: options of the --dataset benchmark that a recording localized against a map has no use for
_DATASET_ONLY = (
    "root", "reference", "query", "first", "count", "tolerance_m", "spacing", "positions_csv",
    "trust_pickle", "no_cache", "cache_dir",
)  # fmt: skip


def _check_truth_options(args) -> None:
    """--tolerance goes with --ground-truth frames, --radius with a --ground-truth CSV
    (``Frames`` in any case is the word, unless a file of that name exists)."""
    gt = args.ground_truth
    if isinstance(gt, str) and gt.lower() == "frames" and not Path(gt).exists():
        args.ground_truth = "frames"
    given = [o for o in ("tolerance", "radius") if getattr(args, o, None) is not None]
    if args.ground_truth is None and given:
        raise UsageError(f"{flag(given[0])}: only with --ground-truth (it scores the run)")
    if args.ground_truth == "frames" and args.radius is not None:
        raise UsageError(
            "--radius: for a --ground-truth CSV (metres); --ground-truth frames takes --tolerance"
        )
    if args.ground_truth not in (None, "frames") and args.tolerance is not None:
        raise UsageError(
            "--tolerance: for --ground-truth frames; a --ground-truth CSV takes --radius (metres)"
        )


def _cmd_recording(args) -> int:
    from ._stream import cmd_localize_recording

    if args.map is None or args.source is None:
        raise UsageError("a recording needs both --map MAP and SOURCE")
    if args.dataset is not None:
        raise UsageError("--dataset: give a benchmark layout or --map MAP SOURCE, not both")
    if args.odometry:
        raise UsageError(
            "--odometry: with --map, odometry comes from the recording's own positions "
            "(--positions or --position-topic) and is on by default; --no-odometry turns it off"
        )
    if args.speed is not None:
        raise UsageError(
            "--speed simulates a robot speed on a --dataset benchmark; with --map the "
            "recording is localized as it was driven (--every thins it)"
        )
    for option in ("method", "param", "seed"):
        if getattr(args, option) not in (None, []):
            raise UsageError(
                f"{flag(option)}: the map fixes the method and its seed; not with --map "
                "(build another map with `flyvpr map`)"
            )
    for option in _DATASET_ONLY:
        if getattr(args, option, None) not in (None, False):
            hint = (
                "; a recording's own positions are --positions CSV (timestamp,x,y or frame,x,y)"
                if option == "positions_csv"
                else "; --every thins the recording"
                if option in ("first", "count", "spacing")
                else ""
            )
            raise UsageError(f"{flag(option)}: a --dataset option, not for --map MAP SOURCE{hint}")
    _check_truth_options(args)
    if is_live(args.source):
        from ._live import cmd_localize_live

        return cmd_localize_live(args)
    for option in LIVE_OPTIONS:
        if getattr(args, option) is not None:
            raise UsageError(f"{flag(option)}: only for a live SOURCE (a stream URL or a camera)")
    args.source = Path(args.source)
    from ..large.recording import is_compact_map

    # by its first bytes; a damaged file named .fvmap (not a model file's zip either) is told
    # what a compact map needs rather than what a model file does
    path = Path(args.map)
    damaged = path.suffix.lower() == ".fvmap" and path.is_file() and not zipfile.is_zipfile(path)
    if is_compact_map(path) or damaged:
        from ._compact import cmd_localize_compact

        return cmd_localize_compact(args)
    if args.index is not None:
        raise UsageError(
            f"--index: only with a compact map (`flyvpr map --compact`); {args.map} is not one"
        )
    return cmd_localize_recording(args)


def _cmd_benchmark(args) -> int:
    from tqdm.auto import tqdm

    from ..evaluation import speed_profile
    from ..localization import LOCALIZED, Localizer

    if args.method not in METHODS:
        raise UsageError(f"--method: unknown method {args.method!r}")
    front_params, filt_params = split_params(args.method, args.param)
    bench = load_benchmark(args.dataset, **dataset_kwargs(args))
    if args.speed is not None:
        keep = speed_profile(bench.n_query, args.speed, random_state=args.seed)
        bench = bench.subset_queries(keep)
    else:
        keep = np.arange(bench.n_query)
    check_outputs(args, bench.input_files(), ("out",))
    check_run_memory(args, bench.n_reference, bench.n_query, score_rows=1)
    ref, qry = bench.load_images(size=args.size, **image_options(args))
    loc = Localizer(args.method, args.seed, front_params, filt_params).fit(ref)
    gt = bench.ground_truth
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(["frame", "source_frame", "place", "confidence", "state", "correct"])
    correct = n_localized = 0
    t0 = time.perf_counter()
    show = not args.quiet and sys.stderr.isatty()
    for i in tqdm(range(len(qry)), desc="localizing", unit="frame", disable=not show):
        velocity = None
        if args.odometry and i > 0:
            velocity = float(keep[i] - keep[i - 1])
        place, conf, state = loc.update(qry[i], velocity=velocity)
        ok = bool(gt[i, place])
        correct += ok
        n_localized += state == LOCALIZED
        writer.writerow([i, int(keep[i]), place, csv_cell(conf), state, int(ok)])
    elapsed = time.perf_counter() - t0
    if args.out is not None:
        write_text_atomic(args.out, buf.getvalue())
    print_protocol(bench.protocol(), args)
    print(
        f"{args.method}: {len(qry)} frames streamed, {correct / len(qry):.3f} correct "
        f"(best place within tolerance), localized {100 * n_localized / len(qry):.1f}% of "
        f"frames, {1000 * elapsed / len(qry):.3f} ms/frame"
    )
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0


def register(sub) -> None:
    """Add ``localize`` to the subcommand parsers ``sub``."""
    p = sub.add_parser(
        "localize",
        help="localize a recording, a camera or a stream frame by frame, one record per frame",
        description=(
            "With --map MAP SOURCE: stream a recording (image folder, video or ROS bag), a live "
            "stream or a camera through the map's localizer and write one record per frame "
            "(frame, timestamp, place, confidence, state, relocated, x, y when the map has "
            "positions, odometry when it drives the filter; latency_ms for a live source) as "
            "CSV, JSON Lines (.jsonl) or MCAP (.mcap); --view shows the run live in a "
            "browser; with --ground-truth it also scores itself. When the recording has "
            "positions and the map too, the distance moved between frames goes to the filter "
            "as odometry (path integration). With --dataset: fit METHOD on the benchmark's "
            "reference traverse, then feed its query frames one at a time to the streaming "
            "localizer and write frame, place, confidence, state and correctness to CSV."
        ),
    )
    p.add_argument(
        "source",
        nargs="?",
        metavar="SOURCE",
        help="with --map: a recording (image folder, video, ROS bag), a stream URL (rtsp://, "
        "http://, udp://, tcp:// ...) or a camera (/dev/video0)",
    )
    p.add_argument("--map", type=Path, help="map file written by `flyvpr map`")
    p.add_argument(
        "--index",
        choices=("exhaustive", "mih"),
        help="with a compact map (`flyvpr map --compact`): how a lost frame's code is looked "
        "up among the places: an exact scan of every code (default; about 10 ms per code at "
        "10 million places) or multi-index hashing (the map's .mih file when there is one, "
        "built at the start otherwise)",
    )
    add_recording_args(p)
    p.add_argument(
        "--realtime", action="store_true", help="pace frames to the recording's timestamps"
    )
    p.add_argument(
        "--render",
        type=Path,
        action="append",
        metavar="PATH",
        help="also write a trace to watch: .mp4/.mkv video or .html page (repeatable)",
    )
    p.add_argument(
        "--ground-truth",
        metavar="GT",
        help="score the run: 'frames' (query frame i shows the place of map frame i, within "
        "--tolerance frames) or a CSV of the query's positions (timestamp,x,y or frame,x,y; "
        "within --radius metres of a place's map position)",
    )
    p.add_argument(
        "--fit-calibration",
        type=Path,
        metavar="TABLE",
        help="with --ground-truth: fit a confidence table for this route from the run (each "
        "frame's confidence and whether its answer was right) and write it as JSON, so that "
        "later runs' confidences are the share of right answers (give it with --calibration)",
    )
    p.add_argument(
        "--calibration",
        type=Path,
        metavar="TABLE",
        help="map every frame's confidence through a table written by --fit-calibration on "
        "a labelled run of this route (places and states do not change); the map's method "
        "must have the CANN filter",
    )
    add_dataset_args(p, required=False)
    add_method_args(
        p, note=f" (with --dataset: an online filter; default {DEFAULT_METHOD})", seed_default=None
    )
    p.add_argument(
        "--speed",
        type=parse_speed,
        metavar="S",
        help="with --dataset: simulate another robot speed, keeping query frames at S places "
        "per frame (e.g. 2) or a seeded random profile LOW-HIGH (e.g. 1-1.5)",
    )
    p.add_argument(
        "--odometry",
        action="store_true",
        help="with --dataset: pass the true places moved per frame to the filter as velocity input",
    )
    p.add_argument(
        "--no-odometry",
        action="store_true",
        help="with --map: do not pass the distance moved between frames (from --positions or "
        "--position-topic) to the filter; it then estimates the movement from the images",
    )
    p.add_argument(
        "--no-breaks",
        action="store_true",
        help="with --map: read the map's places as one route even where their positions jump "
        "(by default the CANN does not carry the robot across a step between places more than "
        "5 times the usual step around it: a stretch of the route the map left out)",
    )
    p.add_argument(
        "--out",
        type=Path,
        help="records file to write (atomically; a live source's records are written as they "
        "are made, each line whole), the format by its suffix: .csv; with --map "
        "also .jsonl (JSON Lines) or .mcap (JSON messages with JSON schemas, for Foxglove and "
        "other MCAP tools); numbers are written exactly (every digit of a float64)",
    )
    p.add_argument(
        "--mcap-thumbnails",
        action="store_true",
        help="with --out X.mcap: also write each frame's query image and its matched place's "
        "thumbnail (PNG, foxglove.CompressedImage on /flyvpr/query and /flyvpr/match)",
    )
    add_live_args(p)
    add_view_args(p)
    add_image_args(p, size_default=None)
    p.set_defaults(func=cmd_localize)

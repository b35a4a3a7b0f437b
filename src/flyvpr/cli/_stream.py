"""``flyvpr localize --map MAP SOURCE``: localize a recording against a map, one record per frame.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import sys
import time
from contextlib import ExitStack

import numpy as np

from .._io import OutputPathError, check_output_path
from .._validation import check_memory
from ..images import IMAGE_EXTENSIONS
from ._calibrate import apply_table, check_calibration_args, fit_and_write
from ._common import UsageError, check_outputs, counted
from ._live import check_view_args, open_view, print_view_summary
from ._records import check_thumbnails, open_records
from .map import recording_inputs


def _ground_truth(args, m, step, gt_positions):
    """The batch's ground truth (n, n_places) and which of its frames have one (a frame the
    --ground-truth CSV gives no position is not scored: its true place is unknown, which is
    not the same as a frame off the map)."""
    from ..localization.tracking import ground_truth_frames, ground_truth_positions

    b = step.batch
    if args.ground_truth == "frames":
        gt = ground_truth_frames(b.indices, m.source_index, args.tolerance)
        return gt, np.ones(len(b), bool)
    if m.positions is None:
        raise UsageError("--ground-truth CSV needs a map built with positions")
    # between two rows of the CSV, the straight line (as the map's places and odometry read it)
    xy = gt_positions.at(b.indices, b.timestamps, interpolate=True)
    return ground_truth_positions(xy, m.positions, args.radius), np.isfinite(xy).all(axis=1)


def placed_frames(positions, b) -> int:
    """How many frames of batch ``b`` have a position in ``positions`` (as odometry reads
    them: interpolated between rows)."""
    xy = positions.at(b.indices, b.timestamps, interpolate=True)
    return int(np.isfinite(xy).all(axis=1).sum())


def refused_note(refused: int) -> None:
    """Print how many frames the filter localized without their odometry (a glitch), if any."""
    if refused:
        from ..temporal.cann import ODOMETRY_JUMP

        print(
            f"odometry: {counted(refused, 'frame')} refused the distance moved as a glitch "
            f"(more than {ODOMETRY_JUMP:g} times the recent distance per frame) and were "
            "localized without it"
        )


def print_run_notes(note, odometry: bool, coverage: tuple, refused: int, breaks) -> None:
    """The lines of a recording's summary after its first: the odometry's (``note``, and with
    path integration how many frames had a position: ``coverage``, the rest of
    :func:`coverage_note`'s arguments), the frames whose odometry was refused, and the
    ``breaks`` line (None: none)."""
    if note is not None:
        print(coverage_note(note, *coverage) if odometry else note)
    if odometry:
        refused_note(refused)
    if breaks is not None:
        print(breaks)


def coverage_note(note: str, positions, placed: int, n_frames: int, source: str) -> str:
    """The summary's odometry line once the run is over: how many frames had a position,
    and none at all said as such (positions of another recording, or on another clock)."""
    if placed == 0:
        return (
            f"odometry: none: no frame of {source} has a position in {positions.origin} (its "
            f"rows: {positions.describe_span()}), so nothing was integrated"
        )
    if placed < n_frames:
        return f"{note}; {placed} of {n_frames} frames have a position in it"
    return note


def left_out_words(n_unknown: int) -> str:
    """The scores line's note on frames the ground truth gives no position ('' for none)."""
    if not n_unknown:
        return ""
    return f" ({counted(n_unknown, 'frame')} without a ground-truth position left out)"


def odometry_note(
    args, positions, map_positions: bool, spacing, takes_it: bool = True, name: str = ""
) -> tuple[bool, str | None]:
    """Whether to integrate the recording's motion, and the summary's line about it.

    ``map_positions``: whether the map has positions; ``spacing``: its metres per place (None
    where they give none); ``takes_it``: whether the map's filter takes odometry (``name``:
    its method, for the line that says it does not).
    """
    if positions is None:
        return False, None
    if args.no_odometry:
        return False, "odometry: off (--no-odometry)"
    where = (
        f"--positions {args.positions}"
        if args.positions is not None
        else f"--position-topic {args.position_topic}"
    )
    if not map_positions:
        return False, (
            f"odometry: off, the map has no positions to turn the metres of {where} into places "
            "(build it with --positions or --position-topic)"
        )
    if spacing is None:
        return False, "odometry: off, the map's positions give no spacing between places"
    if not takes_it:
        return False, f"odometry: off, {name} has no filter that takes it"
    return True, f"odometry: path integration from {where} (map spacing {spacing:.3g} m per place)"


def breaks_note(loc) -> str | None:
    """The summary's line about the breaks of the map's route the filter was given (None where
    it has none to say: no breaks, or a filter that takes none)."""
    filt = loc.method.filter
    if filt is None or "breaks" not in filt.get_params():
        return None
    given = np.asarray(filt.get_params()["breaks"]).ravel()
    built = loc.map_.method.filter.get_params().get("breaks", ())
    return breaks_words(given, loc.map_.breaks, np.size(built))


def compact_breaks_note(loc, cmap) -> str | None:
    """:func:`breaks_note` for a compact map's localizer (``flyvpr.large.LargeLocalizer``)."""
    return breaks_words(loc.filter_.breaks_, cmap.breaks)


def breaks_words(given, found, built: int = 0) -> str | None:
    """The line about the breaks the filter was ``given`` (places), against those the map's
    positions give (``found``) and the number the map's filter was built with (``built``);
    None where there is nothing to say."""
    given = tuple(int(b) for b in given)
    if not given:  # (--no-breaks: what the filter would have had otherwise)
        dropped = built or len(found)
        if dropped:
            return f"breaks: off (--no-breaks): {counted(dropped, 'break')} of the map ignored"
        return None
    pairs = ", ".join(f"{b - 1}-{b}" for b in given[:5]) + (", ..." if len(given) > 5 else "")
    where = "where its positions jump" if given == tuple(found) else "as the map's filter was built"
    return (
        f"breaks: the map's route is broken at {counted(len(given), 'place')} (between places "
        f"{pairs}), {where}: the filter does not carry the robot across (--no-breaks: one "
        "route)"
    )


def cmd_localize_recording(args) -> int:
    from tqdm.auto import tqdm

    from ..localization import LOCALIZED, Localizer
    from ..localization.tracking import track
    from ..sources import RecordingError, open_source, read_positions

    if args.ground_truth is not None and args.ground_truth != "frames" and args.radius is None:
        raise UsageError("--ground-truth CSV needs --radius (metres)")
    if args.ground_truth == "frames" and args.tolerance is None:
        raise UsageError("--ground-truth frames needs --tolerance (frames)")
    check_calibration_args(args)
    check_thumbnails(args)
    renders = args.render or []
    for path in renders:
        if path.suffix.lower() not in (".mp4", ".mkv", ".html", ".htm"):
            raise UsageError(f"--render {path}: expected a .mp4, .mkv or .html file")
    inputs = recording_inputs(args) + [args.map]
    if args.ground_truth not in (None, "frames"):
        inputs.append(args.ground_truth)
    if args.calibration is not None:
        inputs.append(args.calibration)
    check_outputs(args, inputs, ("out", "fit_calibration"))
    taken = [p for p in (args.out, args.fit_calibration) if p is not None]
    if len(taken) == 2 and taken[0].resolve() == taken[1].resolve():
        raise UsageError(f"--fit-calibration {args.fit_calibration}: already an output of this run")
    for path in renders:
        if any(path.resolve() == t.resolve() for t in taken):
            raise UsageError(f"--render {path}: already an output of this run")
        try:
            check_output_path(
                path, inputs + taken, what="--render", image_extensions=IMAGE_EXTENSIONS
            )
        except OutputPathError as exc:
            raise UsageError(str(exc)) from None
        taken.append(path)
    check_view_args(args, inputs)
    loc = Localizer.from_map(args.map, size=args.size, breaks=() if args.no_breaks else None)
    if args.calibration is not None:
        apply_table(loc, args.calibration)
    m = loc.map_
    source = open_source(args.source, topic=args.topic)
    bag = source.path if source.kind == "bag" else None
    positions = read_positions(args.positions, bag=bag, topic=args.position_topic)
    gt_positions = None
    if args.ground_truth not in (None, "frames"):
        gt_positions = read_positions(args.ground_truth)
    odometry, note = odometry_note(
        args, positions, m.has_positions, loc.place_spacing, loc.uses_odometry, m.method.name
    )
    columns = ["frame", "timestamp", "place", "confidence", "state", "relocated"]
    if m.has_positions:
        columns += ["x", "y"]
    if odometry:
        columns.append("odometry")
    if args.ground_truth is not None:
        columns.append("correct")
    show = not args.quiet and sys.stderr.isatty()
    confidences, scores, truth, correct, scored = [], [], [], [], []
    n_frames = n_reloc = n_localized = n_unknown = placed = 0
    timed = False  # whether a frame had a timestamp (--realtime paces only those)
    t0 = time.perf_counter()
    with ExitStack() as stack:
        out = None
        if args.out is not None:
            if args.realtime:
                args.records_kept = args.out  # whatever ends the run (see cli.main)
            out = stack.enter_context(
                open_records(
                    args.out,
                    columns,
                    # replayed as if live: an interrupted run keeps the frames it localized
                    keep_partial=args.realtime,
                    thumbnails=args.mcap_thumbnails,
                    metadata=run_metadata(args, m.method.name, m.n_places, source),
                )
            )
        tracers = [stack.enter_context(_tracer(path, m)) for path in renders]
        view = open_view(args, m, background=False)
        if view is not None:
            stack.callback(view.close)
        bar = stack.enter_context(tqdm(desc="localizing", unit="frame", disable=not show))
        for step in track(loc, source, every=args.every, positions=positions,
                          odometry=odometry, realtime=args.realtime):  # fmt: skip
            b = step.batch
            timed = timed or bool(np.isfinite(b.timestamps).any())
            if odometry:
                placed += placed_frames(positions, b)
            gt = known = None
            if args.ground_truth is not None:
                gt, known = _ground_truth(args, m, step, gt_positions)
                # the score rows and ground truth kept for the metrics: 5 bytes per place and frame
                check_memory(len(b) * m.n_places * 5, "scoring against --ground-truth")
                scores.append(step.scores[known].astype(np.float32))
                truth.append(gt[known])
                scored.append(step.confidences[known].astype(np.float32))
                n_unknown += int((~known).sum())
            for tr in tracers:
                tr.add(step)
            for i in range(len(b)):
                row = {
                    "frame": int(b.indices[i]),
                    "timestamp": float(b.timestamps[i]),
                    "place": int(step.places[i]),
                    "confidence": float(step.confidences[i]),
                    "state": str(step.states[i]),
                    "relocated": int(step.relocated[i]),
                }
                if step.positions is not None:  # the map's positions, where it has them
                    row["x"], row["y"] = (float(v) for v in step.positions[i])
                if step.odometry is not None:  # places moved, as the filter was given them
                    row["odometry"] = float(step.odometry[i])
                if gt is not None and known is not None:
                    row["correct"] = int(gt[i, step.places[i]]) if known[i] else None
                    if known[i]:
                        correct.append(bool(row["correct"]))
                if out is not None:
                    images = None
                    if args.mcap_thumbnails:
                        images = {"query": np.rint(b.images[i] * 255.0).astype(np.uint8)}
                        if m.thumbnails is not None:
                            images["match"] = m.thumbnails[step.places[i]]
                    out.write(row, images)
                if view is not None:
                    view.log(
                        row["frame"], row["timestamp"], b.images[i], row["place"],
                        row["confidence"], row["state"], step.scores[i],
                        model_input=b.images[i], relocated=bool(row["relocated"]),
                    )  # fmt: skip
            confidences.append(step.confidences.astype(np.float32))
            n_frames += len(b)
            n_reloc += int(step.relocated.sum())
            n_localized += int((step.states == LOCALIZED).sum())
            bar.update(len(b))
        if n_frames == 0:  # inside the with: no output file is left behind
            raise RecordingError(f"{source.describe()}: --every {args.every} keeps no frame")
    elapsed = time.perf_counter() - t0
    conf = np.concatenate(confidences)
    print(
        f"{m.method.name}: {counted(n_frames, 'frame')} of {source.describe()} (every "
        f"{args.every or 1}) against {m.n_places} places: {n_frames / elapsed:.1f} frames/s, "
        f"median confidence {float(np.median(conf)):.4g}, localized "
        f"{100 * n_localized / n_frames:.1f}% of frames, {counted(n_reloc, 'relocation')}"
    )
    print_run_notes(
        note,
        odometry,
        (positions, placed, n_frames, source.describe()),
        getattr(loc.method.filter, "n_odometry_refused_", 0),
        breaks_note(loc),
    )
    if args.realtime and not timed:
        print(
            f"--realtime: {source.describe()} has no timestamps (an image folder has none; "
            "videos and ROS bags have them), so the frames were not paced"
        )
    if args.ground_truth is not None:
        _print_scores(args, np.concatenate(scores), np.concatenate(truth), n_unknown)
    if args.fit_calibration is not None:
        fitted_on = {
            "map": str(args.map),
            "method": m.method.name,
            "source": source.describe(),
            "ground_truth": _rule(args),
        }
        scored_conf = np.concatenate(scored)  # the frames with a ground truth
        print(fit_and_write(args.fit_calibration, scored_conf, np.array(correct), fitted_on))
    if args.calibration is not None:
        print(f"confidence through the table of --calibration {args.calibration}")
    print_view_summary(view)
    for path in [args.out, args.fit_calibration, *renders, args.view_save]:
        if path is not None:
            print(f"wrote {path}")
    return 0


def run_metadata(args, method: str, n_places: int, source) -> dict:
    """What an MCAP records file says about its run (strings)."""
    return {
        "map": str(args.map),
        "method": method,
        "n_places": str(n_places),
        "source": source.describe(),
        "every": str(args.every or 1),
    }


def _tracer(path, m):
    from ..localization.trace import open_trace

    return open_trace(path, m)


def _rule(args) -> str:
    """What --ground-truth counts as right, in words."""
    if args.ground_truth == "frames":
        return f"frames within {args.tolerance}"
    return f"{args.ground_truth} within {args.radius:g} m"


def _print_scores(args, S, gt, n_unknown: int = 0) -> None:
    from ..metrics import evaluate

    if not gt.any():
        raise ValueError(f"--ground-truth {args.ground_truth}: no frame has a true place")
    r = evaluate(S, gt)
    rule = _rule(args)
    print(
        f"ground truth ({rule}): AUC {r['auc']:.4f}, R@1 {r['recall_at_1']:.4f}, "
        f"R@5 {r['recall_at_5']:.4f}, R@100%P {r['recall_at_100_precision']:.4f} "
        f"over {r['n_query']} frames" + left_out_words(n_unknown)
    )

"""``flyvpr map --compact`` and ``flyvpr localize --map MAP.fvmap``: maps of compact codes.

A compact map keeps 32 bytes per place (256 bits; :mod:`flyvpr.large.recording`), memory-
mapped, and is localized against by :class:`flyvpr.large.LargeLocalizer`: a window of the
CANN around the packet and an index to relocate, so a frame's cost does not grow with the map.

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time

import numpy as np

from ._common import UsageError, check_outputs, counted, flag, positions_words
from ._records import open_records
from ._stream import (
    compact_breaks_note,
    left_out_words,
    odometry_note,
    placed_frames,
    print_run_notes,
    run_metadata,
)
from .map import recording_inputs

#: ``flyvpr localize`` options a compact map does not take (what they need: score rows over
#: every place, thumbnails, the CANN's calibration hooks)
_NOT_COMPACT = (
    "render",
    "view",
    "view_save",
    "mcap_thumbnails",
    "calibration",
    "fit_calibration",
    "realtime",
)


def compact_method_name(cmap) -> str:
    """What a compact map localizes with, in words (records' metadata, summaries)."""
    return f"compact {cmap.large_map.n_bits}-bit codes + windowed CANN"


def cmd_map_compact(args) -> int:
    """``flyvpr map --compact``."""
    from ..large.recording import FIT_FRAMES, build_compact_map, index_path

    if args.fit_frames is not None and args.fit_frames < 2:
        raise UsageError(f"--fit-frames: must be >= 2; got {args.fit_frames}")
    for option in ("method", "param"):
        if getattr(args, option):
            raise UsageError(
                f"{flag(option)}: a compact map has its own encoder (kenyon's optic lobe and "
                "--bits signs); not with --compact"
            )
    if args.positions is not None and args.position_topic is not None:
        raise UsageError("--positions and --position-topic: give one of them")
    if args.jobs is not None and (args.jobs == 0 or args.jobs < -1):
        raise UsageError(f"--jobs: must be >= 1 or -1 (all cores); got {args.jobs}")
    check_outputs(args, recording_inputs(args), ("out",))
    if args.mih:
        sidecar = index_path(args.out)
        if sidecar.resolve() in {p.resolve() for p in recording_inputs(args)}:
            raise UsageError(f"--mih writes {sidecar}, which is an input of this run")
    from ..images import DEFAULT_SIZE
    from ..large.codes import CompactEncoder

    bits, size = args.bits or 256, tuple(args.size or DEFAULT_SIZE)
    encoder = CompactEncoder(n_bits=bits)
    pool = encoder.pool_size
    if size[0] % pool or size[1] % pool:
        raise UsageError(
            f"--size {size[0]}x{size[1]}: a compact map needs both sides multiples of {pool} "
            "(the optic lobe's pooling cells)"
        )
    most = encoder.max_bits(size)
    if most is not None and bits > most:
        fits = most // 64 * 64  # (--bits is a multiple of 64)
        advice = f"give --bits {fits} or fewer" if fits else "a compact map needs at least 64"
        raise UsageError(
            f"--bits {bits}: a compact map at --size {size[0]}x{size[1]} has at most {most} "
            f"bits (one per optic-lobe feature); {advice}, or a larger --size"
        )
    t0 = time.perf_counter()
    cmap = build_compact_map(
        args.source,
        args.out,
        n_bits=args.bits or 256,
        size=args.size,
        topic=args.topic,
        every=args.every,
        positions=args.positions,
        position_topic=args.position_topic,
        random_state=args.seed,
        fit_frames=args.fit_frames or FIT_FRAMES,
        index="mih" if args.mih else None,
        progress=not args.quiet and sys.stderr.isatty(),
        n_jobs=args.jobs,
        scheduler=args.scheduler,
    )
    where = positions_words(cmap.positions, cmap.info["positions_from"])
    if cmap.place_spacing is not None:
        where += f", {cmap.place_spacing:.3g} m per place"
    print(
        f"compact map of {cmap.n_places} places ({cmap.large_map.n_bits} bits, "
        f"{cmap.large_map.codes.nbytes / 2**20:.3g} MiB of codes) from {cmap.info['source_kind']} "
        f"{args.source} (every {cmap.info['every']}, {where}, size {args.size[0]}x"
        f"{args.size[1]}, encoder fitted on {cmap.info['fit_frames']} frames, seed {args.seed}) "
        f"in {time.perf_counter() - t0:.2f} s"
    )
    print(f"wrote {args.out}")
    if args.mih:
        print(f"wrote {index_path(args.out)}")
    return 0


def _truth(args, cmap, b, gt_positions, lookup):
    """(whether each frame's answer can be right at all, a function of the answers, which
    frames have a ground truth: the --ground-truth CSV may give a frame no position, and such
    a frame is not scored); ``lookup``: the map's frame numbers sorted, or a KD-tree of its
    positions."""
    if args.ground_truth == "frames":
        frames = lookup
        lo = np.searchsorted(frames, b.indices - args.tolerance, side="left")
        hi = np.searchsorted(frames, b.indices + args.tolerance, side="right")
        return (
            hi > lo,
            lambda places: np.abs(cmap.frames[places] - b.indices) <= args.tolerance,
            np.ones(len(b), bool),
        )
    xy = gt_positions.at(b.indices, b.timestamps, interpolate=True)  # (as the map's places)
    known = np.isfinite(xy).all(axis=1)
    near = np.zeros(len(b), bool)
    # distances as ground_truth_from_positions takes them, sqrt(sum((q - r) ** 2)), so that
    # both maps judge a frame at the radius alike (hypot differs from it in the last bit)
    if known.any():
        distance, _ = lookup.query(xy[known], k=1)  # (the tree's is sqrt(sum((q - r) ** 2)))
        near[known] = distance <= args.radius

    def right(places):
        d = np.sqrt(((cmap.positions[places] - xy) ** 2).sum(axis=1))
        return np.isfinite(d) & (d <= args.radius)

    return near, right, known


def cmd_localize_compact(args) -> int:
    """``flyvpr localize --map MAP SOURCE`` with a compact map."""
    from tqdm.auto import tqdm

    from ..large.recording import compact_localizer, open_compact_map
    from ..localization.tracking import distances_moved
    from ..metrics import evaluate_answers
    from ..sources import RecordingError, open_source, read_positions

    for option in _NOT_COMPACT:
        if getattr(args, option):
            raise UsageError(
                f"{flag(option)}: not with a compact map ({args.map}); build the map without "
                "--compact for it"
            )
    if args.size is not None:
        raise UsageError("--size: a compact map fixes the image size (its encoder's)")
    if args.ground_truth not in (None, "frames") and args.radius is None:
        raise UsageError("--ground-truth CSV needs --radius (metres)")
    if args.ground_truth == "frames" and args.tolerance is None:
        raise UsageError("--ground-truth frames needs --tolerance (frames)")
    inputs = recording_inputs(args) + [args.map]
    if args.ground_truth not in (None, "frames"):
        inputs.append(args.ground_truth)
    check_outputs(args, inputs, ("out",))
    t_open = time.perf_counter()
    cmap = open_compact_map(args.map)
    loc = compact_localizer(
        cmap, index=args.index or "exhaustive", breaks=() if args.no_breaks else None
    )
    open_s = time.perf_counter() - t_open
    source = open_source(args.source, topic=args.topic)
    bag = source.path if source.kind == "bag" else None
    positions = read_positions(args.positions, bag=bag, topic=args.position_topic)
    gt_positions = lookup = None
    if args.ground_truth == "frames":
        lookup = np.sort(cmap.frames)
    elif args.ground_truth is not None:
        from scipy.spatial import cKDTree

        if cmap.positions is None:
            raise UsageError("--ground-truth CSV needs a map built with positions")
        gt_positions = read_positions(args.ground_truth)
        known = np.isfinite(cmap.positions).all(axis=1)
        lookup = cKDTree(np.asarray(cmap.positions)[known])
    spacing = cmap.place_spacing
    odometry, note = odometry_note(args, positions, cmap.positions is not None, spacing)
    columns = ["frame", "timestamp", "place", "confidence", "state", "relocated"]
    if cmap.positions is not None:
        columns += ["x", "y"]
    if odometry:
        columns.append("odometry")
    if args.ground_truth is not None:
        columns.append("correct")
    show = not args.quiet and sys.stderr.isatty()
    confidences, rights, matchable, scored = [], [], [], []
    n_frames = n_localized = n_unknown = placed = 0
    last_xy = np.full((1, 2), np.nan)
    metadata = run_metadata(args, compact_method_name(cmap), cmap.n_places, source)
    t0 = time.perf_counter()
    records = (
        open_records(args.out, columns, metadata=metadata)
        if args.out is not None
        else contextlib.nullcontext()
    )
    with records as out, tqdm(desc="localizing", unit="frame", disable=not show) as bar:
        for b in source.batches(cmap.size, every=args.every, positions=positions):
            velocity: list = [None] * len(b)
            if odometry and positions is not None and spacing is not None:
                placed += placed_frames(positions, b)
                moved, last_xy = distances_moved(positions, b, last_xy)
                velocity = [float(d) if np.isfinite(d) else None for d in moved / spacing]
            fixes = loc.update_batch(b.images, velocities=velocity)
            places, conf, states = fixes.places, fixes.confidences, fixes.states.tolist()
            relocated = fixes.relocated.astype(int).tolist()
            right = known = None
            if args.ground_truth is not None:
                can, judge, known = _truth(args, cmap, b, gt_positions, lookup)
                right = judge(places)
                rights.append(right[known])
                matchable.append(can[known])
                scored.append(conf[known])
                n_unknown += int((~known).sum())
            for i in range(len(b)):
                row = {
                    "frame": int(b.indices[i]),
                    "timestamp": float(b.timestamps[i]),
                    "place": int(places[i]),
                    "confidence": float(conf[i]),
                    "state": states[i],
                    "relocated": relocated[i],
                }
                if cmap.positions is not None:
                    row["x"], row["y"] = (float(v) for v in cmap.positions[places[i]])
                if odometry:  # places moved, as the filter was given them
                    row["odometry"] = math.nan if velocity[i] is None else velocity[i]
                if right is not None:
                    row["correct"] = int(right[i]) if known[i] else None
                if out is not None:
                    out.write(row)
            confidences.append(conf)
            n_frames += len(b)
            n_localized += sum(s == "localized" for s in states)
            bar.update(len(b))
        if n_frames == 0:  # inside the with: no output file is left behind
            raise RecordingError(f"{source.describe()}: --every {args.every} keeps no frame")
    elapsed = time.perf_counter() - t0
    index = loc.index_source_
    print(
        f"compact map ({cmap.n_places} places, {cmap.large_map.n_bits} bits, ready in "
        f"{open_s:.3f} s, relocation by {index}): {counted(n_frames, 'frame')} of "
        f"{source.describe()} "
        f"(every {args.every or 1}): {n_frames / elapsed:.1f} frames/s, median confidence "
        f"{float(np.median(np.concatenate(confidences))):.4g}, localized "
        f"{100 * n_localized / n_frames:.1f}% of frames, {counted(loc.n_reseeds_, 're-seed')}, "
        f"{counted(loc.n_searches_, 'code')} searched"
    )
    print_run_notes(
        note,
        odometry,
        (positions, placed, n_frames, source.describe()),
        loc.n_odometry_refused_,
        compact_breaks_note(loc, cmap),
    )
    if args.ground_truth is not None:
        can = np.concatenate(matchable)
        if not can.any():
            raise ValueError(f"--ground-truth {args.ground_truth}: no frame has a true place")
        r = evaluate_answers(np.concatenate(scored), np.concatenate(rights), can)
        rule = (
            f"frames within {args.tolerance}"
            if args.ground_truth == "frames"
            else f"{args.ground_truth} within {args.radius:g} m"
        )
        print(
            f"ground truth ({rule}): AUC {r['auc']:.4f}, R@1 {r['recall_at_1']:.4f}, "
            f"R@100%P {r['recall_at_100_precision']:.4f} over {r['n_query']} frames"
            + left_out_words(n_unknown)
        )
    if args.out is not None:
        print(f"wrote {args.out}")
    return 0

"""``flyvpr map``: build a reference map from a recording (image folder, video or ROS bag)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from ..images import DEFAULT_SIZE
from ..methods import DEFAULT_METHOD, METHODS
from ._common import (
    UsageError,
    add_method_args,
    check_outputs,
    flag,
    parse_size,
    positions_words,
    split_params,
)

__all__ = ["register", "add_recording_args", "recording_inputs"]


def parse_every_arg(text: str):
    from ..sources.base import parse_every

    try:
        return parse_every(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("every: ")) from None


def add_recording_args(p, positions: bool = True) -> None:
    """SOURCE's options: --topic, --every and (for maps) where positions come from."""
    g = p.add_argument_group("recording")
    g.add_argument("--topic", help="image topic of a ROS bag (default: its only image topic)")
    g.add_argument(
        "--every",
        type=parse_every_arg,
        metavar="E",
        help="keep every E-th frame (3), one frame per E seconds (0.5s) or per E metres (2m, "
        "needs positions); default every frame",
    )
    if positions:
        g.add_argument(
            "--positions",
            type=Path,
            metavar="CSV",
            help="frame positions: CSV with header timestamp,x,y or frame,x,y (metres)",
        )
        g.add_argument(
            "--position-topic",
            metavar="T",
            help="frame positions from a sensor_msgs/NavSatFix or nav_msgs/Odometry topic of "
            "the same bag (interpolated between messages by timestamp)",
        )


def recording_inputs(args) -> list:
    """Input paths of a recording command (outputs must differ from them)."""
    return [p for p in (args.source, getattr(args, "positions", None)) if p is not None]


def cmd_map(args) -> int:
    from ..localization.maps import Map

    if args.compact:
        from ._compact import cmd_map_compact

        return cmd_map_compact(args)
    for option in ("bits", "fit_frames", "mih"):
        if getattr(args, option):
            raise UsageError(f"{flag(option)} needs --compact")
    args.method = args.method or DEFAULT_METHOD
    if args.method not in METHODS:
        raise UsageError(f"--method: unknown method {args.method!r}")
    if args.positions is not None and args.position_topic is not None:
        raise UsageError("--positions and --position-topic: give one of them")
    if args.jobs is not None and (args.jobs == 0 or args.jobs < -1):
        raise UsageError(f"--jobs: must be >= 1 or -1 (all cores); got {args.jobs}")
    front_params, filt_params = split_params(args.method, args.param)
    check_outputs(args, recording_inputs(args), ("out",))
    t0 = time.perf_counter()
    m = Map.build(
        args.source,
        args.method,
        size=args.size,
        topic=args.topic,
        every=args.every,
        positions=args.positions,
        position_topic=args.position_topic,
        random_state=args.seed,
        frontend_params=front_params,
        filter_params=filt_params,
        progress=not args.quiet and sys.stderr.isatty(),
        n_jobs=args.jobs,
        scheduler=args.scheduler,
    )
    m.save(args.out)
    where = positions_words(m.positions, m.info["positions_from"])
    if m.place_spacing is not None:
        where += f", {m.place_spacing:.3g} m per place"
    print(
        f"{args.method}: map of {m.n_places} places from {m.info['source_kind']} {args.source} "
        f"(every {m.info['every']}, {where}, size {args.size[0]}x{args.size[1]}, "
        f"seed {args.seed}) in {time.perf_counter() - t0:.2f} s"
    )
    print(f"wrote {args.out}")
    return 0


def register(sub) -> None:
    """Add ``map`` to the subcommand parsers ``sub``."""
    p = sub.add_parser(
        "map",
        help="build a reference map from a recording (image folder, video file or ROS bag)",
        description=(
            "Fit METHOD on the frames of SOURCE (the reference traverse) and save it with each "
            "place's timestamp, frame index, position (when given) and a thumbnail, for "
            "`flyvpr localize --map`."
        ),
    )
    p.add_argument("source", type=Path, metavar="SOURCE", help="image folder, video or ROS bag")
    p.add_argument("--out", type=Path, required=True, help="map file to write (atomically)")
    add_method_args(p, note=f" (default {DEFAULT_METHOD})")
    add_recording_args(p)
    p.add_argument(
        "--size",
        type=parse_size,
        default=DEFAULT_SIZE,
        metavar="HxW",
        help="image size after the gray conversion and area-averaging resize (default 32x64)",
    )
    g = p.add_argument_group(
        "parallel encoding",
        "Frames are read here; the per-frame encoding goes to the workers in chunks. The map "
        "is the same, byte for byte, as without these options.",
    )
    where = g.add_mutually_exclusive_group()
    where.add_argument(
        "--jobs",
        "-j",
        type=int,
        metavar="N",
        help="encode on N local processes (-1: all cores; default: this process only)",
    )
    where.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="encode on a Dask cluster: its scheduler's address, e.g. tcp://host:8786 "
        "(pip install 'flyvpr[dask]')",
    )
    c = p.add_argument_group(
        "compact map (millions of places)",
        "With --compact the map keeps a 32-byte code per place (256 bits: signs of the kenyon "
        "optic lobe's principal directions; with each place's frame number and timestamp, 48 "
        "bytes a place, 64 with positions), memory-mapped, instead of a fitted METHOD; `flyvpr "
        "localize --map` then tracks a window of the CANN around the robot and relocates "
        "through an index, so a frame's cost does not grow with the map (see the large-maps "
        "guide). The recording is read twice: once to fit the encoder on a sample, once to "
        "encode every frame.",
    )
    c.add_argument(
        "--compact", action="store_true", help="write a compact map (conventionally MAP.fvmap)"
    )
    c.add_argument(
        "--bits",
        type=int,
        choices=(64, 128, 192, 256, 320, 384, 448, 512),
        metavar="B",
        help="bits per place, a multiple of 64 up to 512 (default 256)",
    )
    c.add_argument(
        "--fit-frames",
        type=int,
        metavar="N",
        help=(
            "fit the encoder on at most N frames, evenly spaced: every k-th frame, k the "
            "least power of 2 that keeps N or fewer (read in one pass: between N/2 and N "
            "frames of a long recording; default 10000)"
        ),
    )
    c.add_argument(
        "--mih",
        action="store_true",
        help="also write multi-index hash tables beside the map (MAP with the suffix .mih) "
        "for `flyvpr localize --index mih`",
    )
    p.add_argument(
        "--quiet", "-q", action="store_true", help="no progress bar (shown only on a terminal)"
    )
    p.set_defaults(func=cmd_map)

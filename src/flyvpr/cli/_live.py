"""``flyvpr localize --map MAP URL|/dev/videoN``: localize a live stream or camera, and the
live view (``--view``, ``--view-save``) of any ``localize --map`` run.

The localizer takes the newest frame of the stream whenever it is ready (frames it had no time
for are dropped and counted), writes each record as soon as it is made (flushed: ``tail -f``
follows), and runs until the stream ends, the user presses Ctrl-C (exit 130, every processed
frame written) or the stream stalls past its retries (exit 1, records kept).

Nothing outside :mod:`flyvpr.cli` imports this module.
"""

from __future__ import annotations

import math
import signal
import sys
import threading
import time
from contextlib import ExitStack, contextmanager
from pathlib import Path

import numpy as np

from ._calibrate import apply_table
from ._common import (
    UsageError,
    check_outputs,
    counted,
    flag,
    nonnegative_int,
    positive_float,
    positive_int,
)

#: live runs: the latency histogram's bin (ms) and its last bin (everything slower lands there)
_LATENCY_BIN_MS = 0.01
_LATENCY_BINS = 200_000  # up to 2 s in 0.01 ms bins: 1.6 MB whatever the run's length
#: the options of a live SOURCE (None when not given), and their defaults
LIVE_OPTIONS = ("stream_option", "stall_timeout", "retries", "open_timeout")
_DEFAULTS = {"stall_timeout": 5.0, "retries": 3, "open_timeout": 10.0}


def _stream_option(text: str) -> tuple[str, str]:
    import argparse

    if "=" not in text or not text.split("=", 1)[0].strip():
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE (an FFmpeg option); got {text!r}")
    key, value = text.split("=", 1)
    if not value:  # e.g. a shell variable that was not set
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE with a value; got {text!r}")
    return key.strip(), value


def _stream_options(pairs) -> dict[str, str]:
    """The ``--stream-option`` pairs as a dict; a key given twice is refused (which value the
    user meant is not for flyvpr to guess)."""
    options: dict[str, str] = {}
    for key, value in pairs or []:
        if key in options:
            raise UsageError(
                f"--stream-option {key}: given twice ({options[key]!r} and {value!r}); give it once"
            )
        options[key] = value
    return options


def add_live_args(p) -> None:
    """The options of a live SOURCE (a URL or a camera device)."""
    g = p.add_argument_group(
        "live sources",
        "SOURCE may be a stream URL (rtsp://, http(s):// MJPEG or any stream FFmpeg reads, "
        "udp://, tcp://, rtmp://, srt://) or a V4L2 camera (/dev/video0). The localizer takes "
        "the newest frame whenever it is ready and counts the frames it drops; each record "
        "is flushed as it is written; Ctrl-C ends the run (exit 130, every processed frame "
        "written).",
    )
    g.add_argument(
        "--stream-option",
        type=_stream_option,
        action="append",
        metavar="KEY=VALUE",
        help="FFmpeg option of the stream or camera, repeatable: rtsp_transport=tcp, "
        "video_size=640x480, framerate=30, input_format=mjpeg, ...",
    )
    g.add_argument(
        "--stall-timeout",
        type=positive_float,
        metavar="S",
        help="seconds without a frame after which the stream counts as stalled and is "
        "reopened (default 5)",
    )
    g.add_argument(
        "--retries",
        type=nonnegative_int,
        metavar="N",
        help="reopenings of a stalled stream in a row before the run ends with exit 1 (default 3)",
    )
    g.add_argument(
        "--open-timeout",
        type=positive_float,
        metavar="S",
        help="seconds to wait for the stream to answer when it is opened (default 10)",
    )


def add_view_args(p) -> None:
    """``--view``, ``--view-save`` and the viewer's ports (needs the ``view`` extra)."""
    from ..view import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT

    g = p.add_argument_group(
        "live view (with --map; needs pip install 'flyvpr[view]')",
        "Log each frame to the Rerun viewer: the query frame, the matched place's image, the "
        "filter's activity over the places, place / confidence / state over time and the "
        "position on the route when the map has positions.",
    )
    g.add_argument(
        "--view",
        action="store_true",
        help=f"serve the viewer while the run lasts: open http://localhost:{DEFAULT_WEB_PORT} "
        "(the exact address is printed; from another machine use this one's address)",
    )
    g.add_argument(
        "--view-save",
        type=Path,
        metavar="TRACE.rrd",
        help="also write what the viewer shows to a Rerun recording (.rrd) to watch later "
        "with `rerun TRACE.rrd`",
    )
    g.add_argument(
        "--view-port",
        type=positive_int,
        default=DEFAULT_WEB_PORT,
        metavar="PORT",
        help=f"port of the viewer's web page (default {DEFAULT_WEB_PORT})",
    )
    g.add_argument(
        "--view-data-port",
        type=positive_int,
        default=DEFAULT_GRPC_PORT,
        metavar="PORT",
        help=f"port the viewer reads the data from (gRPC; default {DEFAULT_GRPC_PORT})",
    )


def check_view_args(args, inputs) -> None:
    """Usage errors of the view options (before any work)."""
    if args.view_save is not None:
        if args.view_save.suffix.lower() != ".rrd":
            raise UsageError(f"--view-save {args.view_save}: expected a .rrd file")
        if args.out is not None and args.view_save.resolve() == Path(args.out).resolve():
            raise UsageError(f"--view-save {args.view_save}: already the --out of this run")
        check_outputs(args, inputs, ("view_save",))
    from ..view import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT

    defaults = {"view_port": DEFAULT_WEB_PORT, "view_data_port": DEFAULT_GRPC_PORT}
    given = [o for o in defaults if getattr(args, o) != defaults[o]]
    if given and not args.view:
        raise UsageError(f"--{given[0].replace('_', '-')}: only with --view")
    if args.view and args.view_port == args.view_data_port:
        raise UsageError(
            f"--view-port and --view-data-port: two ports are needed; both are {args.view_port}"
        )
    if args.view:
        for option in ("view_port", "view_data_port"):
            port = getattr(args, option)
            if port > 65535:
                raise UsageError(f"--{option.replace('_', '-')} {port}: a port is 1-65535")
            if not _port_free(port):
                raise UsageError(
                    f"--{option.replace('_', '-')} {port}: already in use by another program; "
                    "pick another port"
                )


def _port_free(port: int) -> bool:
    """Whether a TCP server could listen on ``port`` on every interface now (as the viewer's
    servers do), checked before any work so that a busy port fails the run at its start."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            probe.bind(("0.0.0.0", port))
        except OSError:
            return False
    return True


def open_view(args, m, *, background: bool):
    """The :class:`flyvpr.view.LiveView` the options ask for (None without --view/--view-save);
    prints the address to open.  ``background``: log on the view's own thread, skipping frames
    rather than slowing the run (live sources); otherwise every frame is logged."""
    if not args.view and args.view_save is None:
        return None
    from ..view import LiveView

    view = LiveView(
        m,
        serve=args.view,
        save=args.view_save,
        web_port=args.view_port,
        grpc_port=args.view_data_port,
        background=background,
    )
    if view.url is not None:
        print(f"live view: open {view.url}", flush=True)
    return view


def print_view_summary(view) -> None:
    """One line on what the live view showed (nothing without a view)."""
    if view is not None:
        print(
            f"live view: {view.n_logged} frames shown, {view.n_skipped} skipped to keep up "
            "(the records have every frame)"
        )


class _Latencies:
    """A histogram of latencies (ms): fixed memory whatever the run's length."""

    def __init__(self):
        self.counts = np.zeros(_LATENCY_BINS, np.int64)
        self.n = 0
        self.max = 0.0

    def add(self, ms: float) -> None:
        self.counts[min(int(ms / _LATENCY_BIN_MS), _LATENCY_BINS - 1)] += 1
        self.n += 1
        self.max = max(self.max, ms)

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (ms), to the bin's width (the upper edge of its bin)."""
        if self.n == 0:
            return math.nan
        k = int(np.searchsorted(np.cumsum(self.counts), q * self.n, side="left"))
        return (k + 1) * _LATENCY_BIN_MS


#: a Ctrl-C later than this (seconds) after the first is a second one: it interrupts at once
_SECOND_CTRL_C = 0.3


@contextmanager
def _first_ctrl_c_stops(source):
    """Ctrl-C (SIGINT) asks the source to stop: the frame in hand is finished and written,
    then the run ends.  A second Ctrl-C interrupts at once.  Elsewhere than the main thread
    (a test runner's worker) the default handler stays."""
    state = {"interrupted": False}
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    first_at: list[float] = []  # when the first Ctrl-C came

    def stop(signum, frame):
        now = time.monotonic()
        if not first_at:
            first_at.append(now)
            state["interrupted"] = True
            source.stop()
        elif now - first_at[0] > _SECOND_CTRL_C:
            raise KeyboardInterrupt
        # else: the same Ctrl-C delivered again (rerun's handler, with --view and
        # --view-save, passes it on), not a second one

    previous = signal.signal(signal.SIGINT, stop)
    try:
        yield state
    finally:
        signal.signal(signal.SIGINT, previous)


class _MapSteps:
    """A live run's localizer on a map of ``flyvpr map``: one frame in, its answer out."""

    def __init__(self, args):
        from ..localization import Localizer

        self.loc = Localizer.from_map(
            args.map, size=args.size, breaks=() if args.no_breaks else None
        )
        if args.calibration is not None:
            apply_table(self.loc, args.calibration)
        self.map = self.loc.map_
        self.size = tuple(self.loc.method.frontend.image_shape_)
        self.name, self.n_places = self.map.method.name, self.map.n_places
        self.positions, self.thumbnails = self.map.positions, self.map.thumbnails

    def step(self, image):
        """(place, confidence, state, relocated, the filter's score row)."""
        fixes = self.loc.update_batch(image[None])
        return (
            int(fixes.places[0]),
            float(fixes.confidences[0]),
            str(fixes.states[0]),
            bool(fixes.relocated[0]),
            fixes.scores[0],
        )


class _CompactSteps:
    """The same on a compact map (``flyvpr map --compact``): no score rows over the places."""

    def __init__(self, args):
        from ..large.recording import compact_localizer, open_compact_map
        from ._compact import compact_method_name

        cmap = self.cmap = open_compact_map(args.map)
        self.loc = compact_localizer(
            cmap, index=args.index or "exhaustive", breaks=() if args.no_breaks else None
        )
        self.map = None
        self.size = cmap.size
        self.name, self.n_places = compact_method_name(cmap), cmap.n_places
        self.positions, self.thumbnails = cmap.positions, None

    def step(self, image):
        before = self.loc.n_reseeds_
        fix = self.loc.update(image)
        return fix.place, fix.confidence, fix.state, self.loc.n_reseeds_ > before, None


def cmd_localize_live(args) -> int:
    from tqdm.auto import tqdm

    from ..large.recording import is_compact_map
    from ..localization import LOCALIZED
    from ..sources import LiveSource, RecordingError

    for option in (
        "topic", "every", "positions", "position_topic", "ground_truth", "render", "realtime",
        "no_odometry", "fit_calibration",
    ):  # fmt: skip
        if getattr(args, option):
            raise UsageError(
                f"{flag(option)}: not with a live source ({args.source}); it needs a recording"
            )
    options = _stream_options(args.stream_option)
    compact = is_compact_map(args.map)
    if compact:
        for option in ("view", "view_save", "mcap_thumbnails", "calibration", "size"):
            if getattr(args, option):
                raise UsageError(
                    f"{flag(option)}: not with a compact map ({args.map}); build the map "
                    "without --compact for it"
                )
    elif args.index is not None:
        raise UsageError(
            f"--index: only with a compact map (`flyvpr map --compact`); {args.map} is not one"
        )
    from ._records import check_thumbnails

    check_thumbnails(args)
    inputs = [args.map] + ([args.calibration] if args.calibration is not None else [])
    check_outputs(args, inputs, ("out",))
    check_view_args(args, inputs)
    steps = _CompactSteps(args) if compact else _MapSteps(args)
    size = steps.size

    def notify(message: str) -> None:
        print(f"flyvpr localize: {message}", file=sys.stderr, flush=True)

    given = {k: getattr(args, k) for k in _DEFAULTS if getattr(args, k) is not None}
    source = LiveSource(
        args.source,
        options=options,
        notify=notify,
        **{**_DEFAULTS, **given},
    )
    columns = ["frame", "timestamp", "place", "confidence", "state", "relocated"]
    if steps.positions is not None:
        columns += ["x", "y"]
    columns.append("latency_ms")
    show = not args.quiet and sys.stderr.isatty()
    latencies = _Latencies()
    confidences = []
    n_frames = n_reloc = n_localized = 0
    failure = None
    t0 = time.perf_counter()
    with ExitStack() as stack:
        stack.callback(source.close)
        view = None if steps.map is None else open_view(args, steps.map, background=True)
        if view is not None:
            stack.callback(view.close)
        out = None
        if args.out is not None:
            from ._records import open_records
            from ._stream import run_metadata

            args.records_kept = args.out  # whatever ends the run (see cli.main)
            out = stack.enter_context(
                open_records(
                    args.out,
                    columns,
                    flush=True,
                    thumbnails=args.mcap_thumbnails,
                    metadata=run_metadata(args, steps.name, steps.n_places, source),
                )
            )
        bar = stack.enter_context(tqdm(desc="localizing", unit="frame", disable=not show))
        ctrl_c = stack.enter_context(_first_ctrl_c_stops(source))
        try:
            for f in source.frames(size):
                place, confidence, state, relocated, scores = steps.step(f.image)
                row: dict = {
                    "frame": f.index,
                    "timestamp": f.timestamp,
                    "place": place,
                    "confidence": confidence,
                    "state": state,
                    "relocated": int(relocated),
                }
                if steps.positions is not None:
                    row["x"], row["y"] = (float(v) for v in steps.positions[place])
                row["latency_ms"] = 1000.0 * (time.monotonic() - f.arrival)
                if out is not None:
                    images = None
                    if args.mcap_thumbnails:
                        images = {"query": np.rint(f.image * 255.0).astype(np.uint8)}
                        if steps.thumbnails is not None:
                            images["match"] = steps.thumbnails[place]
                    out.write(row, images)
                latencies.add(1000.0 * (time.monotonic() - f.arrival))
                if view is not None:
                    view.log(
                        f.index,
                        f.timestamp,
                        f.frame,
                        place,
                        row["confidence"],
                        row["state"],
                        scores,
                        model_input=f.image,
                        relocated=relocated,
                    )
                confidences.append(row["confidence"])
                n_frames += 1
                n_reloc += row["relocated"]
                n_localized += row["state"] == LOCALIZED
                bar.update(1)
        except RecordingError as exc:  # a stall past the retries: summary first, then exit 1
            failure = exc
    elapsed = time.perf_counter() - t0
    if ctrl_c["interrupted"]:
        ending = "ended by Ctrl-C"
    elif failure is not None:
        ending = "ended: the stream failed (the error line below says how)"
    else:
        ending = "ended: the stream ended"
    # received, not localized, and not damaged: replaced by a newer frame before the
    # localizer took it (or left when the run stopped)
    n_dropped = source.n_received - n_frames - source.n_undecodable
    clock: dict[str | None, str] = {
        "stream": "the stream's clock",
        "wall": "the wall clock at arrival (Unix time)",
    }
    print(
        f"{steps.name}: {source.describe()} against {steps.n_places} places, {ending} after "
        f"{elapsed:.1f} s: {counted(source.n_received, 'frame')} received, {n_frames} localized, "
        f"{n_dropped} dropped (the localizer takes the newest frame), "
        f"{counted(source.n_corrupt, 'damaged packet')} skipped, "
        f"{counted(source.n_reconnects, 'reconnection')}"
    )
    if n_frames:
        conf = np.asarray(confidences)
        print(
            f"latency from a frame's arrival to its record: median "
            f"{latencies.quantile(0.5):.2f} ms, 95% {latencies.quantile(0.95):.2f} ms, max "
            f"{latencies.max:.2f} ms; median confidence {float(np.median(conf)):.4g}, "
            f"localized {100 * n_localized / n_frames:.1f}% of frames, "
            f"{counted(n_reloc, 'relocation')}; "
            f"timestamps: {clock.get(source.clock, 'none')}"
        )
    from ._stream import breaks_note, compact_breaks_note

    if isinstance(steps, _CompactSteps):
        line = compact_breaks_note(steps.loc, steps.cmap)
    else:
        line = breaks_note(steps.loc)
    if line is not None:
        print(line)
    print_view_summary(view)
    if n_frames == 0:  # no frame localized: the records file, a header only, is gone
        args.out = None
    for path in (args.out, args.view_save):
        if path is not None:
            print(f"wrote {path}")
    if failure is not None:
        raise failure
    return 130 if ctrl_c["interrupted"] else 0

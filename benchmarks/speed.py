"""Speed benchmark: FlyNet+CANN and SeqSLAM on Nordland, and streaming over a whole railway line.

Usage::

    python benchmarks/speed.py --json out.json [--data ../shared/data] [--repeat 5]

Measures in one run, each figure the median of ``--repeat`` repetitions (seconds unless named)
but the streaming rows (``stream_*``, one pass each, in a process of its own) and the video's
peak memory (one run per length):

* ``decode_s``: reading and pre-processing the 2000 PNGs (summer + winter, frames 0-999 of
  ``nordland_64x32``) with the cache off;
* ``flynet_fit_s``: training FlyNet on the 1000 summer places (paper settings, 200 epochs);
* ``flynet_cann_query_s`` / ``flynet_cann_per_query_ms``: encoding the 1000 winter images already
  in memory and running the CANN over them, to a best place and confidence per query;
* ``seqslam_s``: the full SeqSLAM (patch normalisation, difference matrix, contrast enhancement,
  sequence search, length 20) on the same 1000 x 1000, and ``seqslam_2400_s`` on all 2400 x 2400;
* ``flyhash_images_per_s``: FlyHash encoding of 32x64 images already in memory, batch of 100,000
  (after one untimed pass);
* ``stream_queries_per_s`` / ``stream_peak_rss_mb``: the streaming ``flynet+cann`` Localizer on a
  35,768-place map, one frame at a time, over 5,000+ query frames; peak resident memory of the
  whole process.  The map: the 2400 summer frames repeated 15 times (35,768 = 14 x 2400 + 2168),
  each copy after the first with its own small perturbation (gain 0.9-1.1, offset +-0.03, a
  shift of up to one pixel, Gaussian noise sd 0.01), as a stand-in for the 35,768 frames of the
  full Nordland line.
  FlyNet is trained on it with mini-batches of 512 for ``--stream-epochs`` epochs (full-batch
  training over 35,768 classes would need a 35,768^2 logit matrix).  It runs in its own
  process so the peak resident memory is that of the streaming job alone.  The queries are winter
  frames in route order, wrapping around the 2400 available; the share of frames whose best
  place (in any copy) lies within 20 places of the true one is reported for information.

* ``video_*``: end to end from a 640x480 H.264 video (see ``benchmarks/video_speed.py`` for
  the protocol): ``flyvpr localize --map`` against PyAV decoding the same video alone (same
  run, threads on both sides), their ratio and ms per frame, and the peak memory of the
  localize command at two video lengths (``--skip-video`` leaves the row out).

Also prints the machine, library versions, and the paper's timing table next to ours.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np

import flyvpr
from flyvpr._io import write_json_atomic
from flyvpr.frontends import FlyHash, FlyNet, KenyonEncoder, PixelsEncoder
from flyvpr.images import list_images, load_images
from flyvpr.localization import Localizer
from flyvpr.methods import Method
from flyvpr.temporal import FILTERS

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import (  # noqa: E402
    DEFAULT_DATA,
    LINE_PLACES,
    make_line_map,
    peak_rss_mb,
)

HERE = Path(__file__).resolve().parent
N_LINE = LINE_PLACES

# Paper, Table "Processing time", Nordland 1000 queries x 1000 references.
PAPER = {
    "FlyNet+CANN": {"feature_s": 35.0, "matching_s": 25.0, "per_query_s": 0.06, "fps": 16.66},
    "SeqSLAM": {"feature_s": 50.0, "matching_s": 40.0, "per_query_s": 0.09, "fps": 11.11},
}


def _video_module():
    """``benchmarks/video_speed.py``, loaded by path (this file also runs as a script)."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("video_speed", HERE / "video_speed.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def timed(fn, repeat):
    times, out = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def stream(data: Path, n_queries: int, epochs: int, method: str = "flynet+cann") -> dict:
    """The 35,768-place streaming figures of ``method``; run in a fresh process by ``main``.

    ``method`` is ``flynet+cann`` (keys ``stream_*``) or ``kenyon+cann`` (keys
    ``stream_kenyon_*``; nothing is trained, the map is the codes of the line's frames).
    """
    root = data / "nordland_64x32"
    summer = load_images(list_images(root / "summer"), progress=False)
    winter = load_images(list_images(root / "winter"), progress=False)
    line = make_line_map(summer, N_LINE, np.random.default_rng(0))
    del summer
    t0 = time.perf_counter()
    if method == "kenyon+cann":
        front = KenyonEncoder(random_state=0)
    else:
        front = FlyNet(random_state=0, epochs=epochs, batch_size=512)
    loc = Localizer(Method(method, front, FILTERS["cann"]())).fit(line)
    map_s = time.perf_counter() - t0
    del line
    src = np.arange(n_queries) % len(winter)
    hits = 0
    loc.update(winter[0])  # warm-up, then start the drive afresh
    loc.reset()
    t0 = time.perf_counter()
    for i in range(n_queries):
        place = loc.update(winter[src[i]]).place
        # The map repeats the 2400 real places, so any copy of the right place is right.
        hits += abs(place % len(winter) - src[i]) <= 20
    stream_s = time.perf_counter() - t0
    prefix = "stream_kenyon_" if method == "kenyon+cann" else "stream_"
    out = {
        "queries_per_s": n_queries / stream_s,
        "per_query_ms": 1000 * stream_s / n_queries,
        "map_build_s": map_s,
        "same_place_within_20_share": hits / n_queries,
        "peak_rss_mb": peak_rss_mb(),
    }
    out = {prefix + k: v for k, v in out.items()}
    out.update(stream_n_places=N_LINE, stream_n_queries=n_queries)
    return out


def kenyon_vs_pixels(ref, qry, line, rep) -> dict:
    """Per-query matching time of kenyon+cann and pixels+cann at 1000 and 35,768 places.

    Matching = scoring the already-encoded queries against every place + the CANN over the
    score matrix (what ``Method.timing_["match_s"]`` times), for the 1000 winter queries; the
    encoding of the queries is timed on its own (``*_encode_ms``).  Both methods run in the
    same process, one after the other, so their ratio is measured under the same load.
    """
    res = {}
    cann = FILTERS["cann"]()
    for label, places in (("1000", ref), ("35768", line)):
        for name, front in (("kenyon", KenyonEncoder(random_state=0)), ("pixels", PixelsEncoder())):
            front.fit(places)
            codes = front.encode(qry)
            cann.filter(front.score_codes(codes[:20]))  # warm-up: compiled kernels
            t, _ = timed(lambda f=front, c=codes: cann.filter(f.score_codes(c)), rep)
            res[f"{name}_cann_match_{label}_per_query_ms"] = 1000 * t / len(qry)
            if label == "1000":
                t, _ = timed(lambda f=front: f.encode(qry), rep)
                res[f"{name}_encode_per_query_ms"] = 1000 * t / len(qry)
            front = None  # free the map (pixels: 293 MB at 35,768 places) before the next
        res[f"kenyon_over_pixels_match_{label}"] = (
            res[f"kenyon_cann_match_{label}_per_query_ms"]
            / res[f"pixels_cann_match_{label}_per_query_ms"]
        )
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--json", type=Path, help="write the figures as JSON (atomically)")
    p.add_argument("--repeat", type=int, default=5, help="repetitions per figure (median)")
    p.add_argument("--stream-queries", type=int, default=6000)
    p.add_argument("--stream-epochs", type=int, default=10)
    p.add_argument("--skip-stream", action="store_true", help="skip the 35,768-place stream")
    p.add_argument("--skip-video", action="store_true", help="skip the 640x480 video row")
    p.add_argument("--skip-kenyon", action="store_true", help="skip the kenyon+cann rows")
    p.add_argument("--stream-only", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--stream-method", default="flynet+cann", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.stream_only:
        import json

        figures = stream(args.data, args.stream_queries, args.stream_epochs, args.stream_method)
        print(json.dumps(figures))
        return 0
    root = args.data / "nordland_64x32"
    if not root.is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 1
    summer_files = list_images(root / "summer")
    winter_files = list_images(root / "winter")
    rep = args.repeat
    res: dict = {}

    def log(msg):
        print(msg, flush=True)

    # -- decoding -----------------------------------------------------------
    files = summer_files[:1000] + winter_files[:1000]
    res["decode_s"], imgs = timed(lambda: load_images(files, cache=False, progress=False), rep)
    ref, qry = imgs[:1000], imgs[1000:]
    log(f"decode 2000 PNGs: {res['decode_s']:.3f} s")

    # -- FlyNet + CANN --------------------------------------------------------
    res["flynet_fit_s"], fn = timed(lambda: FlyNet(random_state=0).fit(ref), rep)
    log(f"FlyNet fit (1000 places, 200 epochs): {res['flynet_fit_s']:.3f} s")
    cann = FILTERS["cann"]()

    def flynet_cann():
        codes = fn.encode(qry)
        S = cann.filter(fn.score_codes(codes))
        best = S.argmax(axis=1)
        return best, S[np.arange(len(best)), best]

    def encode_only():
        return fn.encode(qry)

    flynet_cann()  # warm-up: loads the CANN's compiled kernels from numba's cache
    res["flynet_cann_query_s"], _ = timed(flynet_cann, rep)
    res["flynet_cann_per_query_ms"] = 1000 * res["flynet_cann_query_s"] / len(qry)
    enc_s, _ = timed(encode_only, rep)
    log(
        f"FlyNet+CANN on 1000 queries: {res['flynet_cann_query_s']:.4f} s "
        f"({res['flynet_cann_per_query_ms']:.4f} ms/query); ratio to decode "
        f"{res['flynet_cann_query_s'] / res['decode_s']:.3f}"
    )

    # -- SeqSLAM --------------------------------------------------------------
    def seqslam(r, q):
        S = PixelsEncoder().fit(r).score(q)
        return FILTERS["seqslam"]().filter(S)

    seqslam(ref[:50], qry[:50])  # compile the numba kernel outside the timing
    res["seqslam_s"], _ = timed(lambda: seqslam(ref, qry), rep)
    all_s = load_images(summer_files, progress=False)
    all_w = load_images(winter_files, progress=False)
    res["seqslam_2400_s"], _ = timed(lambda: seqslam(all_s, all_w), rep)
    pix_s, _ = timed(lambda: PixelsEncoder().fit(ref).encode(qry), rep)
    log(f"SeqSLAM 1000x1000: {res['seqslam_s']:.3f} s; 2400x2400: {res['seqslam_2400_s']:.3f} s")

    # -- FlyHash throughput ---------------------------------------------------
    big = np.resize(all_s, (100_000, *all_s.shape[1:]))
    fh = FlyHash(random_state=0).fit(all_s[:10])
    fh.encode(big)  # warm-up: the first pass over a fresh 800 MB batch pays page faults
    t_fh, _ = timed(lambda: fh.encode(big), rep)
    res["flyhash_images_per_s"] = len(big) / t_fh
    log(f"FlyHash: {res['flyhash_images_per_s']:,.0f} images/s (batch of {len(big):,})")
    big = None  # free the 800 MB batch before the streaming process starts

    # -- kenyon+cann vs pixels+cann: matching per query at 1000 and 35,768 places ----
    if not args.skip_kenyon:
        line = make_line_map(all_s, N_LINE, np.random.default_rng(0))
        res.update(kenyon_vs_pixels(ref, qry, line, rep))
        line = None
        for label in ("1000", "35768"):
            log(
                f"match per query at {label} places: kenyon+cann "
                f"{res[f'kenyon_cann_match_{label}_per_query_ms']:.4f} ms, pixels+cann "
                f"{res[f'pixels_cann_match_{label}_per_query_ms']:.4f} ms "
                f"(ratio {res[f'kenyon_over_pixels_match_{label}']:.3f})"
            )

    # -- streaming over a whole line (own process, so its peak memory is its own) ----
    streams = [] if args.skip_stream else ["flynet+cann"]
    if not (args.skip_stream or args.skip_kenyon):
        streams.append("kenyon+cann")
    for method in streams:
        import json
        import subprocess

        cmd = [
            sys.executable,
            __file__,
            "--stream-only",
            "--data",
            str(args.data),
            "--stream-queries",
            str(args.stream_queries),
            "--stream-epochs",
            str(args.stream_epochs),
            "--stream-method",
            method,
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True)
        res.update(json.loads(out.stdout.strip().splitlines()[-1]))
        p = "stream_kenyon_" if method == "kenyon+cann" else "stream_"
        log(
            f"stream {method}: {res[p + 'queries_per_s']:,.0f} queries/s over {N_LINE:,} places "
            f"({res[p + 'per_query_ms']:.3f} ms/query; map built in "
            f"{res[p + 'map_build_s']:.1f} s; peak RSS {res[p + 'peak_rss_mb']:.0f} MB)"
        )

    # -- end to end from a video ---------------------------------------------------------------
    if not args.skip_video:
        res.update(_video_module().run(repeat=rep, log=log))
        lengths = sorted(int(k.rsplit("_", 1)[1]) for k in res if k.startswith("video_peak_rss"))
        short, long = (res[f"video_peak_rss_mb_{n}"] for n in (lengths[0], lengths[-1]))
        res["targets"] = {
            "video_localize_over_decode >= 0.8": res["video_localize_over_decode"] >= 0.8,
            f"video peak RSS at {lengths[-1]} frames <= 1.05 x at {lengths[0]}": long
            <= 1.05 * short,
        }

    # -- context --------------------------------------------------------------
    import numba
    import scipy

    res["machine"] = {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
        "flyvpr": flyvpr.__version__,
    }
    half_decode = res["decode_s"] / 2
    ours = {
        "FlyNet+CANN": (half_decode + enc_s, res["flynet_cann_query_s"] - enc_s),
        "SeqSLAM": (half_decode + pix_s, res["seqslam_s"] - pix_s),
    }
    res["timing_table"] = {
        k: {"feature_s": f, "matching_s": m, "per_query_s": (f + m) / 1000, "fps": 1000 / (f + m)}
        for k, (f, m) in ours.items()
    }
    res["targets"] = {
        **res.get("targets", {}),
        "flynet_cann_query_s <= 0.25 decode_s": res["flynet_cann_query_s"]
        <= 0.25 * res["decode_s"],
        "seqslam_s <= 0.5": res["seqslam_s"] <= 0.5,
        "flynet_fit_s <= 2": res["flynet_fit_s"] <= 2.0,
        "seqslam_2400_s <= 3": res["seqslam_2400_s"] <= 3.0,
        "flyhash_images_per_s >= 100000": res["flyhash_images_per_s"] >= 100_000,
    }
    if "stream_queries_per_s" in res:
        res["targets"]["stream_queries_per_s >= 2000"] = res["stream_queries_per_s"] >= 2000
        res["targets"]["stream_peak_rss_mb <= 1000"] = res["stream_peak_rss_mb"] <= 1000
    for label in ("1000", "35768"):
        key = f"kenyon_over_pixels_match_{label}"
        if key in res:
            res["targets"][f"{key} <= 1"] = res[key] <= 1.0
    if "stream_kenyon_queries_per_s" in res:
        res["targets"]["stream_kenyon_queries_per_s >= 2000"] = (
            res["stream_kenyon_queries_per_s"] >= 2000
        )

    print()
    print(
        f"machine: {res['machine']['cpu']}, {res['machine']['cores']} cores; numpy "
        f"{np.__version__}, scipy {scipy.__version__}, numba {numba.__version__}"
    )
    print(f"{'figure':30s} {'value':>14s}")
    for key in (
        "decode_s",
        "flynet_fit_s",
        "flynet_cann_query_s",
        "flynet_cann_per_query_ms",
        "seqslam_s",
        "seqslam_2400_s",
        "flyhash_images_per_s",
        "stream_queries_per_s",
        "stream_per_query_ms",
        "stream_peak_rss_mb",
        "video_decode_fps",
        "video_localize_fps",
        "video_decode_ms",
        "video_localize_ms",
        "video_localize_over_decode",
        "kenyon_encode_per_query_ms",
        "pixels_encode_per_query_ms",
        "kenyon_cann_match_1000_per_query_ms",
        "pixels_cann_match_1000_per_query_ms",
        "kenyon_over_pixels_match_1000",
        "kenyon_cann_match_35768_per_query_ms",
        "pixels_cann_match_35768_per_query_ms",
        "kenyon_over_pixels_match_35768",
        "stream_kenyon_queries_per_s",
        "stream_kenyon_per_query_ms",
        "stream_kenyon_peak_rss_mb",
    ):
        if key in res:
            print(f"{key:30s} {res[key]:14.4f}")
    print("\nPaper's timing table form (Nordland, 1000 queries x 1000 references):")
    print(f"{'system':22s} {'feature ext.':>13s} {'matching':>10s} {'per query':>11s} {'fps':>9s}")
    for name, row in res["timing_table"].items():
        paper = PAPER[name]
        print(
            f"{name + ' (flyvpr)':22s} {row['feature_s']:12.3f}s {row['matching_s']:9.3f}s "
            f"{row['per_query_s'] * 1000:9.3f}ms {row['fps']:9.0f}"
        )
        print(
            f"{name + ' (paper)':22s} {paper['feature_s']:12.1f}s {paper['matching_s']:9.1f}s "
            f"{paper['per_query_s'] * 1000:9.0f}ms {paper['fps']:9.2f}"
        )
    print(
        "(flyvpr feature extraction = decoding the 1000 query PNGs + encoding them; matching = "
        "scoring + temporal filter)"
    )
    print("\ntargets:")
    for k, ok in res["targets"].items():
        print(f"  {'ok  ' if ok else 'MISS'} {k}")
    if args.json:
        write_json_atomic(args.json, res)
        print(f"wrote {args.json}")
    return 0


#: what each figure of the JSON measures, in the order the results page lists them
FIGURE_NOTES = {
    "decode_s": ("s", "read + pre-process 2000 PNGs (summer + winter 0-999), cache off"),
    "flynet_fit_s": ("s", "train FlyNet on 1000 places, 200 full-batch epochs"),
    "flynet_cann_query_s": ("s", "encode 1000 queries (in memory) + CANN -> place, confidence"),
    "flynet_cann_per_query_ms": ("ms", "the same per query"),
    "seqslam_s": ("s", "SeqSLAM 1000 x 1000 (patch norm., SAD, enhancement, search, length 20)"),
    "seqslam_2400_s": ("s", "the same on all 2400 x 2400 frames"),
    "flyhash_images_per_s": ("images/s", "FlyHash, batch of 100,000 32x64 images in memory"),
    "stream_queries_per_s": ("frames/s", "flynet+cann Localizer, one frame at a time"),
    "stream_per_query_ms": ("ms", "the same per frame"),
    "stream_peak_rss_mb": ("MiB", "peak resident memory of that streaming process"),
    "stream_map_build_s": ("s", "building that map: FlyNet mini-batch training"),
    "stream_same_place_within_20_share": ("share", "streamed frames within 20 places"),
    "video_decode_fps": ("frames/s", "PyAV alone decodes the 640x480 H.264 query video"),
    "video_localize_fps": ("frames/s", "flyvpr localize --map on that video, end to end"),
    "video_decode_ms": ("ms", "PyAV decoding, per frame"),
    "video_localize_ms": ("ms", "flyvpr localize --map, per frame"),
    "video_localize_over_decode": ("ratio", "localize rate / decode rate (target >= 0.8)"),
    "video_localize_over_decode_best": ("ratio", "the same from the fastest run of each"),
    "kenyon_encode_per_query_ms": ("ms", "kenyon: encode the 1000 queries (batch), per query"),
    "pixels_encode_per_query_ms": ("ms", "pixels: the same"),
    "kenyon_cann_match_1000_per_query_ms": (
        "ms",
        "kenyon+cann: score 1000 encoded queries x 1000 places + CANN, per query",
    ),
    "pixels_cann_match_1000_per_query_ms": ("ms", "pixels+cann: the same"),
    "kenyon_over_pixels_match_1000": ("ratio", "kenyon+cann / pixels+cann matching, same run"),
    "kenyon_cann_match_35768_per_query_ms": (
        "ms",
        "kenyon+cann: 1000 queries x the 35,768-place map + CANN, per query",
    ),
    "pixels_cann_match_35768_per_query_ms": ("ms", "pixels+cann: the same"),
    "kenyon_over_pixels_match_35768": ("ratio", "kenyon+cann / pixels+cann matching, same run"),
    "stream_kenyon_queries_per_s": ("frames/s", "kenyon+cann Localizer, one frame at a time"),
    "stream_kenyon_per_query_ms": ("ms", "the same per frame"),
    "stream_kenyon_peak_rss_mb": ("MiB", "peak resident memory of that streaming process"),
    "stream_kenyon_map_build_s": ("s", "building that map: encoding the 35,768 frames"),
    "stream_kenyon_same_place_within_20_share": ("share", "streamed frames within 20 places"),
}


def _figure(value) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return str(value)
    if abs(value) >= 1000:
        return f"{value:,.0f}"
    return f"{value:.4g}"


def render_markdown(data: dict) -> str:
    """The speed results page (Markdown, headings from level 2) from this script's JSON.

    Pure function of ``data`` (what ``--json`` wrote): the machine, the protocol, every
    figure (those without a note in :data:`FIGURE_NOTES` too, so new rows appear by
    themselves), the targets and the paper's timing table next to ours.
    """
    machine = data.get("machine", {})
    repeat = data.get("repeat")
    lines = [
        "## Protocol",
        "",
        "`../shared/data/nordland_64x32`, summer = reference, winter = query, frames 0-999 "
        "(1000 x 1000) unless a row says otherwise; gray 32x64. Each figure is the median of "
        + (f"{repeat} repetitions" if repeat else "`--repeat` repetitions (default 5)")
        + " in one run, but the streaming rows (one pass each) and the video's peak memory (one "
        "run per length). Streaming: a "
        + f"{data.get('stream_n_places', N_LINE):,}-place map (the 2400 summer frames repeated, "
        "each copy after the first perturbed: gain, offset, a one-pixel shift, noise), FlyNet "
        "trained on it in "
        f"mini-batches of 512; {data.get('stream_n_queries', '?'):,} winter frames streamed in "
        "route order, in a process of its own so that its peak memory is its own.",
        "",
        "## Machine",
        "",
        "; ".join(f"{k}: {v}" for k, v in machine.items()) or "Not recorded in this JSON.",
        "",
        "## Figures",
        "",
        "| figure | value | unit | what is timed |",
        "|---|---|---|---|",
    ]
    skip = {"machine", "timing_table", "targets", "repeat", "stream_n_places", "stream_n_queries"}
    skip |= {"video_decode_runs_s", "video_localize_runs_s"}
    keys = [k for k in FIGURE_NOTES if k in data]
    keys += [k for k in data if k not in FIGURE_NOTES and k not in skip]
    for key in keys:
        unit, note = FIGURE_NOTES.get(key, ("", ""))
        lines.append(f"| `{key}` | {_figure(data[key])} | {unit} | {note} |")
    targets = data.get("targets", {})
    if targets:
        lines += ["", "## Targets", "", "| target | met |", "|---|---|"]
        lines += [f"| `{t}` | {'yes' if ok else '**no**'} |" for t, ok in targets.items()]
    table = data.get("timing_table", {})
    if table:
        lines += [
            "",
            "## In the paper's form",
            "",
            "1000 queries x 1000 references. Feature extraction = decoding the 1000 query PNGs "
            "(half of `decode_s`) + encoding them; place matching = scoring + temporal filter. "
            "The paper's figures were measured on other hardware.",
            "",
            "| system | feature extraction (s) | place matching (s) | per query (ms) | fps |",
            "|---|---|---|---|---|",
        ]
        for name, row in table.items():
            for label, r in ((f"{name} (flyvpr)", row), (f"{name} (paper)", PAPER.get(name))):
                if r is None:
                    continue
                lines.append(
                    f"| {label} | {r['feature_s']:.3g} | {r['matching_s']:.3g} | "
                    f"{1000 * r['per_query_s']:.3g} | {_figure(r['fps'])} |"
                )
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())

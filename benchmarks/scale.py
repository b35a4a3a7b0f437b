"""Scale benchmark: compact codes of 10^5 .. 10^7 places, streamed with winter queries.

Usage::

    python benchmarks/scale.py --places N [--queries Q] --json FILE [--data DIR] [--work DIR]

Writes a JSON list with one row per ``--places`` value (the option may be repeated), each with
``places``, ``frames_per_s``, ``peak_rss_mb``, ``build_s``, ``open_s``,
``same_place_within_20_share``, ``kidnap_relocated_share``, ``kidnap_frames_median``, more
figures and the ``protocol``.

Protocol:

* **Codes**: :class:`flyvpr.large.CompactEncoder` (256 bits, or ``--bits``; PCA-rotated signs
  of the ``kenyon`` optic lobe, seed 0) fitted on the 2,400 Nordland 64x32 summer frames.
* **Map** (``build_s``, in its own process, whose peak memory is ``build_peak_rss_mb``): the
  summer codes tiled to N places with :func:`flyvpr.large.write_tiled_map` (tile masks
  flip 25% of the bits, per-place noise 2%), streamed to a map file, then, when ``--index``
  names ``mih``, the multi-index hashing tables (16 x 16-bit substrings: the first 256 bits
  of a longer code, re-ranked by the whole code) built from the memory-mapped codes and
  saved.  A row with ``--index exhaustive`` (the default) relocates by an exact scan, which
  needs no tables: its ``build_s`` is the map file's alone.
* **Localizer** (in its own process; ``peak_rss_mb`` is its VmHWM): open the map and the
  index (``open_s``), refit the encoder on the summer frames (not timed), then
  :class:`flyvpr.large.LargeLocalizer` on the map's memory-mapped codes (window 2,048; a
  lost stretch searched at its 4th frame, then 4 frames after a re-seed or twice as late
  after a search that did not re-seed, each search sending the index at most 4 new codes
  for their top 300; the candidates of the stretch's last 10 frames pooled; a check every
  1000 frames; a layer a lost re-seed displaces, if it had been localized since its seed,
  held beside the new one for at most 30 frames while neither is localized, the more
  confident answering; a guess, never localized since its seed, giving way to any better
  track; on maps of at most 2^20 places a lost guess also scores every place's track; the
  CANN's defaults).
  The frame at map place ``p`` is winter frame ``p mod 2400`` seen on tile ``p // 2400``
  (:func:`flyvpr.large.tile_queries`); its true place is ``p``.  Each frame is encoded from
  its pixels, then given to ``update_code``.
* **Lock-on** (``lock_frames``): from a cold start at a random place, the frames driven until
  the fix is ``localized`` and within 20 places of the truth (limit 500).
* **Stream**: after lock-on and 100 frames more (not timed), ``--queries`` frames driven on:
  the stream measures the localizer *while localized*.  ``frames_per_s`` counts all of it
  (encoding included); ``same_place_within_20_share``: fixes within 20 places of the truth;
  ``localized_share``: fixes ``localized``; ``searched_share``: codes sent to the index per
  frame (some of a check's frames and of the lost frames: see the localizer's schedule).
  The stream's frames are also split: ``tracked_frames_per_s``, the rate of the frames the
  window alone answered (encoding included); ``searched_ms_per_frame``, the mean time of a
  frame that also searched the index.
* **Kidnap** (``--kidnaps`` trials, default 200: with 50 a share's 95% interval is about
  +-10 points, with 200 about +-4.5): while localized, the query jumps to a random
  place and drives on from there; the localizer is not told.  Relocated at the first fix that
  is ``localized`` and within 20 places of the truth, if within 30 frames
  (``kidnap_relocated_share``, ``kidnap_frames_median`` of the relocated).  Between trials
  the stream drives on until the fix is on the place again (``kidnap_unsettled`` counts the
  times it was not within 500 frames).  ``kidnap_ms_per_search``: the relocation cost per
  code searched, index search, pooling, tracks and re-seeds (``search_s_ / n_searches_`` over
  the trials' frames); ``kidnap_ms_per_frame``: the trials' frames, all costs.
  ``kidnap_relocated_ci95``: the share's 95% Wilson score interval.  The trials' jumps come
  from a seeded generator, so the first N of a longer run are a run of N trials.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import DEFAULT_DATA, peak_rss_mb  # noqa: E402

HERE = Path(__file__).resolve().parent
N_BITS = 256
#: multi-index hashing tables (16-bit substrings): the first 256 bits of a longer code
MIH_TABLES = 16
TILE_FLIP = 0.25
PLACE_FLIP = 0.02
WINDOW = 2048
#: untimed frames after locking on, before the timed stream
LOCK = 100
#: frames allowed to lock on from a cold start (and to settle between kidnaps)
LOCK_LIMIT = 500
CHECK_EVERY = 1000
K = 300
POOL = 10
RESEED_AFTER = 4
HOLD = 30
FULL_SEARCH_PLACES = 1 << 20
KIDNAP_LIMIT = 30
TOLERANCE = 20


def load_frames(data: Path):
    from flyvpr.images import list_images, load_images

    root = data / "nordland_64x32"
    summer = load_images(list_images(root / "summer"), progress=False)
    winter = load_images(list_images(root / "winter"), progress=False)
    return summer, winter


def fit_encoder(summer):
    from flyvpr.large import CompactEncoder

    return CompactEncoder(n_bits=N_BITS, random_state=0).fit(summer)


def build(args) -> dict:
    """The map file and its index, from the summer codes (run in a child process)."""
    from flyvpr.large import MultiIndexHash, open_large_map, save_index, write_tiled_map

    base = np.load(args.work / "summer_codes.npy", allow_pickle=False)
    path = args.work / f"map-{args.places}.fvmap"
    t0 = time.perf_counter()
    write_tiled_map(
        path,
        base,
        args.places,
        TILE_FLIP,
        PLACE_FLIP,
        random_state=0,
        metadata={"encoder": f"CompactEncoder(n_bits={N_BITS}, projection='pca', random_state=0)"},
    )
    t1 = time.perf_counter()
    index_mb = 0.0
    if args.index == "mih":  # the tables, only when a row relocates through them
        m = open_large_map(path)
        index = MultiIndexHash(n_tables=min(MIH_TABLES, N_BITS // 16), radius=1).build(m.codes)
        save_index(path.with_suffix(".mih"), index, m)
        index_mb = path.with_suffix(".mih").stat().st_size / 2**20
    t2 = time.perf_counter()
    return {
        "build_s": t2 - t0,
        "build_map_s": t1 - t0,
        "build_index_s": t2 - t1,
        "map_file_mb": path.stat().st_size / 2**20,
        "index_file_mb": index_mb,
        "build_peak_rss_mb": peak_rss_mb(),
    }


def _open(args):
    """The map, its index for relocation and the localizer (``open_s``: map and index)."""
    from flyvpr.large import ExhaustiveIndex, LargeLocalizer, load_index, open_large_map

    t0 = time.perf_counter()
    m = open_large_map(args.work / f"map-{args.places}.fvmap")
    if args.index == "mih":
        index = load_index(args.work / f"map-{args.places}.mih", m)
    else:
        index = ExhaustiveIndex().build(m.codes)
    open_s = time.perf_counter() - t0
    loc = LargeLocalizer(
        m.codes,
        index,
        window=WINDOW,
        k=K,
        pool=POOL,
        reseed_after=RESEED_AFTER,
        check_every=CHECK_EVERY,
        hold=HOLD,
        full_search_places=FULL_SEARCH_PLACES,
    )
    return m, loc, open_s


def stream(args) -> dict:
    """Open, lock on, stream and kidnap (run in a child process)."""
    from flyvpr.large import tile_queries

    m, loc, open_s = _open(args)
    n = m.n_places
    summer, winter = load_frames(args.data)
    enc = fit_encoder(summer)
    del summer
    n_base = len(winter)
    rng = np.random.default_rng(args.seed)

    def code_at(p: int) -> np.ndarray:
        """The winter frame of map place ``p``, encoded from its pixels, seen on its tile."""
        return tile_queries(enc.encode(winter[p % n_base][None]), p // n_base, TILE_FLIP, 0)[0]

    def on_place(fix, p: int) -> bool:
        return fix.state == "localized" and abs(fix.place - p) <= TOLERANCE

    # compile the kernels (not timed), then start cold
    loc.update_code(code_at(0))
    loc.reset()

    # -- lock on from a cold start, then LOCK frames more (not timed) -------------------------
    start = int(rng.integers(0, n - args.queries - LOCK - LOCK_LIMIT - 1))
    p, lock_frames = start, None
    t0 = time.perf_counter()
    while p - start < LOCK_LIMIT:
        fix = loc.update_code(code_at(p))
        p += 1
        if on_place(fix, p - 1):
            lock_frames = p - start
            break
    lock_s = time.perf_counter() - t0
    for _ in range(LOCK):
        fix = loc.update_code(code_at(p))
        p += 1

    # -- the localized stream (timed: encoding and localizing) --------------------------------
    searches0, search_s0 = loc.n_searches_, loc.search_s_
    hits = localized = 0
    tracked_s, tracked = 0.0, 0  # frames whose code did not go to the index
    t0 = time.perf_counter()
    for _ in range(args.queries):
        ta, searches = time.perf_counter(), loc.n_searches_
        fix = loc.update_code(code_at(p))
        if loc.n_searches_ == searches:
            tracked_s += time.perf_counter() - ta
            tracked += 1
        hits += abs(fix.place - p) <= TOLERANCE
        localized += fix.state == "localized"
        p += 1
    stream_s = time.perf_counter() - t0
    stream_searches = loc.n_searches_ - searches0
    stream_search_s = loc.search_s_ - search_s0

    # -- kidnaps: while localized, the query jumps; the localizer is not told ----------------
    frames, settle_failed = [], 0
    lost_searches, lost_s, trial_frames, trial_s = 0, 0.0, 0, 0.0
    for _ in range(args.kidnaps):
        # drive on until the fix is on the place again (after a failed trial)
        for _ in range(LOCK_LIMIT):
            if on_place(fix, p - 1) and p < n - KIDNAP_LIMIT:
                break
            if p >= n - KIDNAP_LIMIT:
                p = int(rng.integers(0, n - LOCK_LIMIT - KIDNAP_LIMIT))
            fix = loc.update_code(code_at(p))
            p += 1
        else:
            settle_failed += 1
        p = int(rng.integers(0, n - LOCK_LIMIT - KIDNAP_LIMIT))
        searches0, search_s0 = loc.n_searches_, loc.search_s_
        got = None
        t0 = time.perf_counter()
        for i in range(KIDNAP_LIMIT):
            fix = loc.update_code(code_at(p))
            p += 1
            if on_place(fix, p - 1):
                got = i + 1
                break
        trial_s += time.perf_counter() - t0
        trial_frames += i + 1
        lost_searches += loc.n_searches_ - searches0
        lost_s += loc.search_s_ - search_s0
        frames.append(got)
    relocated = [f for f in frames if f is not None]
    return {
        "index": args.index,
        "frames_per_s": args.queries / stream_s,
        "ms_per_frame": 1e3 * stream_s / args.queries,
        "localized_share": localized / args.queries,
        "searched_share": stream_searches / args.queries,
        "tracked_frames_per_s": tracked / tracked_s if tracked else None,
        "searched_ms_per_frame": 1e3 * (stream_s - tracked_s) / max(1, args.queries - tracked),
        "search_ms_per_search": 1e3 * stream_search_s / max(1, stream_searches),
        "peak_rss_mb": peak_rss_mb(),
        "open_s": open_s,
        "lock_frames": lock_frames,
        "lock_s": lock_s,
        "same_place_within_20_share": hits / args.queries,
        "kidnap_trials": args.kidnaps,
        "kidnap_relocated_share": len(relocated) / max(1, args.kidnaps),
        "kidnap_frames_median": float(statistics.median(relocated)) if relocated else None,
        "kidnap_relocated_ci95": wilson_interval(len(relocated), args.kidnaps),
        "kidnap_frames": frames,
        "kidnap_unsettled": settle_failed,
        "kidnap_searched_share": lost_searches / max(1, trial_frames),
        "kidnap_ms_per_search": 1e3 * lost_s / max(1, lost_searches),
        "kidnap_ms_per_frame": 1e3 * trial_s / max(1, trial_frames),
        "reseeds": loc.n_reseeds_,
    }


def wilson_interval(successes: int, trials: int, z: float = 1.959964) -> list[float] | None:
    """The Wilson score interval of a binomial share (95% by default); None without trials."""
    if trials <= 0:
        return None
    if not 0 <= successes <= trials:
        raise ValueError(f"successes must be in [0, {trials}]; got {successes}")
    share = successes / trials
    z2 = z * z
    centre = (share + z2 / (2 * trials)) / (1 + z2 / trials)
    half = z / (1 + z2 / trials) * math.sqrt(share * (1 - share) / trials + z2 / (4 * trials**2))
    # exactly 0 and 1 at the ends (the formula's are, up to rounding)
    low = 0.0 if successes == 0 else max(0.0, centre - half)
    high = 1.0 if successes == trials else min(1.0, centre + half)
    return [low, high]


def protocol(args, index: str) -> dict:
    """The row's protocol, in words."""
    tables = min(MIH_TABLES, N_BITS // 16)
    over = "" if tables * 16 == N_BITS else f" over the first {tables * 16} bits"
    name = (
        f"multi-index hashing ({tables} x 16-bit tables{over}, radius 1, re-ranked by the "
        "whole code)"
        if index == "mih"
        else "exact scan"
    )
    return {
        "codes": f"CompactEncoder {N_BITS} bits (PCA-rotated signs of the kenyon optic lobe)",
        "map": f"Nordland 64x32 summer codes tiled, tile flip {TILE_FLIP}, place flip "
        f"{PLACE_FLIP}; relocation index: {name}",
        "localizer": f"LargeLocalizer (windowed CANN, defaults), window {WINDOW}; a lost stretch "
        f"searched at its {RESEED_AFTER}th frame, then {RESEED_AFTER} frames after a re-seed or "
        f"twice as late after a search without one, each search sending at most {RESEED_AFTER} "
        f"new codes for the index's top {K}, the candidates of the stretch's last {POOL} frames "
        f"pooled; a layer a lost re-seed displaces, if it had been localized since its seed, "
        f"held for at most {HOLD} frames while neither is localized, the more confident "
        "answering; a layer never localized since its seed (a guess) giving way to any better "
        f"track and searched every {RESEED_AFTER} frames, and on maps of at most "
        f"{FULL_SEARCH_PLACES} places every place's track scored too; a check every "
        f"{CHECK_EVERY} frames",
        "lock_frames": f"frames from a cold start at a random place until the fix is "
        f"localized and within {TOLERANCE} places of the truth (limit {LOCK_LIMIT})",
        "frames_per_s": f"after locking on and {LOCK} frames more (untimed), {args.queries} "
        "winter frames driven on along the map, each encoded from its pixels and localized; "
        "all of it timed",
        "kidnap": f"{args.kidnaps} trials while localized (seed {args.seed}): the query jumps to "
        "a random place "
        "and drives on from there, the localizer not told; relocated at the first fix "
        f"localized and within {TOLERANCE} of the truth, within {KIDNAP_LIMIT} frames; "
        "between trials the stream drives on until the fix is on the place again",
        "machine": f"{platform.machine()}, {os.cpu_count()} cores",
    }


def _child(mode: str, args) -> dict:
    out = args.work / f"{mode}-{args.places}.json"
    cmd = [
        sys.executable,
        __file__,
        f"--_{mode}",
        "--places",
        str(args.places),
        "--queries",
        str(args.queries),
        "--kidnaps",
        str(args.kidnaps),
        "--index",
        args.index if isinstance(args.index, str) else args.index[0],
        "--bits",
        str(args.bits),
        "--seed",
        str(args.seed),
        "--data",
        str(args.data),
        "--work",
        str(args.work),
        "--json",
        str(out),
    ]
    subprocess.run(cmd, check=True)
    return json.loads(out.read_text())


def main(argv=None) -> int:
    global N_BITS
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--places", type=int, action="append", required=True)
    p.add_argument("--queries", type=int, default=5000)
    p.add_argument(
        "--kidnaps",
        type=int,
        default=200,
        help="kidnap trials per map and index (default 200)",
    )
    p.add_argument(
        "--index",
        nargs="+",
        choices=("mih", "exhaustive"),
        default=["exhaustive"],
        help="the relocation index (one row per index and map size): an exact scan (the "
        "default, as in `flyvpr localize`; the one that meets the kidnap target) or "
        "multi-index hashing (radius 1)",
    )
    p.add_argument(
        "--bits",
        type=int,
        default=N_BITS,
        help=f"bits per place of the compact codes (a multiple of 64; default {N_BITS})",
    )
    p.add_argument(
        "--seed",
        type=int,
        default=1,
        help="seed of the cold start's place and of the kidnaps' jumps (default 1, the "
        "committed run's)",
    )
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--work", type=Path, help="folder for the map files (default: a temporary one)")
    p.add_argument("--keep", action="store_true", help="keep the map files")
    p.add_argument("--_build", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--_stream", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.bits % 64 or not 64 <= args.bits <= 512:
        p.error(f"--bits must be a multiple of 64 from 64 to 512; got {args.bits}")
    for name in ("kidnaps", "seed"):
        if getattr(args, name) < 0:
            p.error(f"--{name} must be >= 0; got {getattr(args, name)}")
    N_BITS = args.bits
    if args._build or args._stream:
        args.places = args.places[0]
        args.index = args.index[0]
        row = build(args) if args._build else stream(args)
        args.json.write_text(json.dumps(row))
        return 0

    from flyvpr._io import write_json_atomic

    if not (args.data / "nordland_64x32").is_dir():
        print(f"data folder not found: {args.data / 'nordland_64x32'}", file=sys.stderr)
        return 1
    if min(args.places) < WINDOW or min(args.places) <= args.queries:
        print(f"--places must exceed {WINDOW} and --queries", file=sys.stderr)
        return 2
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="flyvpr-scale-")
        args.work = Path(tmp.name)
    args.work.mkdir(parents=True, exist_ok=True)
    summer, _ = load_frames(args.data)
    np.save(args.work / "summer_codes.npy", fit_encoder(summer).reference_codes_)
    rows = []
    for n in args.places:
        sub = argparse.Namespace(**{**vars(args), "places": n})
        tables = "mih" if "mih" in args.index else "exhaustive"
        built = _child("build", argparse.Namespace(**{**vars(sub), "index": tables}))
        print(f"{n:>10,} places: built in {built['build_s']:.1f} s", flush=True)
        for index in args.index:
            streamed = _child("stream", argparse.Namespace(**{**vars(sub), "index": index}))
            row = {"places": n, **streamed, **built}
            if index == "exhaustive":
                # an exact scan needs no tables: the map file is all it builds
                row["build_s"] = built["build_map_s"]
                row["build_index_s"] = 0.0
                row["index_file_mb"] = 0.0
            row["protocol"] = protocol(args, index)
            rows.append(row)
            median = row["kidnap_frames_median"]
            print(
                f"{n:>10,} places, {index}: {row['frames_per_s']:,.0f} frames/s localized "
                f"({row['localized_share']:.3f} localized, {row['searched_share']:.3f} searched; "
                f"{row['tracked_frames_per_s']:,.0f} frames/s tracked, "
                f"{row['searched_ms_per_frame']:.1f} ms per searched frame), "
                f"peak {row['peak_rss_mb']:.0f} MB, build {row['build_s']:.1f} s, open "
                f"{row['open_s']:.3f} s, lock-on {row['lock_frames']} frames, same place "
                f"{row['same_place_within_20_share']:.3f}; kidnaps relocated "
                f"{row['kidnap_relocated_share']:.2f} (median {median} frames), "
                f"{row['kidnap_ms_per_search']:.1f} ms per search",
                flush=True,
            )
        if not args.keep:
            for f in args.work.glob(f"map-{n}.*"):
                f.unlink()
    write_json_atomic(args.json, rows)
    if tmp is not None:
        tmp.cleanup()
    return 0


if __name__ == "__main__":
    sys.exit(main())

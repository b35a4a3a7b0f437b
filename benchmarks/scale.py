"""Scale benchmark: compact codes of 10^5 .. 10^7 places, streamed with winter queries.

Usage::

    python benchmarks/scale.py --places N [--queries Q] --json FILE [--data DIR] [--work DIR]

Writes a JSON list with one row per ``--places`` value (the option may be repeated), each with
``places``, ``frames_per_s``, ``peak_rss_mb``, ``build_s``, ``open_s``,
``same_place_within_20_share``, ``kidnap_relocated_share``, ``kidnap_frames_median``, more
figures and the ``protocol``.

Protocol:

* **Codes**: :class:`flyvpr.large.CompactEncoder` (256 bits, PCA-rotated signs of the
  ``kenyon`` optic lobe, seed 0) fitted on the 2,400 Nordland 64x32 summer frames.
* **Map** (``build_s``, in its own process, whose peak memory is ``build_peak_rss_mb``): the
  summer codes tiled to N places with :func:`flyvpr.large.write_tiled_map` (tile masks
  flip 25% of the bits, per-place noise 2%), streamed to a map file, then the multi-index
  hashing tables (16 x 16-bit substrings) built from the memory-mapped codes and saved.
* **Stream** (in its own process; ``peak_rss_mb`` is its VmHWM): open the map and the index
  (``open_s``), refit the encoder on the summer frames (not timed), then ``--queries`` winter
  frames driven along the map from a random place: frame at map place ``p`` is winter frame
  ``p mod 2400`` seen on tile ``p // 2400`` (:func:`flyvpr.large.tile_queries`); its true
  place is ``p``.  Each frame is encoded from its pixels, then scored against a window of
  2,048 places around the tracker's estimate; every 250th frame the index is asked for the
  top 100 (a relocation check, pooled over the last 10 frames).  ``frames_per_s`` counts all
  of it.  Until the windowed CANN lands the tracker is a stand-in (:func:`track`): the
  mean similarity along the diagonal of the last 10 frames, at one place per frame, argmax in
  the window.  ``same_place_within_20_share``: frames whose estimate is within 20 places of
  the true one.
* **Kidnap** (``--kidnaps`` trials, default 20): the tracker forgets its place; every frame
  goes to the index (top 100) and :func:`flyvpr.large.pool_candidates` pools the last
  (up to) 10 frames; relocated at the first frame whose best pooled place lies within 20 of
  the true one, if within 30 frames.  ``kidnap_ms_per_frame``: the relocation cost of a lost
  frame (index + pooling).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data"
N_BITS = 256
TILE_FLIP = 0.25
PLACE_FLIP = 0.02
WINDOW = 2048
SEQ = 10
CHECK_EVERY = 250
K = 100
POOL = 10
KIDNAP_LIMIT = 30
TOLERANCE = 20


def peak_rss_mb() -> float:
    """Peak resident memory of this process in MiB (VmHWM; getrusage where /proc is absent)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


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
        metadata={"encoder": "CompactEncoder(n_bits=256, projection='pca', random_state=0)"},
    )
    t1 = time.perf_counter()
    m = open_large_map(path)
    index = MultiIndexHash(radius=1).build(m.codes)
    save_index(path.with_suffix(".mih"), index, m)
    t2 = time.perf_counter()
    return {
        "build_s": t2 - t0,
        "build_map_s": t1 - t0,
        "build_index_s": t2 - t1,
        "map_file_mb": path.stat().st_size / 2**20,
        "index_file_mb": path.with_suffix(".mih").stat().st_size / 2**20,
        "build_peak_rss_mb": peak_rss_mb(),
    }


def _diagonal_scores(history, codes, lo, hi, out):
    """Mean similarity of the last frames along the diagonal (one place per frame) for every
    place lo..hi-1 (``history`` oldest first)."""
    from flyvpr.large import hamming_similarity

    n = len(history)
    out[:] = 0.0
    for j, q in enumerate(history):
        back = n - 1 - j  # frames ago
        a, b = max(lo - back, 0), max(hi - back, 0)
        s = hamming_similarity(q, codes, a, b)[0]
        out[len(out) - len(s) :] += s
    out /= n
    return out


def track(codes, history, estimate: int, buf) -> tuple[int, float]:
    """Stand-in for the windowed filter: the best place in a window of WINDOW places
    around ``estimate + 1`` by :func:`_diagonal_scores`.  Returns (place, score)."""
    n = len(codes)
    lo = min(max(estimate + 1 - WINDOW // 2, 0), n - WINDOW)
    hi = lo + WINDOW
    s = _diagonal_scores(history, codes, lo, hi, buf)
    i = int(np.argmax(s))
    return lo + i, float(s[i])


def stream(args) -> dict:
    """Open, stream and kidnap (run in a child process)."""
    from flyvpr.large import load_index, open_large_map, pool_candidates, tile_queries

    t0 = time.perf_counter()
    m = open_large_map(args.work / f"map-{args.places}.fvmap")
    index = load_index(args.work / f"map-{args.places}.mih", m)
    open_s = time.perf_counter() - t0
    n = m.n_places
    summer, winter = load_frames(args.data)
    enc = fit_encoder(summer)
    del summer
    n_base = len(winter)
    rng = np.random.default_rng(1)

    def query(p: int, code=None):
        code = enc.encode(winter[p % n_base][None]) if code is None else code
        return tile_queries(code, p // n_base, TILE_FLIP, 0)

    # warm up the compiled kernels (not timed)
    warm = query(0)
    index.search(warm, K)
    buf = np.empty(WINDOW, np.float32)
    track(m.codes, [warm], 0, buf)

    # -- localized stream -------------------------------------------------------------
    start = int(rng.integers(0, n - args.queries))
    history, estimate, hits = [], start - 1, 0
    enc_s = check_s = 0.0
    t0 = time.perf_counter()
    for i in range(args.queries):
        p = start + i
        ta = time.perf_counter()
        q = query(p)
        enc_s += time.perf_counter() - ta
        history.append(q)
        del history[:-SEQ]
        estimate, score = track(m.codes, history, estimate, buf)
        if i % CHECK_EVERY == CHECK_EVERY - 1:
            tb = time.perf_counter()
            places, dist = index.search(np.concatenate(history[-POOL:]), K)
            best, _ = pool_candidates(places, dist, N_BITS)
            if best.size and abs(int(best[0]) - estimate) > WINDOW // 2:
                other, other_score = track(m.codes, history, int(best[0]) - 1, buf)
                if other_score > score:
                    estimate = other
            check_s += time.perf_counter() - tb
        hits += abs(estimate - p) <= TOLERANCE
    stream_s = time.perf_counter() - t0

    # -- kidnaps ------------------------------------------------------------------------
    frames, lost_s, lost_frames = [], 0.0, 0
    for _ in range(args.kidnaps):
        p0 = int(rng.integers(0, n - KIDNAP_LIMIT))
        got = None
        res_p, res_d = [], []
        for i in range(KIDNAP_LIMIT):
            q = query(p0 + i)
            ta = time.perf_counter()
            places, dist = index.search(q, K)
            res_p.append(places[0])
            res_d.append(dist[0])
            best, _ = pool_candidates(np.array(res_p[-POOL:]), np.array(res_d[-POOL:]), N_BITS)
            lost_s += time.perf_counter() - ta
            lost_frames += 1
            if best.size and abs(int(best[0]) - (p0 + i)) <= TOLERANCE:
                got = i + 1
                break
        frames.append(got)
    relocated = [f for f in frames if f is not None]
    return {
        "frames_per_s": args.queries / stream_s,
        "ms_per_frame": 1e3 * stream_s / args.queries,
        "encode_ms_per_frame": 1e3 * enc_s / args.queries,
        "check_ms_per_check": 1e3 * check_s / max(1, args.queries // CHECK_EVERY),
        "peak_rss_mb": peak_rss_mb(),
        "open_s": open_s,
        "same_place_within_20_share": hits / args.queries,
        "kidnap_trials": args.kidnaps,
        "kidnap_relocated_share": len(relocated) / max(1, args.kidnaps),
        "kidnap_frames_median": float(statistics.median(relocated)) if relocated else None,
        "kidnap_frames": frames,
        "kidnap_ms_per_frame": 1e3 * lost_s / max(1, lost_frames),
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
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--places", type=int, action="append", required=True)
    p.add_argument("--queries", type=int, default=5000)
    p.add_argument("--kidnaps", type=int, default=20)
    p.add_argument("--json", type=Path, required=True)
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--work", type=Path, help="folder for the map files (default: a temporary one)")
    p.add_argument("--keep", action="store_true", help="keep the map files")
    p.add_argument("--_build", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--_stream", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args._build or args._stream:
        args.places = args.places[0]
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
        built = _child("build", sub)
        print(f"{n:>10,} places: built in {built['build_s']:.1f} s", flush=True)
        streamed = _child("stream", sub)
        row = {"places": n, **streamed, **built}
        row["protocol"] = {
            "codes": f"CompactEncoder {N_BITS} bits (PCA-rotated signs of the kenyon optic lobe)",
            "map": f"Nordland 64x32 summer codes tiled, tile flip {TILE_FLIP}, place flip "
            f"{PLACE_FLIP}; index: multi-index hashing, 16 x 16-bit tables, radius 1",
            "frames_per_s": f"{args.queries} winter frames, encoded one at a time, scored on a "
            f"window of {WINDOW} places around the estimate by a stand-in tracker (mean "
            f"similarity along the diagonal of the last {SEQ} frames, not the CANN), index "
            f"top {K} pooled over {POOL} frames every {CHECK_EVERY} frames",
            "kidnap": f"index top {K} per frame pooled over up to {POOL} frames; relocated when "
            f"the best pooled place is within {TOLERANCE} of the truth, within "
            f"{KIDNAP_LIMIT} frames",
            "machine": f"{platform.machine()}, {os.cpu_count()} cores",
        }
        rows.append(row)
        print(
            f"{n:>10,} places: {row['frames_per_s']:,.0f} frames/s, peak {row['peak_rss_mb']:.0f} "
            f"MB, build {row['build_s']:.1f} s, open {row['open_s']:.3f} s, same place "
            f"{row['same_place_within_20_share']:.3f}, kidnap relocated "
            f"{row['kidnap_relocated_share']:.2f} (median {row['kidnap_frames_median']} frames, "
            f"{row['kidnap_ms_per_frame']:.1f} ms/frame)",
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

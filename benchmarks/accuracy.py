"""Accuracy benchmark: the paper's single- and multi-frame methods on real Nordland data.

Prints one table (AUC and Recall@1, mean and minimum over seeds) for

* methods ``pixels``, ``flynet``, ``seqslam``, ``flynet+seqslam``, ``flynet+rnn``, ``flynet+cann``;
* conditions: Nordland 64x32 summer -> winter, frames 0-999 and 1000-1999 (tolerance 20 frames),
  and the 100-place FlyNet subset summer -> fall and summer -> winter (tolerance 2 frames);
* speed variation for ``flynet+cann`` and ``seqslam`` on the 64x32 windows: every 2nd query frame
  kept (2x), every 1.5th (1.5x) and a seeded random 1-1.5x speed profile (ground truth follows
  the kept frames);
* recovery after a kidnap: the query stream jumps 200 places ahead; frames until the
  ``flynet+cann`` localizer is back within tolerance, next to how much evidence FlyNet's single
  frames hold for the true place after each landing (the median rank of the true place among
  the references over the next 30 frames; 1 = best, half the references = chance);
* the same for ``flynet+cann[fast]``: the CANN with ``flyvpr.temporal.cann.FAST_RECOVERY``
  (weak attractor, two-timescale evidence), at every speed and in the kidnap test.

Usage::

    python benchmarks/accuracy.py [--data ../shared/data] [--seeds 0 1 2 3 4]
                                  [--json benchmarks/accuracy.json] [--markdown FILE]

Every number comes from this run; the protocol is printed with the table.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

from flyvpr import metrics
from flyvpr._io import write_json_atomic, write_text_atomic
from flyvpr.datasets import load_benchmark
from flyvpr.evaluation import speed_profile
from flyvpr.frontends import FRONTENDS
from flyvpr.temporal import FILTERS
from flyvpr.temporal.cann import FAST_RECOVERY

HERE = Path(__file__).resolve().parent
DEFAULT_DATA = HERE.parent.parent / "shared" / "data"

CONDITIONS = [
    # name, folder, reference, query, first, count, tolerance
    ("nordland64 s->w 0-999", "nordland_64x32", "summer", "winter", 0, 1000, 20),
    ("nordland64 s->w 1000-1999", "nordland_64x32", "summer", "winter", 1000, 1000, 20),
    ("subset100 s->f", "nordland_flynet_subset100", "summer", "fall", 0, 100, 2),
    ("subset100 s->w", "nordland_flynet_subset100", "summer", "winter", 0, 100, 2),
]
METHODS = ["pixels", "flynet", "seqslam", "flynet+seqslam", "flynet+rnn", "flynet+cann"]
DETERMINISTIC = {"pixels", "seqslam"}
SPEED_METHODS = ["flynet+cann", "flynet+cann[fast]", "seqslam"]
#: the filter and its parameters behind each "+cann" label
CANN_VARIANTS = {"flynet+cann": {}, "flynet+cann[fast]": FAST_RECOVERY}
SPEEDS = [("2x", 2.0), ("1.5x", 1.5), ("1-1.5x", (1.0, 1.5))]
KIDNAP_JUMP = 200
#: stream frames at which the query stream jumps KIDNAP_JUMP places ahead
KIDNAP_AT = (100, 200, 300, 400, 500, 600, 700)
#: frames after each landing over which FlyNet's own evidence for the true place is summarised
EVIDENCE_FRAMES = 30


def _filter(name: str, seed: int, reference_scores, S, **params):
    filt = FILTERS[name](**params)
    if "random_state" in filt.get_params():
        filt.set_params(random_state=seed)
    if getattr(filt, "needs_reference_scores", False):
        filt.fit(reference_scores)
    return filt.filter(S)


def _score(S, gt):
    return {"auc": metrics.pr_auc(S, gt), "recall_at_1": metrics.recall_at_k(S, gt, 1)}


def run_condition(cond, data: Path, seeds, methods, log):
    name, folder, ref_name, qry_name, first, count, tol = cond
    bench = load_benchmark(
        "nordland",
        root=data / folder,
        reference=ref_name,
        query=qry_name,
        first=first,
        count=count,
        tolerance=tol,
    )
    ref, qry = bench.load_images(cache=True, progress=False)
    gt = bench.ground_truth
    rows = []  # (condition, method, speed, seed, auc, r1, seconds)

    def add(method, speed, seed, S, seconds, gt_used=gt):
        res = _score(S, gt_used)
        rows.append(
            {
                "condition": name,
                "method": method,
                "speed": speed,
                "seed": seed,
                "seconds": seconds,
                **res,
            }
        )
        log(
            f"  {name:26s} {method:16s} {speed:7s} seed {seed}: AUC {res['auc']:.3f} "
            f"R@1 {res['recall_at_1']:.3f} ({seconds:.2f} s)"
        )

    speed_rows = name.startswith("nordland64")
    kidnap = []
    pixels = FRONTENDS["pixels"]().fit(ref)
    t0 = time.perf_counter()
    S_pix = pixels.score(qry)
    t_pix = time.perf_counter() - t0
    for seed in seeds:
        if "pixels" in methods:
            add("pixels", "1x", seed, S_pix, t_pix)
        if "seqslam" in methods:
            t0 = time.perf_counter()
            S = _filter("seqslam", seed, None, S_pix)
            add("seqslam", "1x", seed, S, t_pix + time.perf_counter() - t0)
        flynet_methods = [m for m in methods if m.startswith("flynet")]
        if not flynet_methods:
            continue
        t0 = time.perf_counter()
        fn = FRONTENDS["flynet"](random_state=seed).fit(ref)
        t_fit = time.perf_counter() - t0
        t0 = time.perf_counter()
        S_fn = fn.score(qry)
        t_fn = time.perf_counter() - t0
        S_ref = None
        for m in flynet_methods:
            if m == "flynet":
                add(m, "1x", seed, S_fn, t_fit + t_fn)
                continue
            filt = m.split("+", 1)[1]
            if FILTERS[filt].__dict__.get("needs_reference_scores") and S_ref is None:
                S_ref = fn.score(ref)
            t0 = time.perf_counter()
            S = _filter(filt, seed, S_ref, S_fn)
            add(m, "1x", seed, S, t_fit + t_fn + time.perf_counter() - t0)
            if m == "flynet+cann":
                t0 = time.perf_counter()
                S = _filter("cann", seed, None, S_fn, **FAST_RECOVERY)
                add("flynet+cann[fast]", "1x", seed, S, t_fit + t_fn + time.perf_counter() - t0)
        if speed_rows and "flynet+cann" in methods:
            kidnap.append(
                {"method": "flynet", "seed": seed, "evidence_rank": flynet_evidence_rank(S_fn)}
            )
            for label, params in CANN_VARIANTS.items():
                k = kidnap_recovery(S_fn, tol, seed, **params)
                kidnap.append(
                    {
                        "method": label,
                        "seed": seed,
                        "jump_at": _jump_positions(len(S_fn)),
                        "frames": k,
                    }
                )
                log(f"  {name}: {label} kidnap +{KIDNAP_JUMP} seed {seed}: frames to recover {k}")
        if not speed_rows:
            continue
        for label, speed in SPEEDS:
            keep = speed_profile(len(qry), speed, random_state=seed)
            gt_k = gt[keep]
            for m in SPEED_METHODS:
                if m.split("[")[0] not in methods:
                    continue
                t0 = time.perf_counter()
                if m == "seqslam":
                    S = _filter("seqslam", seed, None, S_pix[keep])
                else:
                    S = _filter("cann", seed, S_ref, S_fn[keep], **CANN_VARIANTS[m])
                add(m, label, seed, S, time.perf_counter() - t0, gt_k)
    return rows, kidnap or None, bench.protocol()


def _jump_positions(n: int) -> list:
    """The jump positions of KIDNAP_AT that leave at least 60 frames after the landing."""
    return [p for p in KIDNAP_AT if p + KIDNAP_JUMP + 60 <= n]


def kidnap_recovery(S_fn, tol, seed, **params):
    """Frames until flynet+cann is back within ``tol`` after the queries jump KIDNAP_JUMP places.

    For every jump position ``p`` in KIDNAP_AT (stream frames), the query stream is frames
    ``0..p-1`` then ``p+KIDNAP_JUMP..n-1`` of the window; the count is the number of frames
    after the jump until the best place is within ``tol`` of the true one.
    """
    n = S_fn.shape[0]
    out = []
    for p in _jump_positions(n):
        order = np.r_[np.arange(p), np.arange(p + KIDNAP_JUMP, n)]
        S = _filter("cann", seed, None, S_fn[order], **params)
        ok = np.abs(S[p:].argmax(axis=1) - order[p:]) <= tol
        out.append(int(np.argmax(ok)) if ok.any() else None)
    return out


def flynet_evidence_rank(S_fn):
    """Median rank of the true place in FlyNet's scores over the frames after each landing.

    For every jump position ``p`` in KIDNAP_AT, the stream lands on query frame
    ``p + KIDNAP_JUMP``; over that frame and the next ``EVIDENCE_FRAMES - 1`` the true place's
    rank among the references (1 = scored highest) is taken per frame and the median reported.
    """
    n = S_fn.shape[0]
    rows = np.arange(n)
    rank = 1 + (S_fn > S_fn[rows, rows][:, None]).sum(axis=1)  # frame-aligned: true place = row
    return [
        int(np.median(rank[p + KIDNAP_JUMP : p + KIDNAP_JUMP + EVIDENCE_FRAMES]))
        for p in _jump_positions(n)
    ]


def summarise(rows):
    groups = {}
    for r in rows:
        groups.setdefault((r["condition"], r["method"], r["speed"]), []).append(r)
    table = []
    for (cond, method, speed), rs in groups.items():
        auc = np.array([r["auc"] for r in rs])
        r1 = np.array([r["recall_at_1"] for r in rs])
        table.append(
            {
                "condition": cond,
                "method": method,
                "speed": speed,
                "n_seeds": len(rs),
                "auc_mean": float(auc.mean()),
                "auc_min": float(auc.min()),
                "r1_mean": float(r1.mean()),
                "r1_min": float(r1.min()),
                "seconds_mean": float(np.mean([r["seconds"] for r in rs])),
            }
        )
    return table


def to_markdown(table, kidnaps, seeds) -> str:
    lines = [
        "| condition | method | speed | AUC mean | AUC min | R@1 mean | R@1 min |",
        "|---|---|---|---|---|---|---|",
    ]
    for t in table:
        lines.append(
            f"| {t['condition']} | {t['method']} | {t['speed']} | {t['auc_mean']:.3f} | "
            f"{t['auc_min']:.3f} | {t['r1_mean']:.3f} | {t['r1_min']:.3f} |"
        )
    for name, entries in kidnaps.items():
        ranks = [e for e in entries if e["method"] == "flynet"]
        if ranks:
            n_ref = {c[0]: c[5] for c in CONDITIONS}.get(name, "?")
            lines.append("")
            lines.append(
                f"FlyNet's evidence after each landing ({name}): median rank of the true place "
                f"among the {n_ref} references over the {EVIDENCE_FRAMES} frames after the jump "
                "(1 = best; chance = half), per jump as below:"
            )
            for e in ranks:
                lines.append(f"  seed {e['seed']}: {e['evidence_rank']}")
        for label in CANN_VARIANTS:
            k = [e for e in entries if e["method"] == label]
            frames = [f if f is not None else np.inf for e in k for f in e["frames"]]
            if not frames:
                continue
            lines.append("")
            lines.append(
                f"Kidnap ({name}, {label}, query stream jumps +{KIDNAP_JUMP} places at stream "
                f"frame {', '.join(map(str, KIDNAP_AT))}; {len(frames)} jumps over the seeds): "
                f"frames until the best place is within tolerance again: median "
                f"{np.median(frames):.0f}, max {np.max(frames):.0f}, "
                f"{np.mean(np.array(frames) <= 30):.0%} within 30 frames."
            )
            for e in k:
                lines.append(f"  seed {e['seed']}: {e['frames']}")
    lines.append("")
    lines.append(
        f"Seeds {list(seeds)}; pixels and seqslam are deterministic (same value per seed)."
    )
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the shared data folder")
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    p.add_argument("--methods", nargs="+", default=METHODS, choices=METHODS)
    p.add_argument(
        "--conditions",
        nargs="+",
        type=int,
        default=list(range(len(CONDITIONS))),
        help="indices into the condition list (default: all)",
    )
    p.add_argument("--json", type=Path, help="write all rows and the summary as JSON")
    p.add_argument("--markdown", type=Path, help="write the summary table as Markdown")
    p.add_argument("--quiet", action="store_true", help="only the final table")
    args = p.parse_args(argv)
    if not args.data.is_dir():
        print(f"data folder not found: {args.data}", file=sys.stderr)
        return 1
    log = (lambda *_: None) if args.quiet else (lambda s: print(s, flush=True))
    all_rows, kidnaps, protocols = [], {}, []
    t_start = time.perf_counter()
    for i in args.conditions:
        rows, kidnap, proto = run_condition(CONDITIONS[i], args.data, args.seeds, args.methods, log)
        all_rows += rows
        protocols.append(proto)
        if kidnap is not None:
            kidnaps[CONDITIONS[i][0]] = kidnap
    table = summarise(all_rows)
    md = to_markdown(table, kidnaps, args.seeds)
    print()
    print("Protocol: reference = summer; frame-aligned ground truth (|q - r| <= tolerance frames);")
    print("images gray 32x64 area-averaged; AUC = trapezoid area under the precision-recall curve")
    print("of each query's best match (see README, Metrics).")
    print(md)
    print(
        f"\n(total {time.perf_counter() - t_start:.0f} s on "
        f"{platform.processor() or platform.machine()})"
    )
    if args.json:
        write_json_atomic(
            args.json,
            {
                "rows": all_rows,
                "summary": table,
                "kidnap": kidnaps,
                "protocols": json.loads(json.dumps(protocols, default=str)),
                "seeds": args.seeds,
            },
        )
    if args.markdown:
        write_text_atomic(args.markdown, md + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

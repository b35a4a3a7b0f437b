"""Large-map accuracy: the windowed CANN with index relocation against the whole-map CANN.

Usage::

    python benchmarks/large_accuracy.py --json benchmarks/large-accuracy.json [--seeds 0 1 2]

Protocol (written into the JSON):

* **Codes**: :class:`flyvpr.large.CompactEncoder` (256 bits, PCA-rotated signs of the kenyon
  optic lobe, ``random_state`` = seed) fitted on the 2,400 Nordland 64x32 summer frames.
* **Map**: the summer codes tiled to 35,768 places with :func:`flyvpr.large.write_tiled_map`
  (tile masks flip 25% of the bits, per-place noise 2%, seed 0), as ``benchmarks/scale.py``.
* **Queries**: the winter frames of a dev window (0-999 or 1000-1999), in order, seen on tile
  7 (:func:`flyvpr.large.tile_queries`): the true place of winter frame ``i`` is
  ``7 * 2400 + i``; ground truth within 2 and 20 places.
* **Whole map**: the CANN (defaults, but ``hold_repeats=False`` as in the
  ``LargeLocalizer``: compact codes repeat on sensor noise) over every frame's Hamming
  similarity to all 35,768 places.  **Windowed**: :class:`flyvpr.large.LargeLocalizer`
  (window 2,048, multi-index hashing or, with ``--index exhaustive``, an exact scan; top
  300, pooled over 10 frames; a displaced layer that had been localized held for up to 30
  frames while neither is localized; a guess giving way to any better track; a lost guess
  also scoring every place's track, the map being under 2^20 places: the defaults), one
  frame at a time from a fresh start: its answer and confidence per frame.  AUC of the
  precision-recall curve from each frame's answer and confidence
  (:func:`flyvpr.metrics.evaluate`).
* **Calibration** (``summary.calibration_tol2``): every frame's confidence against whether
  its answer is within 2 places, pooled over the seeds and windows, in deciles
  (:func:`flyvpr.metrics.reliability`), for both localizers; for the windowed one also its
  ``lost`` frames' mean confidence and share right.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import DEFAULT_DATA  # noqa: E402
from benchmarks.scale import N_BITS, PLACE_FLIP, TILE_FLIP, load_frames  # noqa: E402

N_PLACES = 35_768
TILE = 7
WINDOWS = ((0, 1000), (1000, 2000))
TOLERANCES = (2, 20)


def _answers_matrix(places, confidences, n_places: int) -> np.ndarray:
    """A score matrix whose row maximum is each frame's answer, at its confidence."""
    S = np.full((len(places), n_places), -1.0, np.float32)
    S[np.arange(len(places)), places] = confidences
    return S


def run(data: Path, seeds, index_name: str = "mih", log=print) -> dict:
    from flyvpr import metrics
    from flyvpr.large import (
        CompactEncoder,
        ExhaustiveIndex,
        LargeLocalizer,
        MultiIndexHash,
        hamming_similarity,
        open_large_map,
        tile_queries,
        write_tiled_map,
    )
    from flyvpr.temporal.cann import CANN

    summer, winter = load_frames(data)
    n_base = len(summer)
    rows = []
    # every frame's confidence, whether it was right (within 2) and its state, for the
    # reliability of each localizer's confidence
    answers: dict[str, list] = {"windowed": [[], [], []], "whole_map": [[], [], []]}
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            enc = CompactEncoder(n_bits=N_BITS, random_state=seed).fit(summer)
            path = Path(tmp) / f"map-{seed}.fvmap"
            write_tiled_map(path, enc.encode(summer), N_PLACES, TILE_FLIP, PLACE_FLIP, 0)
            m = open_large_map(path)
            index = (MultiIndexHash(radius=1) if index_name == "mih" else ExhaustiveIndex()).build(
                m.codes
            )
            for lo, hi in WINDOWS:
                q = tile_queries(enc.encode(winter[lo:hi]), TILE, TILE_FLIP, 0)
                truth = TILE * n_base + np.arange(lo, hi)
                t0 = time.perf_counter()
                # (compact codes repeat on sensor noise: no hold, as in the LargeLocalizer)
                whole = CANN(hold_repeats=False).filter(hamming_similarity(q, m.codes))
                whole_s = time.perf_counter() - t0
                loc = LargeLocalizer(m.codes, index, window=2048)
                loc.update_code(q[0])  # compile the kernels (not timed)
                loc.reset()
                t0 = time.perf_counter()
                fixes = [loc.update_code(code) for code in q]
                windowed_s = time.perf_counter() - t0
                places = np.array([f.place for f in fixes])
                conf = np.array([f.confidence for f in fixes], np.float32)
                windowed = _answers_matrix(places, conf, N_PLACES)
                best = whole.argmax(axis=1)
                for key, where, level, states in (
                    ("windowed", places, conf, [f.state for f in fixes]),
                    ("whole_map", best, whole[np.arange(len(q)), best], None),
                ):
                    answers[key][0] += np.asarray(level, np.float64).tolist()
                    answers[key][1] += (np.abs(where - truth) <= TOLERANCES[0]).tolist()
                    answers[key][2] += states or []
                for tol in TOLERANCES:
                    gt = np.abs(np.arange(N_PLACES)[None, :] - truth[:, None]) <= tol
                    a = metrics.evaluate(whole, gt, ks=(1,))
                    b = metrics.evaluate(windowed, gt, ks=(1,))
                    row = {
                        "seed": seed,
                        "window": f"{lo}-{hi - 1}",
                        "tolerance": tol,
                        "whole_map_auc": a["auc"],
                        "windowed_auc": b["auc"],
                        "whole_map_recall_at_1": a["recall_at_1"],
                        "windowed_recall_at_1": b["recall_at_1"],
                        "whole_map_ms_per_frame": 1e3 * whole_s / len(q),
                        "windowed_ms_per_frame": 1e3 * windowed_s / len(q),
                        "index_searches": loc.n_searches_,
                        "reseeds": loc.n_reseeds_,
                        "localized_share": float(np.mean([f.state == "localized" for f in fixes])),
                    }
                    rows.append(row)
                    log(
                        f"seed {seed} {row['window']} tol {tol}: whole map AUC "
                        f"{row['whole_map_auc']:.3f}, windowed {row['windowed_auc']:.3f} "
                        f"({row['windowed_ms_per_frame']:.2f} vs "
                        f"{row['whole_map_ms_per_frame']:.2f} ms per frame, "
                        f"{loc.n_searches_} index searches, {loc.n_reseeds_} re-seeds)"
                    )
            del m, index
    summary = {}
    for tol in TOLERANCES:
        sel = [r for r in rows if r["tolerance"] == tol]
        summary[f"tol{tol}"] = {
            "whole_map_auc_mean": float(np.mean([r["whole_map_auc"] for r in sel])),
            "windowed_auc_mean": float(np.mean([r["windowed_auc"] for r in sel])),
            "largest_drop": float(max(r["whole_map_auc"] - r["windowed_auc"] for r in sel)),
        }
    calibration = {}
    for key, (conf, right, states) in answers.items():
        entry = {"reliability": metrics.reliability(np.array(conf), np.array(right, bool))}
        if states:
            lost = np.array(states) != "localized"
            entry["lost_frames"] = int(lost.sum())
            entry["lost_mean_confidence"] = float(np.mean(np.array(conf)[lost]))
            entry["lost_right_share"] = float(np.mean(np.array(right)[lost]))
        calibration[key] = entry
    summary["calibration_tol2"] = calibration
    return {"rows": rows, "summary": summary}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument(
        "--index",
        choices=("mih", "exhaustive"),
        default="mih",
        help="the relocation index: multi-index hashing (radius 1) or an exact scan",
    )
    p.add_argument("--json", type=Path, help="write the rows and the summary (atomically)")
    args = p.parse_args(argv)
    out = run(args.data, args.seeds, args.index)
    out["protocol"] = __doc__.split("Protocol (written into the JSON):")[1].strip()
    out["command"] = ["large_accuracy.py", *(argv if argv is not None else sys.argv[1:])]
    for tol, s in out["summary"].items():
        if not tol.startswith("tol"):
            continue
        print(
            f"{tol}: whole-map AUC {s['whole_map_auc_mean']:.3f}, windowed "
            f"{s['windowed_auc_mean']:.3f}, largest drop {s['largest_drop']:+.3f}"
        )
    if args.json:
        tmp = args.json.with_suffix(".tmp")
        tmp.write_text(json.dumps(out, indent=1) + "\n")
        os.replace(tmp, args.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""The ``kenyon`` front end with and without its intensity channel (``intensity=True``).

Usage::

    python benchmarks/kenyon_intensity.py --json benchmarks/kenyon-intensity.json \
        [--data ../shared/data]

The intensity channel gives the Kenyon cells the contrast-normalised image summed over each
pooling cell besides the optic lobe's Gabor energies (see ``KenyonEncoder``).  Compared here,
each as ``kenyon`` alone and ``kenyon+cann`` (the CANN's defaults), AUC at tolerance 2 and 20
frames, seeds 0-2 (the Kenyon cells' connections):

* ``nordland_64x32`` summer (map) -> winter (query), frames 0-999 (the filter's dev window) and
  1000-1999, as they are and through the fisheye disc of the accuracy benchmark (both
  traverses black outside it: the static-pixel mask at work);
* ``nordland_64x32_viewpoint`` summer -> winter (the drifting viewpoint), 0-999 and 1000-1999;
* ``nordland_64x32`` frames 2000-2399, which tuned nothing;
* the dev window with its queries shuffled (``numpy.random.default_rng(0).permutation``, the
  accuracy benchmark's ``r-shuffled``): no sequence to follow, where ``kenyon+cann`` must not
  fall more than 0.01 below ``kenyon`` alone (issue 19);
* the detour of the accuracy benchmark on the dev window (map: summer 0-999 without 400-699,
  query: winter 0-999 in order): the share of off-map frames ``localized`` and the frames
  after the rejoin until the answer is ``localized`` and right (tolerance 2).

And the cost: milliseconds to encode one streamed frame, full and through the fisheye disc,
both encoders alternating in one run.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from flyvpr._io import write_json_atomic
from flyvpr.datasets.nordland import load_nordland
from flyvpr.frontends import KenyonEncoder
from flyvpr.methods import make_method
from flyvpr.metrics import pr_auc

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import DEFAULT_DATA, machine  # noqa: E402
from benchmarks.accuracy_setup import FISHEYE_DISC, fisheye  # noqa: E402

#: key -> (folder, first frame, count, through the fisheye disc, queries shuffled, used for
#: tuning anything)
WINDOWS = {
    "nordland 0-999": ("nordland_64x32", 0, 1000, False, False, True),
    "nordland 0-999 fisheye": ("nordland_64x32", 0, 1000, True, False, True),
    "nordland 0-999 shuffled": ("nordland_64x32", 0, 1000, False, True, True),
    "nordland 1000-1999": ("nordland_64x32", 1000, 1000, False, False, True),
    "nordland 1000-1999 fisheye": ("nordland_64x32", 1000, 1000, True, False, True),
    "viewpoint 0-999": ("nordland_64x32_viewpoint", 0, 1000, False, False, True),
    "viewpoint 1000-1999": ("nordland_64x32_viewpoint", 1000, 1000, False, False, True),
    "nordland 2000-2399 (held out)": ("nordland_64x32", 2000, 400, False, False, False),
}
SEEDS = (0, 1, 2)
TOLERANCES = (2, 20)
#: the detour: the map leaves out these frames of the dev window
GAP = (400, 700)
VARIANTS = {"gabor": False, "gabor+intensity": True}


def _load(data: Path, folder: str, first: int, count: int):
    bench = load_nordland(data / folder, "summer", "winter", first=first, count=count, tolerance=0)
    ref = bench.reference.load_images(progress=False)
    qry = bench.query.load_images(progress=False)
    return ref, qry


def _truth(n: int, tol: int) -> np.ndarray:
    places = np.arange(n)
    return np.abs(places[:, None] - places[None, :]) <= tol


def window_runs(ref, qry, intensity: bool, order: np.ndarray | None = None) -> list[dict]:
    """AUC of kenyon and kenyon+cann per seed and tolerance: query frame i shows place i,
    fed in ``order`` (default: as recorded)."""
    rows = []
    if order is None:
        order = np.arange(len(qry))
    qry = qry[order]
    gts = {tol: _truth(len(ref), tol)[order] for tol in TOLERANCES}
    for seed in SEEDS:
        method = make_method("kenyon+cann", seed, {"intensity": intensity}).fit(ref)
        scores = method.frontend.score(qry)
        filtered = method.filter.filter(scores)
        for tol, gt in gts.items():
            rows.append(
                {
                    "seed": seed,
                    "tolerance": tol,
                    "kenyon": pr_auc(scores, gt),
                    "kenyon+cann": pr_auc(filtered, gt),
                }
            )
    return rows


def detour_runs(ref, qry, intensity: bool) -> list[dict]:
    """The dev detour, frame by frame through the streaming filter, per seed."""
    keep = np.r_[0 : GAP[0], GAP[1] : len(ref)]
    places = np.arange(len(qry))
    gt = np.abs(places[:, None] - keep[None, :]) <= 2
    off = (places >= GAP[0]) & (places < GAP[1])
    rows = []
    for seed in SEEDS:
        method = make_method("kenyon+cann", seed, {"intensity": intensity}).fit(ref[keep])
        scores = method.frontend.score(qry)
        filt = method.filter
        filt.reset()
        out = np.empty(scores.shape, np.float32)
        localized = np.zeros(len(qry), bool)
        for t, row in enumerate(scores):
            out[t] = filt.step(row)
            localized[t] = filt.state_ == "localized"
        right = np.abs(keep[out.argmax(axis=1)] - places) <= 2
        back = np.flatnonzero(localized[GAP[1] :] & right[GAP[1] :])
        rows.append(
            {
                "seed": seed,
                "auc": pr_auc(out, gt),
                "off_map_localized": float(localized[off].mean()),
                "rejoin_frames": int(back[0]) if back.size else None,
            }
        )
    return rows


def encode_ms(ref, rounds: int = 5, frames: int = 400) -> dict:
    """Milliseconds per streamed frame (one image per call), the variants alternating; for the
    full frames and for the same frames through the fisheye disc (the mask at work)."""
    out: dict = {}
    for camera, images in (("full", ref[:frames]), ("fisheye", fisheye(ref[:frames]))):
        encoders = {
            name: KenyonEncoder(random_state=0, intensity=flag).fit(images)
            for name, flag in VARIANTS.items()
        }
        times: dict[str, list[float]] = {name: [] for name in VARIANTS}
        for enc in encoders.values():
            enc.encode(images[:1])  # compile
        for _ in range(rounds):
            for name, enc in encoders.items():
                t0 = time.perf_counter()
                for i in range(len(images)):
                    enc.encode(images[i : i + 1])
                times[name].append((time.perf_counter() - t0) / len(images) * 1e3)
        row = {f"{name}_ms": float(np.median(v)) for name, v in times.items()}
        row["ratio"] = row["gabor+intensity_ms"] / row["gabor_ms"]
        out[camera] = row
    return out


def _mean(rows: list[dict], key: str, tol: int) -> float:
    return float(np.mean([r[key] for r in rows if r["tolerance"] == tol]))


def render_table(data: dict) -> str:
    """The Markdown table of a ``--json`` document: mean AUC over the seeds at tolerance 2 / 20,
    kenyon+cann then kenyon alone, per window and variant; then the detour and the cost."""
    lines = [
        "| window | kenyon+cann | + intensity | kenyon alone | + intensity |",
        "|---|---|---|---|---|",
    ]
    for key, entry in data["windows"].items():
        cells = []
        for method in ("kenyon+cann", "kenyon"):
            for variant in VARIANTS:
                rows = entry[variant]
                cells.append(" / ".join(f"{_mean(rows, method, t):.3f}" for t in TOLERANCES))
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("| detour, dev window | kenyon+cann | + intensity |")
    lines.append("|---|---|---|")
    det = data["detour"]
    for label, key, fmt in (
        ("AUC, tolerance 2 (seeds 0 / 1 / 2)", "auc", "{:.3f}"),
        ("off-map frames localized", "off_map_localized", "{:.1%}"),
        ("frames to localized and right after the rejoin", "rejoin_frames", "{}"),
    ):
        cells = [
            " / ".join(fmt.format(r[key]) if r[key] is not None else "never" for r in det[v])
            for v in VARIANTS
        ]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("| encoding one streamed frame | without | with the intensity channel | ratio |")
    lines.append("|---|---|---|---|")
    for camera, label in (("full", "full frames"), ("fisheye", "through the fisheye disc")):
        cost = data["encode"][camera]
        lines.append(
            f"| {label} | {cost['gabor_ms']:.3f} ms | {cost['gabor+intensity_ms']:.3f} ms | "
            f"{cost['ratio']:.2f}x |"
        )
    lines.append("")
    lines.append("(One run, the variants alternating: medians of 5 rounds of 400 frames.)")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--json", type=Path, help="write the results as JSON (atomically)")
    args = p.parse_args(argv)
    for folder in {w[0] for w in WINDOWS.values()}:
        if not (args.data / folder).is_dir():
            print(f"data folder not found: {args.data / folder}", file=sys.stderr)
            return 1
    windows = {}
    for key, (folder, first, count, disc, shuffled, tuning) in WINDOWS.items():
        ref, qry = _load(args.data, folder, first, count)
        if disc:
            ref, qry = fisheye(ref), fisheye(qry)
        entry = {
            "protocol": {
                "folder": folder,
                "reference": "summer",
                "query": "winter",
                "frames": f"{first}-{first + len(ref) - 1}",
                "fisheye_disc": list(FISHEYE_DISC) if disc else None,
                "query_order": "numpy.random.default_rng(0).permutation" if shuffled else None,
                "used_for_tuning": tuning,
            }
        }
        for variant, flag in VARIANTS.items():
            t0 = time.perf_counter()
            order = np.random.default_rng(0).permutation(len(qry)) if shuffled else None
            entry[variant] = window_runs(ref, qry, flag, order)
            print(
                f"{key:30s} {variant:16s} kenyon+cann AUC tol 2 / 20: "
                + " / ".join(f"{_mean(entry[variant], 'kenyon+cann', t):.3f}" for t in TOLERANCES)
                + f"  ({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
        windows[key] = entry
    ref, qry = _load(args.data, "nordland_64x32", 0, 1000)
    detour = {variant: detour_runs(ref, qry, flag) for variant, flag in VARIANTS.items()}
    out = {
        "benchmark": "kenyon-intensity",
        "what": "kenyon with and without the intensity channel, alone and +cann (CANN defaults)",
        "metric": "PR AUC (flyvpr.metrics.pr_auc), query frame i shows place i",
        "seeds": list(SEEDS),
        "tolerances": list(TOLERANCES),
        "detour_gap": list(GAP),
        "machine": machine(),
        "windows": windows,
        "detour": detour,
        "encode": encode_ms(ref),
    }
    print(render_table(out))
    if args.json:
        write_json_atomic(args.json, out)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Calibration benchmark: the CANN's confidence on a route, as it comes and recalibrated with a
table fitted on a labelled run of that route.

Usage::

    python benchmarks/calibration.py --json benchmarks/calibration.json [--data DIR]

Protocol: ``kenyon+cann`` (defaults) on the robot views of the held-out window (Nordland 64x32
summer -> winter, frames 2000-2399, which tuned nothing: every robot view of
``benchmarks/accuracy.py`` on that window, ``r-walk-2000``, ``r-walk-odo-2000``,
``r-walk-odo-gaps-2000``, ``r-walk-odo-long-2000``, ``r-stopgo-2000``, ``r-stopgo-noisy-2000``
and ``r-detour-2000``), tolerance 2.  The runs of seeds 0-4 (the
front end's random projection) are the labelled run: every frame's confidence and whether its
answer was right give a table through :func:`flyvpr.temporal.cann.fit_calibration`.  The runs
of seeds 5-9 are then scored twice, with the defaults and with ``recalibration`` set to the
fitted table: per confidence decile, answers, mean confidence and share right.  Both halves
see the same route and frames (a user who labels one drive of a route and calibrates the
filter for it); they differ in the front end's projection.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))

from benchmarks._common import machine, machine_sentence, run_page_benchmark  # noqa: E402
from benchmarks.accuracy_run import gap_keep, load_dataset  # noqa: E402
from benchmarks.accuracy_setup import DATASETS, ROBOT_VIEWS  # noqa: E402
from flyvpr import metrics  # noqa: E402
from flyvpr.datasets import ground_truth_from_frames  # noqa: E402
from flyvpr.methods import make_method  # noqa: E402
from flyvpr.temporal.cann import CANN, fit_calibration, route_breaks  # noqa: E402

DATASET = "n64-2000"
TOLERANCE = 2
FIT_SEEDS = (0, 1, 2, 3, 4)
TEST_SEEDS = (5, 6, 7, 8, 9)
BINS = 10


def _runs(data: Path, seeds, progress: bool, dataset_key: str = DATASET):
    """For each seed and robot view of the window ``dataset_key`` (default: the held-out one):
    the front end's scores of the view's frames, its odometry (or None), its ground truth at
    ``TOLERANCE`` and the map's breaks for the CANN (a detour's map keeps its places' frame
    numbers, as in ``benchmarks/accuracy.py``; none otherwise)."""
    dataset = {d.key: d for d in DATASETS}[dataset_key]
    ref, qry, ref_ids, qry_ids, _ = load_dataset(dataset, data)
    views = [v for v in ROBOT_VIEWS if v.dataset == dataset_key]
    for seed in seeds:
        for view in views:
            keep = np.arange(len(ref)) if view.gap is None else gap_keep(len(ref), view.gap)
            method = make_method("kenyon+cann", seed, {}, {})
            method.frontend.fit(ref[keep])
            idx = view.indices(len(qry_ids))
            S = method.frontend.score(view.frames(qry, idx))
            gt = ground_truth_from_frames(qry_ids[idx], ref_ids[keep], TOLERANCE)
            if progress:
                print(f"  seed {seed} {view.key}", file=sys.stderr, flush=True)
            breaks = () if view.gap is None else route_breaks(ref_ids[keep])
            yield view.key, seed, S, view.odometry_steps(qry_ids[idx]), gt, breaks


def _stream(filt: CANN, S, moved, gt):
    """Per frame: confidence, whether the answer is right, and whether it came from the
    sequence."""
    filt.reset()
    out = []
    for t in range(len(S)):
        # (no odometry on the first frame, nor in an outage of it: NaN)
        v = None if moved is None or t == 0 or np.isnan(moved[t]) else float(moved[t])
        row = filt.step(S[t]) if v is None else filt.step(S[t], velocity=v)
        out.append((filt.confidence_, bool(gt[t, int(row.argmax())]), filt.source_ == "sequence"))
    return out


def reliability(answers) -> list[dict]:
    """Per confidence decile: answers, mean confidence, share right."""
    return metrics.reliability([a[0] for a in answers], [a[1] for a in answers], BINS)


def run(data: Path, progress: bool = True) -> dict:
    confidence, right = [], []
    for _key, _seed, S, moved, gt, breaks in _runs(data, FIT_SEEDS, progress):
        for conf, ok, _seq in _stream(CANN(breaks=breaks), S, moved, gt):
            confidence.append(conf)
            right.append(ok)
    table = fit_calibration(confidence, right)
    answers: dict[str, list] = {"default": [], "recalibrated": []}
    for _key, _seed, S, moved, gt, breaks in _runs(data, TEST_SEEDS, progress):
        for name, t in (("default", None), ("recalibrated", table)):
            answers[name] += _stream(CANN(recalibration=t, breaks=breaks), S, moved, gt)
    result = {
        "benchmark": "calibration",
        "protocol": {
            "method": "kenyon+cann (defaults)",
            "data": "nordland_64x32 summer -> winter, frames 2000-2399 (held out)",
            "views": [v.key for v in ROBOT_VIEWS if v.dataset == DATASET],
            "tolerance": TOLERANCE,
            "fit_seeds": list(FIT_SEEDS),
            "test_seeds": list(TEST_SEEDS),
            "fit": "fit_calibration (prior_weight 1) on every frame's confidence",
        },
        "machine": machine(),
        "fit_answers": len(confidence),
        "table": list(table),
        "tables": {name: reliability(a) for name, a in answers.items()},
    }
    for name, rows in result["tables"].items():
        result[f"{name}_largest_gap"] = max(abs(r["right"] - r["confidence"]) for r in rows)
    return result


def render_markdown(data: dict) -> str:
    """The protocol and the two reliability tables (headings from level 2)."""
    p = data["protocol"]
    lines = [
        "## Protocol",
        "",
        f"{p['method']} on {p['data']}; views {', '.join(p['views'])}; tolerance "
        f"{p['tolerance']}.  Seeds {p['fit_seeds'][0]}-{p['fit_seeds'][-1]} are the labelled "
        f"run ({data['fit_answers']} frames; {p['fit']}); seeds "
        f"{p['test_seeds'][0]}-{p['test_seeds'][-1]} are scored with the defaults and with "
        "the fitted table as the CANN's `recalibration`.",
        "",
        "Fitted table (at confidence 0, 0.1, ..., 1): "
        + ", ".join(f"{v:.3f}" for v in data["table"])
        + ".",
        "",
    ]
    for name, title in (("default", "As it comes"), ("recalibrated", "Recalibrated")):
        lines += [
            f"## {title} (largest gap {data[f'{name}_largest_gap']:.3f})",
            "",
            "| confidence | answers | mean confidence | share right | gap |",
            "|---|---|---|---|---|",
        ]
        for r in data["tables"][name]:
            lines.append(
                f"| {r['bin']} | {r['n']} | {r['confidence']:.3f} | {r['right']:.3f} | "
                f"{r['right'] - r['confidence']:+.3f} |"
            )
        lines.append("")
    if machine_sentence(data):
        lines.append(machine_sentence(data))
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    return run_page_benchmark(__doc__, run, render_markdown, argv)


if __name__ == "__main__":
    raise SystemExit(main())

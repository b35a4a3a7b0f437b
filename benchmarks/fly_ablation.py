"""Ablation of the ``kenyon`` front end: what each stage adds, every stage followed by the CANN.

Usage::

    python benchmarks/fly_ablation.py --json benchmarks/fly-ablation.json [--data ../shared/data]

Stages (each scored +cann with the CANN's defaults):

* ``pixels``: SeqSLAM's patch-normalised pixels, mean absolute difference (the bar to beat);
* ``lobe-cosine``: the fixed optic lobe's 512 features, cosine similarity (no Kenyon cells);
* ``kenyon-uncentred``: + the Kenyon-cell expansion (4096 KCs, 10 inputs each, 5% active),
  without subtracting the reference traverse's mean features first;
* ``kenyon``: the front end as shipped (centred features, one population of 4096 KCs);
* ``kenyon-4proj``: the same 4096 KCs as 4 independent populations of 1024, each with its own
  winner-take-all (5% of each);
* ``kenyon-pool2`` and ``kenyon-pool1``: ``kenyon`` with the lobe's max pooling over 2x2 cells
  (2048 features) or none (8192 features) in place of 4x4 (512): how much place information
  the pooling gives away.

Every stage is also scored alone (its front-end scores, no filter): the second table.

Data: ``nordland_64x32`` summer -> winter, frames 0-999 and 1000-1999, and
``nordland_64x32_viewpoint`` summer -> winter frames 0-999 (the tuning sets; tolerance 20
frames); ``nordland_flynet_subset100`` summer -> winter (100 places, tolerance 2) as a check that
was not used for tuning.  Seeds 0-2 for the random stages.  Metric: area under the
precision-recall curve (:func:`flyvpr.metrics.pr_auc`) and recall@1.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from flyvpr._io import write_json_atomic
from flyvpr.datasets.nordland import load_nordland
from flyvpr.frontends import Encoder, KenyonEncoder, PixelsEncoder
from flyvpr.frontends.optic_lobe import varying_pixels
from flyvpr.methods import Method
from flyvpr.metrics import pr_auc, recall_at_k
from flyvpr.temporal import FILTERS

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import DEFAULT_DATA  # noqa: E402

HERE = Path(__file__).resolve().parent

#: key -> (folder, query season, first, count, tolerance, used for tuning)
DATASETS = {
    "nordland 0-999": ("nordland_64x32", "winter", 0, 1000, 20, True),
    "nordland 1000-1999": ("nordland_64x32", "winter", 1000, 1000, 20, True),
    "viewpoint 0-999": ("nordland_64x32_viewpoint", "winter", 0, 1000, 20, True),
    "subset100 s->w": ("nordland_flynet_subset100", "winter", 0, None, 2, False),
}
SEEDS = (0, 1, 2)


class LobeCosine(KenyonEncoder):
    """The optic lobe's features compared by cosine similarity (no Kenyon cells)."""

    def _fit(self, images):
        self._optic_lobe = self._make_lobe()
        self.valid_pixels_ = varying_pixels(images)  # (the lobe's mask, as the encoder's)
        self._set_valid()
        self.reference_codes_ = self._unit(self._lobe(images))

    @staticmethod
    def _unit(features):
        norm = np.linalg.norm(features, axis=1, keepdims=True)
        return features / np.where(norm > 0, norm, 1.0)

    def _encode(self, images):
        return self._unit(self._lobe(images))

    def _score(self, codes):
        return codes @ self.reference_codes_.T


class KenyonUncentred(KenyonEncoder):
    """``kenyon`` without subtracting the reference traverse's mean features."""

    def _fit(self, images):
        super()._fit(images)
        self.feature_mean_ = np.zeros_like(self.feature_mean_)
        self.reference_codes_ = self._codes(self._lobe(images))
        self._index()


#: stage -> (encoder factory taking a seed, seeded?)
STAGES = {
    "pixels": (lambda seed: PixelsEncoder(), False),
    "lobe-cosine": (lambda seed: LobeCosine(), False),
    "kenyon-uncentred": (lambda seed: KenyonUncentred(random_state=seed), True),
    "kenyon": (lambda seed: KenyonEncoder(random_state=seed), True),
    "kenyon-4proj": (lambda seed: KenyonEncoder(n_projections=4, random_state=seed), True),
    "kenyon-pool2": (lambda seed: KenyonEncoder(pool_size=2, random_state=seed), True),
    "kenyon-pool1": (lambda seed: KenyonEncoder(pool_size=1, random_state=seed), True),
}


#: stage -> its row label in the table
LABELS = {
    "pixels": "`pixels` (bar)",
    "lobe-cosine": "optic lobe, cosine",
    "kenyon-uncentred": "+ Kenyon cells, not centred",
    "kenyon": "+ centring (`kenyon`, shipped)",
    "kenyon-4proj": "+ 4 projections (4 x 1024 cells)",
    "kenyon-pool2": "`kenyon`, 2x2 pooling (2048 features)",
    "kenyon-pool1": "`kenyon`, no pooling (8192 features)",
}
#: data set -> its column heading in the table
COLUMNS = {
    "nordland 0-999": "Nordland 0-999",
    "nordland 1000-1999": "Nordland 1000-1999",
    "viewpoint 0-999": "viewpoint 0-999",
    "subset100 s->w": "subset100 s->w",
}


def render_table(data: dict) -> str:
    """The Markdown tables of a ``--json`` document: AUC per stage and data set +cann, then
    (for a document that has them) alone; the random stages as mean [min, max] over the
    seeds."""
    results = data["results"]
    keys = [k for k in COLUMNS if k in results]
    lines = _auc_table(results, keys, "stage (+cann)", "")
    alone = all("front_auc_mean" in row for k in keys for row in results[k]["stages"].values())
    if alone:
        lines += ["", *_auc_table(results, keys, "stage alone (no filter)", "front_")]
    return "\n".join(lines)


def _auc_table(results: dict, keys: list, heading: str, prefix: str) -> list[str]:
    """Rows of ``LABELS`` by columns ``keys``: the AUC fields named ``{prefix}auc_*``."""
    lines = [
        f"| {heading} | " + " | ".join(COLUMNS[k] for k in keys) + " |",
        "|---" * (len(keys) + 1) + "|",
    ]
    for stage, label in LABELS.items():
        cells = []
        for key in keys:
            row = results[key]["stages"].get(stage)
            if row is None:
                cells.append("-")
                continue
            mean, low, high = (row[f"{prefix}auc_{x}"] for x in ("mean", "min", "max"))
            cells.append(f"{mean:.3f} [{low:.3f}, {high:.3f}]" if row["seeds"] else f"{mean:.3f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def run_stage(front: Encoder, ref, qry, gt) -> dict:
    """The stage +cann (its AUC and recall@1) and alone (``front_``: its own scores)."""
    method = Method("ablation+cann", front, FILTERS["cann"]()).fit(ref)
    alone = method.frontend.score(qry)
    S = method.filter.filter(alone)
    return {
        "auc": pr_auc(S, gt),
        "recall_at_1": recall_at_k(S, gt, 1),
        "front_auc": pr_auc(alone, gt),
        "front_recall_at_1": recall_at_k(alone, gt, 1),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--json", type=Path, help="write the results as JSON (atomically)")
    args = p.parse_args(argv)
    results = {}
    for key, (folder, query, first, count, tol, tuning) in DATASETS.items():
        root = args.data / folder
        if not root.is_dir():
            print(f"data folder not found: {root}", file=sys.stderr)
            return 1
        bench = load_nordland(root, "summer", query, first=first, count=count, tolerance=tol)
        ref = bench.reference.load_images(progress=False)
        qry = bench.query.load_images(progress=False)
        results[key] = {
            "protocol": {
                "folder": folder,
                "reference": "summer",
                "query": query,
                "frames": f"{first}-{first + len(ref) - 1}",
                "tolerance_frames": tol,
                "used_for_tuning": tuning,
            },
            "stages": {},
        }
        for stage, (factory, seeded) in STAGES.items():
            t0 = time.perf_counter()
            runs = {
                seed: run_stage(factory(seed), ref, qry, bench.ground_truth)
                for seed in (SEEDS if seeded else (None,))
            }
            row = {
                "seeds": list(SEEDS) if seeded else None,
                "runs": {str(s): r for s, r in runs.items()},
            }
            for prefix in ("", "front_"):
                aucs = [r[f"{prefix}auc"] for r in runs.values()]
                row[f"{prefix}auc_mean"] = float(np.mean(aucs))
                row[f"{prefix}auc_min"] = float(np.min(aucs))
                row[f"{prefix}auc_max"] = float(np.max(aucs))
            results[key]["stages"][stage] = row
            print(
                f"{key:20s} {stage:18s} AUC mean {row['auc_mean']:.3f} "
                f"[{row['auc_min']:.3f}, {row['auc_max']:.3f}], alone {row['front_auc_mean']:.3f}"
                f"  ({time.perf_counter() - t0:.1f} s)",
                flush=True,
            )
    out = {
        "what": "kenyon front end ablation, every stage +cann (CANN defaults) and alone",
        "metric": "PR AUC (flyvpr.metrics.pr_auc) +cann and alone (front_); recall_at_1 per run",
        "seeds": list(SEEDS),
        "results": results,
    }
    if args.json:
        write_json_atomic(args.json, out)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Compact codes (<= 64 bytes per place) against the full 4096-cell ``kenyon`` code.

Usage::

    python benchmarks/compact_codes.py --json benchmarks/compact-codes.json [--data DIR]

Data: ``nordland_64x32`` summer -> winter, frames 0-999 and 1000-1999 (the dev windows),
tolerance 2 and 20 frames, seeds 0-2.  Each code is scored by Hamming similarity
(``1 - hamming / n_bits``; the full code by its overlap, as the front end does), then the
CANN (defaults) filters the score matrix.  Figures: single-frame recall@1 and PR AUC, and PR
AUC after the CANN, mean over the 2 windows x 3 seeds (min and max of the CANN's AUC).

Codes compared (all from the same fitted KenyonEncoder's optic lobe and mean features):

* ``pca``: :class:`flyvpr.large.CompactEncoder` (PCA-rotated signs), 256 and 512 bits;
* ``simhash``: its ``projection="simhash"`` (Gaussian sign random projection);
* ``kc-median``: the first 256 / 512 Kenyon cells' activity, thresholded at its median per
  image (dense bits from the sparse projection);
* ``kc-subset``: 256 / 512 bits of the Kenyon code, every 16th / 8th (sparse: about 5% set);
* ``kc-xor``: the 4096-bit code folded by XOR to 256 / 512 bits.

**Pooling through a fisheye disc.**  ``CompactEncoder.fit`` (what ``flyvpr map --compact``
runs) pools the optic lobe over ``pool_size`` cells whatever its mask of static pixels, where
``kenyon`` takes smaller cells when most of the frame is static
(:func:`flyvpr.frontends.optic_lobe.pool_for_mask`).  On the same windows and seeds, both
traverses through the accuracy benchmark's fisheye disc (``benchmarks/accuracy_setup.py``
``FISHEYE_DISC``): ``CompactEncoder(n_bits=256, random_state=seed).fit`` with 4x4 cells (its
own) and with the 2x2 cells ``kenyon`` takes there, and on whole frames for the cost of the
disc; AUC after the CANN with its defaults and with repeated rows not held (the layer of the
compact localizer, ``LargeLocalizer``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from flyvpr._io import write_json_atomic
from flyvpr.datasets.nordland import load_nordland
from flyvpr.frontends import KenyonEncoder
from flyvpr.large import CompactEncoder, hamming_similarity
from flyvpr.metrics import pr_auc, recall_at_k
from flyvpr.temporal import FILTERS

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: the repository root, for ``benchmarks.``
    sys.path.insert(0, str(ROOT))
from benchmarks._common import DEFAULT_DATA  # noqa: E402
from benchmarks.accuracy_setup import fisheye  # noqa: E402

HERE = Path(__file__).resolve().parent
WINDOWS = (0, 1000)
SEEDS = (0, 1, 2)
TOLERANCES = (2, 20)


def _packed(bits) -> np.ndarray:
    return np.packbits(np.asarray(bits, dtype=bool), axis=1)


def codes_of(ken: KenyonEncoder, ref, qry, seed) -> dict:
    """name -> (reference codes, query codes) of every compact code, bit-packed."""
    out = {}
    for n_bits in (256, 512):
        for proj in ("pca", "simhash"):
            enc = CompactEncoder.from_kenyon(
                ken, ref, n_bits=n_bits, projection=proj, random_state=seed
            )
            out[f"{proj}-{n_bits}"] = (enc.reference_codes_, enc.encode(qry))
        act_r = ken.kenyon_activity(ref)[:, :n_bits]
        act_q = ken.kenyon_activity(qry)[:, :n_bits]
        out[f"kc-median-{n_bits}"] = (
            _packed(act_r > np.median(act_r, axis=1, keepdims=True)),
            _packed(act_q > np.median(act_q, axis=1, keepdims=True)),
        )
        fold = 4096 // n_bits
        full_r = np.unpackbits(ken.reference_codes_, axis=1).reshape(len(ref), n_bits, fold)
        full_q = np.unpackbits(ken.encode(qry), axis=1).reshape(len(qry), n_bits, fold)
        out[f"kc-subset-{n_bits}"] = (_packed(full_r[:, :, 0]), _packed(full_q[:, :, 0]))
        out[f"kc-xor-{n_bits}"] = (
            _packed(full_r.sum(axis=2) % 2),
            _packed(full_q.sum(axis=2) % 2),
        )
    return out


#: the fisheye comparison: (label, frames through the disc, pooling cell side)
FISHEYE_ROWS = (
    ("whole frames, 4x4 cells", False, 4),
    ("fisheye disc, 4x4 cells (fit's own)", True, 4),
    ("fisheye disc, 2x2 cells (kenyon's there)", True, 2),
)
#: the CANN settings the fisheye comparison filters with: the defaults, and the compact
#: localizer's layer (repeated rows not held)
FISHEYE_FILTERS = {"cann_auc": {}, "cann_auc_no_hold": {"hold_repeats": False}}


def fisheye_runs(ref, qry, gts: dict, window: str, seed: int) -> list[dict]:
    """FISHEYE_ROWS on one window and seed: per row and tolerance, the AUC of the 256-bit
    code alone and after each of FISHEYE_FILTERS."""
    disc_ref, disc_qry = fisheye(ref), fisheye(qry)
    rows = []
    for label, disc, pool in FISHEYE_ROWS:
        r, q = (disc_ref, disc_qry) if disc else (ref, qry)
        enc = CompactEncoder(n_bits=256, pool_size=pool, random_state=seed).fit(r)
        S = hamming_similarity(enc.encode(q), enc.reference_codes_)
        filtered = {k: FILTERS["cann"](**v).filter(S) for k, v in FISHEYE_FILTERS.items()}
        for t, gt in gts.items():
            row = {"row": label, "window": window, "seed": seed, "tolerance": t}
            row["features"] = int(enc.n_features_)
            row["auc"] = pr_auc(S, gt)
            row.update({k: pr_auc(C, gt) for k, C in filtered.items()})
            rows.append(row)
    return rows


def _mean(rows: list[dict], key: str) -> float:
    return float(np.mean([r[key] for r in rows]))


def render_table(data: dict) -> str:
    """The codes' table: per code, its bytes, recall@1 at each tolerance, AUC alone at the
    largest, and the mean AUC after the CANN at each (its min and max)."""
    tols = [str(t) for t in TOLERANCES]
    lines = [
        "| code | bytes | "
        + " | ".join(f"R@1 tol {t}" for t in tols)
        + f" | AUC tol {tols[-1]} | "
        + " | ".join(f"+cann AUC tol {t}" for t in tols)
        + " |",
        "|---|---|" + "---|" * (2 * len(tols) + 1),
    ]
    for name, by_tol in data["summary"].items():
        label = name.split(" ")[0]
        nbytes = int(label.rsplit("-", 1)[1]) // 8
        at = [by_tol[t] for t in tols]
        cells = [f"{s['recall_at_1']:.3f}" for s in at] + [f"{at[-1]['auc']:.3f}"]
        cells += [
            f"{s['cann_auc']:.3f} [{s['cann_auc_min']:.3f}, {s['cann_auc_max']:.3f}]" for s in at
        ]
        lines.append(f"| {label} | {nbytes} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def render_fisheye_table(data: dict) -> str:
    """The fisheye comparison: per row, its features and the mean AUCs over the windows and
    seeds, at each tolerance."""
    rows = data["fisheye"]
    lines = [
        "| code (256 bits, `fit`) | features | "
        + " | ".join(
            f"{what}, tol {t}"
            for t in TOLERANCES
            for what in ("AUC", "+cann AUC", "+cann AUC, repeats not held")
        )
        + " |",
        "|---|---|" + "---|" * (3 * len(TOLERANCES)),
    ]
    for label in dict.fromkeys(r["row"] for r in rows):
        mine = [r for r in rows if r["row"] == label]
        features = sorted({r["features"] for r in mine})
        cells = []
        for t in TOLERANCES:
            at = [r for r in mine if str(r["tolerance"]) == str(t)]
            cells += [f"{_mean(at, k):.3f}" for k in ("auc", "cann_auc", "cann_auc_no_hold")]
        lines.append(f"| {label} | {', '.join(map(str, features))} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", type=Path, default=DEFAULT_DATA)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    root = args.data / "nordland_64x32"
    if not root.is_dir():
        print(f"data folder not found: {root}", file=sys.stderr)
        return 1
    runs: dict = {}
    fish: list[dict] = []
    for first in WINDOWS:
        bench = load_nordland(root, "summer", "winter", first=first, count=1000, tolerance=20)
        ref = bench.reference.load_images(progress=False)
        qry = bench.query.load_images(progress=False)
        i = np.arange(len(ref))
        gts = {t: np.abs(i[:, None] - i[None, :]) <= t for t in TOLERANCES}
        for seed in SEEDS:
            ken = KenyonEncoder(random_state=seed).fit(ref)
            scores = {"kenyon-4096 (full, 512 bytes)": ken.score(qry)}
            for name, (r, q) in codes_of(ken, ref, qry, seed).items():
                scores[name] = hamming_similarity(q, r)
            for name, S in scores.items():
                C = FILTERS["cann"]().filter(S)
                for t, gt in gts.items():
                    runs.setdefault(name, {}).setdefault(str(t), []).append(
                        {
                            "window": f"{first}-{first + 999}",
                            "seed": seed,
                            "recall_at_1": recall_at_k(S, gt, 1),
                            "auc": pr_auc(S, gt),
                            "cann_auc": pr_auc(C, gt),
                        }
                    )
            fish += fisheye_runs(ref, qry, gts, f"{first}-{first + 999}", seed)
            print(f"window {first} seed {seed} done", flush=True)
    summary = {}
    for name, by_tol in runs.items():
        summary[name] = {}
        for t, rs in by_tol.items():
            cann = [r["cann_auc"] for r in rs]
            summary[name][t] = {
                "recall_at_1": float(np.mean([r["recall_at_1"] for r in rs])),
                "auc": float(np.mean([r["auc"] for r in rs])),
                "cann_auc": float(np.mean(cann)),
                "cann_auc_min": float(np.min(cann)),
                "cann_auc_max": float(np.max(cann)),
            }
            s = summary[name][t]
            print(
                f"{name:30s} tol {t:>2s}  R@1 {s['recall_at_1']:.3f}  AUC {s['auc']:.3f}  "
                f"+cann AUC {s['cann_auc']:.3f} [{s['cann_auc_min']:.3f}, {s['cann_auc_max']:.3f}]"
            )
    print(render_fisheye_table({"fisheye": fish}))
    if args.json:
        write_json_atomic(
            args.json,
            {
                "what": "compact codes vs the full kenyon code, Nordland 64x32 summer -> winter",
                "windows": [f"{f}-{f + 999}" for f in WINDOWS],
                "seeds": list(SEEDS),
                "summary": summary,
                "runs": runs,
                "fisheye": fish,
            },
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

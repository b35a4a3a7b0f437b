"""The compact-codes benchmark's helpers: the fisheye pooling runs and the two tables."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import compact_codes  # noqa: E402


def _stats(r1, auc, cann, lo, hi):
    return {"recall_at_1": r1, "auc": auc, "cann_auc": cann, "cann_auc_min": lo, "cann_auc_max": hi}


def test_codes_table_gives_bytes_from_the_name_and_both_tolerances():
    data = {
        "summary": {
            "kenyon-4096 (full, 512 bytes)": {
                "2": _stats(0.3, 0.1, 0.97, 0.95, 0.99),
                "20": _stats(0.4, 0.2, 0.98, 0.96, 0.995),
            },
            "pca-256": {
                "2": _stats(0.2, 0.05, 0.9655, 0.93, 0.98),
                "20": _stats(0.25, 0.125, 0.97, 0.9, 0.999),
            },
        }
    }
    lines = compact_codes.render_table(data).splitlines()
    assert lines[0].startswith("| code | bytes | R@1 tol 2 | R@1 tol 20 | AUC tol 20 |")
    assert lines[2] == (
        "| kenyon-4096 | 512 | 0.300 | 0.400 | 0.200 | 0.970 [0.950, 0.990] "
        "| 0.980 [0.960, 0.995] |"
    )
    assert lines[3] == (
        "| pca-256 | 32 | 0.200 | 0.250 | 0.125 | 0.966 [0.930, 0.980] | 0.970 [0.900, 0.999] |"
    )
    assert len(lines) == 4


def test_fisheye_table_is_the_mean_over_windows_and_seeds_per_row_and_tolerance():
    rows = []
    for label, features, shift in (("whole", 512, 0.0), ("disc 4", 368, -0.1)):
        for window, seed, value in (("0-999", 0, 0.9), ("0-999", 1, 0.8), ("1000-1999", 0, 0.7)):
            value += shift
            for t in (2, 20):
                bump = 0.05 if t == 20 else 0.0
                rows.append(
                    {
                        "row": label,
                        "window": window,
                        "seed": seed,
                        "tolerance": t,
                        "features": features,
                        "auc": value / 10 + bump,
                        "cann_auc": value + bump,
                        "cann_auc_no_hold": value + 0.01 + bump,
                    }
                )
    lines = compact_codes.render_fisheye_table({"fisheye": rows}).splitlines()
    assert lines[0] == (
        "| code (256 bits, `fit`) | features | AUC, tol 2 | +cann AUC, tol 2 | "
        "+cann AUC, repeats not held, tol 2 | AUC, tol 20 | +cann AUC, tol 20 | "
        "+cann AUC, repeats not held, tol 20 |"
    )
    assert lines[1] == "|---|---|---|---|---|---|---|---|"
    assert lines[2] == "| whole | 512 | 0.080 | 0.800 | 0.810 | 0.130 | 0.850 | 0.860 |"
    assert lines[3] == "| disc 4 | 368 | 0.070 | 0.700 | 0.710 | 0.120 | 0.750 | 0.760 |"
    assert len(lines) == 4


def test_fisheye_runs_filter_with_the_defaults_and_without_holding_repeats(monkeypatch):
    made = []
    real = compact_codes.FILTERS["cann"]

    def cann(**params):
        made.append(params)
        return real(**params)

    monkeypatch.setitem(compact_codes.FILTERS, "cann", cann)
    rng = np.random.default_rng(1)
    ref = rng.random((12, 32, 64), dtype=np.float32)
    # every query frame the same: held as repeats by the default, not without it
    qry = np.repeat(ref[:1], 12, axis=0)
    i = np.arange(12)
    rows = compact_codes.fisheye_runs(ref, qry, {2: np.abs(i[:, None] - i) <= 2}, "w", 0)
    assert made == [{}, {"hold_repeats": False}] * len(compact_codes.FISHEYE_ROWS)
    assert any(r["cann_auc"] != r["cann_auc_no_hold"] for r in rows)


def test_fisheye_runs_pool_each_row_as_it_says_through_the_disc():
    rng = np.random.default_rng(0)
    ref = rng.random((24, 32, 64), dtype=np.float32)
    qry = np.clip(ref + rng.normal(0, 0.02, ref.shape).astype(np.float32), 0, 1)
    i = np.arange(len(ref))
    gts = {t: np.abs(i[:, None] - i[None, :]) <= t for t in (2, 20)}
    rows = compact_codes.fisheye_runs(ref, qry, gts, "w", 3)
    assert [(r["row"], r["tolerance"]) for r in rows] == [
        (label, t) for label, _, _ in compact_codes.FISHEYE_ROWS for t in (2, 20)
    ]
    # whole frames at 4x4: 8 x 16 cells of 4 orientations; the disc (its pixels outside
    # static, so masked) leaves 92 of the 4x4 cells and 344 of the 2x2 ones
    assert [r["features"] for r in rows[::2]] == [512, 368, 1376]
    assert all(r["window"] == "w" and r["seed"] == 3 for r in rows)
    for r in rows:  # near-copies of the map: found alone, and after the CANN
        assert r["auc"] > 0.9 and r["cann_auc"] > 0.5 and r["cann_auc_no_hold"] > 0.5

"""The compact-map detour benchmark's helpers: the map's places and positions, a run's figures
and the table."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import compact_detour  # noqa: E402
from flyvpr.temporal.cann._route import position_breaks  # noqa: E402


def test_the_map_keeps_all_but_the_stretch_and_its_positions_jump_there():
    assert compact_detour.kept(10, 3, 6).tolist() == [0, 1, 2, 6, 7, 8, 9]
    keep = compact_detour.kept(30, 10, 20)
    rows = compact_detour.positions_csv(keep).splitlines()
    assert rows[0] == "frame,x,y"
    assert rows[1:] == [f"{j},{10.0 * i},0" for j, i in enumerate(keep)]
    xy = np.array([[float(r.split(",")[1]), 0.0] for r in rows[1:]])
    assert position_breaks(xy) == (10,)  # the image after the stretch starts a new one
    # the benchmark's own detours are the accuracy benchmark's (0.4-0.7 of each window)
    for _first, n, lo, hi in compact_detour.DETOURS.values():
        assert (lo, hi) == (int(0.4 * n), int(0.7 * n))


def test_score_counts_off_map_answers_the_rejoin_and_the_auc():
    truth = np.arange(10)
    on_map = ~np.isin(truth, [3, 4, 5])
    places = np.array([0, 1, 2, 6, 6, 6, 0, 7, 8, 9])  # off the map: answers 6; at 6 wrong
    states = np.array(["lost", "localized", "localized", "localized", "lost", "lost",
                       "localized", "lost", "localized", "localized"])  # fmt: skip
    conf = np.linspace(0.9, 0.1, 10)
    row = compact_detour.score(places, states, conf, truth, on_map, 6)
    assert row["offmap_localized_share"] == pytest.approx(1 / 3)
    # frame 6 is localized but 6 places off (tolerance 2), 7 right but lost: 8 is the first
    assert row["rejoin_frames"] == 2
    assert 0.0 < row["auc"] < 1.0
    never = compact_detour.score(places, np.full(10, "lost"), conf, truth, on_map, 6)
    assert never["rejoin_frames"] is None and never["offmap_localized_share"] == 0.0
    # an off-map answer is never right, even where it names the true frame: confident, it
    # lowers the AUC; the least confident of all, it costs nothing
    near = compact_detour.score(truth, np.full(10, "localized"), conf, truth, on_map, 6)
    assert near["rejoin_frames"] == 0 and near["offmap_localized_share"] == 1.0
    assert near["auc"] < 0.9
    last = conf.copy()
    last[~on_map] = 0.0
    assert compact_detour.score(truth, states, last, truth, on_map, 6)["auc"] == pytest.approx(1.0)


def test_table_gives_each_window_and_reading_per_seed():
    rows = [
        {"window": w, "seed": s, "reading": r, "offmap_localized_share": share,
         "rejoin_frames": back, "auc": auc}
        for w, s, r, share, back, auc in [
            ("dev", 0, "breaks", 0.0, 30, 0.91), ("dev", 1, "breaks", 0.01, None, 0.9),
            ("dev", 0, "one route", 0.02, 40, 0.9), ("dev", 1, "one route", 0.03, 41, 0.8),
        ]
    ]  # fmt: skip
    data = {
        "rows": rows,
        "protocol": {
            "tolerance": 2,
            "detours": {"dev": [0, 1000, 400, 700], "other": [2000, 400, 160, 280]},
            "readings": {"breaks": "", "one route": ""},
        },
    }
    lines = compact_detour.render_table(data).splitlines()
    assert lines[0].endswith("| AUC, tolerance 2 |")
    assert (
        lines[2] == "| dev, without 400-699 | breaks | 0.0% / 1.0% | 30 / never | 0.910 / 0.900 |"
    )
    assert (
        lines[3] == "| dev, without 400-699 | one route | 2.0% / 3.0% | 40 / 41 | 0.900 / 0.800 |"
    )
    assert len(lines) == 4  # the window without rows has none


def test_the_committed_figures_cover_every_window_seed_and_reading():
    import json

    data = json.loads((ROOT / "benchmarks" / "compact-detour.json").read_text())
    got = {(r["window"], r["seed"], r["reading"]) for r in data["rows"]}
    assert got == {
        (w, s, r)
        for w in compact_detour.DETOURS
        for s in compact_detour.SEEDS
        for r in compact_detour.READINGS
    }
    for r in data["rows"]:  # the map's positions jump once, at the stretch
        _first, _n, lo, _hi = compact_detour.DETOURS[r["window"]]
        assert r["breaks"] == [lo]

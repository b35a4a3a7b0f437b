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
    # the benchmark's own detours are the accuracy benchmark's (its share of each window)
    from benchmarks.accuracy_setup import VIEWS

    gap = next(v for v in VIEWS if v.key == "r-detour").gap
    assert gap == next(v for v in VIEWS if v.key == "r-detour-2000").gap
    for _first, n, lo, hi in compact_detour.DETOURS.values():
        assert (lo, hi) == (int(gap[0] * n), int(gap[1] * n))


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
    # within the tolerance (2 frames) is right, beyond it is not
    edge = compact_detour.score(places + np.r_[0, 0, 0, 0, 0, 0, 4, 2, 0, 0], states, conf,
                                truth, on_map, 6)  # fmt: skip
    assert edge["rejoin_frames"] == 0  # frame 6 answers 4: 2 off, localized
    assert compact_detour.score(places + 3, states, conf, truth, on_map, 6)["rejoin_frames"] is None
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
    # the stretch in frame numbers of the dataset: the window's first frame added
    for r in rows:
        r["window"] = "other"
    lines = compact_detour.render_table(data).splitlines()
    assert lines[2].startswith("| other, without 2160-2279 | breaks |")


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


def test_run_maps_the_window_and_scores_both_readings(nordland_64x32, tmp_path, monkeypatch):
    # a window of 60 summer frames without 20-34 (linked into a folder of their own), and the
    # same summer frames as the query: every frame back on the map has one right answer
    for season in ("summer", "winter"):
        folder = tmp_path / "nordland_64x32" / season
        folder.mkdir(parents=True)
        for path in sorted((nordland_64x32 / "summer").glob("*.png"))[800:860]:
            (folder / path.name).symlink_to(path)
    monkeypatch.setattr(compact_detour, "DETOURS", {"w": (0, 60, 20, 35)})
    monkeypatch.setattr(compact_detour, "SEEDS", (0,))
    seen = []
    real = compact_detour.score

    def spy(places, states, confidences, truth, on_map, back):
        seen.append((np.asarray(places), np.asarray(truth), np.asarray(on_map), back))
        return real(places, states, confidences, truth, on_map, back)

    monkeypatch.setattr(compact_detour, "score", spy)
    data = compact_detour.run(tmp_path, progress=False)
    assert [(r["window"], r["seed"], r["reading"]) for r in data["rows"]] == [
        ("w", 0, "breaks"), ("w", 0, "one route")
    ]  # fmt: skip
    assert all(r["breaks"] == [20] for r in data["rows"])
    keep = compact_detour.kept(60, 20, 35)
    for places, truth, on_map, back in seen:
        assert np.isin(places, keep).all()  # frame numbers of the window, the map's places
        assert truth.tolist() == list(range(60)) and back == 35
        np.testing.assert_array_equal(on_map, np.isin(truth, keep))
        right = np.abs(places - truth) <= 2
        assert right[on_map][-20:].mean() > 0.9  # its own frames, back on the map: found
    assert not list(tmp_path.glob("**/*.fvmap"))  # the maps were built in a folder removed

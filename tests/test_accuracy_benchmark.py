"""The accuracy benchmark's machinery: tables, one task against flyvpr's own evaluation, reports."""

from __future__ import annotations

import copy
import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import accuracy_report, accuracy_run, accuracy_setup  # noqa: E402
from benchmarks.accuracy_setup import Dataset, Entry, View  # noqa: E402


def test_tables_are_consistent():
    accuracy_setup.check_tables()
    views = {v.key for v in accuracy_setup.VIEWS}
    labels = {m.label for m in accuracy_setup.METHODS}
    assert set(accuracy_setup.QUICK_VIEWS) <= views
    assert set(accuracy_setup.QUICK_METHODS) <= labels
    # The brief's conditions are all there.
    for key in ("n64-0", "n64-1000", "n64-1400", "n64-2000", "sub-sf", "sub-sw", "blank"):
        assert key in views
    assert {"seqslam-20", "seqslam-40", "seqslam-60", "flynet+cann", "pixels+cann"} <= labels


def test_seqslam_labels_say_what_runs():
    # "seqslam-60 v0.25-3" ran SeqSLAM's default length, 20, on the robot views for a while
    import re

    from flyvpr.methods import make_method

    seen = 0
    for entry in accuracy_setup.METHODS:
        m = re.fullmatch(
            r"(?:\w+\+)?seqslam-(\d+)(?: v([\d.]+)-([\d.]+))?(?: backwards ([\d.]+)-([\d.]+))?",
            entry.label,
        )
        if m is None:
            continue
        seen += 1
        filt = make_method(entry.name, 0, entry.frontend_params, entry.filter_params).filter
        assert filt.sequence_length == int(m.group(1)), entry.label
        if m.group(2) is not None:
            assert (filt.v_min, filt.v_max) == (float(m.group(2)), float(m.group(3))), entry.label
        elif m.group(4) is not None:
            assert (filt.v_min, filt.v_max) == (-float(m.group(5)), -float(m.group(4)))
            assert all(v.motion == "reversed" for v in accuracy_setup.VIEWS if entry.runs_on(v))
        else:
            assert (filt.v_min, filt.v_max) == (0.8, 1.2), entry.label
    assert seen >= 9


def test_check_tables_catches_mistakes():
    dup = [*accuracy_setup.METHODS, Entry("flynet")]
    with pytest.raises(ValueError, match="duplicate method labels"):
        accuracy_setup.check_tables(methods=dup)
    with pytest.raises(ValueError, match="unknown flyvpr method"):
        accuracy_setup.check_tables(methods=[Entry("nonsense+cann")])
    stray = [View("x", "no-such-data", "x", "nordland", (20,))]
    with pytest.raises(ValueError, match="unknown data set"):
        accuracy_setup.check_tables(views=stray)


@pytest.mark.parametrize(
    ("kind", "params", "n"),
    [
        ("all", {}, 50),
        ("speed", {"speed": 1.5}, 34),
        ("speed", {"speed": (1.0, 1.5), "view_seed": 3}, None),
        ("shuffle", {"view_seed": 1}, 50),
        ("from", {"start": 20}, 30),
    ],
)
def test_view_indices(kind, params, n):
    view = View("v", "d", "v", "g", (2,), kind, **params)
    idx = view.indices(50)
    assert idx.min() >= 0 and idx.max() < 50 and len(np.unique(idx)) == len(idx)
    if n is not None:
        assert len(idx) == n
    np.testing.assert_array_equal(idx, view.indices(50))  # seeded: the same every time
    if kind == "shuffle":
        assert sorted(idx.tolist()) == list(range(50)) and idx.tolist() != list(range(50))


def test_deterministic_entries_run_once():
    assert Entry("pixels").deterministic and Entry("seqslam-40", "seqslam").deterministic
    assert not Entry("flynet+cann").deterministic
    assert Entry("pixels+cann").runs_with(0, 0) and not Entry("pixels+cann").runs_with(1, 0)
    slow = Entry("flynet+cann", first_seed_only=True)
    assert not slow.runs_with(3, 0)


# -- one task against flyvpr's own evaluation path ---------------------------------------------
TINY = Dataset(
    "tiny",
    "synthetic 120 places",
    "synthetic",
    route={"n_places": 120, "conditions": ["summer", "winter"], "random_state": 2},
)
TINY_VIEWS = (
    View("tiny", "tiny", "tiny", "nordland", (2, 10)),
    View("tiny-2x", "tiny", "tiny 2x", "speed", (2,), "speed", 2.0),
)


def _task(entries, seed=1):
    return accuracy_run.Task(TINY, seed, seed, TINY_VIEWS, tuple(entries), Path("."), kidnap=False)


@pytest.mark.parametrize(
    "entry",
    [
        Entry("flynet", frontend_params={"epochs": 20}),
        Entry("flynet+cann", frontend_params={"epochs": 20}),
        Entry("seqslam-40", "seqslam", filter_params={"sequence_length": 40}),
        Entry("flyhash+seqslam", filter_params={"v_max": 2.0, "v_min": 0.75, "v_step": 0.125}),
    ],
)
def test_task_rows_equal_flyvpr_evaluate(entry):
    from flyvpr.evaluation import evaluate_method
    from flyvpr.synthetic import make_route

    res = accuracy_run.run_task(_task([entry]))
    assert res["errors"] == []
    route = make_route(**TINY.route)
    ref, qry = route.reference_images, route.query_images
    for view in TINY_VIEWS:
        idx = view.indices(len(qry))
        for tol in view.tolerances:
            gt = route.ground_truth(tol)[idx]
            expected = evaluate_method(
                entry.name,
                ref,
                qry[idx],
                gt,
                seed=1,
                frontend_params=entry.frontend_params,
                filter_params=entry.filter_params,
            )
            (row,) = [r for r in res["rows"] if r["condition"] == f"{view.key}@{tol}"]
            for key in ("auc", "recall_at_1", "recall_at_100_precision", "extended_precision"):
                assert row[key] == pytest.approx(expected[key], abs=1e-9), (view.key, tol, key)


def test_random_filter_sees_the_generator_the_front_end_left():
    pytest.importorskip("torch")
    from flyvpr.evaluation import evaluate_method
    from flyvpr.synthetic import make_route

    entries = [
        Entry("flynet", frontend_params={"epochs": 10}),  # fits the shared front end first
        Entry(
            "flynet+rnn",
            frontend_params={"epochs": 10},
            filter_params={"epochs": 1, "hidden_size": 16},
        ),
    ]
    res = accuracy_run.run_task(_task(entries))
    assert res["errors"] == []
    route = make_route(**TINY.route)
    expected = evaluate_method(
        "flynet+rnn",
        route.reference_images,
        route.query_images,
        route.ground_truth(2),
        seed=1,
        frontend_params=entries[1].frontend_params,
        filter_params=entries[1].filter_params,
    )
    (row,) = [r for r in res["rows"] if r["condition"] == "tiny@2" and r["method"] == "flynet+rnn"]
    assert row["auc"] == pytest.approx(expected["auc"], abs=1e-6)


def test_bytes_per_place_of_a_task():
    res = accuracy_run.run_task(_task([Entry("pixels"), Entry("flyhash+cann")]))
    got = {f["method"]: f["bytes_per_place"] for f in res["fitted"]}
    assert got == {"pixels": 8192.0, "flyhash+cann": 8.0}


def test_kidnap_recovery_counts_frames_to_the_new_place():
    # Perfect evidence: a CANN back on the true place within a few frames of each jump.
    from flyvpr.temporal import CANN

    n = 600
    S = -np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]).astype(float)
    frames = accuracy_run.kidnap_recovery(S, 20, CANN())
    assert len(frames) == len(accuracy_run.jump_positions(n)) > 0
    assert all(f is not None and f < 30 for f in frames)
    assert accuracy_run.evidence_rank(S) == [1] * len(frames)


# -- summaries and reports ----------------------------------------------------------------------
def _rows():
    rows = []
    for seed, auc in enumerate([0.5, 0.7, 0.6]):
        rows.append(
            {
                "condition": "c@20",
                "method": "m",
                "seed": seed,
                "auc": auc,
                "recall_at_1": 0.8,
                "recall_at_100_precision": 0.1 * seed,
                "extended_precision": 0.5,
                "top_share": 0.01 * (seed + 1),
                "filter_s": 0.0,
            }
        )
    return rows


def test_summarise_hand_worked():
    (s,) = accuracy_report.summarise(_rows())
    assert s["seeds"] == [0, 1, 2]
    assert s["auc_mean"] == pytest.approx(0.6)
    assert s["auc_worst"] == 0.5
    assert s["auc_spread"] == pytest.approx(0.2)
    assert s["recall_at_100_precision_mean"] == pytest.approx(0.1)
    assert s["top_share_max"] == pytest.approx(0.03)


def _document():
    rows = _rows() + [
        {**_rows()[0], "condition": "blank@20", "method": "m", "auc": 0.4, "seed": 0},
    ]
    return {
        "seeds": [0, 1, 2],
        "methods": [{"label": "m", "method": "flynet+cann", "seeds": "all"}],
        "conditions": [
            {
                "key": "c@20",
                "label": "cond",
                "group": "nordland",
                "tolerance": 20,
                "tolerances": [20],
            },
            {
                "key": "blank@20",
                "label": "blank",
                "group": "control",
                "tolerance": 20,
                "tolerances": [20],
            },
        ],
        "rows": rows,
        "summary": accuracy_report.summarise(rows),
        "bytes_per_place": {"m": 256.0},
        "errors": [],
    }


def test_render_markdown_is_pure_and_complete():
    data = _document()
    before = copy.deepcopy(data)
    md = accuracy_report.render_markdown(data)
    assert data == before  # the input is not touched
    assert md == accuracy_report.render_markdown(json.loads(json.dumps(data)))
    assert "| cond (" not in md  # labels are printed as given
    assert "| cond | m | 0.600 | 0.500 | 0.200 | 0.800 | 0.100 | 0.500 | 0.03 | 0-2 |" in md
    assert "| m | 256 |" in md
    assert "fail: m" in md  # blank AUC 0.4 > 0.1: reported, not hidden
    text = accuracy_report.render_text(data)
    assert "cond" in text and "0.600" in text


def test_render_markdown_importable_from_the_benchmark_script():
    from benchmarks.accuracy import render_markdown

    assert render_markdown is accuracy_report.render_markdown


def test_render_markdown_refuses_other_documents():
    with pytest.raises(ValueError, match="not an accuracy benchmark document"):
        accuracy_report.render_markdown({"rows": []})
    old = _document()
    for row in old["rows"]:
        del row["extended_precision"]
    with pytest.raises(ValueError, match="older benchmarks/accuracy.py"):
        accuracy_report.render_markdown(old)


def _doc(methods, seeds=(0, 1), conditions=("a@20", "b@20"), auc=0.5, cmd="x"):
    rows = [
        {"condition": c, "method": m, "seed": s, "auc": auc}
        for c in conditions
        for m in methods
        for s in seeds
    ]
    return {
        "benchmark": "flyvpr accuracy",
        "command": [cmd],
        "seeds": list(seeds),
        "methods": [{"label": m} for m in methods],
        "conditions": [{"key": c, "view_key": c.split("@")[0]} for c in conditions],
        "rows": rows,
        "kidnap": [{"method": m, "view": "a", "frames": [1]} for m in methods],
        "evidence": [{"view": "a", "frontend": m.split("+")[0]} for m in methods],
        "bytes_per_place": {m: 8 for m in methods},
        "errors": [],
        "elapsed_s": 10.0,
    }


def test_merge_replaces_rerun_methods_and_keeps_the_rest(tmp_path):
    from benchmarks.accuracy_merge import load_previous, merge_runs

    old = _doc(["p", "q+cann"], auc=0.1, cmd="old")
    new = _doc(["q+cann"], auc=0.9, cmd="new")
    new["bytes_per_place"] = {"q+cann": 4}
    merged = merge_runs(old, new, ["q+cann", "p"], ["b@20", "a@20"])
    assert [m["label"] for m in merged["methods"]] == ["q+cann", "p"]
    by = {(r["condition"], r["method"], r["seed"]): r["auc"] for r in merged["rows"]}
    assert len(by) == len(merged["rows"]) == 8  # no duplicates
    assert by[("a@20", "q+cann", 1)] == 0.9 and by[("a@20", "p", 0)] == 0.1
    assert [r["condition"] for r in merged["rows"]][:4] == ["b@20"] * 4  # condition order
    assert merged["bytes_per_place"] == {"p": 8, "q+cann": 4}
    assert sorted(k["method"] for k in merged["kidnap"]) == ["p", "q+cann"]
    assert [p["command"] for p in merged["parts"]] == [["old"], ["new"]]
    assert merged["elapsed_s"] == 20.0
    # A run of one view replaces that view's rows only.
    part = _doc(["p"], conditions=("a@20",), auc=0.7, cmd="part")
    again = merge_runs(merged, part, ["q+cann", "p"], ["b@20", "a@20"])
    by = {(r["condition"], r["method"], r["seed"]): r["auc"] for r in again["rows"]}
    assert len(by) == len(again["rows"]) == 8
    assert by[("a@20", "p", 0)] == 0.7 and by[("b@20", "p", 0)] == 0.1
    assert by[("a@20", "q+cann", 0)] == 0.9
    path = tmp_path / "old.json"
    path.write_text(json.dumps(old))
    assert load_previous(path, [0, 1])["rows"] == old["rows"]
    with pytest.raises(ValueError, match="seeds"):
        load_previous(path, [0, 1, 2])
    path.write_text("{}")
    with pytest.raises(ValueError, match="not a flyvpr accuracy"):
        load_previous(path, [0, 1])


def test_reliability_tables_keep_dev_and_held_out_apart():
    # three views, one held out, one of the subset: bin 9 of the dev view is right 3 of 4 at
    # mean confidence 0.95, the held-out view's 1 of 2 at 0.9, the subset's 1 of 1 at 0.7;
    # pooled, 5 of 7 at 0.9
    data = {
        "conditions": [
            {"key": "a@2", "view_key": "a", "label": "a", "tuning": "tuned the defaults"},
            {"key": "b@2", "view_key": "b", "label": "b", "tuning": "held out: tuned nothing"},
            {"key": "c@2", "view_key": "c", "label": "c", "tuning": "subset: tuned nothing"},
        ],
        "reliability": [
            {"method": "m", "view": "a", "seed": 0, "n": [0] * 9 + [4],
             "confidence": [0.0] * 9 + [3.8], "right": [0] * 9 + [3]},
            {"method": "m", "view": "b", "seed": 0, "n": [1] + [0] * 8 + [2],
             "confidence": [0.05] + [0.0] * 8 + [1.8], "right": [0] * 9 + [1]},
            {"method": "m", "view": "c", "seed": 0, "n": [0] * 9 + [1],
             "confidence": [0.0] * 9 + [0.7], "right": [0] * 9 + [1]},
        ],
    }  # fmt: skip
    dev = accuracy_report.reliability_table(data, "m", "dev")
    held = accuracy_report.reliability_table(data, "m", "held out")
    both = accuracy_report.reliability_table(data, "m")
    assert dev == [["0.9-1.0", "4", "0.950", "0.750", "-0.200"]]
    assert held == [
        ["0.0-0.1", "1", "0.050", "0.000", "-0.050"],
        ["0.9-1.0", "2", "0.900", "0.500", "-0.400"],
    ]
    assert accuracy_report.reliability_table(data, "m", "subset") == [
        ["0.9-1.0", "1", "0.700", "1.000", "0.300"]
    ]
    assert both[-1] == ["0.9-1.0", "7", "0.900", "0.714", "-0.186"]
    assert accuracy_report.reliability_table(data, "other") == []
    doc = _document()
    doc["conditions"] += data["conditions"]
    doc["reliability"] = data["reliability"]
    md = accuracy_report.render_markdown(doc)
    assert md.index("On the dev views") < md.index("| 0.9-1.0 | 4 | 0.950 |")
    assert md.index("On the held-out views") < md.index("| 0.9-1.0 | 2 | 0.900 |")
    assert md.index("On the 100-place subset's robot views") < md.index("| 0.9-1.0 | 1 | 0.700 |")
    text = accuracy_report.render_text(doc)
    assert "on the held-out views" in text


def test_mask_lines_pair_masked_frames_with_the_same_frames_unmasked():
    frames = {"root": "/d/n64", "first": 0, "count": 10}
    masked = {**frames, "mask": "fisheye disc"}

    def cond(key, protocol, tolerance=2, **view):
        return {"key": key, "label": key.upper(), "group": "robot", "tolerance": tolerance,
                "view": {"kind": "all", "group": "robot", "tolerances": [2, 20], **view},
                "protocol": protocol}  # fmt: skip

    data = {
        "methods": [{"label": "a+cann"}, {"label": "a"}, {"label": "b+cann"}],
        "conditions": [
            cond("full@2", frames, group="nordland", tolerances=[20, 2]),  # a twin all the same
            cond("fish@2", masked),
            cond("fish@20", masked, 20),  # no unmasked twin at this tolerance
            cond("fish-odo@2", masked, odometry=True),  # nor with odometry
            cond("other@2", {**masked, "first": 100}),  # nor of other frames
        ],
        "summary": [
            {"condition": c, "method": m, "auc_mean": v}
            for c, m, v in [
                ("full@2", "a+cann", 0.97), ("fish@2", "a+cann", 0.955),
                ("full@2", "a", 0.1), ("fish@2", "a", 0.05),
                ("full@2", "b+cann", 0.9), ("fish@20", "b+cann", 0.5),
                ("fish-odo@2", "a+cann", 0.5), ("other@2", "a+cann", 0.5),
            ]
        ],
    }  # fmt: skip
    lines = accuracy_report._mask_lines(data)
    assert lines == [
        "FISH@2: AUC mean on the same frames without the mask (FULL@2) minus through it: "
        "a+cann +0.0150."
    ]
    # a method with a worse score unmasked shows a negative cost; the report carries the lines
    data["summary"].append({"condition": "fish@2", "method": "b+cann", "auc_mean": 0.95})
    assert accuracy_report._mask_lines(data)[0].endswith("a+cann +0.0150, b+cann -0.0500.")
    doc = _document()
    doc["conditions"] += data["conditions"]
    doc["methods"] += data["methods"]
    doc["rows"] += [
        {**_rows()[0], "condition": x["condition"], "method": x["method"], "auc": x["auc_mean"]}
        for x in data["summary"]
    ]
    doc["summary"] = accuracy_report.summarise(doc["rows"])
    assert "minus through it: a+cann +0.0150" in accuracy_report.render_markdown(doc)
    assert "minus through it: a+cann +0.0150" in accuracy_report.render_text(doc)


def test_motion_profiles_give_the_true_place_of_every_frame():
    from benchmarks.accuracy_setup import MOTIONS, motion_places

    np.testing.assert_array_equal(motion_places("3.25x", 10), [0, 3, 6, 9])
    np.testing.assert_array_equal(motion_places("0.6x", 4), [0, 0, 1, 1, 2, 3, 3])
    np.testing.assert_array_equal(motion_places("2.5x", 8), [0, 2, 5, 7])
    np.testing.assert_array_equal(motion_places("reversed", 3), [2, 1, 0])
    stopgo = motion_places("stopgo", 400)
    assert stopgo.size == 400 + 2 * 30 and (np.diff(stopgo) == 0).sum() == 60
    walk = motion_places("walk", 500, seed=3)
    steps = np.diff(walk)
    assert walk[0] >= 0 and walk[-1] < 500 and steps.min() >= 0 and steps.max() <= 2
    np.testing.assert_array_equal(walk, motion_places("walk", 500, seed=3))
    uneven = motion_places("uneven", 2000, seed=4)  # a speed of 0-2 drawn every frame
    steps = np.diff(uneven)
    assert uneven[0] in (0, 1) and uneven[-1] < 2000 and steps.min() >= 0 and steps.max() <= 2
    assert uneven.size > 1900 and abs(steps.mean() - 1.0) < 0.05 and (steps == 0).mean() > 0.1
    np.testing.assert_array_equal(uneven, motion_places("uneven", 2000, seed=4))
    assert not np.array_equal(uneven[:100], motion_places("uneven", 2000, seed=5)[:100])
    drops = motion_places("drops", 2000, seed=4)  # 1 place per frame, a fifth of them dropped
    steps = np.diff(drops)
    assert drops[0] >= 1 and steps.min() >= 1 and (steps > 1).mean() == pytest.approx(0.2, abs=0.03)
    assert abs(steps.mean() - 1.25) < 0.05
    assert set(MOTIONS) >= {"0.6x", "0.8x", "2.5x", "3.25x", "walk", "stopgo", "reversed"}
    assert {"uneven", "drops"} <= set(MOTIONS)
    with pytest.raises(ValueError, match="unknown motion profile"):
        motion_places("9x", 10)


def test_odometry_steps_are_unsigned_places_moved_times_the_scale():
    views = {v.key: v for v in accuracy_setup.ROBOT_VIEWS}
    assert views["r-walk"].odometry_steps(np.array([0, 1, 3])) is None  # no odometry
    steps = views["r-reversed-odo"].odometry_steps(np.array([9, 8, 6, 6]))
    assert steps.dtype == np.float64 and steps.tolist() == [0.0, 1.0, 2.0, 0.0]
    long = views["r-walk-odo-long"].odometry_steps(np.array([4, 5, 7]))
    assert long.tolist() == pytest.approx([0.0, 1.2, 2.4])
    # outages: NaN on 3 stretches from a quarter, a half and three quarters of the frames
    gaps = views["r-walk-odo-gaps"]
    assert gaps.odometry_outage == 40 and "3 stretches of 40 frames" in gaps.protocol()["odometry"]
    steps = gaps.odometry_steps(np.arange(400))
    assert np.flatnonzero(np.isnan(steps)).tolist() == [
        *range(100, 140),
        *range(200, 240),
        *range(300, 340),
    ]
    assert accuracy_setup.outage_starts(100, 40) == [25, 50, 60]  # (the last one ends at 100)
    assert accuracy_setup.outage_starts(100, 0) == []


def test_stream_gives_no_odometry_where_it_is_nan():
    class Recorder:
        state_ = "localized"

        def reset(self):
            self.seen = []

        def step(self, row, velocity=None):
            self.seen.append(velocity)
            return row

    f = Recorder()
    out, states = accuracy_run._stream(f, np.ones((4, 3)), np.array([0.0, 1.5, np.nan, 2.0]))
    assert f.seen == [None, 1.5, None, 2.0] and states.all() and out.shape == (4, 3)
    del Recorder.state_  # a filter that does not say: never localized
    assert not accuracy_run._stream(f, np.ones((2, 3)), None)[1].any()


def test_stream_collects_where_each_answer_came_from_when_asked():
    class Switcher:
        def reset(self):
            self.t = 0

        def step(self, row, velocity=None):
            self.source_ = "front end" if self.t % 2 else "sequence"
            self.t += 1
            return row

    sources: list = []
    accuracy_run._stream(Switcher(), np.ones((3, 2)), None, sources)
    assert sources == ["sequence", "front end", "sequence"]

    # a filter that does not say gives None; without a list nothing is collected
    class Silent(Switcher):
        def step(self, row, velocity=None):
            return row

    sources.clear()
    accuracy_run._stream(Silent(), np.ones((2, 2)), None, sources)
    assert sources == [None, None]


def _rows_answering(answers, n_ref):
    """A filter's rows whose best place is ``answers[t]``, with confidence ``0.1 + t / 100``."""
    out = np.zeros((len(answers), n_ref), np.float32)
    out[np.arange(len(answers)), answers] = 0.1 + np.arange(len(answers)) / 100
    return out


def test_stands_count_localized_wrong_answers_and_the_run_ahead(monkeypatch):
    monkeypatch.setattr(accuracy_run, "STAND_FRAMES", 4)
    query = np.array([0, 1, 2, 2, 2, 2, 3, 4, 4, 4, 5])  # stands on frames 3-5 (place 2)
    ref = np.arange(10)
    # frame 3 within 2 places, frame 4 four places ahead; frames 8-9: 3 frames, not a stand
    answers = [0, 1, 2, 3, 6, 2, 3, 4, 9, 9, 5]
    states = np.array([0, 1, 1, 1, 1, 0, 1, 1, 1, 1, 1], bool)
    got = accuracy_run._stands(query, ref, _rows_answering(answers, 10), states, 2)
    assert got == {
        "stand_frames": 3,
        "stand_localized": 2,
        "stand_localized_wrong": 1,
        "stand_ahead_max": 4,
    }
    # a lost answer far ahead (the front end's hint) is not the packet running on
    lost_far = [0, 1, 2, 3, 6, 9, 3, 4, 9, 9, 5]
    got = accuracy_run._stands(query, ref, _rows_answering(lost_far, 10), states, 2)
    assert got["stand_ahead_max"] == 4 and got["stand_localized_wrong"] == 1
    # behind the stand is not ahead; a query that never stands has nothing to say
    behind = [0, 1, 2, 0, 0, 2, 3, 4, 4, 4, 5]
    got = accuracy_run._stands(query, ref, _rows_answering(behind, 10), states, 2)
    assert got["stand_ahead_max"] == 0 and got["stand_localized_wrong"] == 0
    assert (
        accuracy_run._stands(np.arange(5), ref, _rows_answering([0] * 5, 10), states[:5], 2) == {}
    )
    monkeypatch.setattr(accuracy_run, "STAND_FRAMES", 5)  # the stand of 4 frames is too short
    assert accuracy_run._stands(query, ref, _rows_answering(answers, 10), states, 2) == {}


def test_detour_scores_the_off_map_confidence():
    ref = np.array([0, 1, 2, 3, 7, 8, 9])  # places 4-6 left out of the map
    query = np.arange(10)
    answers = [0, 1, 2, 3, 3, 3, 4, 5, 5, 6]  # map indices
    states = np.array([1, 1, 1, 1, 0, 0, 1, 0, 1, 1], bool)
    out = _rows_answering(answers, len(ref))
    out[4, answers[4]] = 0.7  # off the map, and sure of it
    got = accuracy_run._detour(query, ref, out, states, 0)
    assert got["offmap_localized_share"] == pytest.approx(1 / 3)
    assert got["offmap_confidence_mean"] == pytest.approx((0.7 + 0.15 + 0.16) / 3, abs=1e-6)
    assert got["offmap_confident_share"] == pytest.approx(1 / 3)
    assert got["rejoin_frames"] == 1  # frame 7 answers place 8 (lost), frame 8 place 8: right


def test_robot_verdicts_pool_stands_and_average_the_off_map_confidence():
    base = {"recall_at_1": 0.9, "recall_at_100_precision": 0.5, "extended_precision": 0.7}
    base.update(top_share=0.01, filter_s=0.0, localized_share=0.9)
    rows = [
        {**base, "condition": "s@2", "method": "m", "seed": seed, "auc": 0.9,
         "stand_frames": 30, "stand_localized": loc, "stand_localized_wrong": wrong,
         "stand_ahead_max": ahead}
        for seed, loc, wrong, ahead in ((0, 20, 5, 7), (1, 10, 5, 12))
    ] + [
        {**base, "condition": "d@2", "method": "m", "seed": seed, "auc": 0.8,
         "offmap_localized_share": 0.01 * seed, "rejoin_frames": 40 + seed,
         "offmap_confidence_mean": conf, "offmap_confident_share": share}
        for seed, conf, share in ((0, 0.2, 0.1), (1, 0.4, 0.3))
    ]  # fmt: skip
    summary = accuracy_report.summarise(rows)
    by = {s["condition"]: s for s in summary}
    assert (by["s@2"]["stand_frames"], by["s@2"]["stand_localized"]) == (60, 30)
    assert (by["s@2"]["stand_localized_wrong"], by["s@2"]["stand_ahead_max"]) == (10, 12)
    assert by["d@2"]["offmap_confidence_mean"] == pytest.approx(0.3)
    assert by["d@2"]["offmap_confident_share_mean"] == pytest.approx(0.2)
    assert "stand_frames" not in by["d@2"]
    data = {
        "methods": [{"label": "m", "method": "kenyon+cann"}],
        "conditions": [
            {"key": k, "label": label, "group": "robot", "tolerance": 2}
            for k, label in (("s@2", "stops"), ("d@2", "detour"))
        ],
        "rows": rows,
        "summary": summary,
    }
    lines = accuracy_report._robot_lines(data)
    assert (
        "stops, m: of 60 frames standing (seeds pooled), 30 localized and 10 of those wrong "
        "(33%); a localized answer lay up to 12 places ahead of the stand." in lines
    )
    assert any(
        line.startswith("detour, m: 0.5% of the off-map frames localized (every off-map answer "
                        "is wrong: their mean confidence 0.30, 20% of them at 0.5 or more); ")
        and line.endswith("per seed: 40, 41.")
        for line in lines
    )  # fmt: skip

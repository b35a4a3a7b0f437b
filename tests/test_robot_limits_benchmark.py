"""The robot-limits benchmark's helpers: same-image stretches and scoring a stretch as one place."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from benchmarks import robot_limits  # noqa: E402


def _frames(pattern):
    """One 2x2 frame per letter; equal letters are equal images."""
    level = {c: i / 10 for i, c in enumerate(sorted(set(pattern)))}
    return np.array([np.full((2, 2), level[c]) for c in pattern], np.float32)


def test_stretches_are_the_runs_of_repeated_frames():
    assert robot_limits.same_image_stretches(_frames("aabcccd")) == [(0, 1), (3, 5)]
    assert robot_limits.same_image_stretches(_frames("abcdd")) == [(3, 4)]
    assert robot_limits.same_image_stretches(_frames("abc")) == []
    assert robot_limits.same_image_stretches(_frames("aaa")) == [(0, 2)]
    # a mean difference above the threshold is another image, below it the same one
    x = np.zeros((3, 2, 2), np.float64)
    x[1] += 0.0125
    x[2] = x[1] + 0.0075
    assert robot_limits.same_image_stretches(x, same=0.01) == [(1, 2)]
    assert robot_limits.same_image_stretches(x, same=0.005) == []
    assert robot_limits.same_image_stretches(x, same=0.02) == [(0, 2)]


def test_a_stretch_scored_as_one_place():
    group = robot_limits.place_groups(6, [(1, 3)])
    np.testing.assert_array_equal(group, [0, 1, 1, 1, 4, 5])
    gt = np.zeros((3, 6), bool)
    gt[0, 2] = True  # right only at place 2, inside the stretch: all of 1-3 become right
    gt[1, 4] = True  # outside it: unchanged
    one = robot_limits.as_one(gt, group)
    np.testing.assert_array_equal(one[0], [0, 1, 1, 1, 0, 0])
    np.testing.assert_array_equal(one[1], gt[1])
    assert not one[2].any()


def test_parked_profile_drives_stands_and_drives_on():
    np.testing.assert_array_equal(
        robot_limits.parked_places(3, 4, 2, 10), [0, 1, 2, 3, 3, 3, 3, 4, 5]
    )
    # the drive on stops at the end of the map
    np.testing.assert_array_equal(robot_limits.parked_places(8, 2, 5, 10), [*range(8), 8, 8, 9])
    # a stop at the start: no approach
    np.testing.assert_array_equal(robot_limits.parked_places(0, 2, 1, 10), [0, 0, 1])
    for bad in (-1, 10):
        with pytest.raises(ValueError, match="stop"):
            robot_limits.parked_places(bad, 2, 1, 10)


def test_stop_places_keep_away_from_the_stretches():
    in_stretch = np.zeros(100, bool)
    in_stretch[40:50] = True
    stops = robot_limits.stop_places(in_stretch, 20, seed=3, margin=3)
    assert len(set(stops)) == 20 and stops == sorted(stops)
    assert all(20 <= a < 80 for a in stops)
    assert not any(37 <= a <= 52 for a in stops)
    assert 36 in robot_limits.stop_places(in_stretch, 60 - 16, seed=0, margin=3)
    assert stops == robot_limits.stop_places(in_stretch, 20, seed=3, margin=3)
    assert stops != robot_limits.stop_places(in_stretch, 20, seed=4, margin=3)
    with pytest.raises(ValueError, match="need 45"):
        robot_limits.stop_places(in_stretch, 45, seed=0, margin=3)


def test_parked_summary_pools_the_seeds_by_their_stops():
    def row(seed, frames, n_right, right, n_wrong, wrong, after):
        return {
            "seed": seed,
            "frames": frames,
            "right_after": after,
            "stops_front_right": n_right,
            "right_front_right": right if n_right else None,
            "localized_front_right": right / 2 if n_right else None,
            "stops_front_wrong": n_wrong,
            "right_front_wrong": wrong if n_wrong else None,
            "localized_front_wrong": wrong / 2 if n_wrong else None,
        }

    rows = [row(0, 30, 1, 1.0, 3, 0.2, 0.9), row(1, 30, 3, 0.6, 1, 0.6, 0.7)]
    rows.append(row(0, 100, 0, 0.0, 4, 0.5, 0.5))
    (first, second) = robot_limits.parked_summary(rows)
    assert first["frames"] == 30 and second["frames"] == 100
    assert first["stops_front_right"] == 4
    assert first["right_front_right"] == pytest.approx((1.0 + 3 * 0.6) / 4)
    assert first["localized_front_right"] == pytest.approx((0.5 + 3 * 0.3) / 4)
    assert first["right_front_wrong"] == pytest.approx((3 * 0.2 + 0.6) / 4)
    assert first["right_after"] == pytest.approx(0.8)
    assert second["stops_front_right"] == 0 and second["right_front_right"] is None
    assert second["right_front_wrong"] == pytest.approx(0.5)
    table = "\n".join(
        robot_limits._parked_table(
            {"protocol": {"parked": "p"}, "parked_stops": [1], "parked": rows}
        )
    )
    assert "| 100 | 0 / - / - | 4 / 0.50 / 0.25 | 0.50 |" in table


def test_jitter_table_is_the_mean_over_seeds_per_view_and_value():
    rows = [
        {"seed": s, "view": v, "jitter": j, "auc": a}
        for s, v, j, a in [
            (0, "r-drops", 0.0, 0.6),
            (1, "r-drops", 0.0, 0.8),
            (0, "r-drops", 0.3, 0.9),
            (1, "r-drops", 0.3, 0.8),
            (0, "r-1x", 0.0, 0.97),
            (1, "r-1x", 0.0, 0.95),
            (0, "r-1x", 0.3, 0.96),
            (1, "r-1x", 0.3, 0.90),
        ]
    ]
    lines = robot_limits._jitter_table({"jitter": rows})
    assert "| view | jitter 0 | jitter 0.3 |" in lines
    assert "| 0-999 at 1x, 20% of frames dropped | 0.700 | 0.850 |" in lines
    assert "| 0-999 at 1x | 0.960 | 0.930 |" in lines
    # the views in the order they came, uneven ones first
    assert lines.index("| 0-999 at 1x, 20% of frames dropped | 0.700 | 0.850 |") < lines.index(
        "| 0-999 at 1x | 0.960 | 0.930 |"
    )


@pytest.mark.parametrize(
    "pattern, start, run, expected",
    [
        ("0011111", 0, 3, 2),  # right from frame 2 on
        ("0110111", 0, 3, 4),  # a run of 2 is not enough
        ("0110111", 0, 2, 1),
        ("1111000", 0, 3, 0),  # right at once
        ("1111011", 2, 2, 0),  # counted from start
        ("1111011", 3, 2, 2),
        ("0101010", 0, 2, None),  # never
        ("11", 0, 3, None),  # fewer frames than the run
        ("0", 0, 1, None),
        ("01", 0, 1, 1),
    ],
)
def test_right_from_is_the_first_run_of_right_answers(pattern, start, run, expected):
    right = np.array([c == "1" for c in pattern])
    assert robot_limits.right_from(right, start, run) == expected


def test_right_from_needs_a_run_of_at_least_one_and_a_start_on_the_frames():
    with pytest.raises(ValueError, match="run must be >= 1; got 0"):
        robot_limits.right_from(np.ones(4, bool), 0, 0)
    with pytest.raises(ValueError, match="start must be >= 0; got -1"):
        robot_limits.right_from(np.ones(4, bool), -1, 1)


def test_matchers_on_a_diagonal_find_it_and_count_from_the_start():
    # scores with a clear diagonal from frame 5 on (noise before): every matcher is right
    # within a few frames of it; counted from frame 20, all are right at once
    rng = np.random.default_rng(0)
    n = 120
    S = rng.normal(0.0, 1.0, (n, n)).astype(np.float32)
    S[np.arange(5, n), np.arange(5, n)] += 6.0
    gt = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]) <= 2
    out = np.zeros((n, n), np.float32)
    out[np.arange(n), np.arange(n)] = 1.0  # a perfect kenyon+cann: right from frame 0
    row = robot_limits._matchers(0, "r-1x", 0, S, gt, out)
    assert row["kenyon+cann"] == 0
    names = [k for k in row if k.startswith("SeqSLAM")]
    assert len(names) == len(robot_limits.SEQ_SPEEDS)
    for name in names + ["kenyon+cann, exact odometry"]:
        assert row[name] is not None and 5 <= row[name] <= 20, (name, row[name])
    later = robot_limits._matchers(0, "r-1x", 20, S, gt, out)
    assert all(later[k] == 0 for k in names + ["kenyon+cann", "kenyon+cann, exact odometry"])
    wrong = np.roll(out, 10, axis=1)  # answers 10 places off: never right
    assert robot_limits._matchers(0, "r-1x", 0, S, gt, wrong)["kenyon+cann"] is None


def test_matcher_table_lists_every_view_and_matcher_per_seed():
    rows = [
        {"seed": s, "view": v, "start": 0, "kenyon+cann": a, "SeqSLAM-60, 0.8-1.2": b}
        for s, v, a, b in [
            (0, "r-1x", 33, 26),
            (1, "r-1x", 29, None),
            (0, "r-detour", 44, 39),
            (1, "r-detour", 43, 32),
        ]
    ]
    lines = robot_limits._matcher_table({"matchers": rows, "protocol": {"matchers": "m"}})
    assert "| view | matcher | seed 0 | seed 1 |" in lines
    assert "| cold start at 1x | kenyon+cann | 33 | 29 |" in lines
    assert "| cold start at 1x | SeqSLAM-60, 0.8-1.2 | 26 | never |" in lines
    assert "| detour, from the rejoin | SeqSLAM-60, 0.8-1.2 | 39 | 32 |" in lines
    assert not any("fisheye" in line for line in lines)  # no rows: no view
    rows.append(
        {"seed": 2, "view": "r-1x", "start": 0, "kenyon+cann": 30, "SeqSLAM-60, 0.8-1.2": 27}
    )
    lines = robot_limits._matcher_table({"matchers": rows, "protocol": {"matchers": "m"}})
    assert "| cold start at 1x | kenyon+cann | 33 | 29 | 30 |" in lines
    assert "| detour, from the rejoin | kenyon+cann | 44 | 43 | - |" in lines  # no seed 2 run


def test_state_row_splits_the_answers_by_state():
    # four frames over three places: answers 0, 1, 2, 2; right where gt says; localized 1 and 2
    out = np.array([[0.9, 0.1, 0.0], [0.2, 0.8, 0.1], [0.0, 0.3, 0.6], [0.1, 0.2, 0.4]])
    gt = np.array([[1, 0, 0], [0, 1, 0], [0, 1, 0], [0, 0, 1]], bool)
    localized = np.array([False, True, True, False])
    row = robot_limits.state_row(3, "r-x", "default", out, localized, gt)
    assert row["seed"] == 3 and row["view"] == "r-x" and row["bank"] == "default"
    assert row["right"] == 0.75 and row["localized"] == 0.5
    assert row["right_when_localized"] == 0.5 and row["right_when_lost"] == 1.0
    assert row["confidence_when_right"] == pytest.approx((0.9 + 0.8 + 0.4) / 3)
    none = robot_limits.state_row(0, "r-x", "default", out, np.zeros(4, bool), gt)
    assert none["right_when_localized"] is None and none["right_when_lost"] == 0.75


@pytest.mark.parametrize(
    "speed, n, expected",
    [
        (0.5, 4, [0, 0, 1, 1, 2, 2, 3, 3]),
        (1.0, 3, [0, 1, 2]),
        (0.33, 2, [0, 0, 0, 0, 1, 1, 1]),
        (2.0, 5, [0, 2, 4]),
    ],
)
def test_slow_places_hold_each_place_for_its_share_of_frames(speed, n, expected):
    np.testing.assert_array_equal(robot_limits.slow_places(speed, n), expected)


def test_slow_table_is_the_mean_over_seeds_per_speed_and_odometry():
    def row(seed, speed, odometry, auc, right):
        return {
            "seed": seed,
            "speed": speed,
            "odometry": odometry,
            "frames": int(10 / speed),
            "auc_front_end": 0.1 + seed / 10,
            "auc": auc,
            "right": right,
            "localized": 0.4 + seed / 10,
        }

    rows = [
        row(0, 0.2, False, 0.7, 0.8),
        row(1, 0.2, False, 0.9, 0.6),
        row(0, 0.2, True, 0.95, 1.0),
        row(1, 0.2, True, 0.85, 0.9),
        row(0, 1.0, False, 0.97, 0.97),
    ]
    lines = robot_limits._slow_table({"slow": rows, "protocol": {"slow": "p"}})
    assert "| 0.2 | 50 | no | 0.150 | 0.800 | 0.700 | 0.450 |" in lines
    assert "| 0.2 | 50 | yes | 0.150 | 0.900 | 0.950 | 0.450 |" in lines
    assert "| 1 | 10 | no | 0.100 | 0.970 | 0.970 | 0.400 |" in lines
    assert lines.index("| 0.2 | 50 | no | 0.150 | 0.800 | 0.700 | 0.450 |") < lines.index(
        "| 1 | 10 | no | 0.100 | 0.970 | 0.970 | 0.400 |"
    )
    assert "Protocol: p." in " ".join(lines)


def test_profiles_table_gives_each_draw_and_the_lowest():
    rows = [
        {"seed": s, "motion": m, "draw": d, "auc": a}
        for s, m, d, a in [
            (0, "walk", 0, 0.96),
            (1, "walk", 0, 0.98),
            (0, "walk", 1, 0.90),
            (1, "walk", 1, 0.92),
            (0, "drops", 0, 0.7),
            (1, "drops", 0, 0.8),
            (0, "drops", 1, 0.8),
            (1, "drops", 1, 0.9),
        ]
    ]
    rows += [dict(r, jitter=0.3, auc=r["auc"] - 0.1) for r in rows if r["motion"] == "drops"]
    lines = robot_limits._profiles_table({"profiles": rows, "protocol": {"profiles": "P"}})
    assert "| motion | jitter | draw 0 | draw 1 | lowest | mean |" in lines
    walk = "| 0-999, random 0.4-1.6x | 0 | 0.970 | 0.910 | 0.910 | 0.940 |"
    drops = "| 0-999 at 1x, 20% of frames dropped | 0 | 0.750 | 0.850 | 0.750 | 0.800 |"
    jittered = "| 0-999 at 1x, 20% of frames dropped | 0.3 | 0.650 | 0.750 | 0.650 | 0.700 |"
    assert walk in lines and drops in lines and jittered in lines
    assert lines.index(walk) < lines.index(drops) < lines.index(jittered)
    assert any("(P)" in line for line in lines)


def test_profile_draw_0_is_the_accuracy_benchmarks_own_view():
    assert robot_limits.PROFILE_SEEDS[0] == 0 and len(set(robot_limits.PROFILE_SEEDS)) > 1
    for kind in robot_limits.PROFILE_KINDS:
        view = robot_limits._view(f"r-{kind}")
        assert view.motion == kind and not view.odometry and not view.camera_noise
        np.testing.assert_array_equal(robot_limits.motion_places(kind, 1000, 0), view.indices(1000))


def test_profile_rows_draw_each_profile_from_its_own_seed(monkeypatch):
    seen = []

    def places(kind, n, seed):
        seen.append((kind, seed))
        return np.arange(0, n, 1 + seed % 2)  # draws differ: every frame, or every other

    made = []
    real = robot_limits.make_method

    def make(name, seed, frontend_params, filter_params):
        made.append((name, seed, dict(filter_params)))
        return real(name, seed, frontend_params, filter_params)

    monkeypatch.setattr(robot_limits, "motion_places", places)
    monkeypatch.setattr(robot_limits, "make_method", make)
    monkeypatch.setattr(robot_limits, "PROFILE_SEEDS", (0, 1))
    n = 60
    S = np.full((n, n), 0.1, np.float32)
    S[np.arange(n), np.arange(n)] = 1.0
    ids = np.arange(n)
    rows = robot_limits._profile_rows(4, S, ids, ids)
    assert seen == [(k, d) for k in robot_limits.PROFILE_KINDS for d in (0, 1)]
    jitters = robot_limits.JITTERS
    assert [(r["motion"], r["draw"], r["jitter"]) for r in rows] == [
        (k, d, j) for k, d in seen for j in jitters
    ]
    assert made == [("kenyon+cann", 4, {"jitter": r["jitter"]}) for r in rows]
    assert all(r["seed"] == 4 and 0.0 <= r["auc"] <= 1.0 for r in rows)
    assert rows[0]["auc"] > 0.9  # a clean diagonal, every frame: found


def test_slow_rows_use_the_views_noise_and_no_odometry_on_the_first_frame(monkeypatch):
    noise_seeds, velocities = [], []

    def frames(images, sd, seed):
        noise_seeds.append((sd, seed))
        return images

    class Spy:
        state_ = "localized"

        def reset(self):
            pass

        def step(self, row, velocity=None):
            velocities.append(velocity)
            return row

    class Method:
        filter = Spy()

    monkeypatch.setattr(robot_limits, "camera_frames", frames)
    monkeypatch.setattr(robot_limits, "SLOW_SPEEDS", (0.5,))
    real = robot_limits.make_method

    def make(name, seed, fp, params):
        return Method() if name == "kenyon+cann" else real(name, seed, fp, params)

    monkeypatch.setattr(robot_limits, "make_method", make)
    rng = np.random.default_rng(0)
    ref = rng.random((12, 32, 64)).astype(np.float32)
    ids = np.arange(12)
    rows = robot_limits._slow_rows(3, ref, ref.copy(), ids, ids)
    assert noise_seeds == [(robot_limits.SLOW_NOISE, robot_limits.SLOW_NOISE_SEED)]
    assert [r["odometry"] for r in rows] == [False, True]
    n = len(robot_limits.slow_places(0.5, 12))
    assert rows[0]["frames"] == n == 24
    # without odometry none; with it nothing on frame 0, then the places moved
    assert velocities[:n] == [None] * n
    assert velocities[n] is None and velocities[n + 1 : n + 4] == [0.0, 1.0, 0.0]
    assert all(r["seed"] == 3 and r["localized"] == 1.0 for r in rows)


def test_stretches_from_keeps_those_with_a_place_in_the_window():
    stretches = [(3, 5), (10, 12), (20, 25)]
    assert robot_limits.stretches_from(stretches, 6, 4) == []  # places 6-9
    assert robot_limits.stretches_from(stretches, 5, 5) == [(3, 5)]  # its last place, 5
    assert robot_limits.stretches_from(stretches, 0, 3) == []  # places 0-2 end before 3
    assert robot_limits.stretches_from(stretches, 0, 4) == [(3, 5)]
    assert robot_limits.stretches_from(stretches, 11, 10) == [(10, 12), (20, 25)]
    assert robot_limits.stretches_from(stretches, 13, 7) == []  # 13-19
    assert robot_limits.stretches_from(stretches, 13, 8) == [(20, 25)]


def test_rejoin_rows_leave_out_each_stretch_and_give_the_break(monkeypatch):
    # a route of 40 distinct places; the map leaves out 10 .. end - 1 for each end
    made, fitted, judged = [], [], []
    real = robot_limits.make_method
    real_detour = robot_limits._detour

    def make(name, seed, fp, params):
        made.append((name, seed, [int(b) for b in params["breaks"]]))
        method = real(name, seed, fp, params)
        fit = method.frontend.fit
        method.frontend.fit = lambda images: fitted.append(len(images)) or fit(images)
        return method

    def detour(query_ids, map_ids, out, states, tol):
        judged.append((list(map_ids), tol, out.shape))
        return real_detour(query_ids, map_ids, out, states, tol)

    monkeypatch.setattr(robot_limits, "make_method", make)
    monkeypatch.setattr(robot_limits, "_detour", detour)
    monkeypatch.setattr(robot_limits, "REJOIN_FIRST", 10)
    monkeypatch.setattr(robot_limits, "REJOIN_ENDS", (15, 20))
    rng = np.random.default_rng(0)
    ref = rng.random((40, 32, 64)).astype(np.float32)
    ids = np.arange(40)
    rows = robot_limits._rejoin_rows(1, ref, ref.copy(), ids, ids)
    # the break is the first place kept after the stretch: index 10 of the map in both
    assert made == [("kenyon+cann", 1, [10]), ("kenyon+cann", 1, [10])]
    # the map keeps places 0-9 and end-39; every query frame is judged against it
    assert fitted == [35, 30]
    assert judged == [
        ([*range(10), *range(15, 40)], robot_limits.TOLERANCE, (40, 35)),
        ([*range(10), *range(20, 40)], robot_limits.TOLERANCE, (40, 30)),
    ]
    assert [(r["seed"], r["first"], r["end"]) for r in rows] == [(1, 10, 15), (1, 10, 20)]
    for r in rows:
        # the query is the map's own frames: back on the map, right within a few frames
        assert r["rejoin_frames"] is not None and 0 <= r["rejoin_frames"] <= 10
        assert 0.0 <= r["offmap_localized_share"] <= 1.0


def test_front_end_rows_rank_the_true_place_from_the_rejoin_on(monkeypatch):
    # 40 places; r-detour's map leaves out 16-27, so the rejoin is frame 28.  A front end whose
    # scores put the true place at a chosen rank on each frame from the rejoin on
    ranks = [0, 3, 12, 0, 9]
    made, fitted = [], []

    class Front:
        def fit(self, images):
            fitted.append(len(images))

        def score(self, images):
            S = np.tile(np.linspace(1.0, 0.0, 28), (len(images), 1))  # place j: j-th best
            for t, r in enumerate(ranks):
                true = 28 - 12 + t  # frame 28 + t is place 28 + t: map column 16 + t
                S[t, [true, r]] = S[t, [r, true]]
            return S

    class Method:
        frontend = Front()

    def make(name, seed, fp=None, params=None):
        made.append((name, seed, fp))
        return Method()

    monkeypatch.setattr(robot_limits, "make_method", make)
    monkeypatch.setattr(
        robot_limits,
        "REJOIN_FRONT_ENDS",
        (("a", "kenyon", {"intensity": True}, True), ("b", "pixels", {}, False)),
    )
    monkeypatch.setattr(robot_limits, "AFTER", 5)
    ref = np.zeros((40, 32, 64), np.float32)
    ids = np.arange(40)
    rows = robot_limits._front_end_rows(robot_limits.SEEDS[0], ref, ref, ids, ids)
    assert made == [("kenyon", 0, {"intensity": True}), ("pixels", 0, {})]
    assert fitted == [28, 28]
    a, b = rows
    assert a == b | {"front_end": "a", "seeded": True}
    assert (a["seed"], a["front_end"], a["map_leaves_out"]) == (0, "a", [16, 27])
    assert (a["top10_frames"], a["top1_frames"], a["rank_best"], a["rank_median"]) == (
        4,
        2,
        0,
        3.0,
    )
    # a front end without a seed runs for the first seed only
    made.clear()
    later = robot_limits._front_end_rows(robot_limits.SEEDS[1], ref, ref, ids, ids)
    assert [m[0] for m in made] == ["kenyon"] and [r["front_end"] for r in later] == ["a"]


def test_front_end_table_pools_the_seeds_per_front_end():
    rows = [
        {
            "seed": s,
            "front_end": f,
            "map_leaves_out": [400, 699],
            "seeded": f != "pixels",
            "rank_median": m,
            "rank_best": b,
            "top10_frames": t,
            "top1_frames": o,
        }
        for s, f, m, b, t, o in [
            (0, "kenyon", 375.5, 19, 0, 0),
            (1, "kenyon", 318.5, 5, 1, 0),
            (2, "kenyon", 286.0, 8, 1, 1),
            (0, "pixels", 250.0, 22, 0, 0),
        ]
    ]
    lines = robot_limits._front_end_table({"rejoin_front_ends": rows})
    assert "| kenyon | 0, 1, 2 | 318.5 | 5 | 2 of 90 | 1 |" in lines
    assert "| pixels | none | 250.0 | 22 | 0 of 30 | 0 |" in lines
    assert lines.index("| kenyon | 0, 1, 2 | 318.5 | 5 | 2 of 90 | 1 |") < lines.index(
        "| pixels | none | 250.0 | 22 | 0 of 30 | 0 |"
    )
    assert any("the map without 400-699" in line for line in lines)


def test_rejoin_table_lists_each_end_with_its_seeds_and_the_mean_share():
    rows = [
        {"seed": s, "first": 400, "end": e, "rejoin_frames": f, "offmap_localized_share": share}
        for s, e, f, share in [
            (0, 700, 42, 0.0),
            (1, 700, None, 0.01),
            (0, 650, 10, 0.02),
            (1, 650, 9, 0.0),
        ]
    ]
    data = {
        "rejoins": rows,
        "rejoin_stretches": {"650": [], "700": [[707, 725]]},
        "protocol": {"rejoins": "r"},
    }
    lines = robot_limits._rejoin_table(data)
    assert "| 400-649 | none | 10 / 9 | 1.0% |" in lines
    assert "| 400-699 | 707-725 | 42 / never | 0.5% |" in lines
    assert lines.index("| 400-649 | none | 10 / 9 | 1.0% |") < lines.index(
        "| 400-699 | 707-725 | 42 / never | 0.5% |"
    )  # in the order of the ends
    assert any("(seed 0 / seed 1)" in line for line in lines)
    # the left-out stretch's first place is the run's, not the module's
    for r in rows:
        r["first"] = 300
    assert "| 300-649 | none | 10 / 9 | 1.0% |" in robot_limits._rejoin_table(data)


def test_start_rows_score_both_cameras_from_each_start(monkeypatch):
    monkeypatch.setattr(robot_limits, "START_FRAMES", (0, 30))
    n = 60
    full = np.full((n, n), 0.1, np.float32)
    full[np.arange(n), np.arange(n)] = 1.0  # a clean diagonal
    disc = full.copy()
    disc[:40] = np.roll(full[:40], 7, axis=1)  # through the disc: 7 places off on 0-39
    ids = np.arange(n)
    rows = robot_limits._start_rows(2, full, disc, ids, ids)
    assert [(r["seed"], r["start"]) for r in rows] == [(2, 0), (2, 30)]
    for r in rows:
        assert r["full_auc_2"] > 0.9 and r["full_auc_20"] > 0.9
    # 7 places off is wrong at tolerance 2 and right at 20
    assert rows[0]["fisheye_auc_2"] < 0.5 and rows[0]["fisheye_auc_20"] > 0.99
    # from frame 0 the disc's first 40 frames are wrong at tolerance 2: a large gap; from
    # frame 30 only 10 of 30 frames are
    first, later = rows
    assert first["full_auc_2"] - first["fisheye_auc_2"] > 0.3
    assert (
        0.0
        < later["full_auc_2"] - later["fisheye_auc_2"]
        < first["full_auc_2"] - first["fisheye_auc_2"]
    )


def test_start_table_gives_the_mean_auc_and_the_gap_per_start():
    rows = [
        {"seed": s, "start": st, "full_auc_2": f, "fisheye_auc_2": d, "full_auc_20": f,
         "fisheye_auc_20": d + 0.01}
        for s, st, f, d in [(0, 0, 0.97, 0.96), (1, 0, 0.98, 0.96), (0, 50, 0.97, 0.97),
                            (1, 50, 0.97, 0.965)]
    ]  # fmt: skip
    lines = robot_limits._start_table({"starts": rows, "protocol": {"starts": "s"}})
    header = next(line for line in lines if line.startswith("| query from frame"))
    assert header.count("gap, tol") == 2 and "tol 2 |" in header and "tol 20 |" in header
    assert "| 0 | 0.9750 | 0.9600 | +0.0150 | 0.9750 | 0.9700 | +0.0050 |" in lines
    assert "| 50 | 0.9700 | 0.9675 | +0.0025 | 0.9700 | 0.9775 | -0.0075 |" in lines


def test_committed_scans_start_from_the_accuracy_benchmarks_own_views():
    # the committed figures: the scan's detour ending at 700 is the accuracy benchmark's
    # r-detour, its start at frame 0 is r-1x and r-fisheye (same seeds, same numbers)
    bench = ROOT / "benchmarks"
    limits = json.loads((bench / "robot-limits.json").read_text())
    accuracy = json.loads((bench / "accuracy.json").read_text())

    def accuracy_row(condition, seed):
        return next(
            r
            for r in accuracy["rows"]
            if r["condition"] == condition and r["method"] == "kenyon+cann" and r["seed"] == seed
        )

    view = robot_limits._view("r-detour")
    first, end = (int(g * 1000) for g in view.gap)
    seeds = sorted({r["seed"] for r in limits["rejoins"]})
    assert seeds == list(robot_limits.SEEDS)
    for seed in seeds:
        scan = next(
            r
            for r in limits["rejoins"]
            if r["seed"] == seed and (r["first"], r["end"]) == (first, end)
        )
        own = next(r for r in limits["detour"] if r["seed"] == seed)
        bench_row = accuracy_row(f"r-detour@{robot_limits.TOLERANCE}", seed)
        assert scan["rejoin_frames"] == own["rejoin_frames"] == bench_row["rejoin_frames"]
        assert scan["offmap_localized_share"] == pytest.approx(bench_row["offmap_localized_share"])
        start = next(r for r in limits["starts"] if r["seed"] == seed and r["start"] == 0)
        for tol in robot_limits.START_TOLERANCES:
            assert start[f"full_auc_{tol}"] == pytest.approx(
                accuracy_row(f"r-1x@{tol}", seed)["auc"]
            )
            assert start[f"fisheye_auc_{tol}"] == pytest.approx(
                accuracy_row(f"r-fisheye@{tol}", seed)["auc"]
            )


def _per_frame_edges(frame: np.ndarray) -> np.ndarray:
    """The Sobel magnitude of one frame alone (scipy's 2-d Sobel), centred, unit length."""
    from scipy import ndimage

    f = frame.astype(np.float64)
    g = np.hypot(ndimage.sobel(f, axis=1), ndimage.sobel(f, axis=0)).ravel()
    g -= g.mean()
    return g / np.linalg.norm(g)


def test_pixel_edges_code_each_frame_alone_by_its_sobel_magnitude():
    rng = np.random.default_rng(3)
    frames = rng.random((5, 32, 64)).astype(np.float32)
    codes = robot_limits.PixelEdges._encode(frames)
    assert codes.shape == (5, 32 * 64)
    for frame, code in zip(frames, codes, strict=True):
        np.testing.assert_allclose(code, _per_frame_edges(frame), atol=1e-5)
    # a frame's code does not depend on its neighbours in the batch
    np.testing.assert_allclose(robot_limits.PixelEdges._encode(frames[2:3])[0], codes[2])
    # a blank frame has no edges: a zero code, no NaN
    blank = robot_limits.PixelEdges._encode(np.full((1, 32, 64), 0.4, np.float32))
    assert not blank.any()


def test_pixel_edges_score_by_cosine_and_need_the_pixels_aligned():
    rng = np.random.default_rng(4)
    ref = ndimage_smooth(rng.random((6, 32, 64)))
    edges = robot_limits.PixelEdges().fit(ref)
    S = edges.score(ref)
    assert S.shape == (6, 6) and S.dtype == np.float32
    np.testing.assert_allclose(np.diag(S), 1.0, atol=1e-5)
    assert (S.argmax(axis=1) == np.arange(6)).all()
    # brighter and with more contrast: the same edges, scaled, so the same code
    np.testing.assert_allclose(edges.score(0.2 + 0.5 * ref), S, atol=1e-5)
    # the same frames moved by 3 pixels score well below themselves
    moved = edges.score(np.roll(ref, 3, axis=2))
    assert (np.diag(moved) < 0.8).all()


def ndimage_smooth(x: np.ndarray) -> np.ndarray:
    """Random frames with structure at a few pixels' scale (so a shift changes them)."""
    from scipy import ndimage

    return ndimage.gaussian_filter(x, (0, 1.0, 1.0)).astype(np.float32)


def test_front_end_names_the_benchmarks_edges_or_makes_the_librarys():
    assert isinstance(robot_limits._front_end("edges", 0, {}), robot_limits.PixelEdges)
    kenyon = robot_limits._front_end("kenyon", 2, {"intensity": True})
    assert (kenyon.name, kenyon.intensity) == ("kenyon", True)
    # the seed goes to the front end: the same seed, the same connections
    ref = ndimage_smooth(np.random.default_rng(7).random((12, 32, 64)))
    again = robot_limits._front_end("kenyon", 2, {"intensity": True})
    other = robot_limits._front_end("kenyon", 3, {"intensity": True})
    for enc in (kenyon, again, other):
        enc.fit(ref)
    assert (kenyon.connections_ == again.connections_).all()
    assert (kenyon.connections_ != other.connections_).any()
    assert robot_limits._plain_labels()["kenyon"] == "kenyon"
    assert robot_limits._plain_labels()["edges"] == robot_limits.EDGES


def test_evidence_rows_feed_the_filter_each_front_end_with_and_without_odometry(monkeypatch):
    # 40 places; r-detour's map leaves out 16-27, so the query rejoins at frame 28
    streamed = []
    real_stream = robot_limits._stream
    made = []
    real_make = robot_limits.make_method

    def stream(filt, S, velocity, sources=None):
        streamed.append((S.shape, None if velocity is None else float(np.unique(velocity)[0])))
        return real_stream(filt, S, velocity, sources)

    def make(name, seed, fp=None, params=None):
        made.append((name, seed, dict(params or {})))
        return real_make(name, seed, fp, params)

    monkeypatch.setattr(robot_limits, "_stream", stream)
    monkeypatch.setattr(robot_limits, "make_method", make)
    ref = ndimage_smooth(np.random.default_rng(5).random((40, 32, 64)))
    ids = np.arange(40)
    rows = robot_limits._evidence_rows(0, ref, ref.copy(), ids, ids)
    assert [(r["front_end"], r["exact_odometry"]) for r in rows] == [
        ("kenyon", False),
        ("kenyon", True),
        (robot_limits.EDGES, False),
        (robot_limits.EDGES, True),
    ]
    # every run streams the 40 frames against the 28 places; odometry 1 place per frame
    assert streamed == [((40, 28), None), ((40, 28), 1.0)] * 2
    filters = [m for m in made if m[0] == "kenyon+cann"]
    assert [p.get("odometry") for _, _, p in filters] == [None, "exact", None, "exact"]
    assert all([int(b) for b in p["breaks"]] == [16] for _, _, p in filters)
    for r in rows:
        assert r["seed"] == 0
        # the query is the map's own frames: right and localized soon after the rejoin
        assert 0 <= r["right_from"] <= r["rejoin_frames"] <= 10
        assert 0.0 <= r["offmap_localized_share"] <= 1.0
    # the benchmark's edges have no seed: the first seed's run only
    later = robot_limits._evidence_rows(robot_limits.SEEDS[1], ref, ref.copy(), ids, ids)
    assert [(r["front_end"], r["seed"]) for r in later] == [("kenyon", 1), ("kenyon", 1)]


def test_alone_rows_score_each_window_without_a_filter():
    rng = np.random.default_rng(6)
    ref = ndimage_smooth(rng.random((30, 32, 64)))
    ids = np.arange(30)
    # window a: the map's own frames; window b: every query frame another place's
    views = {"a": (ref, ref.copy(), ids, ids), "b": (ref, ref[::-1].copy(), ids, ids)}
    rows = robot_limits._alone_rows(0, views)
    assert [(r["window"], r["front_end"]) for r in rows] == [
        ("a", "kenyon"),
        ("a", robot_limits.EDGES),
        ("b", "kenyon"),
        ("b", robot_limits.EDGES),
    ]
    a_k, a_e, b_k, b_e = rows
    assert a_k["recall_at_1"] == a_e["recall_at_1"] == 1.0
    assert a_e["auc"] == pytest.approx(1.0)
    # reversed: only the frames within the tolerance of the middle are right
    assert b_e["recall_at_1"] <= 5 / 30 and b_k["recall_at_1"] <= 5 / 30
    later = robot_limits._alone_rows(robot_limits.SEEDS[1], views)
    assert [(r["window"], r["front_end"], r["seed"]) for r in later] == [
        ("a", "kenyon", 1),
        ("b", "kenyon", 1),
    ]
    # a window whose query is 12 frames, each one place ahead of its id: right within the
    # tolerance (not at 0), the map fitted on the map's frames and the query scored
    query = ref[6:18]
    shifted = {"c": (ref, query, ids, np.arange(5, 17))}
    for r in robot_limits._alone_rows(0, shifted):
        assert r["recall_at_1"] == 1.0, r


def test_evidence_table_lists_each_front_end_and_odometry_and_the_front_ends_alone():
    edges = robot_limits.EDGES
    data = {
        "protocol": {"rejoin_evidence": "E", "front_ends_alone": "A", "tolerance": 2},
        "rejoin_evidence": [
            {
                "seed": s,
                "front_end": f,
                "exact_odometry": o,
                "right_from": r,
                "rejoin_frames": j,
                "offmap_localized_share": share,
                "front_end_answers": hints,
            }
            for s, f, o, r, j, share, hints in [
                (1, "kenyon", False, 38, 41, 0.02, 0.25),
                (0, "kenyon", False, 36, 42, 0.0, 0.5),
                (0, "kenyon", True, 36, None, 0.01, 0.0),
                (1, "kenyon", True, 33, 35, 0.0, None),
                (0, edges, False, 30, 47, 0.0, 0.95),
                (0, edges, True, None, None, 0.007, 1.0),
            ]
        ],
        "front_ends_alone": [
            {"seed": s, "window": w, "front_end": f, "auc": a, "recall_at_1": r}
            for s, w, f, a, r in [
                (0, "n64-0", "kenyon", 0.1, 0.2),
                (1, "n64-0", "kenyon", 0.2, 0.3),
                (0, "vp-0", "kenyon", 0.02, 0.1),
                (1, "vp-0", "kenyon", 0.04, 0.2),
                (0, "n64-0", edges, 0.4, 0.5),
                (0, "vp-0", edges, 0.008, 0.07),
            ]
        ],
    }
    lines = robot_limits._evidence_table(data)
    expected = [
        "| kenyon | none | 36 / 38 | 42 / 41 | 50% / 25% | 1.0% |",
        "| kenyon | exact | 36 / 33 | never / 35 | 0% / - | 0.5% |",
        f"| {edges} | none | 30 | 47 | 95% | 0.0% |",
        f"| {edges} | exact | never | never | 100% | 0.7% |",
        "| front end | n64-0: AUC / R@1 | vp-0: AUC / R@1 |",
        "| kenyon | 0.150 / 0.250 | 0.030 / 0.150 |",
        f"| {edges} | 0.400 / 0.500 | 0.008 / 0.070 |",
    ]
    at = [lines.index(line) for line in expected]
    assert at == sorted(at)
    assert any(line.startswith("The same detour with more to go on (E).") for line in lines)
    assert any(
        line.startswith("| front end | odometry | right from (seed 0 / 1) |") for line in lines
    )
    # without the front ends alone (an older JSON) the first table only
    data.pop("front_ends_alone")
    assert robot_limits._evidence_table(data)[-1] == (
        f"| {edges} | exact | never | never | 100% | 0.7% |"
    )


def test_evidence_rows_stream_each_front_ends_own_scores_of_the_seed(monkeypatch):
    # query frame t shows place t + 1 (one ahead of its id): right within the tolerance only
    ref = ndimage_smooth(np.random.default_rng(8).random((41, 32, 64)))
    qry, ids = ref[1:], np.arange(40)
    ref = ref[:40]
    keep = robot_limits.gap_keep(40, robot_limits._view("r-detour").gap)
    streamed = []
    real_stream = robot_limits._stream

    def stream(filt, S, velocity, sources=None):
        streamed.append(S.copy())
        return real_stream(filt, S, velocity, sources)

    monkeypatch.setattr(robot_limits, "_stream", stream)
    rows = robot_limits._evidence_rows(1, ref, qry, ids, ids)
    kenyon = robot_limits.make_method("kenyon", 1).frontend
    kenyon.fit(ref[keep])
    own = kenyon.score(qry)
    other = robot_limits.make_method("kenyon", 0).frontend
    other.fit(ref[keep])
    assert len(streamed) == 2
    for S in streamed:
        np.testing.assert_array_equal(S, own)
    assert not np.array_equal(other.score(qry), own)
    # one place off is within the tolerance: right soon after the rejoin
    for r in rows:
        assert r["right_from"] is not None and r["right_from"] <= r["rejoin_frames"] <= 10
    streamed.clear()
    robot_limits._evidence_rows(robot_limits.SEEDS[0], ref, qry, ids, ids)
    edges = robot_limits.PixelEdges().fit(ref[keep]).score(qry)
    assert len(streamed) == 4
    for S in streamed[2:]:
        np.testing.assert_array_equal(S, edges)
    # scores already computed are streamed as given, the front end not made again
    streamed.clear()
    given = own[:, ::-1].copy()
    robot_limits._evidence_rows(1, ref, qry, ids, ids, {"kenyon": given})
    assert len(streamed) == 2
    for S in streamed:
        np.testing.assert_array_equal(S, given)


def test_evidence_rows_count_as_the_detour_run_and_the_matchers_do():
    # kenyon's rows are the figures the page's detour and matcher tables give the same data
    rng = np.random.default_rng(9)
    ref = ndimage_smooth(rng.random((40, 32, 64)))
    qry = ndimage_smooth(ref + 0.8 * rng.random(ref.shape)) / 1.8
    ids = np.arange(40)
    view = robot_limits._view("r-detour")
    back = int(view.gap[1] * 40)
    for seed in robot_limits.SEEDS[:2]:
        rows = robot_limits._evidence_rows(seed, ref, qry, ids, ids)
        out, localized, S, gt, map_ids, truth = robot_limits._run(seed, view, ref, qry, ids, ids)
        breaks = robot_limits.route_breaks(map_ids)
        matchers = robot_limits._matchers(seed, "r-detour", back, S, gt, out, breaks)
        detour = robot_limits._detour(truth, map_ids, out, localized, robot_limits.TOLERANCE)
        mine = {r["exact_odometry"]: r for r in rows if r["front_end"] == "kenyon"}
        assert mine[False]["right_from"] == matchers["kenyon+cann"]
        assert mine[True]["right_from"] == matchers["kenyon+cann, exact odometry"]
        assert mine[False]["rejoin_frames"] == detour["rejoin_frames"]
        assert mine[False]["offmap_localized_share"] == detour["offmap_localized_share"]


def test_committed_evidence_agrees_with_the_pages_detour_and_matchers():
    limits = json.loads((ROOT / "benchmarks" / "robot-limits.json").read_text())
    rows = limits["rejoin_evidence"]
    assert sorted({r["seed"] for r in rows}) == list(robot_limits.SEEDS)
    for seed in robot_limits.SEEDS:
        mine = {
            r["exact_odometry"]: r for r in rows if r["seed"] == seed and r["front_end"] == "kenyon"
        }
        detour = next(r for r in limits["detour"] if r["seed"] == seed)
        matchers = next(
            r for r in limits["matchers"] if r["seed"] == seed and r["view"] == "r-detour"
        )
        assert mine[False]["rejoin_frames"] == detour["rejoin_frames"]
        assert mine[False]["right_from"] == matchers["kenyon+cann"]
        assert mine[True]["right_from"] == matchers["kenyon+cann, exact odometry"]
    # the benchmark's edges ran once, with the first seed
    edges = [r for r in rows if r["front_end"] == robot_limits.EDGES]
    assert [(r["seed"], r["exact_odometry"]) for r in edges] == [(0, False), (0, True)]
    alone = limits["front_ends_alone"]
    assert {(r["window"], r["front_end"]) for r in alone} == {
        (w, f)
        for w in (robot_limits.DATASET, robot_limits.EDGES_VIEWPOINT)
        for f in ("kenyon", robot_limits.EDGES)
    }


def test_evidence_rows_give_the_share_answered_from_the_front_end_after_the_rejoin(monkeypatch):
    # a filter whose answers come from the front end on every third frame: the share over
    # the 2 AFTER frames from the rejoin (frame 28 of 40 here: the 12 left)
    real_stream = robot_limits._stream

    def stream(filt, S, velocity, sources=None):
        out = real_stream(filt, S, velocity)
        sources.extend("front end" if t % 3 == 0 else "sequence" for t in range(len(S)))
        return out

    monkeypatch.setattr(robot_limits, "_stream", stream)
    ref = ndimage_smooth(np.random.default_rng(10).random((40, 32, 64)))
    ids = np.arange(40)
    rows = robot_limits._evidence_rows(1, ref, ref.copy(), ids, ids)
    # frames 28-39: 30, 33, 36 and 39 from the front end
    assert [r["front_end_answers"] for r in rows] == [4 / 12, 4 / 12]
    monkeypatch.setattr(robot_limits, "AFTER", 2)
    rows = robot_limits._evidence_rows(1, ref, ref.copy(), ids, ids)
    assert [r["front_end_answers"] for r in rows] == [1 / 4, 1 / 4]  # frames 28-31: 30

"""Tracking a recording: states per batch and odometry from the recording's own positions."""

from __future__ import annotations

import numpy as np
import pytest

from fake_filters import Scripted
from flyvpr.localization import LOCALIZED, LOST, Localizer
from flyvpr.localization.tracking import track
from flyvpr.methods import Method, make_method
from flyvpr.sources import Positions, Source

N = 6


class Frames(Source):
    """A recording in memory: frame i at i / 10 s."""

    kind = "frames"

    def __init__(self, images):
        super().__init__("memory")
        self.images = images

    def _frames(self):
        for i, img in enumerate(self.images):
            yield i, i / 10, lambda size, img=img: img


@pytest.fixture
def images():
    return np.random.default_rng(1).random((N, 32, 64), dtype=np.float32)


def _loc(images, spacing=2.0):
    method = Method(
        "pixels+scripted", make_method("pixels", 0).frontend, Scripted((LOCALIZED, LOST))
    )
    return Localizer(method, place_spacing=spacing).fit(images)


@pytest.mark.parametrize("batch", [1, 2, 32])
def test_odometry_is_the_distance_between_kept_frames(images, batch):
    # frames 0..5 at x = 0, 2, 5, 5, 9, 9 and y = 0 except frame 4 (unknown position)
    xy = np.array([[0, 0], [2, 0], [5, 0], [5, 0], [np.nan, np.nan], [9, 0]])
    keep = np.isfinite(xy[:, 0])
    positions = Positions(np.arange(N)[keep], xy[keep], "frame", "test")
    loc = _loc(images)
    steps = list(track(loc, Frames(images), positions=positions, odometry=True, batch=batch))
    assert sum(len(s.batch) for s in steps) == N
    # frame 4 gets the position between its neighbours (7, 0): steps of 2, 3, 0, 2 and 2 m
    assert loc.method.filter.velocities == [None, 1.0, 1.5, 0.0, 1.0, 1.0]
    places = np.concatenate([s.places for s in steps])
    states = np.concatenate([s.states for s in steps])
    assert places.tolist() == list(range(N))
    assert states.tolist() == [LOCALIZED, LOST] * (N // 2)


def test_frames_without_a_position_get_no_odometry(images):
    positions = Positions(np.array([2, 3, 5]), np.array([[0, 0], [0, 3], [4, 6]]), "frame", "t")
    loc = _loc(images, spacing=3.0)
    list(track(loc, Frames(images), positions=positions, odometry=True, batch=4))
    assert loc.method.filter.velocities == [None, None, None, 1.0, 5 / 6, 5 / 6]


def test_odometry_by_timestamp_and_every(images):
    positions = Positions(np.array([0.0, 0.5]), np.array([[0, 0], [0, 10]]), "timestamp", "t")
    loc = _loc(images, spacing=4.0)
    list(track(loc, Frames(images), every="2", positions=positions, odometry=True, batch=2))
    # frames 0, 2, 4 at t = 0, 0.2, 0.4: 4 m apart (interpolated), one place each
    assert loc.method.filter.velocities == [None, 1.0, 1.0]


def test_frames_before_and_after_timestamped_positions_get_no_odometry(images):
    # fixes from t = 0.2 to 0.4 s (0.1 s apart: a frame within 0.05 s of the ends still gets
    # one); frames at t = 0, 0.1 and 0.5 lie outside, and are not clamped to the end fixes
    t = np.array([0.2, 0.3, 0.4])
    positions = Positions(t, np.c_[t * 40.0, np.zeros(3)], "timestamp", "t")
    loc = _loc(images, spacing=4.0)
    list(track(loc, Frames(images), positions=positions, odometry=True, batch=4))
    assert loc.method.filter.velocities == [None, None, None, 1.0, 1.0, None]


def test_frames_given_a_copied_fix_get_no_odometry():
    # fixes every 0.4 s (a GPS slower than the 10 Hz camera) from 0 to 0.8 s, none from 0.8 to
    # 2.4 s (a gap), then to 3.2 s: a frame within 0.2 s past the ends or into the gap gets the
    # row's own position for its place, but no odometry (two frames with one copied position
    # read as a stand: the filter stopped beside every outage)
    images = np.random.default_rng(2).random((34, 32, 64), dtype=np.float32)
    t = np.array([0.0, 0.4, 0.8, 2.4, 2.8, 3.2])
    positions = Positions(t, np.c_[t * 40.0, np.zeros(6)], "timestamp", "t")
    loc = _loc(images, spacing=4.0)
    list(track(loc, Frames(images), positions=positions, odometry=True, batch=8))
    got = loc.method.filter.velocities
    assert got[1:9] == pytest.approx([1.0] * 8)  # 0.1-0.8 s: interpolated, 4 m each
    assert got[9:25] == [None] * 16  # 0.9-2.4 s: copies of 0.8 s's fix, the gap, then 2.4 s
    assert got[25:33] == pytest.approx([1.0] * 8)  # 2.5-3.2 s
    assert got[33] is None  # 3.3 s: a copy of the last fix
    xy = positions.at(np.arange(34), np.arange(34) / 10)  # (places still get the copies)
    assert xy[9, 0] == 32.0 and xy[33, 0] == 128.0 and np.isnan(xy[15]).all()


def test_without_odometry_the_filter_gets_none(images):
    positions = Positions(np.arange(N), np.c_[np.arange(N) * 2.0, np.zeros(N)], "frame", "t")
    loc = _loc(images)
    list(track(loc, Frames(images), positions=positions))
    assert loc.method.filter.velocities == [None] * N
    with pytest.raises(ValueError, match="odometry needs positions"):
        next(track(loc, Frames(images), odometry=True))


def test_ground_truth_frames_is_the_datasets_one():
    from flyvpr.datasets import ground_truth_from_frames
    from flyvpr.localization.tracking import ground_truth_frames

    q, r = np.array([0, 5, 9]), np.array([0, 2, 4, 6, 8, 10])
    np.testing.assert_array_equal(ground_truth_frames(q, r, 1), ground_truth_from_frames(q, r, 1))
    with pytest.raises(ValueError, match="tolerance"):
        ground_truth_frames(q, r, -1)


def test_ground_truth_positions_skips_unknown_positions():
    from flyvpr.localization.tracking import ground_truth_positions

    q = np.array([[0.0, 0.0], [np.nan, np.nan], [10.0, 0.0]])
    r = np.array([[0.0, 3.0], [10.0, 4.0], [np.nan, 0.0], [0.0, 50.0]])
    expected = np.zeros((3, 4), bool)
    expected[0, 0] = True  # 3 m
    expected[2, 1] = True  # 4 m
    np.testing.assert_array_equal(ground_truth_positions(q, r, 4.0), expected)
    expected[2, 1] = False
    np.testing.assert_array_equal(ground_truth_positions(q, r, 3.999), expected)
    assert not ground_truth_positions(q[1:2], r, 1e9).any()  # a frame without a position
    with pytest.raises(ValueError, match="radius"):
        ground_truth_positions(q, r, -1.0)
    with pytest.raises(ValueError, match="2-d"):
        ground_truth_positions(q[0], r, 1.0)


@pytest.mark.parametrize(
    "batch, error, match",
    [
        (0, ValueError, "batch must be >= 1; got 0"),
        (-5, ValueError, "batch must be >= 1; got -5"),
        (2.5, TypeError, "batch must be an int; got float"),
        (True, TypeError, "batch must be an int; got bool"),
    ],
)
def test_a_bad_batch_is_refused_by_name_before_any_frame(images, batch, error, match):
    loc = _loc(images)
    with pytest.raises(error, match=match):
        next(track(loc, Frames(images), batch=batch))
    with pytest.raises(error, match=match):
        next(Frames(images).batches((32, 64), batch=batch))
    assert loc.n_frames_ == 0

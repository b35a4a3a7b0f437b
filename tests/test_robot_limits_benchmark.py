"""The robot-limits benchmark's helpers: same-image stretches and scoring a stretch as one place."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

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

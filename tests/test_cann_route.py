"""Where a map's route is broken: ``route_breaks``, ``position_breaks`` and ``far_steps``."""

import numpy as np
import pytest

from flyvpr.temporal.cann import route_breaks
from flyvpr.temporal.cann._route import BREAK_FACTOR, BREAK_NEIGHBOURS, far_steps, position_breaks


@pytest.mark.parametrize(
    "coordinates, factor, expected",
    [
        ([10, 20, 30, 40, 3010, 3020, 3030], 5.0, (4,)),
        ([0, 1, 2, 3, 4, 5], 5.0, ()),
        ([0, 1, 2, 6, 7], 5.0, ()),  # (a step of 4: not more than 5 times the usual 1)
        ([0, 1, 2, 6, 7], 3.0, (3,)),
        ([0, 1, 2, 8, 9], 6.0, ()),  # (a step of 6 is not more than 6 times the usual 1)
        ([0, 1, 2, 8, 9], 5.9, (3,)),
        ([5.0, 5.5, 6.0, 0.0, 0.5, 1.0], 5.0, (3,)),  # (the next recording starts over)
        ([3, 4, 4, 5], 5.0, ()),  # (a frame repeated: no step, no break)
        ([0, 1, 100], 5.0, (2,)),  # (a step is judged by its neighbours, not by itself)
        # the usual step is the median of up to 5 steps on either side, not the route's: a
        # stretch driven 6 times faster (places kept by time) is no break, one jump is
        (np.cumsum([0] + [1] * 8 + [6] * 8 + [1] * 8), 5.0, ()),
        (np.cumsum([0] + [1] * 8 + [6] + [1] * 8), 5.0, (9,)),
        (np.cumsum([0] + [6] * 8 + [31] + [6] * 8), 5.0, (9,)),
        (np.cumsum([0] + [6] * 8 + [30] + [6] * 8), 5.0, ()),
        # (two jumps: each is judged by the steps around it, the other among them)
        (np.cumsum([0] + [1] * 6 + [50] + [1] * 2 + [50] + [1] * 6), 5.0, (7, 10)),
        # (a change of pace is no break: around it half the steps are of each)
        (np.cumsum([0] + [1] * 8 + [100] * 8), 5.0, ()),
        ([7], 5.0, ()),
        ([], 5.0, ()),
        ([0, 50, 51, 52, 53, 54], 5.0, (1,)),  # (the first step is judged too)
        ([5.0, 0.0], 5.0, (1,)),  # (two places: a step back, the next recording)
        # (any factor above 1: 1.15 is not more than 1.2 times the usual 1, 1.3 is)
        ([0, 1, 2, 3, 4.15], 1.2, ()),
        ([0, 1, 2, 3, 4.3], 1.2, (4,)),
        # the median of an odd number of known neighbours is the middle one: the first step,
        # 8, has neighbours 1, 1, 2, 2, 2 (median 2, not 1.5)
        (np.cumsum([0, 8, 1, 1, 2, 2, 2]), 5.0, ()),
        (np.cumsum([0, 11, 1, 1, 2, 2, 2]), 5.0, (1,)),
        # of an even number, the mean of the middle two: neighbours 1, 1, 1, 1, 2 | 2, 2, 2, 2, 2
        # (median 2, not 1.5)
        (np.cumsum([0, 1, 1, 1, 1, 2, 8, 2, 2, 2, 2, 2]), 5.0, ()),
        (np.cumsum([0, 1, 1, 1, 1, 2, 11, 2, 2, 2, 2, 2]), 5.0, (6,)),
        ([[0, 0], [3, 4], [6, 8], [6, 100], [9, 104]], 5.0, (3,)),
        ([[0, 0], [0, 0], [0, 0], [1, 0]], 5.0, ()),  # (a median step of 0: no jumps)
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0], [2, 9, 0]], 5.0, (3,)),
    ],
)
def test_route_breaks_from_frame_numbers_and_positions(coordinates, factor, expected):
    assert route_breaks(coordinates, factor) == expected
    # (the guides' figures: more than 5 times the median of up to 5 steps on either side)
    assert (BREAK_FACTOR, BREAK_NEIGHBOURS) == (5.0, 5)


@pytest.mark.parametrize(
    "coordinates, factor, message",
    [
        ([0, 1, float("nan")], 5.0, "coordinates must be finite"),
        (np.zeros((2, 2, 2)), 5.0, r"coordinates must be .* got shape \(2, 2, 2\)"),
        (np.zeros((3, 0)), 5.0, "got shape"),
        ([0, 1, 2], 1.0, "factor"),
    ],
)
def test_route_breaks_refuses_bad_input(coordinates, factor, message):
    with pytest.raises(ValueError, match=message):
        route_breaks(coordinates, factor)


def test_position_breaks_read_a_maps_positions():
    line = np.c_[2.0 * np.arange(20), np.zeros(20)]
    assert position_breaks(line) == ()
    jump = line.copy()
    jump[12:, 0] += 300.0  # the step from place 11 to 12: 302 m among steps of 2
    assert position_breaks(jump) == (12,)
    # a step with an unknown position at either end is not judged; the rest still are
    unknown = jump.copy()
    unknown[12] = np.nan
    assert position_breaks(unknown) == ()
    unknown[5] = np.nan
    unknown[12] = jump[12]
    assert position_breaks(unknown) == (12,)
    assert position_breaks(None) == () and position_breaks(line[:1]) == ()
    assert position_breaks(jump.tolist()) == (12,)  # any array-like
    # as route_breaks reads the same positions, where they are all known
    assert position_breaks(jump) == route_breaks(jump)


def test_far_steps_judges_a_long_route_in_chunks_with_the_same_answer():
    rng = np.random.default_rng(0)
    steps = rng.uniform(0.5, 3.0, 3000)
    steps[rng.random(3000) < 0.1] = np.nan
    steps[rng.random(3000) < 0.02] *= 60.0
    whole = far_steps(steps, chunk=10**6)
    assert 20 < whole.sum() < 120
    for chunk in (1, 2, 5, 6, 11, 997, 2999, 3000):
        np.testing.assert_array_equal(far_steps(steps, chunk=chunk), whole, err_msg=str(chunk))
    # a far step at a chunk's edge is judged with its neighbours in the next chunk
    line = np.full(40, 2.0)
    line[19] = 50.0
    for chunk in (19, 20, 18):
        assert far_steps(line, chunk=chunk).tolist() == [i == 19 for i in range(40)]
    assert far_steps(np.zeros(0)).shape == (0,)

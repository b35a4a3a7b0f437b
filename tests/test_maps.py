"""Map properties that need no recording: the spacing between places."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from flyvpr.localization.maps import Map


def _map(positions):
    n = 5 if positions is None else len(positions)
    return Map(None, (32, 64), np.zeros(n), np.arange(n), positions)


@pytest.mark.parametrize(
    "positions, spacing",
    [
        (None, None),
        ([[0, 0], [3, 4]], 5.0),
        ([[0, 0], [3, 4], [3, 6], [3, 9]], 3.0),  # steps 5, 2, 3: the median, not the mean
        ([[0, 0], [3, 4], [3, 6], [3, 7]], 2.0),  # steps 5, 2, 1
        ([[0, 0], [0, 1], [0, 4], [0, 8], [0, 9]], 2.0),  # steps 1, 3, 4, 1: mean of the middle
        # only neighbours that both have a position: steps 5 and 2 (not 10 across the gap)
        ([[0, 0], [3, 4], [np.nan, np.nan], [9, 12], [9, 14]], 3.5),
        ([[0, 0], [np.nan, 1.0], [2, 0]], None),  # no two neighbours with positions
        ([[np.nan, np.nan]] * 3, None),
        ([[1, 1]] * 4, None),  # a map recorded standing still has no spacing
    ],
)
def test_place_spacing_is_the_median_step_between_neighbours(positions, spacing):
    m = _map(None if positions is None else np.array(positions, dtype=np.float64))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no "mean of empty slice" on the way to None
        assert m.place_spacing == spacing
    if spacing is not None:
        assert type(m.place_spacing) is float


@pytest.mark.parametrize(
    "field, value, match",
    [
        (
            "timestamps",
            np.zeros(3),
            r"timestamps must have shape \(5,\), one entry a place .*\(3,\)",
        ),
        ("positions", np.zeros((4, 2)), r"positions must have shape \(5, 2\).*got \(4, 2\)"),
        ("positions", np.zeros((5, 3)), r"positions must have shape \(5, 2\).*got \(5, 3\)"),
        ("thumbnails", np.zeros((3, 8, 8), np.uint8), r"thumbnails must have shape \(5, H, W\)"),
        ("thumbnails", np.zeros((5, 8), np.uint8), r"thumbnails must have shape \(5, H, W\)"),
        ("source_index", np.arange(0), r"source_index must have shape \(n_places,\)"),
        ("source_index", np.zeros((5, 1)), r"source_index must have shape \(n_places,\)"),
    ],
)
def test_a_map_refuses_arrays_that_do_not_hold_one_entry_a_place(field, value, match):
    args = {"timestamps": np.zeros(5), "source_index": np.arange(5), "positions": None,
            "thumbnails": np.zeros((5, 8, 8), np.uint8)}  # fmt: skip
    args[field] = value
    with pytest.raises(ValueError, match=match):
        Map(None, (32, 64), **args)


def test_a_map_of_a_fitted_method_has_its_places(synthetic_route):
    from flyvpr.methods import make_method

    ref = synthetic_route(20, random_state=0).reference_images
    method = make_method("pixels", 0).fit(ref)
    assert Map(method, (32, 64), np.zeros(20), np.arange(20)).n_places == 20
    with pytest.raises(ValueError, match=r"source_index must have shape \(20 \(the method's pl"):
        Map(method, (32, 64), np.zeros(19), np.arange(19))

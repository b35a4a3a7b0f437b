"""Map properties that need no recording: the spacing between places; the positions a map
built from a recording gives its places."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from flyvpr.localization.maps import Map
from flyvpr.sources import Positions, Source


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


class _Camera(Source):
    """``images`` as a 10 Hz recording from t = 1000 s (frame i at 1000 + i / 10)."""

    kind = "camera"

    def __init__(self, path, images):
        super().__init__(path)
        self.images = images

    def _frames(self):
        for i, image in enumerate(self.images):
            yield i, 1000 + i / 10, lambda size, image=image: image


def _gps(t):
    """Positions at the times ``t``: the robot drives 20 m/s along x."""
    t = np.asarray(t, np.float64)
    return Positions(t, np.c_[(t - 1000) * 20, np.zeros(len(t))], "timestamp", "gps")


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_interpolates_positions_slower_than_the_camera(synthetic_route, tmp_path, compact):
    # a 10 Hz camera and 1 Hz positions: each place gets its point on the way (2 m apart),
    # not the nearest fix's (steps of 0 and 20 m, whose median gave the map no spacing)
    src = _Camera(tmp_path / "cam", synthetic_route(40, random_state=0).reference_images)
    gps = _gps(1000.0 + np.arange(5))
    if compact:
        from flyvpr.large.recording import build_compact_map

        m = build_compact_map(src, tmp_path / "m.fvmap", positions=gps, n_bits=64)
    else:
        m = Map.build(src, "pixels", positions=gps)
    np.testing.assert_allclose(m.positions, np.c_[2.0 * np.arange(40), np.zeros(40)], atol=1e-9)
    assert m.place_spacing == pytest.approx(2.0)


@pytest.mark.parametrize("compact", [False, True])
def test_a_map_leaves_places_in_a_gap_of_its_positions_without_one(
    synthetic_route, tmp_path, compact
):
    # 20 Hz positions with 2 s missing (from 1001.5 to 1003.5): the places recorded then have
    # none, as places before the first fix have none (not the fix next to them, nor a line
    # across, up to 20 m off)
    t = 1000 + np.r_[0:30, 70:80] / 20
    src = _Camera(tmp_path / "cam", synthetic_route(40, random_state=0).reference_images)
    if compact:
        from flyvpr.large.recording import build_compact_map

        m = build_compact_map(src, tmp_path / "m.fvmap", positions=_gps(t), n_bits=64)
    else:
        m = Map.build(src, "pixels", positions=_gps(t))
    unplaced = np.flatnonzero(np.isnan(m.positions).any(axis=1)).tolist()
    assert unplaced == list(range(15, 35))
    np.testing.assert_allclose(m.positions[[14, 35], 0], [28, 70], atol=1e-9)
    assert m.place_spacing == pytest.approx(2.0)

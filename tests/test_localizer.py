import math
import re

import numpy as np
import pytest

from fake_filters import Scripted, Stateless
from flyvpr import images as im
from flyvpr.localization import LOCALIZED, LOST, Fix, Fixes, Localizer
from flyvpr.localization.maps import Map
from flyvpr.methods import Method, make_method
from oracles import odometry_scale


@pytest.fixture(scope="module")
def route(synthetic_route):
    r = synthetic_route(120, random_state=1)
    return r.reference_images, r.query_images


@pytest.mark.parametrize("method", ["flyhash", "flynet+cann", "pixels+seqslam", "flyhash+cann"])
def test_stream_matches_batch(route, method):
    ref, qry = route
    params = {"epochs": 20} if method.startswith("flynet") else None
    batch = make_method(method, 0, frontend_params=params).fit(ref)
    S = batch.score(qry)
    loc = Localizer(method, random_state=0, frontend_params=params).fit(ref)
    places, confs, _ = zip(*(loc.update(img) for img in qry), strict=True)
    np.testing.assert_array_equal(places, S.argmax(axis=1))
    np.testing.assert_allclose(confs, S.max(axis=1), rtol=1e-4, atol=1e-5)
    assert loc.n_frames_ == len(qry)


def test_reset_restarts_the_drive(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)
    first = [loc.update(img) for img in qry[:30]]
    loc.reset()
    again = [loc.update(img) for img in qry[:30]]
    assert first == again


def test_velocity_input_is_passed_to_the_filter(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)
    keep = np.arange(0, len(qry), 2)
    for i, k in enumerate(keep):
        loc.update(qry[k], velocity=None if i == 0 else 2.0)
    filt = loc.method.filter
    assert filt.velocity_ == pytest.approx(2.0 * odometry_scale(filt))  # the odometry, scaled


def test_state_does_not_grow(route):
    ref, qry = route
    loc = Localizer("flyhash+cann", random_state=0).fit(ref)

    def state_size():
        # (the list of the map's tied places only shrinks: checked on its own)
        filt = loc.method.filter
        arrays = [v for k, v in vars(filt).items() if isinstance(v, np.ndarray) and k != "_tied"]
        return sum(v.nbytes for v in arrays), filt._tied.size

    loc.update(qry[0])
    size, tied = state_size()
    for img in qry[1:]:
        loc.update(img)
        assert state_size()[1] <= tied
    assert state_size()[0] == size


def test_offline_filter_refused():
    method = make_method("pixels+seqslam", 0, filter_params={"mode": "centered"})
    loc = Localizer(method)
    with pytest.raises(ValueError, match="future|centred|centered"):
        loc.fit(np.random.default_rng(0).random((10, 32, 64), dtype=np.float32))
        loc.update(np.zeros((32, 64), np.float32))


def test_bad_frame(route):
    ref, _ = route
    loc = Localizer("flyhash", random_state=0).fit(ref)
    with pytest.raises(ValueError, match="image size"):
        loc.update(np.zeros((16, 32), np.float32))
    with pytest.raises(ValueError, match="NaN"):
        loc.update(np.full((32, 64), np.nan, np.float32))
    for shape in ((1, 32, 64), (32, 64, 3), (64,)):
        expected = f"image must be one gray frame of shape (H, W) = (32, 64); got shape {shape}"
        with pytest.raises(ValueError, match=re.escape(expected)):
            loc.update(np.zeros(shape, np.float32))
    with pytest.raises(TypeError, match=r"image must be an array of shape \(H, W\)"):
        loc.update([[0.0, 0.5], [0.5]])
    assert loc.n_frames_ == 0


def test_raw_camera_frames_are_pointed_to_to_gray(route):
    # a camera's uint8/uint16 or colour frame: the message says the dtype and what converts it
    ref, _ = route
    loc = Localizer("flyhash", random_state=0).fit(ref)
    u8 = np.round(ref[3] * 255).astype(np.uint8)
    lo, hi = int(u8.min()), int(u8.max())
    for frame, dtype in ((u8, "uint8"), (u8.astype(np.uint16) * 257, "uint16")):
        k = 257 if dtype == "uint16" else 1
        expected = (
            f"image must hold gray values in [0, 1]; got range [{lo * k}, {hi * k}] (dtype "
            f"{dtype}: convert camera frames with flyvpr.images.to_gray)"
        )
        with pytest.raises(ValueError, match=re.escape(expected)):
            loc.update(frame)
        with pytest.raises(ValueError, match=re.escape(expected.replace("image ", "images ", 1))):
            loc.update_batch(np.stack([frame] * 2))
    for channels, dtype in ((3, np.uint8), (4, np.float32)):
        frame = np.zeros((32, 64, channels), dtype)
        expected = (
            f"image must be one gray frame of shape (H, W) = (32, 64); got shape {frame.shape} "
            f"(a colour frame, dtype {frame.dtype}: convert camera frames with "
            "flyvpr.images.resize_area(flyvpr.images.to_gray(frame), (32, 64)))"
        )
        with pytest.raises(ValueError, match=re.escape(expected) + "$"):
            loc.update(frame)
        with pytest.raises(ValueError, match=r"\(colour frames, dtype .*flyvpr.images.to_gray"):
            loc.update_batch(np.stack([frame] * 2))
    # the hint only where it applies: a float frame out of range, a stack given to update
    with pytest.raises(ValueError, match=rf"got range \[{lo}, {hi}\]$"):
        loc.update(u8.astype(np.float32))
    with pytest.raises(ValueError, match=r"\(update_batch takes a stack of frames\)$"):
        loc.update(np.zeros((3, 32, 64), np.float32))
    with pytest.raises(ValueError, match=r"got shape \(64,\)$"):  # no hint that does not apply
        loc.update(np.zeros(64, np.float32))
    # not an image at all: a TypeError naming what was given (a complex frame's imaginary
    # part was dropped with only numpy's warning)
    for given, what in ((None, "NoneType of dtype object"), ("f.png", "str of dtype <U5"),
                        (np.zeros((32, 64), complex), "ndarray of dtype complex128")):  # fmt: skip
        with pytest.raises(TypeError, match=rf"an array of numbers .*; got {re.escape(what)}$"):
            loc.update(given)
    assert loc.n_frames_ == 0
    # what the message points to does convert the frame
    np.testing.assert_allclose(loc.scores(im.to_gray(u8)), loc.scores(u8 / np.float32(255)))
    # a camera's frame of another size: the message names the resize that fits it
    big = np.zeros((64, 128, 3), np.uint8)
    expected = (
        "image must have image size (H, W) = (32, 64) as at fit time; got (64, 128) (resize "
        "frames of another size with flyvpr.images.resize_area(frame, (32, 64)))"
    )
    with pytest.raises(ValueError, match=re.escape(expected) + "$"):
        loc.update(im.to_gray(big))
    assert loc.update(im.resize_area(im.to_gray(big), (32, 64))).place >= 0


@pytest.mark.parametrize("call", ["update", "scores", "n_places"])
def test_calls_before_fit_raise_not_fitted_naming_the_call(call):
    from flyvpr import NotFittedError

    loc = Localizer("flyhash", random_state=0)
    with pytest.raises(NotFittedError, match=f"Localizer.{call}"):
        getattr(loc, call) if call == "n_places" else getattr(loc, call)(np.zeros((32, 64)))


# -- Fix, states and odometry, with scripted filters (fake_filters.py) ---------------------------
@pytest.fixture(scope="module")
def ref():
    return np.random.default_rng(0).random((6, 32, 64), dtype=np.float32)


def _loc(ref, filt, **kwargs):
    method = Method("pixels+test", make_method("pixels", 0).frontend, filt)
    return Localizer(method, **kwargs).fit(ref)


def test_fix_is_a_named_tuple_of_place_confidence_state(ref):
    assert Fix._fields == ("place", "confidence", "state")
    loc = _loc(ref, Scripted())
    raw = make_method("pixels", 0).fit(ref).score(ref[4][None])[0]
    fix = loc.update(ref[4])
    assert type(fix) is Fix
    assert fix == (4, pytest.approx(float(raw.max())), LOCALIZED)
    assert type(fix.place) is int and type(fix.confidence) is float and type(fix.state) is str


def test_update_batch_returns_fixes(ref):
    assert Fixes._fields == ("places", "confidences", "scores", "relocated", "states")
    loc = _loc(ref, Scripted((LOST, LOCALIZED)))
    out = loc.update_batch(ref[[2, 0, 5]])
    assert type(out) is Fixes
    assert out.places.tolist() == [2, 0, 5]
    assert out.scores.shape == (3, 6)
    np.testing.assert_array_equal(out.confidences, out.scores.max(axis=1))
    assert out.relocated.tolist() == [False, False, False]
    assert out.states.tolist() == [LOST, LOCALIZED, LOST]
    assert out.states.dtype.kind == "U"


def test_states_come_from_the_filter(ref):
    assert (LOCALIZED, LOST) == ("localized", "lost")
    loc = _loc(ref, Scripted((LOCALIZED, LOST, LOST)))
    assert [loc.update(img).state for img in ref[:5]] == [
        LOCALIZED, LOST, LOST, LOCALIZED, LOST
    ]  # fmt: skip
    loc.reset()
    assert loc.update_batch(ref[:4]).states.tolist() == [LOCALIZED, LOST, LOST, LOCALIZED]


@pytest.mark.parametrize("filt", [None, Stateless()], ids=["no filter", "stateless filter"])
def test_without_a_filter_state_the_fix_is_localized_with_the_raw_score(ref, filt):
    loc = _loc(ref, filt)
    raw = make_method("pixels", 0).fit(ref).score(ref)
    scale = 1.0 if filt is None else 2.0  # the stateless filter doubles the row
    for i in range(len(ref)):
        assert loc.update(ref[i]) == (i, pytest.approx(scale * raw[i].max()), LOCALIZED)
    out = loc.update_batch(ref)
    assert out.states.tolist() == [LOCALIZED] * len(ref)
    np.testing.assert_allclose(out.confidences, scale * raw.max(axis=1), rtol=1e-6)


def test_distance_is_divided_by_the_place_spacing(ref):
    loc = _loc(ref, Scripted(), place_spacing=2.0)
    assert loc.place_spacing == 2.0 and loc.uses_odometry
    loc.update(ref[0], distance=3.0)
    loc.update(ref[1])
    loc.update(ref[2], velocity=0.25)
    loc.update(ref[3], distance=0)  # standing still is odometry too
    loc.scores(ref[4], distance=5.0)
    loc.update(ref[5], velocity=-1)  # driving backwards, in places
    assert loc.method.filter.velocities == [1.5, None, 0.25, 0.0, 2.5, -1.0]
    loc.reset()
    loc.update_batch(ref[:4], distances=[3.0, np.nan, None, 0.0])
    loc.update_batch(ref[:2], velocities=np.array([0.5, np.nan]))
    loc.update_batch(ref[:2], velocities=[1, 2])
    loc.update_batch(ref[:1])
    assert loc.method.filter.velocities == [1.5, None, None, 0.0, 0.5, None, 1.0, 2.0, None]


def test_filters_without_odometry_ignore_it(ref):
    loc = _loc(ref, Stateless(), place_spacing=2.0)
    assert not loc.uses_odometry
    assert loc.update(ref[3], distance=4.0).place == 3
    assert loc.update_batch(ref[:2], velocities=[1.0, 1.0]).places.tolist() == [0, 1]
    assert loc.method.filter.n_steps == 3
    assert not _loc(ref, None).uses_odometry
    assert Localizer("pixels+cann").uses_odometry


def test_odometry_taken_from_an_array_is_its_number(ref):
    # a robot's code indexing a 0-d array (odom[t] of a structured array, a numpy reduction)
    loc = _loc(ref, Scripted(), place_spacing=2.0)
    loc.update(ref[0], velocity=np.array(1.5))
    loc.update(ref[1], distance=np.array(3.0, np.float32))
    loc.update(ref[2], velocity=np.float64(-1.0))  # (backwards: signed odometry)
    assert loc.method.filter.velocities == [1.5, 1.5, -1.0]


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"distance": 1.0}, ValueError, "needs place_spacing"),
        ({"distance": 1.0, "velocity": 1.0}, ValueError, "not both"),
        ({"distance": math.nan}, ValueError, "distance must be finite; got nan"),
        ({"distance": math.inf}, ValueError, "distance must be finite"),
        ({"distance": -0.5}, ValueError, "distance must be >= 0; got -0.5"),
        ({"distance": "3"}, TypeError, "distance must be a number; got str"),
        ({"distance": True}, TypeError, "distance must be a number; got bool"),
        ({"velocity": math.nan}, ValueError, "velocity must be finite; got nan"),
        ({"velocity": np.array([1.0])}, TypeError, "velocity must be a number; got ndarray"),
        ({"distance": np.array(np.nan)}, ValueError, "distance must be finite; got nan"),
        ({"velocity": None, "distance": None}, None, None),
    ],
)
@pytest.mark.parametrize("spacing", [None, 2.0])
def test_bad_odometry_is_refused(ref, kwargs, error, match, spacing):
    loc = _loc(ref, Scripted(), place_spacing=spacing)
    if error is None:
        assert loc.update(ref[0], **kwargs).place == 0
        return
    if match == "needs place_spacing" and spacing is not None:
        assert loc.update(ref[0], **kwargs).place == 0
        assert loc.method.filter.velocities == [0.5]
        return
    with pytest.raises(error, match=match):
        loc.update(ref[0], **kwargs)
    assert loc.n_frames_ == 0 and loc.method.filter.velocities == []


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        ({"distances": [1.0, 1.0]}, ValueError, "distances .*need place_spacing"),
        ({"distances": [1.0, 1.0], "velocities": [1.0, 1.0]}, ValueError, "not both"),
        ({"distances": [1.0]}, ValueError, r"distances must have shape \(2,\).*got \(1,\)"),
        ({"velocities": [[1.0, 1.0]]}, ValueError, r"velocities must have shape \(2,\)"),
        ({"distances": [1.0, -2.0]}, ValueError, "distances must be >= 0; got -2"),
        ({"velocities": [np.inf, 1.0]}, ValueError, "velocities must be finite"),
        ({"distances": ["a", 1.0]}, TypeError, "distances must be numbers"),
        ({"velocities": [True, False]}, TypeError, "velocities must be numbers"),
    ],
)
def test_bad_batch_odometry_is_refused(ref, kwargs, error, match):
    spacing = None if "need place_spacing" in match else 2.0
    loc = _loc(ref, Scripted(), place_spacing=spacing)
    with pytest.raises(error, match=match):
        loc.update_batch(ref[:2], **kwargs)
    assert loc.n_frames_ == 0 and loc.method.filter.velocities == []


@pytest.mark.parametrize(
    "spacing, error, match",
    [
        (0.0, ValueError, "place_spacing must be > 0.0 metres; got 0.0"),
        (-1.0, ValueError, "place_spacing must be > 0.0 metres; got -1.0"),
        (math.nan, ValueError, "place_spacing must be finite; got nan"),
        (math.inf, ValueError, "place_spacing must be finite; got inf"),
        ("2", TypeError, "place_spacing must be a number of metres; got str"),
        (True, TypeError, "got bool"),
    ],
)
def test_bad_place_spacing_is_refused(spacing, error, match):
    with pytest.raises(error, match=match):
        Localizer("pixels", place_spacing=spacing)


def test_from_map_takes_the_maps_spacing(ref):
    method = make_method("pixels+cann", 0).fit(ref)
    xy = np.c_[np.arange(6) * 2.5, np.zeros(6)]
    with_xy = Map(method, (32, 64), np.zeros(6), np.arange(6), xy)
    assert Localizer.from_map(with_xy).place_spacing == 2.5
    assert Localizer.from_map(with_xy, place_spacing=4).place_spacing == 4.0
    bare = Map(method, (32, 64), np.zeros(6), np.arange(6))
    assert Localizer.from_map(bare).place_spacing is None
    assert Localizer.from_map(bare, place_spacing=1.5).place_spacing == 1.5
    assert Localizer("pixels").place_spacing is None


def test_from_map_gives_the_cann_the_maps_breaks(ref):
    method = make_method("pixels+cann", 0).fit(ref)
    n = len(ref)
    xy = np.c_[np.arange(n) * 2.0, np.zeros(n)]
    xy[n // 2 :, 0] += 500.0  # the map's second half lies 500 m further along the road
    m = Map(method, (32, 64), np.zeros(n), np.arange(n), xy)
    assert m.breaks == (n // 2,)
    assert Localizer.from_map(m).method.filter.breaks == (n // 2,)
    assert method.filter.breaks == ()  # (the map's own filter is left as it was)
    assert Localizer.from_map(m, breaks=()).method.filter.breaks == ()
    assert Localizer.from_map(m, breaks=np.array([2, 5])).method.filter.breaks == (2, 5)
    with pytest.raises(ValueError, match=f"breaks must be places 1 .. {n - 1} of this map of"):
        Localizer.from_map(m, breaks=[n])
    with pytest.raises(ValueError, match="breaks must be increasing"):
        Localizer.from_map(m, breaks=[5, 2])
    with pytest.raises(ValueError, match=r"breaks must be a 1-d sequence .* shape \(\)"):
        Localizer.from_map(m, breaks=5)
    alone = Map(make_method("pixels", 0).fit(ref), (32, 64), np.zeros(n), np.arange(n), xy)
    assert Localizer.from_map(alone).method.filter is None  # (no filter to give them to)
    assert Localizer.from_map(alone, breaks=()).method.filter is None
    with pytest.raises(ValueError, match="breaks: the map's method pixels has no filter that"):
        Localizer.from_map(alone, breaks=[3])
    # breaks the map's filter was built with stay, over the map's own (none here)
    built = make_method("pixels+cann", 0, filter_params={"breaks": (4,)}).fit(ref)
    bare = Map(built, (32, 64), np.zeros(n), np.arange(n))
    assert bare.breaks == () and Localizer.from_map(bare).method.filter.breaks == (4,)
    assert Localizer.from_map(bare, breaks=()).method.filter.breaks == ()
    # (as an array, empty or not, and checked against the map's places at once)
    for own, expected in ((np.array([3, 5]), [3, 5]), (np.array([], int), list(m.breaks))):
        built = make_method("pixels+cann", 0, filter_params={"breaks": own}).fit(ref)
        with_xy = Map(built, (32, 64), np.zeros(n), np.arange(n), xy)
        assert list(Localizer.from_map(with_xy).method.filter.breaks) == expected
    past = make_method("pixels+cann", 0, filter_params={"breaks": (n,)}).fit(ref)
    with pytest.raises(ValueError, match=rf"the map's filter has \[{n}\]"):
        Localizer.from_map(Map(past, (32, 64), np.zeros(n), np.arange(n)))


def test_a_ready_method_gives_a_localizer_its_own_fresh_filter(route):
    ref, qry = route
    method = make_method("flyhash+cann", 0).fit(ref)
    fresh = [Localizer(make_method("flyhash+cann", 0).fit(ref)).update(img) for img in qry[:1]]
    method.score(qry[:60])  # the method's filter has run a whole traverse
    loc = Localizer(method)
    assert loc.method.filter is not method.filter
    assert loc.method.frontend is method.frontend  # the map itself is shared
    assert [loc.update(qry[0])] == fresh
    # Scoring with the method again, mid-drive, leaves the localizer's frames alone.
    expected = Localizer(make_method("flyhash+cann", 0).fit(ref))
    expected.update(qry[0])
    method.score(qry[:10])
    for img in qry[1:40]:
        assert loc.update(img) == expected.update(img)


def test_two_localizers_over_one_map_keep_their_own_drives(route):
    ref, qry = route

    def new_map():
        method = make_method("pixels+cann", 0).fit(ref)
        return Map(method, (32, 64), np.zeros(len(ref)), np.arange(len(ref)))

    shared = new_map()
    one, two = Localizer.from_map(shared), Localizer.from_map(shared)
    alone = Localizer.from_map(new_map())
    for k, img in enumerate(qry[:60]):
        two.update(qry[-1 - k])  # another robot, driving the route the other way
        assert one.update(img) == alone.update(img)


def test_a_distance_too_large_for_places_names_the_distance(ref):
    loc = _loc(ref, Scripted(), place_spacing=0.5)
    with pytest.raises(ValueError, match="distance 1e.308 m over place_spacing 0.5 m is not a fin"):
        loc.update(ref[0], distance=1e308)
    with pytest.raises(ValueError, match="distances over place_spacing 0.5 m must be a finite"):
        loc.update_batch(ref[:2], distances=[1.0, 1e308])
    assert loc.n_frames_ == 0 and loc.method.filter.velocities == []


def test_odometry_is_given_by_keyword_only(random_images):
    # `update(image, 10.0)` read 10 as places where metres were meant: a number by position
    # could be either unit, so it is refused
    ref = random_images(5)
    loc = Localizer("kenyon+cann").fit(ref)
    with pytest.raises(TypeError, match="positional argument"):
        loc.update(ref[0], 10.0)
    with pytest.raises(TypeError, match="positional argument"):
        loc.update_batch(ref[:2], [None, 1.0])
    with pytest.raises(TypeError, match="positional argument"):
        loc.scores(ref[0], 1.0)
    assert loc.n_frames_ == 0
    loc.update(ref[0], velocity=None)
    loc.update(ref[1], velocity=1.0)

"""Tests of the procedurally generated route (flyvpr.synthetic)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from PIL import Image

from flyvpr.images import list_images, load_images
from flyvpr.synthetic import (
    CONDITIONS,
    MATERIALS,
    Condition,
    SyntheticRoute,
    make_route,
    save_route,
)

LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def _corr(a, b):
    """Pearson correlation of matching frames of two stacks, shape (N,)."""
    a = a.reshape(len(a), -1).astype(np.float64)
    b = b.reshape(len(b), -1).astype(np.float64)
    a = a - a.mean(axis=1, keepdims=True)
    b = b - b.mean(axis=1, keepdims=True)
    return (a * b).sum(axis=1) / np.sqrt((a * a).sum(axis=1) * (b * b).sum(axis=1))


@pytest.fixture(scope="module")
def route():
    return make_route(120, conditions=("summer", "winter"), return_rgb=True, random_state=3)


# -- shapes, dtype, range --------------------------------------------------------------------


@pytest.mark.parametrize(
    "size, supersample", [((32, 64), 2), ((16, 32), 1), ((24, 40), 3), ((8, 8), 2)]
)
def test_shapes_dtype_range(size, supersample):
    r = make_route(10, size=size, conditions=tuple(CONDITIONS), supersample=supersample)
    assert r.conditions == tuple(CONDITIONS)
    assert r.n_places == 10
    assert r.rgb is None and r.reference_rgb is None and r.query_rgb is None
    for name in CONDITIONS:
        img = r.images[name]
        assert img.shape == (10, *size)
        assert img.dtype == np.float32
        assert img.min() >= 0.0 and img.max() <= 1.0
        assert np.isfinite(img).all()
        assert img.std() > 0.01  # not a blank frame stack


def test_reference_and_query_roles(route):
    assert route.reference_images is route.images["summer"]
    assert route.query_images is route.images["winter"]
    assert route.reference_rgb is route.rgb["summer"]
    assert route.query_rgb is route.rgb["winter"]
    assert route.rgb["winter"].shape == (120, 32, 64, 3)
    assert route.rgb["winter"].dtype == np.float32
    single = make_route(5, conditions="fall")
    assert single.conditions == ("fall",)
    assert single.query_images is single.reference_images


def test_gray_is_luma_of_colour(route):
    # Gray is the BT.601 luma of the colour frame (as flyvpr.images.to_gray);
    # they differ only where a channel saturates, which is rare.
    for name in route.conditions:
        luma = route.rgb[name] @ LUMA
        assert np.mean(np.abs(luma - route.images[name])) < 2e-3


def test_return_rgb_does_not_change_gray():
    a = make_route(20, conditions=("summer", "night"), random_state=7)
    b = make_route(20, conditions=("summer", "night"), random_state=7, return_rgb=True)
    for name in a.conditions:
        np.testing.assert_allclose(a.images[name], b.images[name], atol=1e-6)


# -- determinism -----------------------------------------------------------------------------


def test_same_seed_same_route():
    a = make_route(30, conditions=("summer", "fall"), random_state=11)
    b = make_route(30, conditions=("summer", "fall"), random_state=11)
    for name in a.conditions:
        np.testing.assert_array_equal(a.images[name], b.images[name])


def test_generator_random_state():
    a = make_route(20, random_state=np.random.default_rng(5))
    b = make_route(20, random_state=np.random.default_rng(5))
    np.testing.assert_array_equal(a.query_images, b.query_images)
    rng = np.random.default_rng(5)
    first = make_route(20, random_state=rng)
    second = make_route(20, random_state=rng)  # the shared stream has moved on
    assert not np.array_equal(first.reference_images, second.reference_images)


def test_other_seed_other_route():
    a = make_route(30, random_state=0)
    b = make_route(30, random_state=1)
    assert np.mean(np.abs(a.reference_images - b.reference_images)) > 0.02


def test_condition_independent_of_the_others():
    a = make_route(25, conditions=("summer", "winter"), random_state=2)
    b = make_route(25, conditions=("fall", "night", "winter"), random_state=2)
    np.testing.assert_array_equal(a.images["winter"], b.images["winter"])


def test_world_is_shared_across_conditions():
    # Without viewpoint jitter, clouds, exposure flicker and noise, two
    # conditions with the same colours differ in nothing: the world is one.
    calm = dict(noise_std=0.0, exposure_std=0.0, cloud_amount=0.0)
    a = dataclasses.replace(CONDITIONS["summer"], name="a", **calm)
    b = dataclasses.replace(CONDITIONS["summer"], name="b", **calm)
    r = make_route(15, conditions=(a, b), viewpoint_jitter=0.0, random_state=4)
    np.testing.assert_allclose(r.images["a"], r.images["b"], atol=1e-6)


# -- structure of the route ------------------------------------------------------------------


def test_consecutive_places_more_alike_than_distant(route):
    s = route.reference_images
    near = _corr(s[:-1], s[1:]).mean()
    far = _corr(s[:-50], s[50:]).mean()
    assert near > far + 0.1


def test_same_place_across_conditions_more_alike_than_other_places(route):
    s, w = route.reference_images, route.query_images
    same = _corr(s, w).mean()
    other = _corr(s[:-40], w[40:]).mean()
    assert same > other + 0.05


@pytest.mark.parametrize("other", ["fall", "winter", "night"])
def test_conditions_differ(other):
    r = make_route(30, conditions=("summer", other), random_state=0)
    assert np.mean(np.abs(r.reference_images - r.query_images)) > 0.05


def test_places_move_with_step():
    # A larger step moves the view further: consecutive frames correlate less.
    small = make_route(60, step=0.05, viewpoint_jitter=0.0, random_state=8).reference_images
    large = make_route(60, step=0.5, viewpoint_jitter=0.0, random_state=8).reference_images
    assert _corr(small[:-1], small[1:]).mean() > _corr(large[:-1], large[1:]).mean()


# -- ground truth ----------------------------------------------------------------------------


def test_ground_truth_band():
    r = make_route(6, random_state=0)
    gt0 = r.ground_truth()
    assert gt0.dtype == np.bool_ and gt0.shape == (6, 6)
    np.testing.assert_array_equal(gt0, np.eye(6, dtype=bool))
    gt2 = r.ground_truth(tolerance=2)
    expected = np.array([[abs(i - j) <= 2 for j in range(6)] for i in range(6)], dtype=bool)
    np.testing.assert_array_equal(gt2, expected)
    assert gt2.sum(axis=1).tolist() == [3, 4, 5, 5, 4, 3]


@pytest.mark.parametrize(
    "tolerance, error, match",
    [
        (-1, ValueError, "tolerance must be >= 0"),
        (1.5, TypeError, "tolerance must be an int"),
        (True, TypeError, "tolerance must be an int"),
    ],
)
def test_ground_truth_errors(tolerance, error, match):
    r = make_route(3, random_state=0)
    with pytest.raises(error, match=match):
        r.ground_truth(tolerance)


# -- parameter errors ------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(n_places=1), ValueError, "n_places must be >= 2"),
        (dict(n_places=0), ValueError, "n_places must be >= 2"),
        (dict(n_places=10.0), TypeError, "n_places must be an int"),
        (
            dict(conditions=("summer", "monsoon")),
            ValueError,
            r"unknown condition 'monsoon'.*"
            r"known conditions: \['fall', 'night', 'summer', 'winter'\]",
        ),
        (dict(conditions=()), ValueError, "conditions is empty"),
        (dict(conditions=("summer", "summer")), ValueError, "distinct names"),
        (dict(conditions=("summer", 3)), TypeError, "names or Condition objects"),
        (dict(conditions=5), TypeError, "conditions must be a sequence"),
        (dict(size=(2, 64)), ValueError, r"size must be at least \(4, 4\)"),
        (dict(size=32), TypeError, "size must be a pair"),
        (dict(size=(32.0, 64)), TypeError, "size must be a pair"),
        (dict(step=0.0), ValueError, "step must be in"),
        (dict(step=3.0), ValueError, "step must be in"),
        (dict(supersample=0), ValueError, "supersample must be >= 1"),
        (dict(viewpoint_jitter=-1.0), ValueError, "viewpoint_jitter must be"),
        (dict(viewpoint_jitter="big"), TypeError, "viewpoint_jitter must be a number"),
        (dict(random_state="seed"), TypeError, "random_state must be"),
    ],
)
def test_make_route_errors(kwargs, error, match):
    kwargs = {"n_places": 5, **kwargs}
    with pytest.raises(error, match=match):
        make_route(**kwargs)


def test_custom_condition():
    storm = dataclasses.replace(CONDITIONS["winter"], name="storm", noise_std=0.08)
    r = make_route(10, conditions=("summer", storm), random_state=0)
    assert r.conditions == ("summer", "storm")
    assert r.query_images.shape == (10, 32, 64)


def test_incomplete_condition_is_rejected():
    colours = {m: ((0.1, 0.1, 0.1), (0.2, 0.2, 0.2)) for m in MATERIALS if m != "rail"}
    with pytest.raises(ValueError, match=r"no colours for materials \['rail'\]"):
        make_route(5, conditions=(Condition("odd", colours),))
    full = {**colours, "rail": ((0.1, 0.1, 0.1), (0.2, 0.2, 0.2))}
    with pytest.raises(ValueError, match="unknown material 'neon'"):
        make_route(5, conditions=(Condition("odd", full, emission={"neon": (1, 1, 1)}),))


# -- files -----------------------------------------------------------------------------------


def test_save_route_nordland_layout_gray(tmp_path):
    r = make_route(12, conditions=("summer", "winter"), random_state=1)
    written = save_route(r, tmp_path / "synth")
    assert sorted(written) == ["summer", "winter"]
    for name in r.conditions:
        files = list_images(tmp_path / "synth" / name)
        assert [p.name for p in files] == [f"images-{i:05d}.png" for i in range(12)]
        assert files == written[name]
        with Image.open(files[0]) as img:
            assert img.mode == "L" and img.size == (64, 32)
        loaded = load_images(files, cache=False, progress=False)
        np.testing.assert_allclose(loaded, r.images[name], atol=0.5 / 255 + 1e-6)


def test_save_route_rgb_round_trip(tmp_path, route):
    save_route(route, tmp_path)
    files = list_images(tmp_path / "winter")
    with Image.open(files[0]) as img:
        assert img.mode == "RGB"
    loaded = load_images(files, cache=False, progress=False)
    assert loaded.shape == route.query_images.shape
    # 8-bit quantisation per channel plus rare channel saturation.
    assert np.mean(np.abs(loaded - route.query_images)) < 3e-3
    gray_dir = tmp_path / "gray"
    save_route(route, gray_dir, rgb=False)
    with Image.open(list_images(gray_dir / "summer")[0]) as img:
        assert img.mode == "L"


def test_save_route_refuses_to_mix_routes(tmp_path):
    long = make_route(8, random_state=0)
    short = make_route(5, random_state=1)
    save_route(long, tmp_path)
    (tmp_path / "summer" / "notes.txt").write_text("keep me")
    with pytest.raises(FileExistsError, match="overwrite=True"):
        save_route(short, tmp_path)
    # notes.txt is not a frame, so list_images would refuse the folder: count the PNGs
    assert len(list((tmp_path / "summer").glob("*.png"))) == 8  # nothing written on refusal
    save_route(short, tmp_path, overwrite=True)
    # No stale frame of the longer route is left behind; other files are kept.
    assert sorted(p.name for p in (tmp_path / "summer").glob("*.png")) == [
        f"images-{i:05d}.png" for i in range(5)
    ]
    assert (tmp_path / "summer" / "notes.txt").read_text() == "keep me"


def test_save_route_errors(tmp_path):
    with pytest.raises(TypeError, match="route must be a SyntheticRoute"):
        save_route({"summer": np.zeros((2, 4, 4))}, tmp_path)
    r = make_route(3, random_state=0)
    assert isinstance(r, SyntheticRoute)
    with pytest.raises(ValueError, match="return_rgb=True"):
        save_route(r, tmp_path, rgb=True)


def test_saved_route_reads_as_nordland(tmp_path):
    from flyvpr.datasets.nordland import load_nordland

    r = make_route(20, conditions=("summer", "fall"), random_state=6)
    save_route(r, tmp_path)
    bench = load_nordland(tmp_path, "summer", "fall", tolerance=3)
    np.testing.assert_array_equal(bench.ground_truth, r.ground_truth(tolerance=3))
    reference, query = bench.load_images(cache=False, progress=False)
    np.testing.assert_allclose(reference, r.reference_images, atol=0.5 / 255 + 1e-6)
    np.testing.assert_allclose(query, r.query_images, atol=0.5 / 255 + 1e-6)


@pytest.mark.parametrize("name", ["../escaped", "a/b", "..", ""])
def test_save_route_writes_no_condition_outside_its_folder(tmp_path, name):
    from flyvpr.synthetic import make_route, save_route

    route = make_route(5, random_state=0)
    route.images[name] = route.images.pop(route.conditions[0])
    route = dataclasses.replace(route, conditions=(name, *route.conditions[1:]))
    target = tmp_path / "out"
    with pytest.raises(ValueError, match="is not a plain folder name"):
        save_route(route, target)
    assert not (tmp_path / "escaped").exists() and not target.exists()

"""The package's one check of a real-valued parameter, and the integer and fraction checks."""

from __future__ import annotations

import math
import re

import numpy as np
import pytest

from flyvpr._validation import check_fraction, check_positive_int, check_real, is_integer, is_real


@pytest.mark.parametrize(
    ("value", "kwargs", "expected"),
    [
        (0.5, {}, 0.5),
        (np.float32(0.25), {"high": 1.0}, 0.25),
        (np.int64(3), {}, 3.0),
        (0, {"low": None}, 0.0),
        (-7.5, {"low": None}, -7.5),
        (0.0, {"low": 0.0, "inclusive": True}, 0.0),
        (1.0, {"high": 1.0}, 1.0),  # the upper bound is inclusive
        (2.0, {"low": 2.0, "inclusive": True, "high": 2.0}, 2.0),
    ],
)
def test_check_real_accepts(value, kwargs, expected):
    got = check_real(value, "x", **kwargs)
    assert got == expected and type(got) is float


@pytest.mark.parametrize(
    ("value", "kwargs", "error", "message"),
    [
        ("1", {}, TypeError, "x must be a number; got str"),
        (True, {}, TypeError, "x must be a number; got bool"),
        (None, {"low": None}, TypeError, "x must be a number; got NoneType"),
        ([1.0], {}, TypeError, "x must be a number; got list"),
        ("1", {"unit": "seconds"}, TypeError, "x must be a number of seconds; got str"),
        (math.nan, {"low": None}, ValueError, "x must be finite; got nan"),
        (-math.inf, {"low": None}, ValueError, "x must be finite; got -inf"),
        (10**400, {"low": None}, ValueError, "x must be finite; got a number past a float's range"),
        (-(10**400), {}, ValueError, "x must be finite; got a number past a float's range"),
        (0.0, {}, ValueError, "x must be > 0.0; got 0.0"),
        (-1, {"low": 0, "inclusive": True}, ValueError, "x must be >= 0; got -1.0"),
        (1.5, {"low": None, "high": 1.0}, ValueError, "x must be <= 1.0; got 1.5"),
        (1.5, {"high": 1.0}, ValueError, "x must be in (0.0, 1.0]; got 1.5"),
        (0.0, {"high": 1.0}, ValueError, "x must be in (0.0, 1.0]; got 0.0"),
        (-1.0, {"inclusive": True, "high": 1.0}, ValueError, "x must be in [0.0, 1.0]; got -1.0"),
        (0.0, {"unit": "metres"}, ValueError, "x must be > 0.0 metres; got 0.0"),
    ],
)
def test_check_real_refuses_naming_the_parameter(value, kwargs, error, message):
    with pytest.raises(error) as info:
        check_real(value, "x", **kwargs)
    assert str(info.value) == message


def test_is_integer_and_is_real():
    assert is_integer(3) and is_integer(np.int8(3)) and not is_integer(True)
    assert not is_integer(3.0) and not is_integer("3")
    assert is_real(3) and is_real(np.float16(0.5)) and is_real(2.5) and not is_real(False)
    assert not is_real("2.5") and not is_real(None) and not is_real(1j)


def test_check_positive_int_and_fraction():
    assert check_positive_int(np.int32(4), "n") == 4 and check_positive_int(0, "n", 0) == 0
    with pytest.raises(TypeError, match="^n must be an int; got float"):
        check_positive_int(4.0, "n")
    with pytest.raises(ValueError, match="^n must be >= 1; got 0"):
        check_positive_int(0, "n")
    assert check_fraction(1.0, "f") == 1.0
    with pytest.raises(ValueError, match=r"^f must be in \(0.0, 1.0\]; got 0.0"):
        check_fraction(0.0, "f")


@pytest.mark.parametrize(
    "size, expected",
    [
        ((32, 64), (32, 64)),
        ((np.int64(8), 16), (8, 16)),
        ((32.0, 64.0), (32, 64)),
        ([4, 5], (4, 5)),
    ],
)
def test_image_sizes_are_whole_numbers(size, expected):
    from flyvpr.images import _check_size

    assert _check_size(size) == expected


@pytest.mark.parametrize(
    "size", [(32.9, 64), (32, 64.7), (True, 64), (np.True_, 64), (1, 2, 3), (32,), "ab", None,
             (math.nan, 4), (math.inf, 4)],
)  # fmt: skip
def test_image_sizes_that_are_not_whole_numbers_are_refused(size):
    from flyvpr.images import _check_size

    with pytest.raises(TypeError, match=r"size must be a pair \(H, W\) of ints"):
        _check_size(size)


def test_float64_images_past_float32_are_out_of_range_not_infinite():
    import warnings

    from flyvpr._validation import check_images

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # (no overflow in a cast on the way)
        with pytest.raises(ValueError, match=r"gray values in \[0, 1\]; got range \[0, 1e\+300\]"):
            check_images(np.array([[[0.0, 1e300]]]))
    with pytest.raises(ValueError, match="contains NaN or infinite values"):
        check_images(np.array([[[0.0, np.inf]]]))
    np.testing.assert_array_equal(check_images(np.array([[[0.0, 0.5]]])), [[[0.0, 0.5]]])


@pytest.mark.parametrize("dtype", ["uint8", "uint16", "int32", ">u2"])
def test_integer_images_out_of_range_name_their_dtype_and_to_gray(dtype):
    from flyvpr._validation import check_images

    images = np.array([[[0, 3], [200, 255]]], dtype=dtype)
    expected = (
        f"images must hold gray values in [0, 1]; got range [0, 255] (dtype {images.dtype}: "
        "convert camera frames with flyvpr.images.to_gray)"
    )
    with pytest.raises(ValueError, match=re.escape(expected) + "$"):
        check_images(images)


def test_colour_stacks_are_pointed_to_to_gray_and_floats_are_not():
    from flyvpr._validation import check_images

    for shape in ((2, 4, 4, 3), (2, 4, 4, 4)):
        with pytest.raises(
            ValueError,
            match=re.escape(
                f"images must have shape (N, H, W); got shape {shape} (colour frames, dtype "
                "uint8: convert each camera frame with flyvpr.images.to_gray)"
            ),
        ):
            check_images(np.zeros(shape, np.uint8))
    with pytest.raises(ValueError, match=r"got shape \(2, 4, 4, 2\)$"):
        check_images(np.zeros((2, 4, 4, 2), np.uint8))
    # a float image out of range: to_gray would refuse it too, so no hint
    with pytest.raises(ValueError, match=r"gray values in \[0, 1\]; got range \[0, 255\]$"):
        check_images(np.array([[[0.0, 255.0]]], np.float32))
    # integers within [0, 1] are gray values (a binary mask)
    np.testing.assert_array_equal(check_images(np.array([[[0, 1]]], np.uint8)), [[[0.0, 1.0]]])

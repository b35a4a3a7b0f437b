"""Input checks and small helpers shared by encoders, filters and the localizer.

Kept free of any other flyvpr import so every layer can use it.
"""

from __future__ import annotations

import numbers

import numpy as np

__all__ = [
    "NotFittedError",
    "check_random_state",
    "check_images",
    "check_scores",
    "check_positive_int",
    "check_fraction",
]


class NotFittedError(ValueError, AttributeError):
    """Raised when ``encode``/``score``/``filter`` is called before ``fit``."""


def check_random_state(random_state) -> np.random.Generator:
    """Turn ``random_state`` (None, int or Generator) into a numpy Generator.

    Parameters
    ----------
    random_state : None, int, numpy.random.Generator
        ``None`` draws fresh entropy, an int seeds a new PCG64 generator, a
        Generator is returned unchanged (so callers share its stream).

    Raises
    ------
    TypeError
        For any other type.
    """
    if random_state is None or isinstance(random_state, (numbers.Integral, np.integer)):
        if random_state is not None and int(random_state) < 0:
            raise ValueError(f"random_state must be a non-negative int; got {random_state}")
        return np.random.default_rng(random_state)
    if isinstance(random_state, np.random.Generator):
        return random_state
    raise TypeError(
        "random_state must be None, an int or a numpy.random.Generator; "
        f"got {type(random_state).__name__}"
    )


def check_images(images, name: str = "images", shape: tuple[int, int] | None = None) -> np.ndarray:
    """Validate a stack of gray images and return it as float32 (N, H, W).

    Raises
    ------
    TypeError
        If ``images`` is not array-like of numbers.
    ValueError
        For a wrong number of dimensions, an empty stack, a mismatching
        ``(H, W)``, NaN/inf values or values outside [0, 1].
    """
    try:
        arr = np.asarray(images)
    except Exception as exc:  # ragged lists and such
        raise TypeError(f"{name} must be an array of shape (N, H, W); {exc}") from exc
    if arr.dtype == object or not (np.issubdtype(arr.dtype, np.number) or arr.dtype == np.bool_):
        raise TypeError(f"{name} must be a numeric array; got dtype {arr.dtype}")
    if arr.ndim != 3:
        raise ValueError(f"{name} must have shape (N, H, W); got shape {arr.shape}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty: got shape {arr.shape}")
    if shape is not None and tuple(arr.shape[1:]) != tuple(shape):
        raise ValueError(
            f"{name} must have image size (H, W) = {tuple(shape)} as at fit time; "
            f"got {tuple(arr.shape[1:])}"
        )
    arr = arr.astype(np.float32, copy=False)
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        raise ValueError(f"{name} must hold gray values in [0, 1]; got range [{lo:g}, {hi:g}]")
    return arr


def check_scores(S, name: str = "S", ndim: int = 2) -> np.ndarray:
    """Validate a score matrix (or row when ``ndim == 1``) and return float arrays."""
    arr = np.asarray(S)
    if arr.dtype == object or not np.issubdtype(arr.dtype, np.number):
        raise TypeError(f"{name} must be a numeric array; got dtype {arr.dtype}")
    if arr.ndim != ndim:
        expect = "(n_query, n_reference)" if ndim == 2 else "(n_reference,)"
        raise ValueError(f"{name} must have shape {expect}; got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty: got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    if not np.issubdtype(arr.dtype, np.floating):
        arr = arr.astype(np.float64)
    return arr


def check_positive_int(value, name: str, minimum: int = 1) -> int:
    """Return ``value`` as int, requiring an integral value >= ``minimum``."""
    if isinstance(value, bool) or not isinstance(value, (numbers.Integral, np.integer)):
        raise TypeError(f"{name} must be an int; got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}; got {value}")
    return int(value)


def check_fraction(value, name: str, low: float = 0.0, high: float = 1.0) -> float:
    """Return ``value`` as float, requiring ``low < value <= high``."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a number; got {type(value).__name__}")
    value = float(value)
    if not (low < value <= high) or not np.isfinite(value):
        raise ValueError(f"{name} must be in ({low}, {high}]; got {value}")
    return value

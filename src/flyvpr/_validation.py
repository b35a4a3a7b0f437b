"""Input checks and small helpers shared by encoders, filters and the localizer.

Kept free of any other flyvpr import so every layer can use it.
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass

import numpy as np

__all__ = [
    "NotFittedError",
    "check_random_state",
    "check_images",
    "check_scores",
    "check_positive_int",
    "check_fraction",
    "InsufficientMemoryError",
    "available_memory",
    "format_bytes",
    "array_nbytes",
    "check_memory",
    "ScalarSpec",
    "ArraySpec",
    "PartSpec",
]

#: Environment variable capping the memory flyvpr plans for, in bytes (``4e9``, ``4GB``).
MEMORY_LIMIT_ENV = "FLYVPR_MAX_MEMORY"


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
        return np.random.default_rng(None if random_state is None else int(random_state))
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
        colour = arr.ndim == 4 and arr.shape[-1] in (3, 4)
        hint = (
            f" (colour frames, dtype {arr.dtype}: convert each camera frame with "
            "flyvpr.images.to_gray)"
            if colour
            else ""
        )
        raise ValueError(f"{name} must have shape (N, H, W); got shape {arr.shape}{hint}")
    if arr.shape[0] == 0:
        raise ValueError(f"{name} is empty: got shape {arr.shape}")
    if shape is not None and tuple(arr.shape[1:]) != tuple(shape):
        raise ValueError(
            f"{name} must have image size (H, W) = {tuple(shape)} as at fit time; "
            f"got {tuple(arr.shape[1:])} (resize frames of another size with "
            f"flyvpr.images.resize_area(frame, {tuple(shape)}))"
        )
    # Other floats are checked before the cast to float32, which would turn a value past its
    # range into inf; the rest after it.
    before = arr.dtype.kind == "f" and arr.dtype != np.float32
    if before:
        _check_gray(arr, name)
    dtype = arr.dtype
    arr = arr.astype(np.float32, copy=False)
    if not before:
        _check_gray(arr, name, dtype)
    return arr


def _check_gray(arr: np.ndarray, name: str, dtype: np.dtype | None = None) -> None:
    """Every value of ``arr`` finite and in [0, 1], or a ValueError naming ``name`` (and, for
    integers, ``dtype``, the type before the cast to float32)."""
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    lo, hi = float(arr.min()), float(arr.max())
    if lo < 0.0 or hi > 1.0:
        dtype = arr.dtype if dtype is None else np.dtype(dtype)
        hint = (
            f" (dtype {dtype}: convert camera frames with flyvpr.images.to_gray)"
            if dtype.kind in "iu"
            else ""
        )
        raise ValueError(
            f"{name} must hold gray values in [0, 1]; got range [{lo:g}, {hi:g}]{hint}"
        )


def check_scores(S, name: str = "S", ndim: int = 2) -> np.ndarray:
    """Validate a score matrix (or row when ``ndim == 1``) and return float arrays."""
    arr = np.asarray(S)
    kind = arr.dtype.kind  # (the kinds of np.number; faster than np.issubdtype per row)
    if kind not in "iuf":
        what = "real numbers" if kind == "c" else "a numeric array"
        raise TypeError(f"{name} must be {what}; got dtype {arr.dtype}")
    if arr.ndim != ndim:
        expect = "(n_query, n_reference)" if ndim == 2 else "(n_reference,)"
        raise ValueError(f"{name} must have shape {expect}; got shape {arr.shape}")
    if arr.size == 0:
        raise ValueError(f"{name} is empty: got shape {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} contains NaN or infinite values")
    if kind != "f":
        arr = arr.astype(np.float64)
    elif not arr.dtype.isnative:  # (bytes in the other order: the same floats, this machine's)
        arr = arr.astype(arr.dtype.newbyteorder("="))
    return arr


def is_integer(value: object) -> bool:
    """Whether ``value`` is an integer (Python's or numpy's), a bool excluded.

    A plain bool rather than a type guard, for parameters annotated ``int`` or ``float`` that
    are still checked at run time: to a type checker ``int`` is not a ``numbers.Integral`` (nor
    ``float`` a ``numbers.Real``), so narrowing such a parameter with ``isinstance`` would make
    the code after the check unreachable, and unchecked.
    """
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_real(value: object) -> bool:
    """Whether ``value`` is a real number (Python's or numpy's), a bool excluded; see
    :func:`is_integer`."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_real(
    value,
    name: str,
    *,
    low: float | None = 0.0,
    inclusive: bool = False,
    high: float | None = None,
    unit: str = "",
) -> float:
    """Return ``value`` as float: a finite real number (Python's or numpy's, not a bool) above
    ``low`` (or at it when ``inclusive``; ``None``: no lower bound) and at most ``high``.

    The one check of a real-valued parameter in the package (scikit-learn's ``check_scalar``
    plays the same part there); ``unit`` names what the number counts, in the messages.

    Raises
    ------
    TypeError
        ``"{name} must be a number; got str"``.
    ValueError
        ``"{name} must be finite; got nan"``, ``"{name} must be > 0; got -1.0"``, ``"{name}
        must be in (0.0, 1.0]; got 2.0"``.

    Examples
    --------
    >>> check_real(np.float32(0.5), "rate", high=1.0)
    0.5
    >>> check_real(0, "speed", low=None)
    0.0
    """
    of = f" of {unit}" if unit else ""
    if not is_real(value):
        raise TypeError(f"{name} must be a number{of}; got {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # an int past the floats' range, such as 10**400
        raise ValueError(f"{name} must be finite; got a number past a float's range") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite; got {value}")
    too_low = low is not None and (value < low or (value == low and not inclusive))
    if too_low or (high is not None and value > high):
        if low is not None and high is not None:
            relation = f"in {'[' if inclusive else '('}{low}, {high}]"
        elif low is not None:
            relation = f"{'>=' if inclusive else '>'} {low}"
        else:
            relation = f"<= {high}"
        raise ValueError(f"{name} must be {relation}{' ' + unit if unit else ''}; got {value}")
    return value


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


# -- memory ------------------------------------------------------------------------------------
class InsufficientMemoryError(ValueError):
    """A request needs more memory than the machine has available; raised before allocating."""


_UNITS = {"": 1, "B": 1, "K": 1 << 10, "M": 1 << 20, "G": 1 << 30, "T": 1 << 40}


def _parse_bytes(text: str) -> int:
    t = text.strip().upper().removesuffix("IB").removesuffix("B")
    unit = t[-1] if t and t[-1] in _UNITS else ""
    number = float(t[: len(t) - len(unit)])
    if not math.isfinite(number) or number <= 0:
        raise ValueError
    return int(number * _UNITS[unit])


def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def available_memory() -> int:
    """Bytes of memory a computation may plan to use now.

    ``MemAvailable`` of ``/proc/meminfo`` (free memory plus what the kernel can reclaim) on
    Linux; elsewhere the free physical pages, else all physical memory.  The environment
    variable ``FLYVPR_MAX_MEMORY`` (bytes, or with a unit: ``512M``, ``4G``) lowers the figure,
    e.g. on a machine shared with other jobs.

    Returns
    -------
    int
    """
    avail = _meminfo_available()
    if avail is None:
        for pages in ("SC_AVPHYS_PAGES", "SC_PHYS_PAGES"):
            try:
                avail = os.sysconf(pages) * os.sysconf("SC_PAGE_SIZE")
                break
            except (ValueError, OSError, AttributeError):
                continue
    if avail is None or avail <= 0:
        avail = 1 << 62  # unknown: do not refuse on a guess
    cap = os.environ.get(MEMORY_LIMIT_ENV)
    if cap:
        try:
            avail = min(avail, _parse_bytes(cap))
        except ValueError:
            raise ValueError(
                f"{MEMORY_LIMIT_ENV} must be a positive number of bytes such as 4000000000 or 4G; "
                f"got {cap!r}"
            ) from None
    return int(avail)


def format_bytes(n: int) -> str:
    """``n`` bytes in a short human form: ``'1.5 GB'`` (powers of 1000)."""
    n = int(n)
    for unit, scale in (("TB", 10**12), ("GB", 10**9), ("MB", 10**6), ("kB", 10**3)):
        if abs(n) >= scale:
            value = n / scale
            return f"{value:.3g} {unit}" if value < 1000 else f"{value:,.0f} {unit}"
    return f"{n} bytes"


def array_nbytes(shape, dtype=np.float32) -> int:
    """Bytes of an array of ``shape`` and ``dtype``, in exact Python integers (never overflows)."""
    return math.prod(int(d) for d in shape) * np.dtype(dtype).itemsize


def check_memory(n_bytes: int, what: str) -> int:
    """Refuse, before allocating, a request for more memory than is available.

    Parameters
    ----------
    n_bytes : int
        Bytes the request would allocate (an estimate of its peak).
    what : str
        The request in the caller's words, naming the parameter or option, e.g.
        ``"n_hidden=10**9 (projection of 2048 x 10**9 float32)"``.

    Returns
    -------
    int
        ``n_bytes``.

    Raises
    ------
    InsufficientMemoryError
        If ``n_bytes`` exceeds :func:`available_memory`; the message names ``what``, the size
        it would need and what is available.

    Examples
    --------
    >>> check_memory(1000, "a small buffer")
    1000
    """
    n_bytes = int(n_bytes)
    avail = available_memory()
    if n_bytes > avail:
        raise InsufficientMemoryError(
            f"{what} would need {format_bytes(n_bytes)} of memory; "
            f"{format_bytes(avail)} is available"
        )
    return n_bytes


# -- saved state -------------------------------------------------------------------------------
@dataclass(frozen=True)
class ScalarSpec:
    """Expected form of a scalar attribute in a model file (see :mod:`flyvpr.modelio`).

    Parameters
    ----------
    kind : {'int', 'float', 'bool', 'str', 'shape'}
        ``'shape'`` is a pair of positive ints (an image size).
    low, high : float, optional
        Inclusive bounds of ints and floats.
    optional : bool
        ``None`` is accepted too.
    """

    kind: str
    low: float | None = None
    high: float | None = None
    optional: bool = False

    def check(self, value, name: str):
        """Return ``value`` (a tuple for shapes) or raise ValueError naming ``name``."""
        if value is None and self.optional:
            return None
        kind = self.kind
        if kind == "shape":
            ok = (
                isinstance(value, (list, tuple))
                and len(value) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) and v >= 1 for v in value)
            )
            if not ok:
                raise ValueError(f"{name} must be a pair of positive ints; got {value!r}")
            return tuple(value)
        types = {"int": (int,), "float": (int, float), "bool": (bool,), "str": (str,)}[kind]
        if not isinstance(value, types) or (kind != "bool" and isinstance(value, bool)):
            article = "an" if kind == "int" else "a"
            raise ValueError(f"{name} must be {article} {kind}; got {value!r}")
        if kind in ("int", "float"):
            assert isinstance(value, (int, float))  # checked against `types` above
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite; got {value!r}")
            if (self.low is not None and value < self.low) or (
                self.high is not None and value > self.high
            ):
                raise ValueError(f"{name} must lie in [{self.low}, {self.high}]; got {value!r}")
        return value


@dataclass(frozen=True)
class ArraySpec:
    """Expected dtype and shape of an array attribute in a model file.

    ``dtype=None`` accepts any numeric dtype; ``shape=None`` any shape; a ``None`` entry in
    ``shape`` any length on that axis.  Float arrays must be finite unless ``finite=False``.
    """

    dtype: str | None
    shape: tuple | None
    finite: bool = True


@dataclass(frozen=True)
class PartSpec:
    """A nested saved part (e.g. FlyNet's hash layer): one of the registry ``names``."""

    names: tuple[str, ...]

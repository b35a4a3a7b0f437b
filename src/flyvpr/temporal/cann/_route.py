"""Where a map's route is broken: the places that do not continue the place before them."""

from __future__ import annotations

import numpy as np

from ..._validation import check_real

#: a step between consecutive places this many times the usual step around it is a break
BREAK_FACTOR = 5.0

#: the usual step around a step: the median of the steps up to this many places on each side
BREAK_NEIGHBOURS = 5

#: steps judged at a time: the neighbourhoods of a chunk take 11 floats per step (and a sorted
#: copy), about 180 MB for 2^20 steps, whatever the length of the map
_FAR_CHUNK = 1 << 20


def far_steps(
    size: np.ndarray, factor: float = BREAK_FACTOR, chunk: int = _FAR_CHUNK
) -> np.ndarray:
    """Whether each step (``size``, >= 0; NaN where unknown) is more than ``factor`` times the
    median of the known steps up to :data:`BREAK_NEIGHBOURS` places on either side of it (not
    itself).  Local, so that a stretch driven faster (a map kept by time) is no break, while
    one step that leaves a stretch of the route out is.  An unknown step, or one whose
    neighbours' median is 0 or unknown, is not far.  Judged ``chunk`` steps at a time (the
    same answer for any ``chunk``; memory bounded on a map of millions of places)."""
    size = np.asarray(size, dtype=np.float64)
    n, w = size.shape[0], BREAK_NEIGHBOURS
    out = np.zeros(n, bool)
    for lo in range(0, n, chunk):
        hi = min(lo + chunk, n)
        # the chunk's steps with up to w neighbours on each side (NaN beyond the route's ends)
        part = np.full(hi - lo + 2 * w, np.nan)
        a, b = max(lo - w, 0), min(hi + w, n)
        part[a - (lo - w) : b - (lo - w)] = size[a:b]
        out[lo:hi] = _far_in(part, size[lo:hi], factor)
    return out


def _far_in(padded: np.ndarray, size: np.ndarray, factor: float) -> np.ndarray:
    """:func:`far_steps` of ``size``, given ``padded``: the same steps with the
    :data:`BREAK_NEIGHBOURS` steps before and after them (NaN where there are none)."""
    n, w = size.shape[0], BREAK_NEIGHBOURS
    around = np.lib.stride_tricks.sliding_window_view(padded, 2 * w + 1).copy()
    around[:, w] = np.nan  # (not the step itself)
    known = np.isfinite(around)
    counts = known.sum(axis=1)
    ordered = np.sort(np.where(known, around, np.inf), axis=1)  # (the known ones first)
    rows = np.arange(n)
    lo = ordered[rows, np.maximum((counts - 1) // 2, 0)]
    hi = ordered[rows, np.maximum(counts // 2, 0)]
    usual = np.where(counts > 0, 0.5 * (lo + hi), np.nan)
    with np.errstate(invalid="ignore"):
        return np.isfinite(size) & (usual > 0) & (size > factor * usual)


def position_breaks(positions) -> tuple[int, ...]:
    """The breaks of a map's route from its places' positions (``(n_places, 2)``, NaN where a
    place has none): each place more than :data:`BREAK_FACTOR` times the usual step around it
    from the place before it (:func:`far_steps`); a step with an unknown position at either
    end is not judged.  Empty without positions (None) or with fewer than two places."""
    if positions is None or len(positions) < 2:
        return ()
    steps = np.hypot(*np.diff(np.asarray(positions, dtype=np.float64), axis=0).T)
    return tuple(int(i) + 1 for i in np.flatnonzero(far_steps(steps)))


def route_breaks(coordinates, factor: float = BREAK_FACTOR) -> tuple[int, ...]:
    """The breaks of a route (the :class:`CANN`'s ``breaks``) from where its places were taken.

    Parameters
    ----------
    coordinates : array_like, shape (n_places,) or (n_places, d)
        Per place, in the map's order: a frame number or timestamp (1-d), or a position
        (2-d, e.g. metres east and north).
    factor : float, default 5.0
        A step to the next place more than ``factor`` times the usual step around it (the
        median of the steps up to 5 places on either side) is a break: the map leaves part of
        the route out (a gap in the frame numbers, a pause of the recording, a jump of
        position).  For frame numbers and timestamps a step back is one too (the next
        recording starts over).  A stretch of larger steps (driven faster, where places were
        kept by time) is not.

    Returns
    -------
    tuple of int
        The first place of each stretch after a break, increasing; empty for one route.

    Raises
    ------
    ValueError
        If ``coordinates`` is not 1-d or 2-d, holds a NaN or an infinity, or ``factor`` is not
        above 1.

    Examples
    --------
    >>> route_breaks([10, 20, 30, 40, 3010, 3020, 3030])
    (4,)
    >>> route_breaks([[0.0, 0.0], [5.0, 0.0], [10.0, 0.0], [10.0, 5.0], [400.0, 5.0]])
    (4,)
    """
    factor = check_real(factor, "factor", low=1.0, inclusive=False)
    try:
        xy = np.asarray(coordinates, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise TypeError(f"coordinates must be numbers per place; {exc}") from exc
    if xy.ndim not in (1, 2) or (xy.ndim == 2 and xy.shape[1] == 0):
        raise ValueError(
            "coordinates must be (n_places,) frame numbers or timestamps, or (n_places, d) "
            f"positions; got shape {xy.shape}"
        )
    if not np.isfinite(xy).all():
        raise ValueError("coordinates must be finite; got a NaN or an infinity")
    if len(xy) < 2:
        return ()
    if xy.ndim == 1:
        step = np.diff(xy)
        back = step < 0.0
        size = np.where(back, np.nan, step)  # (a step back is no measure of the usual step)
    else:
        size = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        back = np.zeros(size.shape, bool)
    return tuple(int(i) + 1 for i in np.flatnonzero(back | far_steps(size, factor)))

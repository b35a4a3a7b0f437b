"""Where a map's route is broken: the places that do not continue the place before them."""

from __future__ import annotations

import numpy as np

from ..._validation import check_real

#: a step between consecutive places this many times the median step is a break
BREAK_FACTOR = 5.0


def route_breaks(coordinates, factor: float = BREAK_FACTOR) -> tuple[int, ...]:
    """The breaks of a route (the :class:`CANN`'s ``breaks``) from where its places were taken.

    Parameters
    ----------
    coordinates : array_like, shape (n_places,) or (n_places, d)
        Per place, in the map's order: a frame number or timestamp (1-d), or a position
        (2-d, e.g. metres east and north).
    factor : float, default 5.0
        A step to the next place more than ``factor`` times the median step is a break (the
        map leaves part of the route out: a gap in the frame numbers, a pause of the
        recording, a jump of position).  For frame numbers and timestamps a step that does not
        go forwards is one too (the next recording starts).

    Returns
    -------
    tuple of int
        The first place of each stretch after a break, increasing; empty for one route.  With
        a median step of 0 (places that mostly stand still) only the steps back are breaks.

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
        back = step <= 0.0
        size = np.abs(step)
    else:
        size = np.linalg.norm(np.diff(xy, axis=0), axis=1)
        back = np.zeros(size.shape, bool)
    usual = float(np.median(size[~back])) if (~back).any() else 0.0
    far = size > factor * usual if usual > 0.0 else np.zeros(size.shape, bool)
    return tuple(int(i) + 1 for i in np.flatnonzero(back | far))

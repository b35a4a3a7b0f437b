"""Fitting a confidence table for the CANN on a labelled route of one's own.

The filter's confidence comes through a table fitted on Nordland's dev window (its
``calibration``); on another route or camera the same confidence can mean a different chance
of being right.  :func:`fit_calibration` fits a table from a labelled run's confidences and
whether each answer was right; given as the filter's ``recalibration`` it maps every answer's
confidence to the share right on that run.
"""

from __future__ import annotations

import numpy as np

from ..._validation import check_real
from ...metrics import as_floats
from ._filter import _KNOTS as KNOTS  # the confidences at which a table is given

#: the least step between neighbouring values of a fitted table (the filter requires a strictly
#: increasing table, which keeps the order of its answers)
MIN_STEP = 1e-3


def _pool_adjacent_violators(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """The non-decreasing sequence nearest ``values`` in weighted least squares (every weight
    positive): neighbours out of order are pooled into their weighted mean until none is."""
    means: list[float] = []
    masses: list[float] = []
    counts: list[int] = []
    for i, v in enumerate(values.tolist()):
        means.append(v)
        masses.append(float(weights[i]))
        counts.append(1)
        while len(means) > 1 and means[-2] > means[-1]:
            v2, w2, c2 = means.pop(), masses.pop(), counts.pop()
            v1, w1, c1 = means.pop(), masses.pop(), counts.pop()
            means.append((v1 * w1 + v2 * w2) / (w1 + w2))
            masses.append(w1 + w2)
            counts.append(c1 + c2)
    return np.repeat(means, counts)


def fit_calibration(raw, right, prior_weight: float = 1.0) -> tuple[float, ...]:
    """A confidence table for :class:`~flyvpr.temporal.cann.CANN` from a labelled run.

    Parameters
    ----------
    raw : array-like of float in [0, 1]
        Confidences of a labelled run: ``confidence_`` of a
        :class:`~flyvpr.temporal.cann.CANN` after each frame (for its ``recalibration``),
        or, for its ``calibration`` (the sequence's own table), the fourth root of that of a
        ``CANN(calibration=None)`` after each frame whose ``source_`` is ``"sequence"``.
    right : array-like of bool, same length
        Whether each of those answers was right (within the filter's ``tolerance``).
    prior_weight : float, default 1.0
        Weight, in answers, of the identity (a table equal to the raw confidence) at every
        knot: where few answers fall the table stays near the raw confidence (for a
        ``calibration`` table, near the fourth root of the raw confidence it is given at,
        which is more than the raw confidence: fit it on enough answers).

    Returns
    -------
    tuple of 11 float
        The share of right answers at raw confidence 0, 0.1, ..., 1, as a piecewise-linear
        function between them: the least-squares fit (each answer weighs on its two nearest
        knots, linearly), made non-decreasing by pooling adjacent violators, then strictly
        increasing by steps of at least 0.001 within [0, 1].  Pass it as the CANN's
        ``recalibration`` (or ``calibration``, as above).

    Raises
    ------
    ValueError
        For empty, mismatched or non-finite input, raw confidences outside [0, 1], labels
        other than 0/1, or a negative or non-finite ``prior_weight``.
    TypeError
        For raw confidences that are not numbers, or a ``prior_weight`` that is not a number.

    Examples
    --------
    >>> import numpy as np
    >>> rng = np.random.default_rng(0)
    >>> raw = rng.uniform(size=20000)
    >>> right = rng.uniform(size=raw.size) < 0.2 + 0.7 * raw   # right at 0.2 + 0.7 raw
    >>> table = fit_calibration(raw, right)
    >>> [round(v, 1) for v in table[::5]]
    [0.2, 0.6, 0.9]
    """
    r = as_floats(raw, "raw")
    y = np.asarray(right)
    if r.ndim != 1 or r.size == 0:
        raise ValueError(f"raw must be a non-empty 1-d array of confidences; got shape {r.shape}")
    if y.shape != r.shape:
        raise ValueError(
            f"right must hold one label per raw confidence: shape {r.shape}; got {y.shape}"
        )
    if not np.isfinite(r).all() or r.min() < 0.0 or r.max() > 1.0:
        raise ValueError("raw confidences must be finite and lie in [0, 1]")
    if y.dtype != bool and not np.isin(y, (0, 1)).all():
        raise ValueError("right must hold booleans (or 0 and 1): whether each answer was right")
    y = y.astype(np.float64)
    prior_weight = check_real(prior_weight, "prior_weight", inclusive=True)
    step = 1.0 / (KNOTS.size - 1)
    # Hat functions: an answer at raw confidence r weighs 1 - |r - knot| / step on each of its
    # two nearest knots (the interpolation the filter applies).
    basis = np.maximum(0.0, 1.0 - np.abs(r[:, None] - KNOTS[None, :]) / step)
    gram = basis.T @ basis + prior_weight * np.eye(KNOTS.size)
    target = basis.T @ y + prior_weight * KNOTS
    # With no prior, a knot no answer reaches leaves the system singular: least squares.
    table = np.linalg.lstsq(gram, target)[0]
    mass = basis.sum(axis=0) + prior_weight
    table = _pool_adjacent_violators(table, np.maximum(mass, 1e-12))
    table = np.maximum(table, 0.0)
    for k in range(1, KNOTS.size):  # strictly increasing ...
        table[k] = max(table[k], table[k - 1] + MIN_STEP)
    last = KNOTS.size - 1
    for k in range(last, -1, -1):  # ... and at most 1 (which bounds every value above)
        table[k] = min(table[k], 1.0 - MIN_STEP * (last - k))
    return tuple(float(v) for v in table)

"""What both CANNs share: their public calls with odometry, the input normalisation of a score
row, and filtering a traverse with odometry."""

from __future__ import annotations

import numpy as np

from ..._validation import check_real, check_scores
from ..base import OnlineFilter
from ._kernels import VAR_FLOOR

#: smallest positive float32, the floor before the log of a probability row
TINY = np.float32(np.finfo(np.float32).tiny)
#: rows are treated as probability vectors when they sum to 1 within this tolerance
PROBABILITY_ATOL = 1e-3


def begin_frame(filt, row: np.ndarray) -> None:
    """Before a CANN's step: its parameters checked (the first step after construction
    resets), its state allocated for this many places, or the row's length checked against
    the previous rows'."""
    if getattr(filt, "_params", None) is None:
        filt.reset()
    n = row.shape[0]
    if filt._n is None:
        filt._allocate(n)
    elif n != filt._n:
        raise ValueError(
            f"scores_row must have shape ({filt._n},) as the previous rows; got {row.shape} "
            "(call reset() before a new reference traverse)"
        )


#: what ``normalised_input`` passes the kernel for no blended read
_NO_READ = np.empty(0)


def normalised_input(
    filt,
    row: np.ndarray,
    gain: float,
    *,
    prior_var: bool,
    buffers=None,
    weight: float = 1.0,
    read=None,
) -> np.ndarray:
    """Frame ``filt.n_frames_``'s input: ``row`` as z-scores, adapted per place, clipped, times
    ``gain`` (see "Input" on the user guide's CANN page).

    Uses ``filt``'s validated parameters (``input_transform``, ``adaptation``,
    ``adapt_variance``, ``input_clip``), its buffers ``_x``, ``_mean`` and ``_var`` (or the
    three ``buffers`` given) and its ``normalise`` kernel; returns the first buffer.
    ``prior_var``: each place's input is divided by the spread of its frames before this one
    (the place-velocity CANN's), not with this one's included (the paper's attractor, as it
    was calibrated).  ``weight`` (in [0, 1]) scales this frame's share in the running mean and
    variance.  ``read``: ``(out, mix)``, ``out`` (float64, as long as the row) filled with
    ``mix`` times the input plus ``1 - mix`` times the row's plain z-score (zeros for a
    constant row).
    """
    p = filt._params
    t = filt.n_frames_
    transform = p["input_transform"]
    lowest = float(row.min())
    if transform == "auto":
        # (A float32 row's pairwise float32 sum: within 1e-6 of its float64 sum, far below
        # the tolerance.)
        probability = lowest >= 0 and abs(float(row.sum()) - 1.0) <= PROBABILITY_ATOL
        transform = "log" if probability else "linear"
    if transform == "log" and lowest < 0:
        raise ValueError(
            "scores_row must be non-negative for input_transform='log'; got minimum "
            f"{lowest:g} (use input_transform='linear' for such scores)"
        )
    # Running mean (and variance) of each place's input: the mean of the frames so far at
    # first, then an exponential average over ``adaptation`` frames.  The variance starts from
    # a prior of 1 (the z-scored row's) worth one frame.
    adapt = p["adaptation"] is not None
    rate = max(1.0 / (t + 1), 1.0 / p["adaptation"]) if adapt else 0.0
    var_rate = max(1.0 / (t + 2), 1.0 / p["adaptation"]) if adapt else 0.0
    if prior_var and adapt:
        # The first frame's adapted input is 0 everywhere (its own mean): no sample of the
        # spread.  The prior (1, worth one frame) then meets the second frame's.
        var_rate = 0.0 if t == 0 else max(1.0 / (t + 1), 1.0 / p["adaptation"])
    rate *= weight
    var_rate *= weight
    x, mean, var = (filt._x, filt._mean, filt._var) if buffers is None else buffers
    out, mix = (_NO_READ, 0.0) if read is None else read
    x[:] = row
    if transform == "log":
        # numpy's log, compiled or not: numba's rounds differently in the last bit, which the
        # gain would carry on.
        np.maximum(x, TINY, out=x)
        np.log(x, out=x)
    filt._kernels["normalise"](
        x,
        mean,
        var,
        False,
        TINY,
        rate,
        var_rate,
        adapt,
        p["adapt_variance"],
        prior_var,
        VAR_FLOOR,
        np.inf if p["input_clip"] is None else p["input_clip"],
        gain,
        mix,
        out,
    )
    return x


def filter_with_odometry(filt, S, velocity) -> np.ndarray:
    """``filt.filter(S, velocity)`` for a CANN: from a fresh state, every row stepped with the
    places moved before it (the first entry is not used: there is nothing to move yet)."""
    arr = check_scores(S, "S")
    vel = np.asarray(velocity)
    if vel.dtype == object or not np.issubdtype(vel.dtype, np.number):
        raise TypeError(f"velocity must be a numeric array; got dtype {vel.dtype}")
    if vel.shape != (arr.shape[0],):
        raise ValueError(
            f"velocity must have shape ({arr.shape[0]},), one entry per query; got {vel.shape}"
        )
    if not np.isfinite(vel).all():
        raise ValueError("velocity contains NaN or infinite values")
    filt.reset()
    out = np.empty(arr.shape, dtype=np.float32 if arr.dtype == np.float32 else np.float64)
    for t in range(arr.shape[0]):
        out[t] = filt._step(arr[t], float(vel[t]))
    return out


class OdometryFilter(OnlineFilter):
    """An online filter that also takes odometry: the public ``step`` and ``filter`` of both
    CANNs (each fills ``_step(row, velocity)``; the class's docstring says what a row holds)."""

    def step(self, scores_row, velocity=None) -> np.ndarray:
        """Feed one query frame's scores and return the filter's row for it.

        Parameters
        ----------
        scores_row : array-like, shape (n_reference,)
            The front end's scores of this frame, higher = more similar.
        velocity : float, optional
            Places moved since the previous frame (odometry), used instead of the filter's
            own estimate of the motion for this frame.

        Returns
        -------
        ndarray of float32, shape (n_reference,)
            Its argmax is the answer and its maximum the confidence (see the class's
            docstring for what the values mean).

        Raises
        ------
        ValueError
            For a row that is not 1-d, empty, holds NaN/inf, changes length since
            :meth:`reset`, or is negative with ``input_transform="log"``; a non-finite
            ``velocity``; invalid parameters (naming them).
        TypeError
            For a non-numeric row or ``velocity``.
        InsufficientMemoryError
            When the state for this many places would not fit in memory (naming the
            parameters that size it).
        """
        row = check_scores(scores_row, "scores_row", ndim=1)
        if velocity is not None:
            velocity = check_real(velocity, "velocity", low=None)
        return self._step(row, velocity)

    def filter(self, S, velocity=None) -> np.ndarray:
        """Filter a whole traverse from a fresh state.

        Parameters
        ----------
        S : array-like, shape (n_query, n_reference)
        velocity : array-like, shape (n_query,), optional
            Places moved before each query frame (odometry; the first entry is not used).

        Returns
        -------
        ndarray, same shape as S (float32, or float64 for float64 scores)
            Row ``t`` is what :meth:`step` returns for frame ``t``.
        """
        if velocity is None:
            return super().filter(S)
        return filter_with_odometry(self, S, velocity)

    def _step(self, row: np.ndarray, velocity: float | None = None) -> np.ndarray:
        raise NotImplementedError

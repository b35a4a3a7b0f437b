"""The CANN on a window of places around its packet: a frame's cost does not grow with the map.

The place-velocity layer's packet covers a few places; the rest of the map holds only the
re-seeding floor.  :class:`WindowedCANN` runs a :class:`~flyvpr.temporal.cann.CANN` on
``window`` consecutive places and moves the window along the route with the packet, so a
tracked frame needs the front end's scores of those places only.  A robot that leaves the
window (a kidnap, a long stretch off the map) is found again by the caller: an index over the
map's codes proposes candidate places and :meth:`WindowedCANN.reseed` moves the window there.
See "Large maps" on the user guide's CANN page.
"""

from __future__ import annotations

import numpy as np

from ..._validation import check_positive_int, check_real, check_scores
from ._filter import CANN
from ._params import _check_breaks

__all__ = ["WindowedCANN"]


class WindowedCANN:
    """A :class:`CANN` over a window of ``window`` places that follows its packet.

    Parameters
    ----------
    n_places : int
        Places of the whole map.
    window : int, default 2048
        Places the layer covers; a map with at most this many places is covered whole, and the
        filter is then exactly the :class:`CANN` (same answers, same confidences).
    recentre : float, default 0.125
        The window moves when the filter is ``localized`` and its packet more than
        ``recentre * window`` places from the centre (so it moves in steps, not every frame).
    **params
        The :class:`CANN`'s parameters (``tolerance``, ``velocities``, ...).  ``breaks`` are
        places of the whole map (the first place of each stretch after a break, as
        :func:`~flyvpr.temporal.cann.route_breaks` gives them); the layer is given those
        inside its window, as places of the window, each time the window moves.

    Attributes
    ----------
    window_ : tuple of int
        ``(lo, hi)``: the places whose scores the next :meth:`step` takes.
    place_, confidence_, state_ : int, float, str
        The last answer (a place of the whole map), its confidence and the filter's state.
    cann_ : CANN
        The layer over the window (its ``support_``, ``velocity_``, ``source_``; its
        ``breaks`` are the window's).
    breaks_ : ndarray of int64
        The breaks of the whole map.
    n_moves_ : int
        Times the window moved since :meth:`reset` (re-seeds included).

    Examples
    --------
    >>> import numpy as np
    >>> from flyvpr.temporal.cann import WindowedCANN
    >>> rng = np.random.default_rng(0)
    >>> S = rng.normal(size=(300, 5000))
    >>> S[np.arange(300), 1000 + np.arange(300)] += 3.0    # the robot drives from place 1000
    >>> f = WindowedCANN(5000, window=512)
    >>> f.reseed([1000])
    >>> for row in S:
    ...     lo, hi = f.window_
    ...     _ = f.step(row[lo:hi])
    >>> f.place_, f.state_, f.window_[0] > 1000
    (1299, 'localized', True)
    """

    def __init__(self, n_places: int, window: int = 2048, recentre: float = 0.125, **params):
        self.n_places = check_positive_int(n_places, "n_places")
        self.window = check_positive_int(window, "window", minimum=16)
        self.recentre = check_real(recentre, "recentre", low=0.0, inclusive=True)
        if self.recentre >= 0.5:
            raise ValueError(f"recentre must be < 0.5 (a share of the window); got {recentre}")
        breaks = _check_breaks(params.pop("breaks", ()))
        if breaks.size and breaks[-1] >= self.n_places:
            raise ValueError(
                f"breaks must be places 1 .. {self.n_places - 1} of this map of {self.n_places} "
                f"places (the first place of each stretch after a break); got {breaks.tolist()}"
            )
        self.breaks_ = breaks
        self.cann_ = CANN(**params)
        self.reset()

    @property
    def width(self) -> int:
        """Places the layer covers: ``min(window, n_places)``."""
        return min(self.window, self.n_places)

    def _window_breaks(self, lo: int) -> np.ndarray:
        """The map's breaks inside the window from ``lo``, as places of the window (a break at
        the window's first place parts nothing the layer holds)."""
        b = self.breaks_
        return b[(b > lo) & (b < lo + self.width)] - lo

    def _give_breaks(self, lo: int) -> None:
        """The layer's breaks for the window from ``lo``: set as its parameter and, where it
        has checked its parameters already, in the set it runs with."""
        c = self.cann_
        local = self._window_breaks(lo)
        c.breaks = tuple(int(b) for b in local)
        if getattr(c, "_params", None) is not None:
            c._params["breaks"] = local

    def reset(self) -> None:
        """Forget all frames; the window starts at the beginning of the map."""
        self._give_breaks(0)
        self.cann_.reset()
        self._lo = 0
        self.place_ = -1
        self.confidence_ = 0.0
        self.state_ = "lost"
        self.n_moves_ = 0

    @property
    def window_(self) -> tuple[int, int]:
        return self._lo, self._lo + self.width

    def step(self, scores, velocity=None) -> tuple[int, float, str]:
        """Feed the scores of the window's places for one frame.

        Parameters
        ----------
        scores : array-like, shape (hi - lo,)
            The front end's scores of places ``window_[0] .. window_[1] - 1``, higher = more
            similar.
        velocity : float, optional
            Places moved since the previous frame (odometry).

        Returns
        -------
        (place, confidence, state)
            ``place`` indexes the whole map.

        Raises
        ------
        ValueError
            For scores of the wrong length (naming ``window_``), NaN/inf, or what
            :meth:`CANN.step` refuses.
        """
        row = check_scores(scores, "scores", ndim=1)
        if row.shape[0] != self.width:
            raise ValueError(
                f"scores must hold the {self.width} places of window_ {self.window_}; "
                f"got shape {row.shape}"
            )
        out = self.cann_.step(row, velocity)
        answer = int(np.argmax(out))
        self.place_ = self._lo + answer
        self.confidence_ = self.cann_.confidence_
        self.state_ = self.cann_.state_
        self._follow()
        return self.place_, self.confidence_, self.state_

    def _follow(self) -> None:
        """Move the window when the packet of a localized filter strays from its centre (a
        lost filter's packet is no evidence of where to go: the caller re-seeds it)."""
        width = self.width
        if width == self.n_places or self.state_ != "localized":
            return
        packet = int(np.argmax(self.cann_._marginal))
        if abs(packet - width // 2) <= self.recentre * width:
            return
        self._move(self._lo + packet - width // 2)

    def _move(self, lo: int) -> None:
        """Put the window at ``lo`` (clipped to the map), carrying the layer's state along."""
        lo = min(max(int(lo), 0), self.n_places - self.width)
        d = lo - self._lo
        if d == 0:
            return
        c = self.cann_
        if c._n is not None:
            # Places that enter the window hold the floor (the least activity of each velocity
            # row); their running input statistics start from the z-score's own (0, 1).
            floor = c._p.min(axis=1, keepdims=True)
            _shift(c._p, d, floor)
            _shift(c._mean, d, np.float32(0.0))
            _shift(c._var, d, np.float32(1.0))
            _shift(c._front_mean, d, np.float32(0.0))  # (the front end's own, the same)
            _shift(c._front_var, d, np.float32(1.0))
            # The last frame's row and answer move with the places (what enters is unknown: 0,
            # and tied until a frame says otherwise).
            _shift(c._last_row, d, 0.0)
            _shift(c._last_out, d, np.float32(0.0))
            _shift(c._marginal, d, np.float32(0.0))  # (a held frame's packet, read by _follow)
            c._tied = _shift_tied(c._tied, d, self.width)
            if c._last_front is not None:  # (the front end's last best place, for the snap)
                c._last_front -= d
        self._give_breaks(lo)
        self._lo = lo
        self.n_moves_ += 1

    def reseed(self, places, weights=None) -> None:
        """Start again around candidate places (from an index over the map's codes).

        The window is centred on the best candidate and the layer restarts from a prior that
        puts its mass on the candidates inside the window (``weights``, default equal; the
        velocity prior of the :class:`CANN` on each), plus a small floor everywhere.

        Parameters
        ----------
        places : array-like of int
            Candidate places of the whole map, best first when ``weights`` is omitted.
        weights : array-like of float, optional
            Non-negative weight of each candidate.
        """
        cand = np.asarray(places)
        if cand.ndim != 1 or cand.size == 0 or not np.issubdtype(cand.dtype, np.integer):
            raise ValueError(f"places must be a non-empty 1-d array of integers; got {places!r}")
        if cand.min() < 0 or cand.max() >= self.n_places:
            raise ValueError(
                f"places must lie in [0, {self.n_places}); got {cand.min()}..{cand.max()}"
            )
        if weights is None:
            w = np.ones(cand.size)
            best = int(cand[0])
        else:
            w = np.asarray(weights, dtype=np.float64)
            if w.shape != cand.shape or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
                raise ValueError(
                    f"weights must be {cand.size} finite non-negative numbers, not all 0; "
                    f"got {weights!r}"
                )
            best = int(cand[np.argmax(w)])
        c = self.cann_
        self._lo = min(max(best - self.width // 2, 0), self.n_places - self.width)
        self._give_breaks(self._lo)
        c.reset()
        self.n_moves_ += 1
        c._allocate(self.width)
        inside = (cand >= self._lo) & (cand < self._lo + self.width)
        mass = np.zeros(self.width)
        np.add.at(mass, cand[inside] - self._lo, w[inside])
        mass /= mass.sum()
        # A tenth of the mass stays spread over the window: the candidates may all be wrong.
        mass = 0.9 * mass + 0.1 / self.width
        prior = c._params["prior"]
        c._p[:] = (prior[:, None] * mass[None, :]).astype(np.float32)
        self.place_ = best
        self.confidence_ = 0.0
        self.state_ = "lost"


def _shift_tied(tied: np.ndarray, d: int, n: int) -> np.ndarray:
    """The tied places (ascending, each tied with the one before) after moving the window by
    ``d``: those kept, moved, and every place entering (tied until a frame says otherwise)."""
    kept = tied - d
    kept = kept[(kept >= 1) & (kept < n)]
    entering = np.arange(max(n - d, 1), n) if d > 0 else np.arange(1, min(-d, n - 1) + 1)
    return np.union1d(kept, entering).astype(np.int32)


def _shift(a: np.ndarray, d: int, fill) -> None:
    """Shift ``a`` along its last axis by ``d`` in place: ``a[..., i] = a[..., i + d]``, what
    enters from beyond the end is ``fill``."""
    n = a.shape[-1]
    if abs(d) >= n:
        a[...] = fill
    elif d > 0:
        a[..., : n - d] = a[..., d:]
        a[..., n - d :] = fill
    else:
        a[..., -d:] = a[..., : n + d]
        a[..., :-d] = fill

"""Streaming localization on a map of millions of places: a window while tracked, an index
when lost.

:class:`LargeLocalizer` runs the place-velocity layer
(:class:`~flyvpr.temporal.cann.WindowedCANN`) on a window of places around its packet, scoring
each frame's compact code against those places only, so a tracked frame costs the same on a
map of 10^3 or 10^7 places.  When the layer has been ``lost`` for ``reseed_after`` frames (and
every ``pool`` lost frames after that; at once on the first frame), the codes of the last
``pool`` frames go to an index over the map's codes, their candidates are pooled
(:func:`~flyvpr.large.pool_candidates`) and ranked by the similarity along their recent
tracks, and the layer re-seeds around the best unless its own track is as good.  Every
``check_every`` tracked frames the index is asked too, and a candidate outside the window
whose track clearly beats the layer's makes it re-seed (a kidnap the layer has not noticed).
"""

from __future__ import annotations

import time

import numpy as np

from .._validation import check_positive_int
from ..localization import LOCALIZED, Fix
from ..temporal.cann import WindowedCANN
from .codes import as_words, hamming_similarity, hamming_similarity_at
from .index import CandidateIndex, pool_candidates

__all__ = ["LargeLocalizer"]

#: pooled candidates whose recent tracks are compared with the layer's
_COMPARED = 100
#: speeds (places per frame) over which a recent track is scored
_TRACK_SPEEDS = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
#: a lost layer re-seeds where a candidate's track beats its own by this much mean similarity
#: (0.02: five bits of 256 per frame)
_LOST_MARGIN = 0.02
#: a tracked layer, at a check, by this much (a stronger case against a tracked packet)
_CHECK_MARGIN = 0.06


class LargeLocalizer:
    """One frame in, a :class:`~flyvpr.localization.Fix` out, on a very large map.

    Parameters
    ----------
    codes : array-like of uint8, shape (n_places, n_bytes)
        The map's bit-packed compact codes (a :class:`~flyvpr.large.LargeMap`'s ``codes``
        memmap: only the window's rows are read while tracking).
    index : CandidateIndex
        Built over ``codes`` (it answers ``search(query_codes, k)``).
    encoder : CompactEncoder, optional
        Fitted; needed by :meth:`update` (images), not by :meth:`update_code`.
    window : int, default 2048
        Places the layer covers.
    k : int, default 100
        Candidates per frame from the index.
    pool : int, default 10
        Frames whose candidates are pooled; a lost layer re-seeds every ``pool`` frames.
    reseed_after : int, default 10
        Lost frames before the first re-seed of a lost stretch (a layer often dips below
        ``localized`` for a few frames on the right stretch).
    check_every : int, default 1000
        Tracked frames between two checks against the index (0: never).
    speed : (float, float), default (0.0, 2.0)
        Speeds, places per frame, the pooling allows between frames.
    **params
        The :class:`~flyvpr.temporal.cann.CANN`'s parameters.

    Attributes
    ----------
    filter_ : WindowedCANN
    n_frames_, n_searches_, n_reseeds_ : int
    search_s_ : float
        Seconds spent in the index and the pooling since :meth:`reset`.

    Examples
    --------
    >>> import numpy as np
    >>> from flyvpr.large import ExhaustiveIndex, LargeLocalizer
    >>> rng = np.random.default_rng(0)
    >>> codes = rng.integers(0, 256, size=(20000, 32), dtype=np.uint8)
    >>> loc = LargeLocalizer(codes, ExhaustiveIndex().build(codes), window=512)
    >>> flips = rng.random((60, 256)) < 0.3       # each frame: 30% of its bits flipped
    >>> for t in range(60):
    ...     truth = 12000 + t
    ...     query = np.unpackbits(codes[truth]) ^ flips[t]
    ...     fix = loc.update_code(np.packbits(query))
    >>> fix.place, fix.state
    (12059, 'localized')
    """

    def __init__(
        self,
        codes,
        index: CandidateIndex,
        encoder=None,
        *,
        window: int = 2048,
        k: int = 100,
        pool: int = 10,
        reseed_after: int = 10,
        check_every: int = 1000,
        speed=(0.0, 2.0),
        **params,
    ):
        self.codes = codes
        as_words(codes[:1], "codes")  # a multiple of 8 bytes per code
        if codes.ndim != 2 or codes.dtype != np.uint8 or codes.shape[0] == 0:
            raise ValueError(
                f"codes must be a 2-d uint8 array (n_places, n_bytes); got {codes.dtype} "
                f"{codes.shape}"
            )
        n_places = codes.shape[0]
        if not isinstance(index, CandidateIndex):
            raise TypeError(f"index must be a CandidateIndex; got {type(index).__name__}")
        if getattr(index, "n_places_", None) != n_places:
            raise ValueError(
                f"index must be built over the map's {n_places} codes; it holds "
                f"{getattr(index, 'n_places_', 'no')} places (build it first)"
            )
        self.index = index
        self.encoder = encoder
        self.k = check_positive_int(k, "k")
        self.pool = check_positive_int(pool, "pool")
        self.reseed_after = check_positive_int(reseed_after, "reseed_after")
        self.check_every = check_positive_int(check_every, "check_every", minimum=0)
        self.speed = tuple(float(v) for v in speed)
        self.n_bits = codes.shape[1] * 8
        self.filter_ = WindowedCANN(n_places, window=window, **params)
        self.reset()

    @property
    def n_places(self) -> int:
        return self.codes.shape[0]

    def reset(self) -> None:
        """Forget all frames (the next one is searched for in the whole map)."""
        self.filter_.reset()
        self._recent: list[np.ndarray] = []  # the last ``pool`` query codes
        self._places: list[np.ndarray] = []
        self._dists: list[np.ndarray] = []
        self._lost = 0
        self._next_search, self._gap = self.reseed_after, self.pool
        self.n_frames_ = 0
        self.n_searches_ = 0
        self.n_reseeds_ = 0
        self.search_s_ = 0.0

    def update(self, image, velocity=None) -> Fix:
        """Encode one frame (needs ``encoder``) and localize it; see :meth:`update_code`."""
        if self.encoder is None:
            raise ValueError("update needs an encoder (LargeLocalizer(..., encoder=...))")
        code = self.encoder.encode(np.asarray(image)[None])
        return self.update_code(code[0], velocity)

    def update_code(self, code, velocity=None) -> Fix:
        """Localize one frame from its compact code.

        Parameters
        ----------
        code : array-like of uint8, shape (n_bytes,)
        velocity : float, optional
            Places moved since the previous frame (odometry).

        Returns
        -------
        Fix
            ``place`` indexes the whole map; ``confidence`` and ``state`` are the layer's.
        """
        q = np.asarray(code)
        if q.shape != (self.codes.shape[1],) or q.dtype != np.uint8:
            raise ValueError(
                f"code must be uint8 of shape ({self.codes.shape[1]},); got {q.dtype} {q.shape}"
            )
        f = self.filter_
        self._recent.append(q)
        del self._recent[: -self.pool]
        if f.state_ != LOCALIZED:
            self._lost += 1
            # Re-seed on the very first frame, then after ``reseed_after`` lost frames; the
            # index is asked only then, for the last ``pool`` frames at once, so a short dip
            # below ``localized`` costs no search.  Then again every ``pool`` lost frames,
            # twice as long after each time the layer's own track won (a long dip on the
            # right stretch backs off; a kidnapped layer keeps asking).
            if self.n_frames_ == 0 or self._lost == self._next_search:
                self._search_recent()
                reseeded = self._reseed(None)
                self._gap = self.pool if reseeded or self.n_frames_ == 0 else 2 * self._gap
                self._next_search = self._lost + self._gap
        else:
            self._lost = 0
            self._next_search, self._gap = self.reseed_after, self.pool
            check = self.check_every and self.n_frames_ % self.check_every == self.check_every - 1
            if check:
                self._search_recent()
                if self._far_candidate_wins():
                    self._reseed(_CHECK_MARGIN)
        lo, hi = f.window_
        scores = hamming_similarity(q[None], self.codes, lo, hi)[0]
        place, confidence, state = f.step(scores, velocity)
        self.n_frames_ += 1
        return Fix(int(place), float(confidence), state)

    def _search_recent(self) -> None:
        """The index's candidates for each of the last ``pool`` frames (one batch)."""
        t0 = time.perf_counter()
        places, dist = self.index.search(np.stack(self._recent), self.k)
        self._places, self._dists = list(places), list(dist)
        self.n_searches_ += len(self._recent)
        self.search_s_ += time.perf_counter() - t0

    def _pooled(self) -> tuple[np.ndarray, np.ndarray]:
        t0 = time.perf_counter()
        out = pool_candidates(
            np.stack(self._places), np.stack(self._dists), self.n_bits, speed=self.speed
        )
        self.search_s_ += time.perf_counter() - t0
        return out

    def _reseed(self, margin: float | None) -> bool:
        """Re-seed the layer around the pooled candidates whose recent track beats the
        layer's own by ``margin`` (mean similarity; any candidate on the first frame).  Returns
        whether it did."""
        places, scores = self._pooled()
        keep = places < self.n_places  # moved on past the end of the map
        places, scores = places[keep][:_COMPARED], scores[keep][:_COMPARED]
        if places.size == 0 or scores[0] <= 0:
            return False
        t0 = time.perf_counter()
        tracks = self._track_scores(places)
        self.search_s_ += time.perf_counter() - t0
        if margin is None:
            # Lost: the candidates ranked by their recent tracks.  Where the best is near the
            # packet, the layer already weighs it; where the layer's own recent track is as
            # good, the layer is only unsure (a dip in its support), not somewhere else.
            best = int(places[np.argmax(tracks)])
            here = self.filter_.place_
            if here >= 0:
                if abs(best - here) <= self.filter_.width // 4:
                    return False
                if self._track_scores(np.array([here]))[0] >= tracks.max():
                    return False
            w = np.exp((tracks - tracks.max()) * (self.n_bits / 8.0))
            self.filter_.reseed(places, w)
            self.n_reseeds_ += 1
            return True
        t0 = time.perf_counter()
        own = self._track_scores(np.array([self.filter_.place_]))[0]
        better = tracks > own + margin
        self.search_s_ += time.perf_counter() - t0
        if not better.any():
            return False
        # The candidates' weights: how much better than the rest their tracks are, in units
        # of a few bits of similarity.
        w = np.exp((tracks[better] - tracks[better].max()) * (self.n_bits / 8.0))
        self.filter_.reseed(places[better], w)
        self.n_reseeds_ += 1
        return True

    def _track_scores(self, places: np.ndarray) -> np.ndarray:
        """Mean similarity of the recent query codes along a track ending at each of
        ``places`` (the best over a few speeds: 0 to 2 places per frame)."""
        codes = np.stack(self._recent)
        n = len(codes)
        back = (n - 1 - np.arange(n))[:, None] * _TRACK_SPEEDS[None, :]  # (frames, speeds)
        at = places[:, None, None] - np.rint(back)[None].astype(np.int64)
        at = np.clip(at, 0, self.n_places - 1)  # (places, frames, speeds)
        sims = np.empty(at.shape, np.float32)
        for t in range(n):
            flat = at[:, t, :].ravel()
            sims[:, t, :] = hamming_similarity_at(codes[t][None], self.codes, flat)[0].reshape(
                at.shape[0], at.shape[2]
            )
        return sims.mean(axis=1).max(axis=1)

    def _far_candidate_wins(self) -> bool:
        """At a check: whether a pooled candidate outside the window has a recent track
        better than the layer's by the check's margin."""
        return self._reseed_would(_CHECK_MARGIN)

    def _reseed_would(self, margin: float) -> bool:
        places, _ = self._pooled()
        lo, hi = self.filter_.window_
        places = places[(places < self.n_places) & ((places < lo) | (places >= hi))][:_COMPARED]
        if places.size == 0 or self.filter_.place_ < 0:
            return False
        own = self._track_scores(np.array([self.filter_.place_]))[0]
        return bool((self._track_scores(places) > own + margin).any())

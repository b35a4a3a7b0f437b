"""Streaming localization on a map of millions of places: a window while tracked, an index
when lost.

:class:`LargeLocalizer` runs the place-velocity layer
(:class:`~flyvpr.temporal.cann.WindowedCANN`) on a window of places around its packet, scoring
each frame's compact code against those places only, so a tracked frame costs the same on a
map of 10^3 or 10^7 places.  When the layer has been ``lost`` for ``reseed_after`` frames (at
once on the first frame), the codes of the newest frames go to an index over the map's codes,
the candidates of the lost stretch's frames are pooled (:func:`~flyvpr.large.pool_candidates`)
and ranked by their tracks over those frames (each place's similarity less its baseline, the
layer's own adaptation), and the layer re-seeds around the best, when it beats the layer's own
track by more than chance, and is run over those frames again (a replay) so that it has
weighed their evidence already.  Searches come ``reseed_after`` frames after a re-seed or
after a search where a candidate's track beat the layer's own (by less than chance allows),
and twice as far apart each time the layer's own track was the best of all.  On every
``check_every``-th frame, if the layer is localized then, the index is asked too, and a
candidate outside the window whose track clearly beats the layer's makes it re-seed (a kidnap
the layer has not noticed).
"""

from __future__ import annotations

import time
from collections import deque
from typing import NamedTuple

import numpy as np

from .._validation import check_images, check_positive_int
from ..localization import LOCALIZED, Fix
from ..localization.localizer import _check_place_spacing, odometry_places, odometry_places_batch
from ..temporal.cann import WindowedCANN
from .codes import as_words, hamming_similarity, hamming_similarity_at
from .index import CandidateIndex, ExhaustiveIndex, check_speed_range, pool_candidates

__all__ = ["LargeLocalizer", "LargeFixes"]

#: pooled candidates whose tracks are compared with the layer's
_COMPARED = 300
#: speeds (places per frame) over which a track is scored
_TRACK_SPEEDS = np.array([0.0, 0.5, 1.0, 1.5, 2.0])
#: a candidate's tracks may end this many places either side of it
_REFINE = 10
#: a place's baseline is shrunk towards chance as if this many more frames had scored 1/2
_PRIOR_FRAMES = 5
#: a lost layer re-seeds where a candidate's track beats its own by this many standard errors
#: of a mean similarity of unrelated codes over the tracks' frames
_LOST_Z = 3.5
#: a tracked layer, at a check, by this much mean similarity (a stronger case against a
#: tracked packet)
_CHECK_MARGIN = 0.06
#: ends the search of every place's track adds to the candidates (at least _REFINE apart)
_FULL_ENDS = 50


class LargeFixes(NamedTuple):
    """:meth:`LargeLocalizer.update_batch`'s answers for consecutive frames: as
    :class:`~flyvpr.localization.Fixes` without the score rows (a row over every place of a
    very large map per frame is what this localizer avoids).

    Attributes
    ----------
    places : ndarray of int64, shape (n,)
    confidences : ndarray, shape (n,)
    relocated : ndarray of bool, shape (n,)
        Whether the layer re-seeded at that frame.
    states : ndarray of str, shape (n,)
        ``"localized"`` or ``"lost"`` per frame.
    """

    places: np.ndarray
    confidences: np.ndarray
    relocated: np.ndarray
    states: np.ndarray


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
    k : int, default 300
        Candidates per frame from the index.  On a map of at most ``k`` places every place is
        a candidate, whatever the index (an approximate one such as multi-index hashing finds
        only the codes near the query's; scanning so few codes costs next to nothing).
    pool : int, default 10
        Frames whose candidates are pooled and over which tracks are scored: the last
        ``pool`` frames, only those of the lost stretch when lost.
    reseed_after : int, default 4
        Lost frames before the first search of a lost stretch (a layer often dips below
        ``localized`` for a few frames on the right stretch), and between a re-seed and the
        next search.  A search sends the index the codes of at most this many frames, the
        newest it has not seen (each code is searched once).
    check_every : int, default 1000
        Checks against the index come on every ``check_every``-th frame since ``reset()``
        (0: never), if the layer is localized when that frame arrives; a check that finds it
        lost is skipped (a lost layer searches anyway).
    speed : (float, float), default (0.0, 2.0)
        Speeds, places per frame, the pooling allows between frames.
    hold : int, default 30
        Frames the layer a lost re-seed displaced is held (stepped on beside the new one)
        while neither is localized (chosen on the 35,768-place benchmark's dev windows,
        ``benchmarks/large_accuracy.py``, seeds 0-2: at 10 a dip on the right stretch
        outlasted it and the right layer was let go, seed 2, frames 712-741; 30 was better
        than 20 with the exact scan, seed 1, frames 0-999: 0.955 against 0.946).
    place_spacing : float, optional
        Metres between consecutive places, to turn the ``distance`` given to :meth:`update`,
        :meth:`update_code` or :meth:`update_batch` into places (as
        :class:`~flyvpr.localization.Localizer` does);
        :func:`~flyvpr.large.recording.compact_localizer` takes it from the map's positions.
    full_search_places : int, default 1048576
        On maps of at most this many places, a lost layer that has not been localized since
        its seed (a guess) also scores every place's track over the lost frames, as the
        index's candidates are scored, and adds the best ends to them: the index answers
        single frames, and on a stretch where no single frame finds the true place its track
        over several frames still can.  Its cost grows with the map (about 1 ms at 35,768
        places and 0.1 s at 10^6 on the 2-core machine of the benchmarks); 0: never.
    **params
        The :class:`~flyvpr.temporal.cann.CANN`'s parameters.  ``hold_repeats`` is off unless
        given: a map's short binary codes (256 bits in a compact map) repeat over frames that
        differ by sensor noise only, so a repeated row is no sign of a repeated frame (held,
        they cost the compact map of the Nordland traverses 0.988 -> 0.970 AUC, tolerance 2,
        measured 2026-11-26).  ``breaks`` are places of the whole map (the layer is given
        those inside its window, :class:`~flyvpr.temporal.cann.WindowedCANN`);
        :func:`~flyvpr.large.recording.compact_localizer` takes them from the map's
        positions.

    Attributes
    ----------
    filter_ : WindowedCANN
        The layer that answers.
    held_ : WindowedCANN or None
        The layer a lost re-seed displaced (of the displaced layers localized since their
        seed, the more confident; a guess is not held), stepped on beside ``filter_`` for at
        most ``hold`` frames while the answer is not localized; whichever is more confident
        answers.
    n_frames_, n_searches_, n_reseeds_, n_full_searches_ : int
        Frames, codes sent to the index, re-seeds and searches of every place's track since
        :meth:`reset`.
    n_odometry_refused_ : int
        Frames since :meth:`reset` whose odometry the answering layer refused as a glitch
        (the CANN's ``n_odometry_refused_``, counted across re-seeds: each starts a new
        layer).
    search_s_ : float
        Seconds spent relocating since :meth:`reset`: the index, the pooling, the tracks and
        the re-seeds' replays.

    Notes
    -----
    A lost stretch is searched at its ``reseed_after``-th frame, then ``reseed_after``
    frames after each re-seed or each search where some candidate's track beat the layer's
    own without clearing the margin, or, where the layer's own track was the best of all,
    after as many frames as the stretch has lasted (with the default, at lost frames 4, 8,
    16, 32, ...: a long dip on the right stretch, where the layer's own track is the best,
    backs off; a kidnapped layer, whose track at its wrong place is beaten by the
    candidates', keeps being searched every 4 frames until one of them clears the margin.
    Backing off there too cost kidnaps: the 4th search of a stretch came at its 32nd
    frame).

    A candidate's track is scored, at speeds of 0 to 2 places per frame and ending within
    10 places of it, by the mean over the frames of each frame's similarity to the track's
    place less that place's baseline, its mean similarity to all these frames (shrunk
    towards 1/2 as if five more frames had scored 1/2): the layer's own adaptation, which
    keeps a place whose code resembles every query of these conditions from winning on all of
    them.  A lost layer re-seeds where the best track beats the layer's own (at its place) by
    more than 3.5 standard errors of a mean similarity of unrelated codes; where neither the
    answering layer nor a held one has been localized since its seed (only guesses, with no
    track to defend), wherever any track beats theirs, the guesses' own tracks weighed among
    the candidates.  The layer then restarts around the candidates as they were at the
    oldest of these frames and steps through them (the replay), so that it is ``localized``
    as soon as their evidence allows instead of after as many new frames.  A displaced layer
    that had been localized is not thrown away: a lost layer is as often dipping on the
    right stretch, where a look-alike can match a few frames better, as kidnapped, and only
    the frames that follow tell the two apart, so it is held and integrated on and answers
    whenever it is the more confident.  A guess is searched again every ``reseed_after``
    frames instead of backing off, and on a map of at most ``full_search_places`` places its
    search also scores the track of every place (the ends of the 50 best, 11 places apart or
    more, join the index's candidates ahead of them): where no single frame of the stretch
    finds the true place, its track over the frames still can.  On the 35,768-place benchmark this
    brought frames 0-999 from 0.949-0.960 to 0.959-0.962 AUC (whole map 0.964-0.968).
    Holding guesses to the margin too cost the exact scan 0.012 there (seed 0, frames
    1000-1999, tolerance 20: a first-frame guess 1,266 places off answered for 24 frames,
    while the true track beat its own by 0.024 at frames 8 and 20, under the margin's 0.035).

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
        k: int = 300,
        pool: int = 10,
        reseed_after: int = 4,
        check_every: int = 1000,
        speed=(0.0, 2.0),
        hold: int = 30,
        place_spacing=None,
        full_search_places: int = 1 << 20,
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
        self._every: ExhaustiveIndex | None = None  # (see _search)
        #: where the index came from, in words (set by flyvpr.large.compact_localizer)
        self.index_source_: str | None = None
        self.pool = check_positive_int(pool, "pool")
        self.reseed_after = check_positive_int(reseed_after, "reseed_after")
        self.check_every = check_positive_int(check_every, "check_every", minimum=0)
        self.speed = check_speed_range(speed)
        self.hold = check_positive_int(hold, "hold")
        self.place_spacing = _check_place_spacing(place_spacing)
        self.full_search_places = check_positive_int(
            full_search_places, "full_search_places", minimum=0
        )
        self.n_bits = codes.shape[1] * 8
        self._layer = {"window": window, "hold_repeats": False, **params}
        self.filter_ = WindowedCANN(n_places, **self._layer)
        self.reset()

    @property
    def _search(self) -> CandidateIndex:
        """The index that answers for candidates: ``index``, or on a map of at most ``k``
        places an exact scan of every code (every place a candidate, whatever the index)."""
        if self.n_places <= self.k and not isinstance(self.index, ExhaustiveIndex):
            if self._every is None:
                every = ExhaustiveIndex()
                every.build(self.codes)
                self._every = every
            return self._every
        return self.index

    @property
    def n_places(self) -> int:
        return self.codes.shape[0]

    def reset(self) -> None:
        """Forget all frames (the next one is searched for in the whole map)."""
        self.filter_.reset()
        # the layer a re-seed displaced, integrated on while neither is localized
        self.held_: WindowedCANN | None = None
        self._held_frames = 0
        # whether the answering layer (and the held one) has been localized since its seed: a
        # layer that never was is a guess, with no track to defend
        self._proven = self._held_proven = False
        # the last ``pool`` frames' codes and odometry, newest last
        self._recent: deque[np.ndarray] = deque(maxlen=self.pool)
        self._velocities: deque[float | None] = deque(maxlen=self.pool)
        # frame number -> the index's (places, distances) for its code, for the last frames
        self._found: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self._lost = 0
        self._next_search = self.reseed_after
        self.n_frames_ = 0
        self.n_searches_ = 0
        self.n_reseeds_ = 0
        self.n_full_searches_ = 0
        self.n_odometry_refused_ = 0
        self.search_s_ = 0.0

    def _encoder(self, what: str):
        if self.encoder is None:
            raise ValueError(f"{what} needs an encoder (LargeLocalizer(..., encoder=...))")
        return self.encoder

    def update(self, image, velocity=None, *, distance=None) -> Fix:
        """Encode one frame (needs ``encoder``) and localize it; see :meth:`update_code`."""
        code = self._encoder("update").encode(np.asarray(image)[None])
        return self.update_code(code[0], velocity, distance=distance)

    def update_batch(self, images, *, velocities=None, distances=None) -> LargeFixes:
        """Consecutive frames: encoded in one vectorised call (needs ``encoder``), then
        localized in order, as :meth:`update` frame by frame.

        ``images`` (n, H, W), ``velocities`` (places) or ``distances`` (metres, over
        ``place_spacing``), one per frame (NaN or None: no odometry for that frame), and the
        errors are those of :meth:`flyvpr.localization.Localizer.update_batch`, checked before
        any frame is localized.

        Returns
        -------
        LargeFixes
            ``places``, ``confidences``, ``relocated`` (re-seeded at that frame) and
            ``states``.
        """
        encoder = self._encoder("update_batch")
        frames = check_images(images, "images", getattr(encoder, "image_shape_", None))
        moves = odometry_places_batch(
            velocities, distances, len(frames), self.place_spacing, "LargeLocalizer"
        )
        codes = encoder.encode(frames)
        places = np.empty(len(frames), np.int64)
        confidences = np.empty(len(frames))
        relocated = np.zeros(len(frames), bool)
        states = []
        for i, code in enumerate(codes):
            before = self.n_reseeds_
            fix = self.update_code(code, moves[i])
            places[i], confidences[i] = fix.place, fix.confidence
            relocated[i] = self.n_reseeds_ != before
            states.append(fix.state)
        return LargeFixes(places, confidences, relocated, np.array(states, dtype=np.str_))

    def update_code(self, code, velocity=None, *, distance=None) -> Fix:
        """Localize one frame from its compact code.

        Parameters
        ----------
        code : array-like of uint8, shape (n_bytes,)
        velocity : float, optional
            Places moved since the previous frame (odometry).
        distance : float, optional
            Metres moved since the previous frame, instead of ``velocity``: the layer gets
            ``distance / place_spacing`` places (keyword-only).

        Returns
        -------
        Fix
            ``place`` indexes the whole map; ``confidence`` and ``state`` are the layer's.

        Raises
        ------
        ValueError, TypeError
            For a code of another length or type, or odometry as
            :meth:`flyvpr.localization.Localizer.update` refuses it (both ``velocity`` and
            ``distance``, a negative or non-finite one, ``distance`` without
            ``place_spacing``); a refused frame changes nothing.
        """
        q = np.asarray(code)
        if q.shape != (self.codes.shape[1],) or q.dtype != np.uint8:
            raise ValueError(
                f"code must be uint8 of shape ({self.codes.shape[1]},); got {q.dtype} {q.shape}"
            )
        # (checked before anything is kept: a refused frame leaves none)
        velocity = odometry_places(velocity, distance, self.place_spacing, "LargeLocalizer")
        f = self.filter_
        self._recent.append(q)
        self._velocities.append(velocity)
        if f.state_ != LOCALIZED:
            self._lost += 1
            if self.n_frames_ == 0 or self._lost == self._next_search:
                # The lost stretch's frames (the frames before it belong to the track the
                # layer lost): again soon after a re-seed or where a candidate's track beat
                # the layer's own, twice as late after each time the layer's own track was
                # the best (a long dip on the right stretch backs off).
                reseeded, own_best = self._reseed_lost(min(self._lost, self.pool))
                soon = reseeded or not own_best or not self._proven
                again = self.reseed_after if soon else self._lost
                self._next_search = self._lost + again
        else:
            self._lost = 0
            self._next_search = self.reseed_after
            check = self.check_every and self.n_frames_ % self.check_every == self.check_every - 1
            if check:
                self._check()
        refused = {}  # each layer's count of refused odometry before this frame
        for layer in (self.filter_, self.held_):
            if layer is not None:
                lo, hi = layer.window_
                refused[id(layer)] = layer.cann_.n_odometry_refused_
                layer.step(hamming_similarity(q[None], self.codes, lo, hi)[0], velocity)
        held = self.held_
        if held is not None:
            # Two hypotheses: the one more likely right answers (the confidence is that
            # probability); the other is kept while the answer is not localized (a re-seed in
            # a dip on the right stretch must not throw the right track away).
            if held.confidence_ > self.filter_.confidence_:
                self.filter_, self.held_ = held, self.filter_
                self._proven, self._held_proven = self._held_proven, self._proven
            self._held_frames += 1
            if self.filter_.state_ == LOCALIZED or self._held_frames >= self.hold:
                self.held_, self._held_proven = None, False
        f = self.filter_
        place, confidence, state = f.place_, f.confidence_, f.state_
        # (the answering layer's refusal of this frame's odometry: a replay's own steps and a
        # layer that does not answer count no frame)
        self.n_odometry_refused_ += f.cann_.n_odometry_refused_ > refused[id(f)]
        self._proven |= state == LOCALIZED
        self.n_frames_ += 1
        for frame in [t for t in self._found if t <= self.n_frames_ - self.pool]:
            del self._found[frame]  # no longer pooled
        return Fix(int(place), float(confidence), state)

    def _candidates(self, n_frames: int) -> np.ndarray:
        """Candidate places at this frame, best first (at most _COMPARED): the index's answers
        for the last ``n_frames`` frames, pooled; the newest ``reseed_after`` of them not
        searched yet are searched first, in one batch (a frame never searched adds nothing)."""
        now = self.n_frames_
        frames = range(now - n_frames + 1, now + 1)
        new = [t for t in frames if t not in self._found][-self.reseed_after :]
        k = min(self.k, self.n_places)  # (a map smaller than k: every place)
        t0 = time.perf_counter()
        if new:
            codes = np.stack([self._recent[t - now - 1] for t in new])
            places, dist = self._search.search(codes, k)
            self._found.update(zip(new, zip(places, dist, strict=True), strict=True))
            self.n_searches_ += len(new)
        none = (np.full(k, -1, np.int64), np.full(k, self.n_bits + 1, np.int32))
        answers = [self._found.get(t, none) for t in frames]
        pooled, scores = pool_candidates(
            np.stack([a[0] for a in answers]),
            np.stack([a[1] for a in answers]),
            self.n_bits,
            speed=self.speed,
        )
        keep = (pooled < self.n_places) & (scores > 0)  # not moved on past the end of the map
        pooled = pooled[keep]
        if (
            not self._proven
            and self._lost >= self.reseed_after
            and 0 < self.n_places <= self.full_search_places
        ):
            # a guess that is lost: every place's track too (first, ahead of the index's)
            full = self._full_track_ends(n_frames)
            self.n_full_searches_ += 1
            pooled = np.concatenate([full, pooled[~np.isin(pooled, full)]])
        self.search_s_ += time.perf_counter() - t0
        return pooled[:_COMPARED]

    def _full_track_ends(self, n_frames: int) -> np.ndarray:
        """The ends of the best tracks over the last ``n_frames`` frames among every place's
        (scored as :meth:`_track_scores` scores a candidate's, at its end), best first, at most
        _FULL_ENDS of them and at least _REFINE + 1 places apart."""
        codes = np.stack(list(self._recent)[-n_frames:])
        n = self.n_places
        sims = hamming_similarity(codes, self.codes)  # (frame, place)
        baseline = (sims.sum(axis=0) + 0.5 * _PRIOR_FRAMES) / (n_frames + _PRIOR_FRAMES)
        sims -= baseline[None, :]
        best = np.full(n, -np.inf, np.float32)
        track = np.empty(n, np.float32)
        for speed in _TRACK_SPEEDS:
            track[:] = 0.0
            for t in range(n_frames):
                back = int(np.rint(speed * (n_frames - 1 - t)))  # the track's place at frame t
                if back < n:  # (on a map shorter than that every such track is masked below)
                    track[back:] += sims[t, : n - back]
            track[: int(np.rint(speed * (n_frames - 1)))] = -np.inf  # began before place 0
            np.maximum(best, track, out=best)
        m = min(n, 20 * _FULL_ENDS)  # enough to leave _FULL_ENDS apart from each other
        top = np.argpartition(-best, m - 1)[:m] if m < n else np.arange(n)
        ranked = top[np.argsort(-best[top], kind="stable")]
        ends: list[int] = []
        for place in ranked.tolist():
            if all(abs(place - e) > _REFINE for e in ends):
                ends.append(place)
                if len(ends) == _FULL_ENDS:
                    break
        return np.array(ends, np.int64)

    def _reseed_lost(self, n_frames: int) -> tuple[bool, bool]:
        """A lost layer: search, and re-seed around the candidates whose tracks over the last
        ``n_frames`` frames beat the layer's own by more than chance (any candidate when the
        layer has no place yet; any better one when the layers are guesses, never localized
        since their seed).  Returns whether it did, and whether the layer's own track (the
        answering or the held layer's) was at least as good as every candidate's."""
        places = self._candidates(n_frames)
        if places.size == 0:
            return False, True
        t0 = time.perf_counter()
        # The layers' own tracks: the answering layer's and the one it displaced, if kept.
        # The best of ~_COMPARED candidates at several speeds and ends beats an unrelated
        # track by a few standard errors by chance alone (the layer's own track may be on
        # the right stretch, dipping where its frames match poorly).
        margin = _LOST_Z * 0.5 / np.sqrt(self.n_bits * n_frames)
        own = [layer.place_ for layer in (self.filter_, self.held_) if layer is not None]
        own = [p for p in own if p >= 0]
        ends = np.append(places, np.array(own, np.int64))
        tracks, ends, speeds = self._track_scores(ends, n_frames)
        self.search_s_ += time.perf_counter() - t0
        if own:
            mine = tracks[-len(own) :].max()
            theirs = tracks[: -len(own)].max()
            if not (self._proven or self._held_proven):
                # only guesses (no layer localized since its seed): no track to defend, so the
                # best of all wins, and a re-seed weighs the guesses' tracks with the others
                if theirs <= mine:
                    return False, True
            else:
                tracks, ends, speeds = tracks[: -len(own)], ends[: -len(own)], speeds[: -len(own)]
                if theirs <= mine + margin:
                    return False, bool(mine >= theirs)
        # (a layer that never had a place, the first frame's, is no hypothesis to keep)
        self._replay(ends, tracks, speeds, n_frames, hold=self.n_frames_ > 0)
        return True, False

    def _check(self) -> None:
        """A tracked layer: search, and re-seed around the candidates outside the window whose
        tracks over the last ``pool`` frames beat the layer's own by _CHECK_MARGIN (a kidnap
        the layer has not noticed)."""
        n_frames = len(self._recent)
        places = self._candidates(n_frames)
        lo, hi = self.filter_.window_
        places = places[(places < lo) | (places >= hi)]
        if places.size == 0:
            return
        t0 = time.perf_counter()
        tracks, ends, speeds = self._track_scores(np.append(places, self.filter_.place_), n_frames)
        self.search_s_ += time.perf_counter() - t0
        own, tracks, ends, speeds = tracks[-1], tracks[:-1], ends[:-1], speeds[:-1]
        better = tracks > own + _CHECK_MARGIN
        if better.any():
            self._replay(ends[better], tracks[better], speeds[better], n_frames)

    def _replay(self, ends, tracks, speeds, n_frames: int, hold: bool = False) -> None:
        """Start a layer around the tracks ending at ``ends`` as they were ``n_frames - 1``
        frames ago and step it through those frames' codes (not this one's), so that it has
        weighed their evidence by the time this frame comes; it answers from now on.  With
        ``hold``, the more confident of the layers it displaces is kept (:attr:`held_`)."""
        t0 = time.perf_counter()
        # The candidates' weights: how much better than the rest their tracks are, in units
        # of a few bits of similarity.
        w = np.exp((tracks - tracks.max()) * (self.n_bits / 8.0))
        start = ends - np.rint(speeds * (n_frames - 1)).astype(np.int64)
        f = WindowedCANN(self.n_places, **self._layer)
        f.reseed(np.clip(start, 0, self.n_places - 1), w)
        self.n_reseeds_ += 1
        for i in range(-n_frames, -1):
            lo, hi = f.window_
            scores = hamming_similarity(self._recent[i][None], self.codes, lo, hi)[0]
            f.step(scores, None if i == -n_frames else self._velocities[i])
        # a guess (never localized since its seed) is not kept: the search found a track
        # at least as good as its own
        kept = [
            layer
            for layer, proven in ((self.filter_, self._proven), (self.held_, self._held_proven))
            if layer is not None and proven
        ]
        self.held_ = max(kept, key=lambda layer: layer.confidence_) if hold and kept else None
        self._held_proven = self.held_ is not None
        self._held_frames = 0
        self._proven = False
        self.filter_ = f
        self.search_s_ += time.perf_counter() - t0

    def _track_scores(
        self, places: np.ndarray, n_frames: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The best track over the last ``n_frames`` frames ending within _REFINE places of
        each of ``places``: its score, its end and its speed.

        A track ending at a place at a speed (_TRACK_SPEEDS, places per frame) scores the mean,
        over the frames, of the frame's similarity to the track's place there less that
        place's baseline: its mean similarity to all these frames, shrunk towards chance (1/2)
        as if _PRIOR_FRAMES more frames had scored 1/2.  The baseline is the layer's
        adaptation (each place's running mean input, subtracted): a place whose code
        resembles every query of these conditions stands out on none of them.  The shrinking
        keeps a standing query (frames all alike, each place's baseline its similarity) from
        scoring nothing.  The ends tried around each place: an index's candidate is the best
        match of one frame, often a few places from where the frames fit best together.
        """
        codes = np.stack(list(self._recent)[-n_frames:])
        reach = int(np.ceil(_TRACK_SPEEDS.max() * (n_frames - 1)))
        width = reach + 2 * _REFINE + 1  # the places one candidate's tracks visit
        block = (places - _REFINE - reach)[:, None] + np.arange(width)[None, :]
        block = np.clip(block, 0, self.n_places - 1)
        sims = hamming_similarity_at(codes, self.codes, block.ravel())
        sims = sims.reshape(n_frames, len(places), width).transpose(1, 0, 2)  # place, frame
        baseline = (sims.sum(axis=1) + 0.5 * _PRIOR_FRAMES) / (n_frames + _PRIOR_FRAMES)
        sims -= baseline[:, None, :]
        # speed s, end e (in the block): at frame t the block's place e - round(s * (n - 1 - t))
        back = np.rint(_TRACK_SPEEDS[:, None] * (n_frames - 1 - np.arange(n_frames))[None, :])
        ends = reach + np.arange(2 * _REFINE + 1)
        at = ends[None, :, None] - back[:, None, :].astype(np.int64)  # (speed, end, frame)
        at += (np.arange(n_frames) * width)[None, None, :]
        score = sims.reshape(len(places), -1)[:, at].mean(axis=3).reshape(len(places), -1)
        best = np.argmax(score, axis=1)
        speed, end = np.divmod(best, 2 * _REFINE + 1)
        return (
            score[np.arange(len(places)), best],
            np.clip(places + end - _REFINE, 0, self.n_places - 1),
            _TRACK_SPEEDS[speed],
        )

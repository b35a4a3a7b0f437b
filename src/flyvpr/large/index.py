"""Indexes over compact codes: the top ``k`` candidate places of a query, for relocation.

A filter that tracks the route looks at a window of places around its packet; when it is
lost (or as a periodic check) it asks an index for the places whose codes are nearest the
query's, pools them over several frames (:func:`pool_candidates`) and re-seeds from the best.

Indexes (``INDEXES``, name -> class; all take bit-packed uint8 codes, ``n_bytes`` a multiple
of 8, and answer ``search(query_codes, k) -> (places, distances)``):

* ``exhaustive``: every code's Hamming distance (compiled popcount), exact; the reference.
* ``mih``: multi-index hashing (Norouzi, Punjani & Fleet, CVPR 2012): the code is cut into
  16-bit substrings, each with a hash table (a counting sort of the places by substring:
  bucket starts and place numbers, as arrays); a query probes, in every table, the buckets
  within ``radius`` bits of its own substring and re-ranks the places found by their full
  distance.  Exact for neighbours nearer than ``n_tables * (radius + 1)`` bits (pigeonhole);
  beyond that, approximate.  Its arrays can be stored in a map file and memory-mapped.
* ``faiss-ivf`` and ``faiss-hnsw``: faiss's ``IndexBinaryIVF`` and ``IndexBinaryHNSW``
  (``pip install flyvpr[faiss]``; faiss is imported only when one is built).
"""

from __future__ import annotations

import itertools
import math
import time
from typing import Any

import numpy as np

from .._validation import check_positive_int
from .codes import _kernels, _pair, as_words

__all__ = [
    "INDEXES",
    "CandidateIndex",
    "ExhaustiveIndex",
    "FaissHNSWIndex",
    "FaissIVFIndex",
    "MultiIndexHash",
    "pool_candidates",
]


class CandidateIndex:
    """Base class: the public calls and their checks; subclasses fill ``_build`` and
    ``_search``.

    Attributes set by ``build``
    ---------------------------
    n_places_ : int
    n_bytes_ : int
        Bytes per code.
    build_s_ : float
        Seconds the build took.
    """

    name = "index"

    def build(self, codes) -> CandidateIndex:
        """Index the codes of the map's places.

        Parameters
        ----------
        codes : ndarray of uint8, shape (n_places, n_bytes)
            May be memory-mapped; ``exhaustive`` and ``mih`` keep a reference to it (the
            re-ranking reads it), so keep it open.

        Returns
        -------
        self
        """
        words = as_words(codes, "codes")
        if len(words) == 0:
            raise ValueError("codes must hold at least one place; got 0")
        t0 = time.perf_counter()
        self.n_places_ = int(len(words))
        self.n_bytes_ = int(words.shape[1] * 8)
        self._codes = np.asarray(codes)
        self._words = words
        self._build(words)
        self.build_s_ = time.perf_counter() - t0
        return self

    def search(self, query_codes, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest places of each query (or as many as the index finds).

        Parameters
        ----------
        query_codes : ndarray of uint8, shape (n_query, n_bytes) or (n_bytes,)
        k : int
            Candidates per query, >= 1 (at most the number of places).

        Returns
        -------
        places : ndarray of int64, shape (n_query, k)
            Nearest first; -1 where the index found fewer than ``k``.
        distances : ndarray of int32, shape (n_query, k)
            Hamming distances; ``n_bits + 1`` where ``places`` is -1.

        Raises
        ------
        ValueError
            Before ``build``, for codes of another width, or ``k`` out of range; when the
            tables of a loaded index name a place past the map (a corrupt index file).
        """
        if not hasattr(self, "n_places_"):
            raise ValueError(f"this {type(self).__name__} is not built yet; call build(codes)")
        q, _ = _pair(query_codes, self._codes)
        k = check_positive_int(k, "k")
        if k > self.n_places_:
            raise ValueError(f"k must be <= the number of places ({self.n_places_}); got {k}")
        places = np.full((len(q), k), -1, dtype=np.int64)
        dist = np.full((len(q), k), self.n_bytes_ * 8 + 1, dtype=np.int32)
        if len(q):
            self._search(q, k, places, dist)
        return places, dist

    def _build(self, words: np.ndarray) -> None:
        raise NotImplementedError

    def _search(self, q: np.ndarray, k: int, places: np.ndarray, dist: np.ndarray) -> None:
        raise NotImplementedError

    @property
    def nbytes(self) -> int:
        """Bytes the index holds besides the codes it reads."""
        return 0


class ExhaustiveIndex(CandidateIndex):
    """Every place's Hamming distance; exact top ``k`` (ties: lower place first).

    Examples
    --------
    >>> codes = np.zeros((5, 8), np.uint8)
    >>> codes[:, 0] = [0, 1, 3, 7, 15]
    >>> places, dist = ExhaustiveIndex().build(codes).search(codes[2], 3)
    >>> places.tolist(), dist.tolist()
    ([[2, 1, 3]], [[0, 1, 1]])
    """

    name = "exhaustive"

    def _build(self, words):
        pass

    def _search(self, q, k, places, dist):
        kern = _kernels()
        n_bits = self.n_bytes_ * 8
        fn = kern.top_k_parallel if len(q) > 1 else kern.top_k
        fn(q, self._words, k, n_bits, places, dist)


class MultiIndexHash(CandidateIndex):
    """Multi-index hashing over 16-bit substrings, with exact re-ranking.

    Parameters
    ----------
    n_tables : int or None, default None
        Substrings indexed, the first ``n_tables`` 16-bit pieces of the code (None: all,
        ``n_bits / 16``).  Each table costs 4 bytes per place.
    radius : int, default 1
        Bits a probed bucket's substring may differ from the query's (0, 1 or 2: 1, 17 or
        137 buckets per table).
    max_candidates : int, default 200_000
        Cap on the places gathered per query (closest buckets first) before re-ranking.

    Attributes
    ----------
    starts_ : ndarray of int64, shape (n_tables, 65537)
        Bucket ``b`` of table ``t`` holds ``places_[t, starts_[t, b]:starts_[t, b + 1]]``.
    places_ : ndarray of uint32, shape (n_tables, n_places)

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> codes = rng.integers(0, 256, (1000, 32), dtype=np.uint8)
    >>> query = codes[7].copy(); query[0] ^= 1
    >>> places, dist = MultiIndexHash().build(codes).search(query, 1)
    >>> int(places[0, 0]), int(dist[0, 0])
    (7, 1)
    """

    name = "mih"

    def __init__(self, n_tables=None, radius=1, max_candidates=200_000):
        self.n_tables = n_tables
        self.radius = radius
        self.max_candidates = max_candidates

    def _check(self, n_bits: int) -> tuple[int, int, int]:
        n_all = n_bits // 16
        n_tables = n_all if self.n_tables is None else check_positive_int(self.n_tables, "n_tables")
        if n_tables > n_all:
            raise ValueError(f"n_tables must be <= {n_all} for {n_bits}-bit codes; got {n_tables}")
        radius = check_positive_int(self.radius, "radius", minimum=0)
        if radius > 2:
            raise ValueError(f"radius must be 0, 1 or 2; got {radius}")
        cap = check_positive_int(self.max_candidates, "max_candidates")
        return n_tables, radius, cap

    def _keys(self, words_or_codes: np.ndarray, n_tables: int) -> np.ndarray:
        # substring t = bytes 2t, 2t + 1 of the code read as a little-endian uint16
        codes = np.asarray(words_or_codes).view(np.uint8)
        return codes.view(np.uint16)[:, :n_tables]

    def _build(self, words):
        n_tables, _, _ = self._check(self.n_bytes_ * 8)
        n = self.n_places_
        self.starts_ = np.empty((n_tables, 65537), dtype=np.int64)
        self.places_ = np.empty((n_tables, n), dtype=np.uint32)
        for t in range(n_tables):
            keys = np.ascontiguousarray(self._keys(words, n_tables)[:, t])
            self.starts_[t, 0] = 0
            np.cumsum(np.bincount(keys, minlength=65536), out=self.starts_[t, 1:])
            self.places_[t] = np.argsort(keys, kind="stable")
        self._prepare()

    @classmethod
    def from_arrays(cls, codes, starts, places, **params) -> MultiIndexHash:
        """An index from stored tables (e.g. memory-mapped from a map file), without a build.

        Raises
        ------
        ValueError
            If the tables do not fit the codes.
        """
        index = cls(**params)
        words = as_words(codes, "codes")
        starts, places = np.asanyarray(starts), np.asanyarray(places)
        n_tables = starts.shape[0] if starts.ndim == 2 else -1
        if (
            starts.shape != (n_tables, 65537)
            or places.shape != (n_tables, len(words))
            or starts.dtype != np.int64
            or places.dtype != np.uint32
        ):
            raise ValueError(
                f"starts and places must be int64 (n_tables, 65537) and uint32 (n_tables, "
                f"{len(words)}); got {starts.dtype} {starts.shape} and {places.dtype} "
                f"{places.shape}"
            )
        if n_tables and (starts[:, -1] != len(words)).any():
            raise ValueError(f"starts must end at the number of places ({len(words)})")
        if n_tables and ((starts[:, 0] != 0).any() or (np.diff(starts, axis=1) < 0).any()):
            raise ValueError(f"starts must rise from 0 to the number of places ({len(words)})")
        index.n_tables = n_tables
        index.n_places_, index.n_bytes_ = int(len(words)), int(words.shape[1] * 8)
        index._check(index.n_bytes_ * 8)
        index._codes, index._words = np.asarray(codes), words
        index.starts_, index.places_ = starts, places
        index.build_s_ = 0.0
        index._prepare()
        return index

    def _prepare(self) -> None:
        _, radius, _ = self._check(self.n_bytes_ * 8)
        masks = [0]
        for r in range(1, radius + 1):
            for bits in itertools.combinations(range(16), r):
                masks.append(sum(1 << b for b in bits))
        self._probes = np.array(masks, dtype=np.int64)
        self._probe_radius = np.array([bin(m).count("1") for m in masks], dtype=np.int64)

    def _search(self, q, k, places, dist):
        n_tables, radius, cap = self._check(self.n_bytes_ * 8)
        kern = _kernels()
        n_bits = self.n_bytes_ * 8
        buf = np.empty(cap, dtype=np.int64)
        keys = self._keys(q, n_tables).astype(np.int64)
        for i in range(len(q)):
            m = kern.mih_candidates(
                keys[i],
                self._probes,
                self._probe_radius,
                radius,
                self.starts_,
                self.places_,
                cap,
                buf,
            )
            if m < 0:
                raise ValueError(
                    f"the index's tables name a place past the map's {self.n_places_} places: "
                    "the index is corrupt (build it again)"
                )
            cand = np.unique(buf[:m])
            kern.rerank(q[i], self._words, cand, k, n_bits, places[i], dist[i])

    @property
    def nbytes(self) -> int:
        return int(self.starts_.nbytes + self.places_.nbytes)


def _faiss():
    try:
        import faiss
    except ImportError:
        raise ImportError("the faiss indexes need faiss-cpu: pip install 'flyvpr[faiss]'") from None
    return faiss


class _FaissIndex(CandidateIndex):
    _index: Any  # the faiss binary index, made by the subclass's _build

    def _search(self, q, k, places, dist):
        d, i = self._index.search(np.ascontiguousarray(q.view(np.uint8)), k)
        found = i >= 0
        places[found] = i[found]
        dist[found] = d[found]

    @property
    def nbytes(self) -> int:
        faiss = _faiss()
        return int(faiss.serialize_index_binary(self._index).size)


class FaissIVFIndex(_FaissIndex):
    """faiss ``IndexBinaryIVF``: places clustered around ``n_lists`` binary centroids; a query
    scans the ``n_probe`` nearest lists.

    Parameters
    ----------
    n_lists : int or None
        Number of clusters (None: ``4 * sqrt(n_places)``).
    n_probe : int, default 32
    n_train : int, default 100_000
        Places (an even sample) the centroids are trained on.
    """

    name = "faiss-ivf"

    def __init__(self, n_lists=None, n_probe=32, n_train=100_000):
        self.n_lists = n_lists
        self.n_probe = n_probe
        self.n_train = n_train

    def _build(self, words):
        faiss = _faiss()
        n = self.n_places_
        n_lists = self.n_lists or max(1, int(4 * np.sqrt(n)))
        n_lists = min(check_positive_int(n_lists, "n_lists"), n)
        d = self.n_bytes_ * 8
        quantizer = faiss.IndexBinaryFlat(d)
        index = faiss.IndexBinaryIVF(quantizer, d, n_lists)
        index.own_fields = True
        quantizer.this.disown()
        step = max(1, n // check_positive_int(self.n_train, "n_train"))
        index.train(np.ascontiguousarray(self._codes[::step]))
        for lo in range(0, n, 1 << 20):
            index.add(np.ascontiguousarray(self._codes[lo : lo + (1 << 20)]))
        index.nprobe = check_positive_int(self.n_probe, "n_probe")
        self._index = index


class FaissHNSWIndex(_FaissIndex):
    """faiss ``IndexBinaryHNSW``: a navigable small-world graph over the codes.

    Parameters
    ----------
    m : int, default 16
        Links per node.
    ef_search : int, default 128
        Breadth of the search (>= k is used).
    """

    name = "faiss-hnsw"

    def __init__(self, m=16, ef_search=128):
        self.m = m
        self.ef_search = ef_search

    def _build(self, words):
        faiss = _faiss()
        index = faiss.IndexBinaryHNSW(self.n_bytes_ * 8, check_positive_int(self.m, "m"))
        for lo in range(0, self.n_places_, 1 << 20):
            index.add(np.ascontiguousarray(self._codes[lo : lo + (1 << 20)]))
        self._index = index

    def _search(self, q, k, places, dist):
        self._index.hnsw.efSearch = max(k, check_positive_int(self.ef_search, "ef_search"))
        super()._search(q, k, places, dist)


#: index name -> class
INDEXES = {
    cls.name: cls for cls in (ExhaustiveIndex, MultiIndexHash, FaissIVFIndex, FaissHNSWIndex)
}


def check_speed_range(speed) -> tuple[float, float]:
    """``speed`` as (low, high), finite numbers with 0 <= low <= high (places per frame)."""
    try:
        low, high = (float(v) for v in speed)
    except (TypeError, ValueError):
        raise ValueError(f"speed must be (low, high), two numbers; got {speed!r}") from None
    if not (math.isfinite(high) and 0 <= low <= high):
        raise ValueError(f"speed must be (low, high) with 0 <= low <= high, finite; got {speed}")
    return low, high


def pool_candidates(
    frame_places, frame_distances, n_bits: int, speed=(0.5, 2.0), slack: int = 3
) -> tuple[np.ndarray, np.ndarray]:
    """Pool the candidates of consecutive frames into ranked places at the last frame.

    A candidate place ``p`` of frame ``t`` (of ``T``, the last being ``T - 1``) supports
    every place between ``p + speed[0] * (T - 1 - t) - slack`` and ``p + speed[1] * (T - 1 -
    t) + slack`` at the last frame (the route is driven forward at a speed in that range, in
    places per frame).  Its weight is its similarity margin over chance,
    ``max(0, 1/2 - distance / n_bits)``.  A place at the last frame scores the sum over frames
    of the strongest weight among that frame's candidates that support it; the places scored
    are the candidates moved at the mid speed and those of the last frame.

    Parameters
    ----------
    frame_places : array-like of int, shape (T, k)
        Each frame's candidates (an index's ``search`` over consecutive frames, oldest
        first); -1 entries are ignored.
    frame_distances : array-like of int, shape (T, k)
        Their Hamming distances.
    n_bits : int
        Bits per code.
    speed : (float, float), default (0.5, 2.0)
        Slowest and fastest speed along the route, places per frame, 0 <= low <= high.
    slack : int, default 3
        Places of tolerance either side.

    Returns
    -------
    places : ndarray of int64
        Candidate places at the last frame, best first (ties: lower place).
    scores : ndarray of float64
        Their pooled scores, descending.

    Raises
    ------
    ValueError
        For arrays of different or wrong shapes, or a bad speed range or slack.

    Examples
    --------
    Three frames whose best candidates step along the route (100, 101, 102) beat a place
    that is top in the last frame alone:

    >>> places = [[100, 500], [101, 700], [900, 102]]
    >>> dist = [[80, 100], [80, 100], [70, 85]]
    >>> best, score = pool_candidates(places, dist, n_bits=256)
    >>> int(best[0])
    102
    """
    p = np.asarray(frame_places)
    d = np.asarray(frame_distances)
    if p.ndim != 2 or p.shape != d.shape or p.shape[0] == 0:
        raise ValueError(
            "frame_places and frame_distances must be 2-d arrays (T, k) of the same shape, "
            f"T >= 1; got {p.shape} and {d.shape}"
        )
    n_bits = check_positive_int(n_bits, "n_bits")
    low, high = check_speed_range(speed)
    slack = check_positive_int(slack, "slack", minimum=0)
    n_frames = p.shape[0]
    ahead = (n_frames - 1 - np.arange(n_frames))[:, None].astype(np.float64)
    valid = p >= 0
    weight = np.where(valid, np.maximum(0.0, 0.5 - d / n_bits), 0.0)
    mid = np.rint(p + 0.5 * (low + high) * ahead).astype(np.int64)
    scored = np.unique(np.concatenate([mid[valid], p[-1][valid[-1]]]))
    if scored.size == 0:
        return np.empty(0, np.int64), np.empty(0, np.float64)
    total = np.zeros(scored.size)
    for t in range(n_frames):
        if not valid[t].any():
            continue
        # p supports s where p + low * a - slack <= s <= p + high * a + slack: the frame's
        # candidates between s - high * a - slack and s - low * a + slack, a run of them once
        # sorted; the strongest weight of each run from a table of running maxima.
        order = np.argsort(p[t][valid[t]], kind="stable")
        at = p[t][valid[t]][order]
        w = weight[t][valid[t]][order]
        first = np.searchsorted(at, scored - high * ahead[t, 0] - slack, side="left")
        stop = np.searchsorted(at, scored - low * ahead[t, 0] + slack, side="right")
        total += _range_max(w, first, stop)
    order = np.lexsort((scored, -total))
    return scored[order], total[order]


def _range_max(values: np.ndarray, first: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """``max(values[first[i]:stop[i]])`` for each ``i`` (0 where the run is empty), from a
    sparse table of maxima over runs of 1, 2, 4, ... values."""
    table = [values]  # table[j][i] = max(values[i : i + 2**j])
    while 2 ** len(table) <= len(values):
        half = 2 ** (len(table) - 1)
        table.append(np.maximum(table[-1][:-half], table[-1][half:]))
    length = stop - first
    out = np.zeros(first.shape)
    some = length > 0
    level = np.floor(np.log2(np.maximum(length, 1))).astype(np.int64)
    for j, row in enumerate(table):
        pick = some & (level == j)
        if pick.any():
            out[pick] = np.maximum(row[first[pick]], row[stop[pick] - 2**j])
    return out

"""Compiled (numba) Hamming kernels over bit-packed codes viewed as 64-bit words.

Imported on first use (:func:`flyvpr.large.codes._kernels`), so that ``import flyvpr`` does
not import numba.  The population count is LLVM's ``ctpop`` intrinsic: one ``popcnt``
instruction on the CPUs numba compiles for.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numba import prange, types
from numba.extending import intrinsic

from .._numba import jit


@intrinsic
def _ctpop(typingctx, x):
    """Number of set bits of a uint64 (LLVM ``ctpop``)."""
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return sig, codegen


#: ``_popcount(x)`` in compiled code (numba passes the intrinsic's typing context itself)
_popcount: Callable[[int], int] = _ctpop  # type: ignore[assignment]


@jit
def distances_range(query, codes, lo, hi, out):
    """``out[i - lo]`` = Hamming distance of ``query`` (w,) and ``codes[i]`` (n, w), i in lo..hi."""
    w = query.shape[0]
    for i in range(lo, hi):
        d = 0
        for j in range(w):
            d += _popcount(query[j] ^ codes[i, j])
        out[i - lo] = d
    return out


@jit
def distances_at(query, codes, places, out):
    """``out[k]`` = Hamming distance of ``query`` and ``codes[places[k]]``."""
    w = query.shape[0]
    for k in range(places.shape[0]):
        i = places[k]
        d = 0
        for j in range(w):
            d += _popcount(query[j] ^ codes[i, j])
        out[k] = d
    return out


@jit(parallel=True)
def distances_batch(queries, codes, lo, hi, out):
    """``out[q, i - lo]`` for every query (parallel over the places' blocks)."""
    w = queries.shape[1]
    n = hi - lo
    n_blocks = (n + 4095) // 4096
    for b in prange(n_blocks):
        start = lo + b * 4096
        stop = min(hi, start + 4096)
        for q in range(queries.shape[0]):
            for i in range(start, stop):
                d = 0
                for j in range(w):
                    d += _popcount(queries[q, j] ^ codes[i, j])
                out[q, i - lo] = d
    return out


@jit
def _top_k_one(query, codes, k, n_bits, dist, hist, out_places, out_dist):
    # pass 1: every distance (uint16) and their histogram
    n = codes.shape[0]
    w = query.shape[0]
    hist[:] = 0
    for i in range(n):
        d = 0
        for j in range(w):
            d += _popcount(query[j] ^ codes[i, j])
        dist[i] = d
        hist[d] += 1
    # the k-th smallest distance
    total = 0
    cut = n_bits
    for d in range(n_bits + 1):
        total += hist[d]
        if total >= k:
            cut = d
            break
    # pass 2: counting sort of the places at distance <= cut (ties: lower place first)
    start = np.zeros(cut + 2, dtype=np.int64)
    for d in range(cut + 1):
        start[d + 1] = start[d] + hist[d]
    m = 0
    for i in range(n):
        d = dist[i]
        if d <= cut:
            pos = start[d]
            if pos < k:
                out_places[pos] = i
                out_dist[pos] = d
                m += 1
            start[d] = pos + 1
            if m == k:
                break
    return m


@jit
def top_k(queries, codes, k, n_bits, out_places, out_dist):
    """Exact ``k`` nearest codes of each query by Hamming distance, nearest first, ties by
    lower place; serial (one streamed query)."""
    dist = np.empty(codes.shape[0], dtype=np.uint16)
    hist = np.empty(n_bits + 1, dtype=np.int64)
    for q in range(queries.shape[0]):
        _top_k_one(queries[q], codes, k, n_bits, dist, hist, out_places[q], out_dist[q])
    return out_places


@jit(parallel=True)
def top_k_parallel(queries, codes, k, n_bits, out_places, out_dist):
    """:func:`top_k`, parallel over the queries of a batch."""
    for q in prange(queries.shape[0]):
        dist = np.empty(codes.shape[0], dtype=np.uint16)
        hist = np.empty(n_bits + 1, dtype=np.int64)
        _top_k_one(queries[q], codes, k, n_bits, dist, hist, out_places[q], out_dist[q])
    return out_places


@jit
def rerank(query, codes, candidates, k, n_bits, out_places, out_dist):
    """The ``k`` nearest of ``candidates`` (distinct places) to ``query``, nearest first, ties
    by lower place; returns how many were written (fewer than ``k`` candidates: all)."""
    m = candidates.shape[0]
    w = query.shape[0]
    dist = np.empty(m, dtype=np.int64)
    for c in range(m):
        i = candidates[c]
        d = 0
        for j in range(w):
            d += _popcount(query[j] ^ codes[i, j])
        # sort key: distance, then place
        dist[c] = d * (1 << 40) + i
    order = np.argsort(dist)
    n_out = min(k, m)
    for r in range(n_out):
        key = dist[order[r]]
        out_places[r] = key & ((1 << 40) - 1)
        out_dist[r] = key >> 40
    return n_out


@jit
def mih_candidates(keys, probes, probe_radius, max_radius, starts, places, cap, out):
    """Places sharing a substring with the query within ``max_radius`` bits, closest probes
    first, at most ``cap`` (with repeats); returns how many were written to ``out``, or -1
    when the tables name a place past the map (``places.shape[1]`` places: a corrupt index
    file; nothing is read out of bounds).

    ``keys[t]``: the query's substring of table ``t``; ``probes``: the XOR masks to probe,
    with their popcounts ``probe_radius`` (ascending); ``starts[t, key]``: bucket starts of
    table ``t`` in ``places[t]`` (checked when the index is loaded).
    """
    m = 0
    n_tables = keys.shape[0]
    n = places.shape[1]
    for r in range(max_radius + 1):
        for t in range(n_tables):
            for j in range(probes.shape[0]):
                if probe_radius[j] != r:
                    continue
                key = keys[t] ^ probes[j]
                a = starts[t, key]
                b = starts[t, key + 1]
                for i in range(a, b):
                    if m == cap:
                        return m
                    place = places[t, i]
                    if place >= n:
                        return -1
                    out[m] = place
                    m += 1
    return m

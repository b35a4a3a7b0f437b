"""The compiled (numba) kernel of the ``pixels`` front end: sums of absolute differences.

Imported on first use (:func:`flyvpr.frontends.pixels.sad_matrix`), so that ``import flyvpr``
does not import numba.  Compiled with ``fastmath`` (reassociation only, see
:mod:`flyvpr._numba`): LLVM splits the float sums into SIMD lanes.

The kernel is serial (``nogil``) and :func:`sad_kernel` runs its blocks of queries on Python
threads, not on a ``numba.prange`` loop: numba compiles a ``parallel=True`` function's loop body
twice, and the copy it caches on disk is optimised again after linking, so with reassociation
the code loaded from the cache summed in another order than the code compiled in the process
(about 1 in 10^7 of the sums changed, a last-bit difference that the CANN's thresholds turned
into different benchmark rows, depending on whether a run compiled the kernel or found it
cached).  A serial function's cached object code is the code the compiling process ran, and
every query is summed by the same loop whatever the blocks, so the distances are the same bits
in every run, with any number of threads and any batch of queries.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np

from .._numba import jit

_pool: ThreadPoolExecutor | None = None
_pool_lock = threading.Lock()


def _reset_pool() -> None:  # a forked child has none of its parent's threads
    global _pool, _pool_lock
    _pool, _pool_lock = None, threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_reset_pool)


def _threads() -> ThreadPoolExecutor:
    global _pool
    with _pool_lock:
        if _pool is None:
            # (numba.config.NUMBA_NUM_THREADS: the most numba.set_num_threads may ask for)
            most = getattr(numba.config, "NUMBA_NUM_THREADS", os.cpu_count() or 1)
            _pool = ThreadPoolExecutor(most, "flyvpr-sad")
        return _pool


@jit(nogil=True, fastmath=True)
def sad_rows(query, reference, q0, q1, out):
    """``out[i, j]`` for the queries ``q0 <= i < q1`` and every reference ``j``, float32."""
    n_features = query.shape[1]
    n_reference = reference.shape[0]
    for j in range(n_reference):
        i = q0
        # Four queries at a time share every load of the reference code.
        while i + 4 <= q1:
            a0 = np.float32(0.0)
            a1 = np.float32(0.0)
            a2 = np.float32(0.0)
            a3 = np.float32(0.0)
            for k in range(n_features):
                r = reference[j, k]
                a0 += abs(query[i, k] - r)
                a1 += abs(query[i + 1, k] - r)
                a2 += abs(query[i + 2, k] - r)
                a3 += abs(query[i + 3, k] - r)
            out[i, j] = a0
            out[i + 1, j] = a1
            out[i + 2, j] = a2
            out[i + 3, j] = a3
            i += 4
        while i < q1:
            acc = np.float32(0.0)
            for k in range(n_features):
                acc += abs(query[i, k] - reference[j, k])
            out[i, j] = acc
            i += 1


def sad_kernel(query, reference, block, out):
    """``out[i, j]``: the L1 distance of query ``i`` and reference ``j``, float32; queries in
    blocks of ``block``, spread over ``numba.get_num_threads()`` threads."""
    n_query = query.shape[0]
    starts = list(range(0, n_query, block))
    n_threads = min(numba.get_num_threads(), len(starts))

    def run(first):
        for q0 in starts[first::n_threads]:
            sad_rows(query, reference, q0, min(q0 + block, n_query), out)

    if n_threads <= 1:
        run(0)
    else:
        for done in [_threads().submit(run, t) for t in range(n_threads)]:
            done.result()

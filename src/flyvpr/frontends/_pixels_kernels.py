"""The compiled (numba) kernel of the ``pixels`` front end: sums of absolute differences.

Imported on first use (:func:`flyvpr.frontends.pixels.sad_matrix`), so that ``import flyvpr``
does not import numba.  Compiled with ``fastmath`` (reassociation only, see
:mod:`flyvpr._numba`): LLVM splits the float sums into SIMD lanes.
"""

from __future__ import annotations

import numba
import numpy as np

from .._numba import jit


@jit(parallel=True, fastmath=True)
def sad_kernel(query, reference, block, out):
    """``out[i, j]``: the L1 distance of query ``i`` and reference ``j``, float32; queries in
    blocks of ``block`` (one parallel work item each)."""
    n_query, n_features = query.shape
    n_reference = reference.shape[0]
    n_blocks = (n_query + block - 1) // block
    for b in numba.prange(n_blocks):
        q0 = b * block
        q1 = min(q0 + block, n_query)
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

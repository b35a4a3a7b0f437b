"""The compiled (numba) kernel of the area resize (:func:`flyvpr.images.area_resize`).

Imported on first use, so that ``import flyvpr`` does not import numba.  ``nogil``: frames
resize while a video decoder's threads run.
"""

from __future__ import annotations

from ._numba import jit


@jit(nogil=True)
def band(y, starts, counts, weights, out):
    """``out[i] += sum_k weights[i, k] * y[starts[i] + k]``: each output row the weighted sum
    of the band of ``counts[i]`` input rows it covers."""
    for i in range(out.shape[0]):
        for k in range(counts[i]):
            wk = weights[i, k]
            r = starts[i] + k
            for j in range(out.shape[1]):
                out[i, j] += wk * y[r, j]

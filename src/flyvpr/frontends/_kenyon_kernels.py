"""Compiled (numba) kernels of the ``kenyon`` front end: optic lobe, Kenyon cells, matching.

Imported on first use by :mod:`flyvpr.frontends.optic_lobe` and
:mod:`flyvpr.frontends.kenyon`, so that ``import flyvpr`` does not import numba.

Every kernel but the Gabor filtering reproduces, operation for operation, the NumPy/SciPy
computation it replaces; ``tests/test_kenyon_kernels.py`` compares them bit for bit.  What
makes that possible:

* Gaussian filtering as ``scipy.ndimage.correlate1d`` does it for a symmetric kernel: each
  line converted to float64 and extended by reflection, ``x[i] * w[0]`` plus the pairs
  ``(x[i - t] + x[i + t]) * w[t]`` for ``t = r, ..., 1`` (outermost first), accumulated in
  float64 and stored as float32 after each axis.
* Sums of float32 rows as NumPy's ``add.reduce`` does them (pairwise summation with eight
  accumulators in blocks of at most 128), means and variances divided in float64.
* The contrast normalisation under a mask of valid pixels (:func:`lcn_masked`): the same
  Gaussian filter of ``m x`` and of ``m (x - mean)^2``, each divided by ``G m`` in float32,
  as NumPy divides the filtered arrays.
* The Kenyon-cell sums accumulated in float32 in the order of the (sorted) connections, as
  ``scipy.sparse`` does for a CSR matrix times a dense one.
* Every other step is exact (maximum, comparisons) or one correctly rounded float32 operation
  (subtraction, product, quotient, square root).

The Gabor filtering (:func:`optic_lobe`) is a direct convolution: each complex Gabor kernel
is the sum of two separable ones, so it takes one pass along the rows and one along the
columns per orientation, in float32.  It agrees with an FFT convolution (the tests' oracle,
``tests/oracles.py``) to float32 rounding (relative 1e-6), not bit for bit: for a 32x64 frame
it costs about a third of the FFTs and their calls.

Compiled by :func:`flyvpr._numba.jit`, without ``fastmath``: reassociating or fusing
operations would change the rounding (and make it depend on the CPU).
"""

from __future__ import annotations

import numba
import numpy as np

from .._numba import jit

__all__ = [
    "gaussian_taps",
    "reflect_index",
    "lcn",
    "lcn_masked",
    "optic_lobe",
    "optic_lobe_masked",
    "zscore_rows",
    "kenyon_activity",
    "kenyon_codes",
    "overlap_counts",
    "overlap_parallel",
]


def gaussian_taps(sigma: float, truncate: float = 4.0) -> np.ndarray:
    """The float64 taps of ``scipy.ndimage.gaussian_filter1d``: ``w[0]`` the centre, then out."""
    radius = int(truncate * float(sigma) + 0.5)
    x = np.arange(-radius, radius + 1)
    phi = np.exp(-0.5 / (float(sigma) * float(sigma)) * x**2)
    phi = phi / phi.sum()
    return np.ascontiguousarray(phi[radius:])


def reflect_index(n: int, radius: int) -> np.ndarray:
    """Indices of a line of length ``n`` extended by ``radius`` on both sides ('reflect' mode).

    ``d c b a | a b c d | d c b a``, repeated for a radius longer than the line: position
    ``p`` of the extended line reads element ``reflect_index(n, r)[p]``.  Unsigned, which
    spares the kernels numba's negative-index check.
    """
    p = np.arange(-radius, n + radius) % (2 * n)
    return np.where(p < n, p, 2 * n - 1 - p).astype(np.uint32)


@jit
def _smooth(pad, n, m, taps, acc, dst, transpose):
    # ``pad``: n + 2r lines of m float64 values (flat, lines extended by reflection); line i
    # of the result, float32, into row i of ``dst`` (or column i when ``transpose``).  The
    # loops run over all n * m outputs at once: long, vectorisable, and each output still
    # sums its terms in scipy's order.
    r = taps.shape[0] - 1
    size = n * m
    centre = pad[r * m : r * m + size]
    w0 = taps[0]
    for k in range(size):
        acc[k] = centre[k] * w0
    for t in range(r, 0, -1):
        a = pad[(r - t) * m : (r - t) * m + size]
        b = pad[(r + t) * m : (r + t) * m + size]
        wt = taps[t]
        for k in range(size):
            acc[k] += (a[k] + b[k]) * wt
    for i in range(n):
        for j in range(m):
            if transpose:
                dst[j, i] = np.float32(acc[i * m + j])
            else:
                dst[i, j] = np.float32(acc[i * m + j])


@jit
def _gaussian(src, taps, index_h, index_w, pad, acc, tmp, dst):
    # along axis 0, then axis 1 (on the transposed float32 result), as gaussian_filter
    h, w = src.shape
    for p in range(index_h.shape[0]):
        for j in range(w):
            pad[p * w + j] = src[index_h[p], j]
    _smooth(pad, h, w, taps, acc, tmp, False)
    for p in range(index_w.shape[0]):
        for i in range(h):
            pad[p * h + i] = tmp[i, index_w[p]]
    _smooth(pad, w, h, taps, acc, dst, True)


@jit
def _lcn_image(img, taps, index_h, index_w, eps2, o, pad, acc, tmp, mean, centred):
    # one image (H, W) into o; the other arrays are scratch (see lcn)
    h, w = img.shape
    _gaussian(img, taps, index_h, index_w, pad, acc, tmp, mean)
    for i in range(h):
        for j in range(w):
            c = img[i, j] - mean[i, j]
            centred[i, j] = c
            o[i, j] = c * c
    _gaussian(o, taps, index_h, index_w, pad, acc, tmp, mean)  # ``mean``: the variance
    for i in range(h):
        for j in range(w):
            o[i, j] = centred[i, j] / np.sqrt(mean[i, j] + eps2)


@jit
def _lcn_masked_image(img, valid, gm, taps, index_h, index_w, eps2, o, pad, acc, tmp, mean, c):
    # as _lcn_image, with the Gaussian windows restricted to the valid pixels (normalised
    # convolution): the local mean is G (m x) / G m and the variance G (m (x - mean)^2) / G m
    # (``gm`` = G m, with m the 0/1 mask ``valid``); invalid pixels give 0.  Their values never
    # enter: ``m x`` is exactly 0 there.
    h, w = img.shape
    for i in range(h):
        for j in range(w):
            o[i, j] = img[i, j] if valid[i, j] else np.float32(0.0)
    _gaussian(o, taps, index_h, index_w, pad, acc, tmp, mean)  # ``mean``: G (m x)
    for i in range(h):
        for j in range(w):
            d = img[i, j] - mean[i, j] / gm[i, j] if valid[i, j] else np.float32(0.0)
            c[i, j] = d
            o[i, j] = d * d
    _gaussian(o, taps, index_h, index_w, pad, acc, tmp, mean)  # ``mean``: G (m (x - mean)^2)
    for i in range(h):
        for j in range(w):
            if valid[i, j]:
                o[i, j] = c[i, j] / np.sqrt(mean[i, j] / gm[i, j] + eps2)
            else:
                o[i, j] = 0.0


@jit
def _lcn_scratch(h, w, r):
    pad = np.empty(max((h + 2 * r) * w, (w + 2 * r) * h), dtype=np.float64)
    acc = np.empty(h * w, dtype=np.float64)
    tmp = np.empty((h, w), dtype=np.float32)
    mean = np.empty((h, w), dtype=np.float32)
    centred = np.empty((h, w), dtype=np.float32)
    return pad, acc, tmp, mean, centred


@jit
def lcn(x, taps, index_h, index_w, eps2, out):
    """Local contrast normalisation of float32 images (N, H, W) into ``out``.

    ``(x - G x) / sqrt(G (x - G x)^2 + eps2)`` with ``G`` the Gaussian of ``taps`` along both
    axes (``index_h``, ``index_w`` from :func:`reflect_index`), float32 between steps.
    """
    n, h, w = x.shape
    pad, acc, tmp, mean, centred = _lcn_scratch(h, w, taps.shape[0] - 1)
    for m in range(n):
        _lcn_image(x[m], taps, index_h, index_w, eps2, out[m], pad, acc, tmp, mean, centred)
    return out


@jit
def lcn_masked(x, valid, gm, taps, index_h, index_w, eps2, out):
    """:func:`lcn` over the pixels where ``valid`` (bool (H, W)) is True; 0 elsewhere.

    The local mean is ``G (m x) / gm`` and the local variance ``G (m (x - mean)^2) / gm``,
    with ``m`` the mask as 0/1 and ``gm = G m`` (float32, as ``gaussian_filter`` computes it).
    """
    n, h, w = x.shape
    pad, acc, tmp, mean, centred = _lcn_scratch(h, w, taps.shape[0] - 1)
    for m in range(n):
        _lcn_masked_image(
            x[m], valid, gm, taps, index_h, index_w, eps2, out[m], pad, acc, tmp, mean, centred
        )
    return out


@jit
def _gabor_pool(img, g, ar, ai, br, bi, dc, inv_z, pool, out, xpad, hp, hg, vr, vi, vg):
    # The pooled Gabor energies of one image (H, W) into ``out`` (see optic_lobe).  Rows are
    # laid out flat, each widened by r zeros on both sides (width W2 = W + 2r), so that every
    # pass is one long loop over all rows at a fixed offset per tap.  Values that land in the
    # widening are never read by the outputs that count.
    h, w = img.shape
    s = g.shape[0]
    r = s // 2
    n_k = ar.shape[0]
    w2 = w + 2 * r
    size = h * w2
    xpad[:] = 0.0  # the image from 2r on, row i at 2r + i * w2
    for i in range(h):
        for j in range(w):
            xpad[2 * r + i * w2 + j] = img[i, j]
    # Along the rows, into rows r .. r + h of hg (real Gaussian) and hp (complex factor of
    # each orientation: real, imaginary); rows 0 .. r and r + h .. h + 2r stay zero.
    top = r * w2
    blur = hg[top : top + size]
    blur[:] = 0.0
    for k in range(n_k):
        hp[k, 0, top : top + size] = 0.0
        hp[k, 1, top : top + size] = 0.0
    for t in range(s):  # tap t takes the pixel t - r columns to the left
        src = xpad[2 * r - t : 2 * r - t + size]
        gt = g[t]
        for p in range(size):
            blur[p] += src[p] * gt
        for k in range(n_k):
            re = hp[k, 0, top : top + size]
            im = hp[k, 1, top : top + size]
            cr = ar[k, t]
            ci = ai[k, t]
            for p in range(size):
                v = src[p]
                re[p] += v * cr
                im[p] += v * ci
    # Along the columns: the Gaussian blur once, then each orientation's complex factor.
    vg[:] = 0.0
    for t in range(s):
        src = hg[(2 * r - t) * w2 : (2 * r - t) * w2 + size]
        gt = g[t]
        for p in range(size):
            vg[p] += src[p] * gt
    ph, pw = h // pool, w // pool
    for k in range(n_k):
        vr[:] = 0.0
        vi[:] = 0.0
        for t in range(s):
            o = (2 * r - t) * w2
            s_re = hp[k, 0, o : o + size]
            s_im = hp[k, 1, o : o + size]
            cr = br[k, t]
            ci = bi[k, t]
            for p in range(size):
                a = s_re[p]
                b = s_im[p]
                vr[p] += a * cr - b * ci
                vi[p] += a * ci + b * cr
        # The kernel is (A x B - dc G x G) / Z: its response's squared magnitude into vr.
        dk = dc[k]
        zk = inv_z[k]
        for p in range(size):
            re = (vr[p] - dk * vg[p]) * zk
            im = vi[p] * zk
            vr[p] = re * re + im * im
        # Max pooling of the squared magnitudes; the feature is the square root of the
        # largest magnitude.
        for a in range(ph):
            for b in range(pw):
                first = a * pool * w2 + r + b * pool
                best = vr[first]
                for u in range(pool):
                    row = first + u * w2
                    for v in range(pool):
                        e = vr[row + v]
                        if e > best:
                            best = e
                out[k * ph * pw + a * pw + b] = np.sqrt(np.sqrt(best))


@jit
def _gabor_scratch(h, w, r, n_kernels):
    # the buffers of _gabor_pool for images of (h, w) and kernels of radius r
    w2 = w + 2 * r
    xpad = np.empty(h * w2 + 4 * r, dtype=np.float32)
    hp = np.zeros((n_kernels, 2, (h + 2 * r) * w2), dtype=np.float32)
    hg = np.zeros((h + 2 * r) * w2, dtype=np.float32)
    vr = np.empty(h * w2, dtype=np.float32)
    vi = np.empty(h * w2, dtype=np.float32)
    vg = np.empty(h * w2, dtype=np.float32)
    return xpad, hp, hg, vr, vi, vg


@jit
def optic_lobe(x, taps, index_h, index_w, eps2, g, ar, ai, br, bi, dc, inv_z, pool, out):
    """Optic-lobe features of float32 images (N, H, W) into ``out`` (N, K * H/pool * W/pool).

    Per image: local contrast normalisation (as :func:`lcn`); the energy ``|image * K_k|`` of
    every complex Gabor kernel ``K_k = (A_k(x) B_k(y) - dc_k G(x) G(y)) / Z_k`` (zero padding,
    "same" size; ``g`` the real 1-d Gaussian, ``ar + i ai`` and ``br + i bi`` the complex 1-d
    factors, one row per kernel, all of odd length); max pooling over ``pool x pool`` cells
    (cells in (kernel, row, column) order) and the square root; then every row z-scored as
    :func:`zscore_rows` does it.
    """
    n, h, w = x.shape
    pad, acc, tmp, mean, centred = _lcn_scratch(h, w, taps.shape[0] - 1)
    normalised = np.empty((h, w), dtype=np.float32)
    xpad, hp, hg, vr, vi, vg = _gabor_scratch(h, w, g.shape[0] // 2, ar.shape[0])
    for m in range(n):
        _lcn_image(x[m], taps, index_h, index_w, eps2, normalised, pad, acc, tmp, mean, centred)
        _gabor_pool(
            normalised, g, ar, ai, br, bi, dc, inv_z, pool, out[m], xpad, hp, hg, vr, vi, vg
        )
    return zscore_rows(out, np.float32(1e-12))


@jit
def optic_lobe_masked(
    x, valid, gm, taps, index_h, index_w, eps2, g, ar, ai, br, bi, dc, inv_z, pool, keep, out
):
    """:func:`optic_lobe` of the pixels where ``valid`` is True, keeping the features ``keep``.

    Per image: the contrast normalisation of :func:`lcn_masked` (0 outside the valid pixels,
    whose values never enter); the Gabor energies and pooling of :func:`optic_lobe`; of the
    pooled features those at the indices ``keep`` (uint32, ascending), in that order, into
    ``out`` (N, len(keep)); then every row z-scored over these features only.
    """
    n, h, w = x.shape
    pad, acc, tmp, mean, centred = _lcn_scratch(h, w, taps.shape[0] - 1)
    normalised = np.empty((h, w), dtype=np.float32)
    xpad, hp, hg, vr, vi, vg = _gabor_scratch(h, w, g.shape[0] // 2, ar.shape[0])
    full = np.empty(ar.shape[0] * (h // pool) * (w // pool), dtype=np.float32)
    for m in range(n):
        _lcn_masked_image(
            x[m], valid, gm, taps, index_h, index_w, eps2, normalised, pad, acc, tmp, mean, centred
        )
        _gabor_pool(normalised, g, ar, ai, br, bi, dc, inv_z, pool, full, xpad, hp, hg, vr, vi, vg)
        row = out[m]
        for f in range(keep.shape[0]):
            row[f] = full[keep[f]]
    return zscore_rows(out, np.float32(1e-12))


@jit
def _block_sum(a, lo, n):
    # a leaf of NumPy's pairwise summation (``add.reduce`` of contiguous float32): a plain
    # loop below 8 values, else eight interleaved accumulators and the leftover at the end
    if n < 8:
        s = np.float32(0.0)
        for i in range(lo, lo + n):
            s += a[i]
        return s
    r = np.empty(8, dtype=np.float32)
    for u in range(8):
        r[u] = a[lo + u]
    i = 8
    while i < n - n % 8:
        for u in range(8):
            r[u] += a[lo + i + u]
        i += 8
    s = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        s += a[lo + i]
        i += 1
    return s


@jit
def _pairwise_sum(a, n, frames, partial):
    """NumPy's pairwise sum of ``a[:n]`` (float32): halves (cut at a multiple of 8) until at
    most 128 values, summed as left + right.  Iterative (numba cannot cache recursion):
    ``frames`` (int64, (64, 3): start, length, stage) and ``partial`` (float32, 64) are the
    explicit stack."""
    top = 0
    frames[0, 0] = 0
    frames[0, 1] = n
    frames[0, 2] = 0
    value = np.float32(0.0)
    have = False
    while True:
        if not have:
            lo, m = frames[top, 0], frames[top, 1]
            if m <= 128:
                value = _block_sum(a, lo, m)
                have = True
                top -= 1
            else:  # descend into the left half
                half = m // 2
                frames[top, 2] = 1
                frames[top + 1, 0] = lo
                frames[top + 1, 1] = half - half % 8
                frames[top + 1, 2] = 0
                top += 1
        elif top < 0:
            return value
        elif frames[top, 2] == 1:  # left half done: keep it, descend into the right half
            partial[top] = value
            half = frames[top, 1] // 2
            half -= half % 8
            frames[top, 2] = 2
            frames[top + 1, 0] = frames[top, 0] + half
            frames[top + 1, 1] = frames[top, 1] - half
            frames[top + 1, 2] = 0
            top += 1
            have = False
        else:  # both halves done
            value = partial[top] + value
            top -= 1


@jit
def zscore_rows(features, min_std):
    """Per row, in place: subtract the mean, divide by the standard deviation if > ``min_std``.

    As ``f.mean(axis=1)`` and ``f.std(axis=1)`` of NumPy compute them for float32 rows.
    """
    n, d = features.shape
    sq = np.empty(d, dtype=np.float32)
    frames = np.empty((64, 3), dtype=np.int64)
    partial = np.empty(64, dtype=np.float32)
    for m in range(n):
        row = features[m]
        mean = np.float32(np.float64(_pairwise_sum(row, d, frames, partial)) / np.float64(d))
        for i in range(d):
            c = row[i] - mean
            sq[i] = c * c
        var = np.float32(np.float64(_pairwise_sum(sq, d, frames, partial)) / np.float64(d))
        std = np.sqrt(var)
        for i in range(d):
            row[i] -= mean
        if std > min_std:
            for i in range(d):
                row[i] /= std
    return features


@jit
def _activity_row(features, feature_mean, connections, centred, y):
    for i in range(features.shape[0]):
        centred[i] = features[i] - feature_mean[i]
    n_kenyon, n_inputs = connections.shape
    for c in range(n_kenyon):
        s = np.float32(0.0)
        for j in range(n_inputs):
            s += centred[connections[c, j]]
        y[c] = s


@jit
def kenyon_activity(features, feature_mean, connections, out):
    """Summed centred input of every Kenyon cell: ``out`` float32 (N, n_kenyon)."""
    centred = np.empty(features.shape[1], dtype=np.float32)
    for m in range(features.shape[0]):
        _activity_row(features[m], feature_mean, connections, centred, out[m])
    return out


@jit
def _select(a, n, kk):
    # the kk-th smallest (0-based) of a[:n], which it reorders: Wirth's quickselect with a
    # median-of-three pivot
    lo, hi = 0, n - 1
    while lo < hi:
        x, pivot, z = a[lo], a[(lo + hi) // 2], a[hi]
        if x > pivot:
            x, pivot = pivot, x
        if pivot > z:
            pivot = max(x, z)
        i, j = lo, hi
        while i <= j:
            while a[i] < pivot:
                i += 1
            while pivot < a[j]:
                j -= 1
            if i <= j:
                a[i], a[j] = a[j], a[i]
                i += 1
                j -= 1
        if j < kk:
            lo = i
        if kk < i:
            hi = j
    return a[kk]


@jit
def _kth_largest(y, k, buf):
    # The k-th largest value of y (as a multiset).  A sample of about 128 values gives a
    # threshold with about 2k values of y at or above it; the k-th largest of those is the
    # answer whenever there are at least k of them (else select from all of y).
    n = y.shape[0]
    step = max(1, n // 128)
    n_sample = (n + step - 1) // step
    for i in range(n_sample):
        buf[i] = y[i * step]
    rank = min(n_sample - 1, (2 * k * n_sample) // n)
    floor = _select(buf, n_sample, n_sample - 1 - rank)
    c = 0
    for i in range(n):  # branch-free: keep the values >= floor at the front of buf
        v = y[i]
        buf[c] = v
        c += v >= floor
    if c < k:
        buf[:n] = y
        c = n
    return _select(buf, c, c - k)


@jit
def _winners(y, k, buf, bits):
    # bits[i] = 1 for the k largest of y, among equal values the lower index (as
    # winner_take_all does), else 0
    kth = _kth_largest(y, k, buf)
    free = k
    for v in y:
        if v > kth:
            free -= 1
    for i in range(y.shape[0]):
        v = y[i]
        win = v > kth
        if not win and v == kth and free > 0:
            win = True
            free -= 1
        bits[i] = win


@jit
def kenyon_codes(features, feature_mean, connections, n_projections, k, out):
    """Bit-packed winner-take-all codes (``np.packbits`` order) of every row of ``features``.

    Each of the ``n_projections`` consecutive populations of Kenyon cells keeps its ``k``
    most active cells.  ``out``: uint8 (N, n_kenyon // 8).
    """
    n_kenyon = connections.shape[0]
    per = n_kenyon // n_projections
    centred = np.empty(features.shape[1], dtype=np.float32)
    y = np.empty(n_kenyon, dtype=np.float32)
    bits = np.empty(n_kenyon, dtype=np.uint8)
    buf = np.empty(per, dtype=np.float32)
    for m in range(features.shape[0]):
        _activity_row(features[m], feature_mean, connections, centred, y)
        for p in range(n_projections):
            _winners(y[p * per : (p + 1) * per], k, buf, bits[p * per : (p + 1) * per])
        for b in range(n_kenyon // 8):  # np.packbits order: the first bit is the highest
            byte = 0
            for t in range(8):
                byte = (byte << 1) | bits[8 * b + t]
            out[m, b] = byte
    return out


@jit
def _count(packed, indptr, places, chunk, counts):
    # counts[place] += 1 for every active bit of the query that the place shares
    counts[:] = 0
    for c in range(indptr.shape[0]):
        # a view per chunk, indexed by the unsigned offsets themselves: no index arithmetic
        # or negative-index check in the innermost loop
        sub = counts[c * chunk :]
        ptr = indptr[c]
        for j in range(packed.shape[0]):
            byte = packed[j]
            if byte == 0:
                continue
            for t in range(8):  # np.packbits order: the first bit is the highest
                if byte & (128 >> t):
                    b = 8 * j + t
                    for p in range(ptr[b], ptr[b + 1]):
                        sub[places[p]] += 1


@jit
def overlap_counts(packed, indptr, places, chunk, scale, out):
    """``scale`` x the overlap of one bit-packed query with every indexed place, into ``out``.

    ``indptr`` (n_chunks, n_bits + 1) and ``places`` (offsets within each chunk of ``chunk``
    places): the inverted index.  The counts go to the narrowest integers that hold the
    largest possible overlap (the query's number of bits): with at most 255, one byte per
    place, an array small enough to stay in the fastest cache.  ``out`` float32 receives
    ``count * scale`` (as a float32 product, which equals a float32 ``+= 1.0`` per shared
    bit followed by ``*= scale``).
    """
    n_on = 0
    for byte in packed:
        while byte:
            n_on += 1
            byte &= byte - 1
    n = out.shape[0]
    if n_on < 256:
        small = np.empty(n, dtype=np.uint8)
        _count(packed, indptr, places, chunk, small)
        for p in range(n):
            out[p] = np.float32(small[p]) * scale
    else:
        wide = np.empty(n, dtype=np.int64)
        _count(packed, indptr, places, chunk, wide)
        for p in range(n):
            out[p] = np.float32(wide[p]) * scale
    return out


@jit(parallel=True)
def overlap_parallel(packed, indptr, places, chunk, scale, out):
    """``scale`` x the overlap of every bit-packed query (rows of ``packed``), into ``out``.

    The index as for :func:`overlap_counts`.  Queries are independent work items: no two
    threads write the same row of ``out``.  The counts are small integers, exact in float32.
    """
    for i in numba.prange(packed.shape[0]):
        row = out[i]
        row[:] = 0.0
        for c in range(indptr.shape[0]):
            sub = row[c * chunk :]
            ptr = indptr[c]
            for j in range(packed.shape[1]):
                byte = packed[i, j]
                if byte == 0:
                    continue
                for t in range(8):
                    if byte & (128 >> t):
                        b = 8 * j + t
                        for p in range(ptr[b], ptr[b + 1]):
                            sub[places[p]] += 1.0
        for p in range(row.shape[0]):
            row[p] *= scale
    return out

"""The place-velocity layer's per-frame updates, compiled with numba like the other kernels.

The layer holds one unit per (velocity, place) pair; its activity ``P[j, i]`` is the
probability that the robot is at place ``i`` moving ``velocities[j]`` places per frame
(see "The place-velocity layer" on the user guide's CANN page).  :func:`advance` moves it
by one frame and weighs it by the evidence, after :func:`jitter` has moved a share of every
row one place ahead or behind (uneven motion); :func:`window_sums` finds the window of places
that holds the most probability, :func:`exceedance` ranks the evidence at one place
among all, :func:`likeness` correlates a frame's scores with the last frame's (the
sequence test's novelty), :func:`repeats` tells a repeated frame and :func:`leave_at_breaks`
takes off what would cross a break of the map.  Each function is
written once, as explicit loops over places, and runs compiled or as plain Python
(``_kernels``).
"""

from __future__ import annotations

import math

import numpy as np


def window_sums(marginal, radius, out):
    """``out[i]`` = the sum of ``marginal`` over places ``i - radius .. i + radius`` (clipped
    at the route's ends), each a float64 sum of its ``2 radius + 1`` terms (no running sum:
    independent sums are SIMD loops).  Returns the index of the largest (the first of
    equals)."""
    n = marginal.shape[0]
    for i in range(n):
        out[i] = 0.0
    for d in range(-radius, radius + 1):
        lo = max(-d, 0)
        hi = min(n - d, n)
        if hi <= lo:
            continue
        src = marginal[lo + d : hi + d]
        dst = out[lo:hi]
        for i in range(hi - lo):
            dst[i] += float(src[i])
    best = 0
    top = out[0]
    for i in range(1, n):
        if out[i] > top:
            top = out[i]
            best = i
    return best


def exceedance(x, place, stride):
    """The share of sampled places whose evidence ``x`` reaches that of ``place`` (at least
    one place counts).  Every ``stride``-th place is sampled.  Under the hypothesis that
    ``place`` is no better than any other (the sequence is not there), the share is uniform
    in (0, 1].
    """
    n = x.shape[0]
    level = x[place]
    count = 0
    m = 0
    for i in range(0, n, stride):
        count += x[i] >= level
        m += 1
    return max(count, 1) / m


def advance(p, out, shifts, stay, neighbour, jump, redraw, prior, floor_rate, weight,
            predicted, marginal, row_mass):  # fmt: skip
    """One frame of the layer: the move, the mixing of velocities, the redraw, the re-seed,
    then the evidence.  ``p`` is only read; the new activity goes to ``out``.

    Row ``j`` of ``p`` (the activity, at any positive scale) moves by ``shifts[j]`` places
    (what enters at the open end is 0; what leaves is lost), and what is left is normalised
    to ``1 - floor_rate``.  Then each unit keeps ``stay`` of its activity, gives
    ``neighbour / 2`` to each neighbouring velocity (the rows at the ends keep the share that
    would leave the bank), every row receives ``jump * redraw[j]`` of the place's total over
    velocities (a velocity drawn afresh from ``redraw``: a stop or a start), and
    ``floor_rate * prior[j] / n`` is added to every unit (the robot may be anywhere:
    relocation).  If nothing is left after the move (every row moved off the route, or every
    unit at 0), this prior is ``prior[j] / n`` instead, whatever ``floor_rate``.  Its place
    marginal goes to ``predicted``: computed as the moved marginal times the normalisation
    plus ``floor_rate / n`` (``1 / n`` after a restart), which is the marginal when
    ``stay + neighbour + jump = 1`` and ``redraw`` and ``prior`` each sum to 1.

    Each unit of the prior is then weighed by the evidence ``weight[i]`` (the filter passes
    ``exp(gain * (x[i] - max(x)))``, at most 1) and written to ``out``, not normalised.  If
    the weighed layer holds nothing (the evidence underflowed wherever the prior holds mass),
    the layer starts again from the prior alone: ``out[j, i] = prior[j] / n * weight[i]``
    (``predicted`` keeps the prior before this restart).  The posterior's place marginal
    (normalised) goes to ``marginal`` and the posterior mass of every velocity row
    (normalised) to ``row_mass``.  Returns the posterior's normaliser (the sum of ``out``).
    """
    n_v, n = p.shape
    # Pass 1: the place marginal after the move (what enters at the open end is 0).
    for i in range(n):
        predicted[i] = 0.0
    for j in range(n_v):
        k = shifts[j]
        lo = min(max(k, 0), n)
        hi = max(min(n + k, n), lo)
        src = p[j, lo - k : hi - k]
        dst = predicted[lo:hi]
        for i in range(hi - lo):
            dst[i] += src[i]
    total = 0.0
    for i in range(n):
        total += float(predicted[i])
    reset = not total > 0.0
    scale = 0.0 if reset else (1.0 - floor_rate) / total
    rate = 1.0 if reset else floor_rate
    half = 0.5 * neighbour
    # Pass 2: mix velocities, redraw, re-seed, weigh by the evidence.
    for i in range(n):
        marginal[i] = 0.0
    drawn_total = np.float32(jump * scale)
    z = 0.0
    for j in range(n_v):
        jl = max(j - 1, 0)
        ju = min(j + 1, n_v - 1)
        k, kl, ku = shifts[j], shifts[jl], shifts[ju]
        a = np.float32(stay * scale)
        b = np.float32(half * scale)
        c = drawn_total * np.float32(redraw[j])
        base = np.float32(rate * prior[j] / n)
        own, lower, upper = p[j], p[jl], p[ju]
        dst = out[j]
        mass = 0.0
        # Where all three source rows are on the route: no bounds checks (a SIMD loop) ...
        lo = min(max(max(k, kl), max(ku, 0)), n)
        hi = max(min(n + min(min(k, kl), ku), n), lo)
        s_own = own[lo - k : hi - k]
        s_low = lower[lo - kl : hi - kl]
        s_up = upper[lo - ku : hi - ku]
        m_mid = predicted[lo:hi]
        w_mid = weight[lo:hi]
        d_mid = dst[lo:hi]
        g_mid = marginal[lo:hi]
        middle = np.float32(0.0)  # a float32 sum: a SIMD reduction (partial sums)
        for i in range(hi - lo):
            w = (a * s_own[i] + b * (s_low[i] + s_up[i]) + c * m_mid[i] + base) * w_mid[i]
            d_mid[i] = w
            g_mid[i] += w
            middle += w
        mass += float(middle)
        # ... and near the ends, where a shifted row may have nothing to give.
        for end in range(2):
            start, stop = (0, lo) if end == 0 else (hi, n)
            for i in range(start, stop):
                v = c * predicted[i] + base
                if 0 <= i - k < n:
                    v += a * own[i - k]
                if 0 <= i - kl < n:
                    v += b * lower[i - kl]
                if 0 <= i - ku < n:
                    v += b * upper[i - ku]
                w = v * weight[i]
                dst[i] = w
                marginal[i] += w
                mass += float(w)
        row_mass[j] = mass
        z += mass
    if not z > 0.0:
        # The evidence underflowed wherever the layer holds mass: start again from the prior,
        # weighed by the evidence alone.
        z = 0.0
        for i in range(n):
            marginal[i] = 0.0
        for j in range(n_v):
            row = out[j]
            fresh = np.float32(prior[j] / n)
            mass = 0.0
            for i in range(n):
                w = fresh * weight[i]
                row[i] = w
                marginal[i] += w
                mass += float(w)
            row_mass[j] = mass
            z += mass
    prior_scale = np.float32(scale)  # stay + neighbour + jump = 1: the mixing keeps the mass
    prior_base = np.float32(rate / n)
    for i in range(n):
        predicted[i] = predicted[i] * prior_scale + prior_base
    inv = np.float32(1.0 / z)
    for i in range(n):
        marginal[i] *= inv
    for j in range(n_v):
        row_mass[j] /= z
    return z


def jitter(p, out, shares, breaks):
    """Row by row, ``out[j, i] = (1 - s) p[j, i] + s / 2 (p[j, i - 1] + p[j, i + 1])`` with
    ``s = shares[j]`` (nothing beyond the route's ends: what would come from there is 0, and
    what leaves is lost, as in the move).  The layer before the move: a share ``s`` of row
    ``j`` ends the frame one place ahead of or behind where its velocity takes it, half each
    way (moving then blurring is blurring then moving, away from the ends).  A break of the
    map (``breaks``: the first places of the stretches after one, increasing, in ``1 .. n -
    1``) is an end too: nothing moves between places ``b - 1`` and ``b``.  ``p`` is only
    read."""
    n_v, n = p.shape
    n_b = breaks.shape[0]
    for j in range(n_v):
        src = p[j]
        dst = out[j]
        keep = np.float32(1.0 - shares[j])
        side = np.float32(0.5 * shares[j])
        if n == 1:
            dst[0] = keep * src[0]
            continue
        dst[0] = keep * src[0] + side * src[1]
        dst[n - 1] = keep * src[n - 1] + side * src[n - 2]
        mid = dst[1 : n - 1]
        left = src[: n - 2]
        own = src[1 : n - 1]
        right = src[2:]
        for i in range(n - 2):
            mid[i] = keep * own[i] + side * (left[i] + right[i])
        zero = np.float32(0.0)
        for m in range(n_b):
            # The two places beside the break, each without its neighbour across it.  Place
            # b keeps the one ahead (where b + 1 is a break too, the next pass writes place b
            # again, without it); place b - 1 the one behind, unless b - 1 is a break too.
            b = breaks[m]
            ahead = zero
            if b + 1 < n:
                ahead = src[b + 1]
            dst[b] = keep * src[b] + side * ahead
            behind = zero
            if b >= 2 and not (m > 0 and breaks[m - 1] == b - 1):
                behind = src[b - 2]
            dst[b - 1] = keep * src[b - 1] + side * behind


def likeness(row, last):
    """The correlation of the score ``row`` with the ``last`` one, in one pass; then ``row``
    is copied into ``last``.  0 where either row is constant.  The sums are float64 sums of
    each row less its first value (a shift that keeps the variances from cancelling when a
    row's values are large and close together)."""
    n = row.shape[0]
    a0 = float(row[0])
    b0 = float(last[0])
    sa = 0.0
    sb = 0.0
    saa = 0.0
    sbb = 0.0
    sab = 0.0
    for i in range(n):
        a = float(row[i]) - a0
        b = float(last[i]) - b0
        sa += a
        sb += b
        saa += a * a
        sbb += b * b
        sab += a * b
        last[i] = row[i]
    va = saa - sa * sa / n
    vb = sbb - sb * sb / n
    if not (va > 0.0 and vb > 0.0):
        return 0.0
    return (sab - sa * sb / n) / math.sqrt(va * vb)


def variation(row, lo, hi):
    """How much neighbouring places' scores differ: the mean absolute difference between
    consecutive places' scores over the whole ``row``, and over places ``lo`` to ``hi``
    (inclusive); 0 where there is no pair."""
    n = row.shape[0]
    total = 0.0
    for i in range(1, n):
        total += abs(float(row[i]) - float(row[i - 1]))
    local = 0.0
    for i in range(lo + 1, hi + 1):
        local += abs(float(row[i]) - float(row[i - 1]))
    whole = total / (n - 1) if n > 1 else 0.0
    near = local / (hi - lo) if hi > lo else 0.0
    return whole, near


def leave_at_breaks(p, shifts, breaks):
    """Take off what each moving row of ``p`` (float32, changed in place) would carry across a
    break of the map this frame, and share it out equally over the row's units that land on
    the route without crossing one.

    Row ``j`` moves ``shifts[j]`` whole places; ``breaks`` are the first places of the
    stretches after the breaks, increasing.  Unit ``i`` crosses when a break ``b`` lies in
    ``(i, i + k]`` (``k > 0``) or ``(i + k, i]`` (``k < 0``): forwards, the ``k`` units before
    each break; backwards, the ``-k`` units from it (taken once where two breaks' units
    overlap).  A row none of whose units lands (a move longer than the route) only loses what
    crossed, as its move would.  The breaks must lie in ``1 .. n - 1`` (the filter checks them
    before the first frame): compiled, nothing checks the indices here.
    """
    n_v, n = p.shape
    n_b = breaks.shape[0]
    for j in range(n_v):
        k = shifts[j]
        if k == 0:
            continue
        lo = 0 if k > 0 else -k  # (the units whose move lands on the route: lo .. hi - 1)
        hi = n - k if k > 0 else n
        gone = 0.0
        crossed = 0  # (crossing units among those that land)
        for m in range(n_b):
            b = breaks[m]
            if k > 0:
                first = max(b - k, 0)
                if m > 0:
                    first = max(first, breaks[m - 1])
                stop = b
            else:
                first = b
                stop = min(b - k, n)
                if m + 1 < n_b:
                    stop = min(stop, breaks[m + 1])
            for i in range(first, stop):
                gone += float(p[j, i])
                p[j, i] = 0.0
                if lo <= i < hi:
                    crossed += 1
        landing = hi - lo - crossed
        if gone > 0.0 and landing > 0:
            share = np.float32(gone / landing)
            for i in range(lo, hi):
                p[j, i] += share
            for m in range(n_b):  # (and the crossing units stay empty)
                b = breaks[m]
                first = max(b - k, 0) if k > 0 else b
                stop = b if k > 0 else min(b - k, n)
                for i in range(first, stop):
                    p[j, i] = 0.0


def repeats(row, last):
    """Whether ``row`` equals ``last`` place for place (stops at the first difference)."""
    for i in range(row.shape[0]):
        if row[i] != last[i]:
            return False
    return True


PLAIN = {
    "advance": advance,
    "jitter": jitter,
    "window_sums": window_sums,
    "exceedance": exceedance,
    "likeness": likeness,
    "repeats": repeats,
    "variation": variation,
    "leave_at_breaks": leave_at_breaks,
}

"""The place-velocity layer's per-frame updates, compiled with numba like the other kernels.

The layer holds one unit per (velocity, place) pair; its activity ``P[j, i]`` is the
probability that the robot is at place ``i`` moving ``velocities[j]`` places per frame
(see "The place-velocity layer" on the user guide's CANN page).  Each function is written
once, as explicit loops over places, and runs compiled or as plain Python (``_kernels``).
"""

from __future__ import annotations

import numpy as np


def propagate(p, spare, shifts, stay, neighbour, jump, redraw, prior, floor_rate):
    """Move every velocity row of ``p`` along the route, mix velocities, re-seed; in place.

    Row ``j`` moves by ``shifts[j]`` places (what enters at the open end is 0; what leaves
    is lost).  Then each unit keeps ``stay`` of its activity, gives ``neighbour / 2`` to each
    neighbouring velocity (the rows at the ends keep the share that would leave the bank),
    and every row receives ``jump * redraw[j]`` of the place's total over velocities (a
    velocity drawn afresh from ``redraw``: a stop or a start).  Finally the layer is normalised to
    ``1 - floor_rate`` and ``floor_rate * prior[j] / n`` is added to every unit (the robot may
    be anywhere: relocation).  ``spare`` is scratch of ``p``'s shape.  Returns the mass that
    was left after the move (before normalising).
    """
    n_v, n = p.shape
    for j in range(n_v):
        k = shifts[j]
        dst = spare[j]
        src = p[j]
        lo = min(max(k, 0), n)
        hi = max(min(n + k, n), lo)
        for i in range(lo):
            dst[i] = 0.0
        mid = dst[lo:hi]
        part = src[lo - k : hi - k]
        for i in range(hi - lo):
            mid[i] = part[i]
        for i in range(hi, n):
            dst[i] = 0.0
    total = 0.0
    for j in range(n_v):
        row = spare[j]
        for i in range(n):
            total += float(row[i])
    marginal = np.zeros(n, np.float32)
    for j in range(n_v):
        row = spare[j]
        for i in range(n):
            marginal[i] += row[i]
    scale = (1.0 - floor_rate) / total if total > 0.0 else 0.0
    half = 0.5 * neighbour
    for j in range(n_v):
        lower = spare[max(j - 1, 0)]
        upper = spare[min(j + 1, n_v - 1)]
        own = spare[j]
        out = p[j]
        drawn = np.float32(jump * redraw[j])
        base = np.float32(floor_rate * prior[j] / n if total > 0.0 else prior[j] / n)
        a = np.float32(stay * scale)
        b = np.float32(half * scale)
        c = np.float32(scale) * drawn
        for i in range(n):
            out[i] = a * own[i] + b * (lower[i] + upper[i]) + c * marginal[i] + base
    return total


def observe(p, x, gain, marginal):
    """Weigh every unit by ``exp(gain * (x[i] - max(x)))``, normalise, and write the place
    marginal (the sum over velocities) into ``marginal``.  Returns the normaliser's log:
    ``log(sum_ij p[j, i] exp(gain * x[i]))`` of the activity before the update.
    """
    n_v, n = p.shape
    top = x[0]
    for i in range(n):
        if x[i] > top:
            top = x[i]
    weight = np.empty(n, np.float32)
    for i in range(n):
        weight[i] = np.exp(np.float32(gain) * (x[i] - top))
    for i in range(n):
        marginal[i] = 0.0
    for j in range(n_v):
        row = p[j]
        for i in range(n):
            v = row[i] * weight[i]
            row[i] = v
            marginal[i] += v
    total = 0.0
    for i in range(n):
        total += float(marginal[i])
    inv = np.float32(1.0 / total)
    for j in range(n_v):
        row = p[j]
        for i in range(n):
            row[i] *= inv
    for i in range(n):
        marginal[i] *= inv
    return np.log(total) + gain * float(top)


def window_sums(marginal, radius, out):
    """``out[i]`` = the sum of ``marginal`` over places ``i - radius .. i + radius`` (clipped
    at the route's ends), in float64 running sums.  Returns the index of the largest (the
    first of equals)."""
    n = marginal.shape[0]
    total = 0.0
    for i in range(min(radius, n)):
        total += float(marginal[i])
    best = 0
    top = -1.0
    for i in range(n):
        enter = i + radius
        if enter < n:
            total += float(marginal[enter])
        leave = i - radius - 1
        if leave >= 0:
            total -= float(marginal[leave])
        value = max(total, 0.0)
        out[i] = value
        if value > top:
            top = value
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
    """One frame of the layer in two passes: :func:`propagate` then :func:`observe` fused.

    ``p`` holds the activity (any positive scale: it is normalised here); ``out`` receives the
    new activity, weighted by the evidence ``weight`` (``exp(gain * (x - max x))``) but not
    normalised.  Writes the prior's place marginal (after the move, before the evidence) into
    ``predicted``, the posterior's (normalised) into ``marginal`` and the posterior mass of
    every velocity row (normalised) into ``row_mass``.  With ``shifts`` all equal to a
    negative of at least ``n``, or every unit at 0, the layer starts again from
    ``prior / n``.  Returns the posterior's normaliser (the sum of ``out``).
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


PLAIN = {
    "advance": advance,
    "propagate": propagate,
    "observe": observe,
    "window_sums": window_sums,
    "exceedance": exceedance,
}

"""The CANN's per-frame updates: one implementation, compiled with numba.

Each function below is written once, as explicit loops over places (fused: each pass over
the route does as much as it can), so that numba compiles it to SIMD loops
(:func:`flyvpr._numba.jit`, with reassociation for the sums).  :func:`get_kernels` returns
the compiled functions.  For tests and mutation testing the same functions also run
uncompiled: ``FLYVPR_CANN_NUMBA=0`` in the environment (read at import) or ``USE_NUMBA =
False`` (read when the state is allocated), as does numba's own ``NUMBA_DISABLE_JIT=1``;
both give the same results up to the order of floating-point sums, the uncompiled ones
about two hundred times slower per frame.  The measured costs are on the user guide's CANN
page ("Cost").
"""

from __future__ import annotations

import os

import numpy as np

#: compile the kernels with numba (False: run the same functions uncompiled, for tests)
USE_NUMBA = os.environ.get("FLYVPR_CANN_NUMBA", "1") != "0"

#: kernel radius in units of the excitation width
KERNEL_RADIUS = 3.0
#: added to each place's running input variance before dividing by its square root
VAR_FLOOR = 0.1
#: places per block of an Euler step: a block is rescanned for firing units only when some
#: potential in it is above threshold
BLOCK = 512


def excitation_kernel(strength: float, width: float) -> np.ndarray:
    """Recurrent excitation weights ``k_d`` for place distances ``d = -R..R``.

    ``k_d = strength * exp(-d^2 / (2 width^2)) / (sqrt(2 pi) width)`` with
    ``R = max(1, ceil(3 width))``: a Gaussian of the distance, as the authors' CANN demo
    (which uses ``strength = 3.5`` and ``width = 1``).  The weights sum to about ``strength``
    (exactly, up to the tails beyond ``3 width``, for widths of a place or more).

    Returns
    -------
    ndarray of float32, shape (2R + 1,)

    Examples
    --------
    >>> excitation_kernel(3.5, 1.0).shape
    (7,)
    """
    radius = max(1, int(np.ceil(KERNEL_RADIUS * width)))
    d = np.arange(-radius, radius + 1, dtype=np.float64)
    k = strength * np.exp(-0.5 * (d / width) ** 2) / (np.sqrt(2.0 * np.pi) * width)
    return k.astype(np.float32)


def shift(a, k, fill):
    """Shift the 1-d array ``a`` by ``k`` places in place, filling what enters with ``fill``.

    Element by element in the direction that reads each value before it is overwritten (no
    copy of the array; compiled, a memmove).
    """
    n = a.shape[0]
    if k >= n or -k >= n:
        a[:] = fill
    elif k > 0:
        src = a[: n - k]
        dst = a[k:]
        for i in range(n - k - 1, -1, -1):
            dst[i] = src[i]
        a[:k] = fill
    elif k < 0:
        src = a[-k:]
        dst = a[: n + k]
        for i in range(n + k):
            dst[i] = src[i]
        a[n + k :] = fill


def normalise(
    x,
    mean,
    var,
    take_log,
    tiny,
    rate,
    var_rate,
    adapt,
    adapt_var,
    prior_var,
    floor,
    clip,
    gain,
    mix,
    read,
):
    """The input row ``x`` (float32, in place) -> ``gain`` times its adapted, clipped z-scores.

    ``take_log``: first the log of the row (floored at ``tiny``).  A (numerically) constant row
    gives zeros.  ``adapt``: subtract each place's running mean ``mean`` (updated in place
    with weight ``rate``); ``adapt_var``: then divide by the square root of its running
    variance ``var`` (weight ``var_rate``) plus ``floor``: of the frames before this one when
    ``prior_var`` (a frame's own peak then does not damp itself), else this one's included.
    Then clip to ``[-clip, clip]``.  ``read`` (float64, as long as the row, or empty for
    none): ``mix`` times that plus ``1 - mix`` times the plain z-score (0 for a constant row).
    Three passes over the row: its mean, its spread, then the rest fused.
    """
    if take_log:
        x[:] = np.log(np.maximum(x, tiny))
    n = x.shape[0]
    # The mean in float64: of a constant row it is exactly the row's value.
    total = 0.0
    for i in range(n):
        total += float(x[i])
    centre = np.float32(total / n)
    squares = 0.0
    for i in range(n):
        d = float(x[i] - centre)
        squares += d * d
    spread = np.sqrt(squares / n)
    # A (numerically) constant row says nothing about the place.  (The spread is compared
    # with 1e-6 alone: max |x - centre| <= sqrt(n) * spread, so against 1e-6 times the largest
    # deviation the spread of any row shorter than 1e12 places passes.)
    scale = np.float32(1.0 / spread) if spread > 1e-6 else np.float32(0.0)
    keep, fresh = np.float32(1.0 - rate), np.float32(rate)
    var_keep, var_fresh = np.float32(1.0 - var_rate), np.float32(var_rate)
    low, high = np.float32(-clip), np.float32(clip)
    floor32, gain32 = np.float32(floor), np.float32(gain)
    blend = read.shape[0] == n
    for i in range(n):
        v = (x[i] - centre) * scale
        plain = v
        if adapt:
            m = mean[i] * keep + v * fresh
            mean[i] = m
            v = v - m
            if adapt_var:
                before = var[i]
                q = before * var_keep + (v * v) * var_fresh
                var[i] = q
                v = v / np.sqrt((before if prior_var else q) + floor32)
        x[i] = min(max(v, low), high) * gain32
        if blend:
            read[i] = mix * float(x[i]) + (1.0 - mix) * float(plain) if scale > 0 else 0.0


def update_traces(old, new, shifts, keeps, coefs, x):
    """Leaky evidence traces moved along the route: ``new`` from ``old`` and the input ``x``.

    ``old`` and ``new`` have shape (n_currents, n_rows, n); row ``j`` of current ``c`` becomes
    ``shift(old[c, j], shifts[j]) * keeps[c] + x * coefs[c]``, with zero evidence entering at
    the open end.  One pass per row and current.
    """
    n = x.shape[0]
    for c in range(old.shape[0]):
        keep = keeps[c]
        coef = coefs[c]
        for j in range(old.shape[1]):
            k = shifts[j]
            lo = min(max(k, 0), n)  # dst[lo:hi] reads old[c, j, lo - k:hi - k]
            hi = max(min(n + k, n), lo)
            dst = new[c, j]
            # Slices indexed from 0: numba drops its negative-index checks and the loop
            # becomes SIMD.
            src = old[c, j, lo - k : hi - k]
            mid = dst[lo:hi]
            x_mid = x[lo:hi]
            for i in range(hi - lo):
                mid[i] = src[i] * keep + x_mid[i] * coef
            for i in range(lo):
                dst[i] = x[i] * coef
            for i in range(hi, n):
                dst[i] = x[i] * coef


def evidence_stats(traces, evidence, stride, centre, spread):
    """Per bank row ``j``: its evidence and that evidence's sampled mean and spread.

    ``evidence[j]`` becomes the sum of ``traces[:, j]`` over the currents (with one current
    ``evidence`` must be ``traces[0]`` and is left as it is); ``centre[j]`` and ``spread[j]``
    the mean and standard deviation of ``evidence[j, ::stride]`` (float64 sums).
    """
    n_cur, n_rows, n = traces.shape
    m = (n + stride - 1) // stride
    gathered = np.empty(m, np.float32)  # contiguous: the sums below are SIMD loops
    for j in range(n_rows):
        row = evidence[j]
        if n_cur > 1:
            row[:] = traces[0, j]
            for c in range(1, n_cur):
                src = traces[c, j]
                for i in range(n):
                    row[i] = row[i] + src[i]
        sample = row
        if stride > 1:
            for i in range(m):
                gathered[i] = row[i * stride]
            sample = gathered
        total = 0.0
        for i in range(m):
            total += float(sample[i])
        mu = total / m
        squares = 0.0
        for i in range(m):
            d = float(sample[i]) - mu
            squares += d * d
        centre[j] = mu
        spread[j] = np.sqrt(squares / m)


def integrate(u, s, h, decay, theta, tonic, hw, hk, n_steps):
    """``n_steps`` Euler steps of ``tau du/dt = -u + K * r - inhibition * g + s`` on ``u``.

    ``h = dt / tau``, ``decay = 1 - h``, ``hw = h * inhibition``, ``hk = h * K``.  Only units
    above ``theta`` fire (rate ``min(u - theta, 1)``); the inhibitor's rate ``g`` is the sum of
    the rates, at least ``tonic``, and follows them within the step.  The recurrent
    excitation is spread from the firing units only.  Returns the last step's ``g``.  Per
    step one pass over the route, which also marks the blocks of ``BLOCK`` places holding a
    unit above threshold; the firing units are then looked for in the marked blocks only
    (a pass that marks them comes before the first step).  Candidates far apart along the
    route (a route that passes one place twice) cost a block each, not the stretch between.
    """
    n = u.shape[0]
    radius = (hk.shape[0] - 1) // 2
    n_blocks = (n + BLOCK - 1) // BLOCK
    hot = np.zeros(n_blocks, np.bool_)  # blocks holding a unit above threshold
    n_hot = 0
    for b in range(n_blocks):
        u_block = u[b * BLOCK : min(b * BLOCK + BLOCK, n)]
        above = 0  # a count, not a branch: the pass stays a SIMD loop
        for i in range(u_block.shape[0]):
            above += u_block[i] > theta
        hot[b] = above > 0
        n_hot += above > 0
    g = tonic
    for _ in range(n_steps):
        # The firing units and their rates, from the potentials at the start of the step
        # (in route order, so the rates are summed in that order).
        firing = np.empty(n_hot * BLOCK, np.int64)
        rates = np.empty(n_hot * BLOCK, np.float32)
        total = 0.0
        count = 0
        for b in range(n_blocks):
            if hot[b]:
                for i in range(b * BLOCK, min(b * BLOCK + BLOCK, n)):
                    if u[i] > theta:
                        r = min(u[i] - theta, np.float32(1.0))
                        firing[count] = i
                        rates[count] = r
                        total += float(r)
                        count += 1
        g = max(total, tonic) if count else tonic
        inhibit = np.float32(hw * g)
        n_hot = 0
        for b in range(n_blocks):
            u_block = u[b * BLOCK : min(b * BLOCK + BLOCK, n)]
            s_block = s[b * BLOCK : min(b * BLOCK + BLOCK, n)]
            above = 0
            for i in range(u_block.shape[0]):
                v = u_block[i] * decay + s_block[i] * h - inhibit
                u_block[i] = v
                above += v > theta
            hot[b] = above > 0
        # The recurrent excitation, spread from each firing unit over its neighbours (never
        # negative, so it can only add units above threshold).
        for f in range(count):
            i = firing[f]
            r = rates[f]
            for t in range(max(i - radius, 0), min(i + radius + 1, n)):
                u[t] += hk[t - i + radius] * r
                if u[t] > theta:
                    hot[t // BLOCK] = True
        for b in range(n_blocks):
            n_hot += hot[b]
    return g


def relocate(u, s, p, q, radius, floor, margin, rest):
    """Relocation: move the packet peaking at ``p`` to place ``q`` if ``q``'s evidence leads.

    ``q``'s evidence must exceed ``floor`` and the packet's own (the most evidence within
    ``radius`` of ``p``) by ``margin``, and ``q`` must lie more than ``2 radius`` places from
    ``p``; then the potentials of the ``2 radius + 1`` units around ``p`` are copied around
    ``q`` (clipped at the route's ends) and those around ``p`` set to ``rest``.  Returns
    whether the packet moved.  The caller checks that ``p`` is above threshold.
    """
    n = u.shape[0]
    if not s[q] > floor or abs(q - p) <= 2 * radius:
        return False
    a0 = max(p - radius, 0)
    b0 = min(p + radius + 1, n)
    if not s[q] - s[a0:b0].max() > margin:
        return False
    packet = np.full(2 * radius + 1, rest, np.float32)
    packet[a0 - (p - radius) : b0 - (p - radius)] = u[a0:b0]
    u[a0:b0] = rest
    a = max(q - radius, 0)
    b = min(q + radius + 1, n)
    u[a:b] = packet[a - (q - radius) : b - (q - radius)]
    return True


_PLAIN = {
    "shift": shift,
    "normalise": normalise,
    "update_traces": update_traces,
    "evidence_stats": evidence_stats,
    "integrate": integrate,
    "relocate": relocate,
}
_compiled: dict = {}  # compiled tables by name, on first use: ``import flyvpr`` skips numba


def get_kernels(n_places: int = 0, table: str = "attractor") -> tuple[dict, bool]:
    """The kernels of ``table`` by name, and whether they are compiled (``n_places`` is not
    used).  Tables: ``"attractor"`` (this module's) and ``"layer"`` (the place-velocity
    layer's, :mod:`._layer`, with this module's ``normalise``)."""
    plain = _tables()[table]
    if not USE_NUMBA:
        return plain, False
    if table not in _compiled:  # pragma: no mutate block (numba's options)
        from ..._numba import jit

        # fastmath: SIMD sums (flyvpr._numba's policy); numpy's error model (a division by
        # zero gives inf, as in the plain functions, instead of raising)
        _compiled[table] = {
            name: jit(f, fastmath=True, error_model="numpy") for name, f in plain.items()
        }
    return _compiled[table], True


def _tables() -> dict:
    from . import _layer

    return {"attractor": _PLAIN, "layer": {**_layer.PLAIN, "normalise": normalise}}

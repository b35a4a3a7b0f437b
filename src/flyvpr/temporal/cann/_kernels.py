"""The CANN's per-frame updates: one implementation, compiled with numba where it can be.

Each function below is written once, in array operations (no loop over places), so that it
runs as plain numpy and, unchanged, compiles with ``numba.njit``.  :func:`get_kernels` returns
the compiled functions when numba is importable, :data:`USE_NUMBA` is true and the route has
at most :data:`COMPILED_MAX_PLACES` places, the plain ones otherwise; both give the same
results up to float rounding.  ``FLYVPR_CANN_NUMBA=0`` in the environment (read at import) or
``USE_NUMBA = False`` (read when the state is allocated) selects the plain functions, as does
numba's own ``NUMBA_DISABLE_JIT=1``.

Why the size limit: compiled, these array operations save numpy's per-call overhead, which
dominates on short routes, but numba's loops over array slices do not vectorise as numpy's
do.  Per frame with the defaults (shared 2-core machine, noisy): 1000 places 132 us compiled
against 222 us plain; 35,768 places 2362 us against 840 us.
"""

from __future__ import annotations

import logging
import os

import numpy as np

logger = logging.getLogger(__name__)

#: compile the kernels with numba when it is importable (else, or when False: plain numpy)
USE_NUMBA = os.environ.get("FLYVPR_CANN_NUMBA", "1") != "0"

#: longest route (places) on which the compiled kernels are used (see the module docstring)
COMPILED_MAX_PLACES = 4096
#: kernel radius in units of the excitation width
KERNEL_RADIUS = 3.0
#: added to each place's running input variance before dividing by its square root
VAR_FLOOR = 0.1


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
    """Shift the 1-d array ``a`` by ``k`` places in place, filling what enters with ``fill``."""
    n = a.shape[0]
    if k >= n or -k >= n:
        a[:] = fill
    elif k > 0:
        a[k:] = a[: n - k].copy()
        a[:k] = fill
    elif k < 0:
        a[: n + k] = a[-k:].copy()
        a[n + k :] = fill


def normalise(x, mean, var, take_log, tiny, rate, var_rate, adapt, adapt_var, floor, clip, gain):
    """The input row ``x`` (float32, in place) -> ``gain`` times its adapted, clipped z-scores.

    ``take_log``: first the log of the row (floored at ``tiny``).  A (numerically) constant row
    gives zeros.  ``adapt``: subtract each place's running mean ``mean`` (updated in place
    with weight ``rate``); ``adapt_var``: then divide by the square root of its running
    variance ``var`` (weight ``var_rate``) plus ``floor``.  Then clip to ``[-clip, clip]``.
    """
    if take_log:
        x[:] = np.log(np.maximum(x, tiny))
    n = x.shape[0]
    # The mean in float64: of a constant row it is exactly the row's value.
    centre = np.float32(x.astype(np.float64).sum() / n)
    x -= centre
    spread = np.sqrt((x.astype(np.float64) ** 2).sum() / n)
    if not spread > 1e-6 * max(1.0, np.abs(x).max()):
        x[:] = 0.0  # a constant row says nothing about the place
    else:
        x *= np.float32(1.0 / spread)
    if adapt:
        mean *= np.float32(1.0 - rate)
        mean += x * np.float32(rate)
        x -= mean
        if adapt_var:
            var *= np.float32(1.0 - var_rate)
            var += (x * x) * np.float32(var_rate)
            x /= np.sqrt(var + np.float32(floor))
    x[:] = np.minimum(np.maximum(x, np.float32(-clip)), np.float32(clip))
    x *= np.float32(gain)


def update_traces(old, new, shifts, keeps, coefs, x):
    """Leaky evidence traces moved along the route: ``new`` from ``old`` and the input ``x``.

    ``old`` and ``new`` have shape (n_currents, n_rows, n); row ``j`` of current ``c`` becomes
    ``shift(old[c, j], shifts[j]) * keeps[c] + x * coefs[c]``, with zero evidence entering at
    the open end.  Loops over the few rows and currents only.
    """
    n = x.shape[0]
    fresh = np.empty_like(x)
    for c in range(old.shape[0]):
        keep = keeps[c]
        np.multiply(x, coefs[c], fresh)
        for j in range(old.shape[1]):
            k = shifts[j]
            dst = new[c, j]
            src = old[c, j]
            # Written through output arguments: no temporary arrays, numpy or compiled.
            if 0 <= k < n:
                np.multiply(src[: n - k], keep, dst[k:])
                np.add(dst[k:], fresh[k:], dst[k:])
                dst[:k] = fresh[:k]
            elif -n < k < 0:
                np.multiply(src[-k:], keep, dst[: n + k])
                np.add(dst[: n + k], fresh[: n + k], dst[: n + k])
                dst[n + k :] = fresh[n + k :]
            else:
                dst[:] = fresh


def integrate(u, s, h, decay, theta, tonic, hw, hk, n_steps):
    """``n_steps`` Euler steps of ``tau du/dt = -u + K * r - inhibition * g + s`` on ``u``.

    ``h = dt / tau``, ``decay = 1 - h``, ``hw = h * inhibition``, ``hk = h * K``.  Only units
    above ``theta`` fire (rate ``min(u - theta, 1)``); the inhibitor's rate ``g`` is the sum of
    the rates, at least ``tonic``, and follows them within the step.  The recurrent
    excitation is a short convolution over the stretch the firing units span.  Returns the
    last step's ``g``.
    """
    n = u.shape[0]
    radius = (hk.shape[0] - 1) // 2
    drive = s * h
    g = tonic
    for _ in range(n_steps):
        active = np.flatnonzero(u > theta)
        g = tonic
        if active.size:
            lo = active[0]
            rates = np.zeros(active[-1] - lo + 1, np.float32)
            rates[active - lo] = np.minimum(u[active] - theta, np.float32(1.0))
            g = max(rates.astype(np.float64).sum(), tonic)
            excitation = np.convolve(rates, hk)  # hk is symmetric: a correlation too
        u *= decay
        u += drive
        u -= np.float32(hw * g)
        if active.size:
            a = max(lo - radius, 0)
            b = min(active[-1] + radius + 1, n)
            u[a:b] += excitation[a - (lo - radius) : b - (lo - radius)]
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
    "integrate": integrate,
    "relocate": relocate,
}
_compiled = None  # compiled on first use, so that ``import flyvpr`` does not import numba


def _jit(numba, func):  # pragma: no mutate block (numba's options; no-ops under mutmut)
    # Fast-math flags allow SIMD reductions but no fused multiply-adds ("contract"), so the
    # compiled updates round close to numpy's.  cache=True keeps the code on disk; where no
    # cache folder is writable numba refuses it with a RuntimeError, and it compiles in memory.
    opts = {"fastmath": {"nnan", "ninf", "nsz", "reassoc"}, "error_model": "numpy"}
    try:
        return numba.njit(cache=True, **opts)(func)
    except RuntimeError:
        return numba.njit(**opts)(func)


def get_kernels(n_places: int = 0) -> tuple[dict, bool]:
    """The kernels by name for a route of ``n_places``, and whether they are compiled."""
    global _compiled
    if not USE_NUMBA or n_places > COMPILED_MAX_PLACES:
        return _PLAIN, False
    if _compiled is None:
        try:
            import numba
        except ImportError:
            logger.info("numba is not installed; the CANN runs as plain numpy (slower)")
            _compiled = False
        else:
            _compiled = {name: _jit(numba, f) for name, f in _PLAIN.items()}
    if _compiled is False:
        return _PLAIN, False
    return _compiled, True

"""The one way flyvpr compiles a kernel: :func:`jit`, numba's ``njit`` with one policy.

numba is a core dependency: every kernel is compiled, and there is no pure-Python fallback
for a missing numba.  The kernel modules (``frontends/_kenyon_kernels.py``,
``frontends/_pixels_kernels.py``, ``_image_kernels.py`` (the area resize), ``large/_kernels.py`` and
the CANN's ``temporal/cann/_kernels.py``) are imported on first use, never by ``import
flyvpr``, so that importing the package does not import numba.  (The CANN's
``_kernels.USE_NUMBA = False`` runs the same functions uncompiled: a switch for tests and
mutation testing, not a fallback.)

The policy:

* **Cache.** Compiled code is kept on disk (``cache=True``), so only the first run on a
  machine pays the compilation; where no cache folder is writable (a read-only install)
  numba refuses the cache with a ``RuntimeError`` and the kernel compiles in memory.
* **Fast math: off**, so results are bit-reproducible and do not depend on the CPU.  The
  one exception, ``fastmath=True``, allows reassociation only (with ``nnan``, ``ninf`` and
  ``nsz``): LLVM may then split a float sum into SIMD lanes.  It is used where the order of a
  sum's terms is not part of the result's meaning and the tests compare to a tolerance: the
  CANN's per-frame updates and ``pixels``' sums of absolute differences (both serial: see
  below).  Never fused multiply-adds (``contract``) or approximate functions (``afn``,
  ``arcp``): the compiled results stay within float rounding of numpy's.
* **Never ``parallel=True`` with ``fastmath=True``.**  numba compiles a ``prange`` loop's body
  as a library of its own and links it into the function, and the object code it caches is
  optimised again after that linking: with reassociation the cached code may sum in another
  order than the code the compiling process ran, so results changed in the last bit between
  the run that compiled a kernel and the runs that loaded it (``pixels``' distances did, and the
  CANN's thresholds turned that into different benchmark rows).  A reassociated kernel is
  serial (``nogil``), and its caller spreads it over threads (see
  ``frontends/_pixels_kernels.py``).
"""

from __future__ import annotations

import numba

#: the fast-math flags of ``jit(..., fastmath=True)``: reassociation, without FMA or
#: approximations (see the module's docstring)
REASSOCIATE = frozenset({"nnan", "ninf", "nsz", "reassoc"})


def jit(fn=None, *, parallel: bool = False, fastmath: bool = False, **options):
    """Compile ``fn`` with numba under flyvpr's policy (see the module's docstring).

    Parameters
    ----------
    fn : function, optional
        Without it, ``jit(...)`` returns a decorator.
    parallel : bool, default False
        numba's ``parallel`` (``numba.prange`` loops run on its threads).
    fastmath : bool, default False
        Allow the reassociation of float operations (:data:`REASSOCIATE`).
    **options
        Other ``numba.njit`` options (``nogil``, ``error_model``).
    """
    if parallel and fastmath:
        raise ValueError(
            "parallel=True with fastmath=True: the cached code may sum in another order than "
            "the compiled code (see flyvpr._numba); make the kernel serial and thread its caller"
        )
    flags = {"parallel": parallel, **options}
    if fastmath:
        flags["fastmath"] = set(REASSOCIATE)

    def compile_(f):
        try:
            return numba.njit(cache=True, **flags)(f)
        except RuntimeError:  # pragma: no cover - a read-only install without a cache folder
            return numba.njit(**flags)(f)

    return compile_ if fn is None else compile_(fn)

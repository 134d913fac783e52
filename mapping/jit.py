"""Compiled kernels for the per-scan hot path (numba).

A scan's correction and segment extraction work on a few dozen segments: in numpy every
step is a call over arrays of tens of elements, and the calls, not the arithmetic, were
the cost (about 2 ms per Intel scan on the 2-core machine, most of it call overhead).  The
few loops that carry that work are compiled; everything else stays numpy.

Compiled code is cached on disk next to the module (numba's ``cache=True``), or under
``NUMBA_CACHE_DIR`` when set (the systemd unit points it at the service's cache
directory).  Where neither location is writable the kernels compile in memory at first
use, with a warning, rather than fail.  ``NUMBA_DISABLE_JIT=1`` runs them as plain Python
(for a debugger; slow).
"""

from __future__ import annotations

import warnings

import numba


def kernel(fn):
    """``fn`` compiled in nopython mode, cached, releasing the GIL (the daemon maps in a
    thread next to its device threads)."""
    try:
        return numba.njit(cache=True, nogil=True)(fn)
    except RuntimeError as exc:  # no cache locator: a read-only install, no cache dir
        warnings.warn(f"numba cannot cache {fn.__qualname__} ({exc}); compiling in memory",
                      RuntimeWarning, stacklevel=2)
        return numba.njit(cache=False, nogil=True)(fn)

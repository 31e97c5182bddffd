"""Compiled kernels: numba's ``njit`` with on-disk caches kept in step with the sources, and the
helpers every kernel module shares.

Every module that defines a kernel takes :func:`njit` from here. Its first use in a process
runs :func:`graph.kernel_cache.refresh_installed`, before any kernel is defined and so before any
cached kernel loads; importing a package compiles or checks nothing.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba
import numpy as np
from numpy.typing import NDArray

from graph.kernel_cache import refresh_installed

PYTHON_MAX_ITEMS = 50_000
"""Inputs of up to this many items run a kernel as plain Python (:func:`for_size`); about
0.2 s at that size, against 1-3 s to compile each kernel."""

_refreshed = False


def njit(*args: Any, **options: Any) -> Any:
    """``numba.njit``, after the caches of changed sources are cleared (once per process)."""
    global _refreshed
    if not _refreshed:
        _refreshed = True
        refresh_installed()
    return numba.njit(*args, **options)


def read_only(a: Any, dtype: Any) -> NDArray[Any]:
    """``a`` as a C-contiguous array of ``dtype`` that kernels cannot write: a read-only view.

    A map read from its file has read-only arrays, one built in memory writable ones, and numba
    compiles a kernel once per argument type, writability included: every array a kernel only
    reads goes in read-only, whatever its source, so one compile serves both."""
    v = np.ascontiguousarray(a, dtype=dtype).view()
    v.flags.writeable = False
    return v


def interpreted() -> bool:
    """Whether kernels run as plain Python in this process (``NUMBA_DISABLE_JIT``, set by
    :func:`mapmatch.kernels.choose_mode` before the first kernel is defined): ``njit`` then
    returns each function itself, and the few numba-only constructs take their Python stand-ins."""
    return bool(numba.config.DISABLE_JIT)


def py_func(kernel: Any) -> Callable[..., Any]:
    """The Python function of ``kernel``: a dispatcher's ``py_func``, or ``kernel`` itself when
    kernels run interpreted (``NUMBA_DISABLE_JIT``: ``njit`` then returns the function)."""
    return getattr(kernel, "py_func", kernel)  # type: ignore[no-any-return]


def for_size(kernel: Any, items: int) -> Callable[..., Any]:
    """``kernel`` (a numba dispatcher) for an input of ``items`` items: its Python function when
    the input is small (no compile; the same code, so the same results), else the compiled kernel.

    Only for kernels that call no other compiled function (those would compile anyway).
    """
    return py_func(kernel) if items <= PYTHON_MAX_ITEMS else kernel  # type: ignore[no-any-return]

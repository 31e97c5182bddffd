"""The whole compiled match in one call, and the call itself without the dispatch cost.

numba's dispatcher types every argument on every call, which for nested named tuples of
arrays costs tens of microseconds; :class:`CompiledRun` resolves the compiled entry point
once and then calls it directly.
"""

from __future__ import annotations

import threading
from typing import Any

import numba
import numpy as np
from numba import njit

from mapmatch.batch.arrays import Assembly, CandidateArrays, EdgeGeometry, KernelParams, TrackPoints
from mapmatch.batch.lattice import build_lattice
from mapmatch.batch.route import assemble
from mapmatch.batch.viterbi import solve
from mapmatch.routing import Router


@njit(cache=True, nogil=True)
def run(pt, cands, p, geom, router):  # type: ignore[no-untyped-def]
    """Lattice (:func:`build_lattice`), Viterbi (:func:`solve`) and route assembly (:func:`assemble`)."""
    lat = build_lattice(pt, cands, p)
    choice, seg_start, via_u, used_bound = solve(lat, p, router)
    return assemble(pt, lat, choice, seg_start, via_u, used_bound, p, geom, router)


def fresh(a: Any, dtype: Any) -> Any:
    """``a`` as a C-contiguous, writable array of ``dtype`` (copied only when it is not one).

    Every per-call argument of :class:`CompiledRun` goes through this, so their numba types are
    fixed by the code that builds them.
    """
    out = np.asarray(a, dtype=dtype)
    if not (out.flags.c_contiguous and out.flags.writeable):
        out = np.array(out, dtype=dtype, order="C")
    return out


class CompiledRun:
    """Calls :func:`run` through its compiled entry point, resolved on the first call.

    numba's entry point does not check argument types, so every call must pass the types of
    the first: the map's arrays (geometry, router) are one matcher's and never change, and
    the per-call arrays are built by :func:`fresh` with fixed dtypes and ranks.
    """

    def __init__(self) -> None:
        self._entry: Any = None
        self.signature: tuple[Any, ...] = ()
        self._lock = threading.Lock()

    def __call__(
        self, pt: TrackPoints, cands: CandidateArrays, p: KernelParams, geom: EdgeGeometry, router: Router
    ) -> Assembly:
        entry = self._entry
        if entry is None:
            with self._lock:
                if self._entry is None:
                    self.signature = tuple(numba.typeof(a) for a in (pt, cands, p, geom, router))
                    self._entry = run.compile(self.signature)
                entry = self._entry
        return entry(pt, cands, p, geom, router)  # type: ignore[no-any-return]

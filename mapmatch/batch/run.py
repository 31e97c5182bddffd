"""The whole compiled match in one call, and the call itself without the dispatch cost.

Two entry points: :func:`run` takes the candidates (and emissions) the Python side computed,
:func:`run_track` also finds the candidates itself (the common case of one σ and no heading,
where a match is then one compiled call after the projection). numba's dispatcher types every
argument on every call, which for nested named tuples of arrays costs tens of microseconds;
:class:`CompiledRun` resolves the compiled entry point once and then calls it directly.
"""

from __future__ import annotations

import math
import threading
from typing import Any, NamedTuple

import numba
import numpy as np
from numba import njit
from numpy.typing import NDArray

from mapmatch.batch.arrays import Assembly, CandidateArrays, TrackPoints
from mapmatch.batch.lattice import build_lattice, thin
from mapmatch.batch.route import assemble
from mapmatch.batch.viterbi import solve
from mapmatch.gridindex import query_grid


class TrackInput(NamedTuple):
    """One track as :func:`run_track` takes it: WGS84 degrees, their projection to the map's CRS
    (any value where the degrees are invalid), times and odometer readings (empty: none)."""

    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    x: NDArray[np.float64]
    y: NDArray[np.float64]
    time: NDArray[np.float64]
    odo: NDArray[np.float64]


class QueryParams(NamedTuple):
    """The candidate search and thinning part of the batch config, as :func:`run_track` reads it."""

    radius: float
    """``search_radius``."""
    outlier: float
    """``outlier_distance``: a point with no road within ``radius`` looks again this far."""
    k: int
    """``max_candidates``."""
    min_dist: float
    """``interpolate_distance``."""


@njit(cache=True, nogil=True)
def run(pt, cands, p, geom, router):  # type: ignore[no-untyped-def]
    """Lattice (:func:`build_lattice`), Viterbi (:func:`solve`) and route assembly (:func:`assemble`)."""
    lat = build_lattice(pt, cands, p)
    choice, seg_start, via_u, used_bound = solve(lat, p, router)
    return assemble(pt, lat, choice, seg_start, via_u, used_bound, p, geom, router)


@njit(cache=True, nogil=True)
def run_track(ti, q, p, geom, router, grid, gsc):  # type: ignore[no-untyped-def]
    """Validity, thinning, the candidate search (:func:`mapmatch.gridindex.query_grid`, again
    up to the outlier distance for points with no road in the search radius), then :func:`run`
    with distance-only emissions: the same answer as the Python side's steps and :func:`run`."""
    n = len(ti.lat)
    valid = np.zeros(n, dtype=np.bool_)
    xy = np.full((n, 2), np.nan)
    for i in range(n):
        la, lo = ti.lat[i], ti.lon[i]
        if math.isfinite(la) and math.isfinite(lo) and abs(la) <= 90.0 and abs(lo) <= 180.0:
            valid[i] = True
            xy[i, 0] = ti.x[i]
            xy[i, 1] = ti.y[i]
    kept = thin(xy, valid, q.min_dist)
    kidx = np.flatnonzero(kept)
    nk = len(kidx)
    cp, ce, cd, co, cq = query_grid(xy[kidx], q.radius, q.k, grid, gsc)
    count = np.zeros(nk, dtype=np.int64)
    for i in range(len(cp)):
        count[cp[i]] += 1
    lonely = np.flatnonzero(count == 0)
    if len(lonely) and q.outlier > q.radius:
        mp, me, md, mo, mq = query_grid(xy[kidx[lonely]], q.outlier, q.k, grid, gsc)
        # merge by point: a lonely point has no rows in the first answer
        tot = len(cp) + len(mp)
        point = np.empty(tot, dtype=np.int64)
        edge = np.empty(tot, dtype=np.int32)
        dist = np.empty(tot)
        off = np.empty(tot)
        cxy = np.empty((tot, 2))
        a = 0
        b = 0
        for r in range(tot):
            if b < len(mp) and (a >= len(cp) or lonely[mp[b]] < cp[a]):
                point[r], edge[r], dist[r], off[r] = lonely[mp[b]], me[b], md[b], mo[b]
                cxy[r, 0], cxy[r, 1] = mq[b, 0], mq[b, 1]
                b += 1
            else:
                point[r], edge[r], dist[r], off[r] = cp[a], ce[a], cd[a], co[a]
                cxy[r, 0], cxy[r, 1] = cq[a, 0], cq[a, 1]
                a += 1
        cp, ce, cd, co, cq = point, edge, dist, off, cxy
    cands = CandidateArrays(cp, ce.astype(np.int64), co, cq, cd, np.zeros(0), np.zeros(0), np.zeros(0))
    pt = TrackPoints(valid, kept, xy, ti.time, ti.odo, kidx)
    return run(pt, cands, p, geom, router)


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
    """Calls a compiled kernel (:func:`run` unless told) through its entry point, resolved on
    the first call.

    numba's entry point does not check argument types, so every call must pass the types of
    the first: the map's arrays (geometry, router, grid) are one matcher's and never change,
    and the per-call arrays are built by :func:`fresh` with fixed dtypes and ranks.
    """

    def __init__(self, kernel: Any = None) -> None:
        self._kernel = run if kernel is None else kernel
        self._entry: Any = None
        self.signature: tuple[Any, ...] = ()
        self._lock = threading.Lock()

    def __call__(self, *args: Any) -> Assembly:
        entry = self._entry
        if entry is None:
            with self._lock:
                if self._entry is None:
                    self.signature = tuple(numba.typeof(a) for a in args)
                    self._entry = self._kernel.compile(self.signature)
                entry = self._entry
        return entry(*args)  # type: ignore[no-any-return]

"""The whole compiled match in one call, and the call itself without the dispatch cost.

:func:`run_track` is a match: the fixes' validity, thinning and rules, the candidates and
their emissions, then :func:`run` (lattice, Viterbi, route assembly), which also serves the
Python reference steps. numba's dispatcher types every argument on every call, which for nested
named tuples of arrays costs tens of microseconds; :class:`CompiledRun` resolves the compiled
entry point once and then calls it directly. The answer comes back packed in one array
(:func:`mapmatch.batch.packed.pack`), as each array handed to Python costs about a microsecond.
"""

from __future__ import annotations

import math
import threading
from typing import Any, NamedTuple

import numba
import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.arena import (
    Arena,
    borrowed,
    full_b1,
    full_f8,
    full_i8,
    reset,
    take_b1,
    take_f8,
    take_i8,
    take_xy,
)
from mapmatch.batch.arrays import CandidateArrays, EdgeGeometry, KernelParams, TrackPoints
from mapmatch.batch.lattice import (
    bearing_on,
    build_lattice,
    drop_spikes_into,
    lattice_sigma,
    motion_heading_into,
    thin_into,
)
from mapmatch.batch.packed import Packed, pack
from mapmatch.batch.route import assemble
from mapmatch.batch.viterbi import solve
from mapmatch.gridindex import Grid, GridScratch, ScanRows, query_grid
from mapmatch.model import emission_logp_one, heading_kappa_compiled, track_sigma_compiled


class TrackInput(NamedTuple):
    """One track as :func:`run_track` takes it: WGS84 degrees and their projection to the map's
    CRS in one buffer (any projected value where the degrees are invalid), times, and the
    optional columns (empty: none)."""

    pos: NDArray[np.float64]
    """(4, n): longitude, latitude, x, y."""
    time: NDArray[np.float64]
    odo: NDArray[np.float64]
    """Cumulative odometer distance."""
    pos_sigma: NDArray[np.float64]
    """The fixes' own position σ (metres; NaN or <= 0: the configured one)."""
    heading: NDArray[np.float64]
    """Compass degrees, NaN where unknown."""
    speed: NDArray[np.float64]
    """m/s, NaN where unknown (a heading below ``heading_min_speed`` is not trusted)."""


class QueryParams(NamedTuple):
    """The candidate search and thinning part of the batch config, as :func:`run_track` reads it."""

    radius: float
    """``search_radius``."""
    outlier: float
    """``outlier_distance``: a point with no road within ``radius`` looks again this far."""
    k: int
    """``max_candidates``."""
    min_dist: float
    """Metres; fixes closer than this to the previous kept one are interpolated (the
    configured σ)."""


class RuleParams(NamedTuple):
    """The rules :func:`run_track` applies before the lattice (jumps, headings), as it reads them."""

    gps_sigma: float
    """The configured position σ (metres)."""
    spike_sigmas: float
    spike_speed: float
    """m/s; 0: jumps are not dropped."""
    spike_max_time: float
    """Seconds a jump of several fixes may last."""
    motion_sigma: float
    """Degrees; 0: no direction of travel."""
    motion_min_distance: float
    """Metres; the shortest leg that tells the direction (the configured σ)."""
    motion_end_leg_max: float
    """Metres; the longest first or last leg whose end fix takes its direction (0: any)."""
    straight_max_deg: float
    heading_sigma: float
    """Default heading σ (degrees) of a track's own heading."""
    heading_min_speed: float
    track_sigma_max: float
    """The most σ a track's own residuals may give (:func:`track_sigma`); 0: ``gps_sigma``."""
    sigma_min_fixes: int
    """The fewest fixes near a road that give a track's own σ (fewer: ``gps_sigma``)."""
    thin_sigmas: float
    """Fixes are thinned at this many times the track's σ beyond ``gps_sigma``."""
    pos_sigma_floor: float
    """The least σ (metres) of a fix's own accuracy."""
    heading_sigma_floor: float
    """The least heading σ (degrees)."""


class RoadArrays(NamedTuple):
    """Per-edge arrays the emissions read beside the geometry."""

    seg_end: NDArray[np.float64]
    """:func:`mapmatch.batch.lattice.along_lengths`."""
    seg_bearing: NDArray[np.float64]
    """:func:`mapmatch.batch.lattice.segment_bearings`."""


@njit(cache=True, nogil=True, inline="always")
def _run(pt, cands, p, geom, router, ar):  # type: ignore[no-untyped-def]
    """Lattice, Viterbi and assembly; compiled into its callers, as a call of its own copied
    its arguments (hundreds of words of array structs) at every match."""
    lat = build_lattice(pt, cands, p, ar)
    sig = lattice_sigma(pt, cands, p.sigma, lat, ar)
    return assemble(pt, lat, solve(lat, p, router, ar, sig), p, geom, router, ar)


class MatchInputs(NamedTuple):
    """What :func:`run_track` reads besides the track: a
    :class:`~mapmatch.batch.context.Context`'s fields (see
    :data:`~mapmatch.batch.context.CONTEXT_FIELDS`), its arrays borrowed."""

    q: QueryParams
    r: RuleParams
    p: KernelParams
    geom: EdgeGeometry
    roads: RoadArrays
    router: Any
    """:class:`~mapmatch.routing.Router`."""
    grid: Grid
    gsc: GridScratch
    ar: Arena


class TrackFixes(NamedTuple):
    """The track's fixes as the emissions read them: projected, the kept ones, the track's σ."""

    xy: NDArray[np.float64]
    kidx: NDArray[np.int64]
    """The kept fixes' indices."""
    sigma: float
    """:func:`track_sigma`."""


@njit(cache=True, nogil=True, inline="always")
def run_track(ti, mi):  # type: ignore[no-untyped-def]
    """The whole match of one track ``ti`` with ``mi`` (:class:`MatchInputs`): validity,
    thinning and the candidate search (:func:`kept_candidates`), the track's own σ
    (:func:`track_sigma`) and, where it exceeds the configured one, the thinning and search
    again at ``thin_sigmas`` times the excess, jumps (:func:`drop_spikes_into`), emissions with
    the fixes' σ and heading or the direction of travel (:func:`candidate_emissions`), then
    :func:`_run`; working arrays from the arena ``mi.ar`` (:mod:`mapmatch.arena`). Compiled
    into :func:`run_track_in`, its one caller (a call of its own would copy its arguments, as
    :func:`_run`'s would, a noticeable part of a small track's match)."""
    q, r, ar = mi.q, mi.r, mi.ar
    reset(ar)
    valid, xy = _valid_xy(ti.pos, ar)
    kept, kidx, cp, ce, cd, co, cq = kept_candidates(xy, valid, q.min_dist, q, mi.grid, mi.gsc, ar)
    sigma = track_sigma(cp, cd, len(kidx), r.gps_sigma, (r.track_sigma_max, r.sigma_min_fixes), ar)
    # a worse receiver's fixes close together share their error: thinned out further
    far = r.thin_sigmas * (sigma - r.gps_sigma)
    if far > q.min_dist:
        kept, kidx, cp, ce, cd, co, cq = kept_candidates(xy, valid, far, q, mi.grid, mi.gsc, ar)
    # jumps (a fix reached and left in opposite directions too fast) get no candidates
    nojump = take_b1(ar, len(valid))
    nojump[:] = valid
    drop_spikes_into(xy, ti.time, kidx, sigma, r.spike_sigmas, r.spike_speed, r.spike_max_time, nojump)
    rows = _without_jumps(ScanRows(cp, ce, cd, co, cq), kidx, nojump)
    cands = candidate_emissions(ti, TrackFixes(xy, kidx, sigma), rows, r, mi.p, mi.geom, mi.roads, ar)
    pt = TrackPoints(valid, kept, xy, ti.time, ti.odo, kidx)
    return pack(_run(pt, cands, mi.p, mi.geom, mi.router, ar))


@njit(cache=True, nogil=True)
def _valid_xy(pos, ar):  # type: ignore[no-untyped-def]
    """Which fixes are valid (finite WGS84 degrees in range) and their projected positions
    (NaN where not valid), from :class:`TrackInput`'s ``pos``."""
    n = pos.shape[1]
    valid = full_b1(ar, n, False)
    xy = take_xy(ar, n)
    for i in range(n):
        lo, la = pos[0, i], pos[1, i]
        if math.isfinite(la) and math.isfinite(lo) and abs(la) <= 90.0 and abs(lo) <= 180.0:
            valid[i] = True
            xy[i, 0] = pos[2, i]
            xy[i, 1] = pos[3, i]
        else:
            xy[i, 0] = np.nan
            xy[i, 1] = np.nan
    return valid, xy


@njit(cache=True, nogil=True)
def _without_jumps(rows, kidx, nojump):  # type: ignore[no-untyped-def]
    """The candidate ``rows`` (:class:`~mapmatch.gridindex.ScanRows`, by kept point) of the
    fixes that are no jump (``nojump``, by fix), compacted in place."""
    cp, ce, cd, co, cq = rows
    nc = 0
    for i in range(len(cp)):
        if nojump[kidx[cp[i]]]:
            nc += 1
    if nc == len(cp):
        return rows
    c = 0
    for i in range(len(cp)):
        if nojump[kidx[cp[i]]]:
            cp[c], ce[c], cd[c], co[c] = cp[i], ce[i], cd[i], co[i]
            cq[c, 0], cq[c, 1] = cq[i, 0], cq[i, 1]
            c += 1
    return ScanRows(cp[:nc], ce[:nc], cd[:nc], co[:nc], cq[:nc])


@njit(cache=True, nogil=True)
def kept_candidates(xy, valid, min_dist, q, grid, gsc, ar):  # type: ignore[no-untyped-def]
    """The fixes kept by thinning at ``min_dist`` (:func:`thin_into`) and their candidates
    (:func:`mapmatch.gridindex.query_grid`, again up to the outlier distance for fixes with no
    road in the search radius): ``kept, kidx`` and the rows ``point, edge, dist, offset, xy``
    sorted by kept point, nearest first."""
    n = len(valid)
    kept = thin_into(xy, valid, min_dist, full_b1(ar, n, False))
    nk = 0
    for i in range(n):
        if kept[i]:
            nk += 1
    kidx = take_i8(ar, nk)
    kxy = take_xy(ar, nk)
    c = 0
    for i in range(n):
        if kept[i]:
            kidx[c] = i
            kxy[c, 0] = xy[i, 0]
            kxy[c, 1] = xy[i, 1]
            c += 1
    cp, ce, cd, co, cq = query_grid(kxy, q.radius, q.k, grid, gsc, ar)
    count = full_i8(ar, nk, 0)
    for i in range(len(cp)):
        count[cp[i]] += 1
    nl = 0
    for i in range(nk):
        if count[i] == 0:
            nl += 1
    if nl and q.outlier > q.radius:
        lonely = take_i8(ar, nl)
        lxy = take_xy(ar, nl)
        c = 0
        for i in range(nk):
            if count[i] == 0:
                lonely[c] = i
                lxy[c, 0] = kxy[i, 0]
                lxy[c, 1] = kxy[i, 1]
                c += 1
        mp, me, md, mo, mq = query_grid(lxy, q.outlier, q.k, grid, gsc, ar)
        # merge by point: a lonely point has no rows in the first answer
        tot = len(cp) + len(mp)
        point = take_i8(ar, tot)
        edge = take_i8(ar, tot)
        dist = take_f8(ar, tot)
        off = take_f8(ar, tot)
        cxy = take_xy(ar, tot)
        a = 0
        b = 0
        for i in range(tot):
            if b < len(mp) and (a >= len(cp) or lonely[mp[b]] < cp[a]):
                point[i], edge[i], dist[i], off[i] = lonely[mp[b]], me[b], md[b], mo[b]
                cxy[i, 0], cxy[i, 1] = mq[b, 0], mq[b, 1]
                b += 1
            else:
                point[i], edge[i], dist[i], off[i] = cp[a], ce[a], cd[a], co[a]
                cxy[i, 0], cxy[i, 1] = cq[a, 0], cq[a, 1]
                a += 1
        cp, ce, cd, co, cq = point, edge, dist, off, cxy
    return kept, kidx, cp, ce, cd, co, cq


@njit(cache=True, nogil=True)
def run_track_in(ti, c):  # type: ignore[no-untyped-def]
    """:func:`run_track` with everything but the track from one
    :class:`~mapmatch.batch.context.Context` (one pointer to unbox instead of some 80 values),
    all of them :func:`~mapmatch.arena.borrowed` (the caller holds the track and the context
    for the whole call; the answer is a new array, :func:`pack`)."""
    mi = MatchInputs(
        c.q, c.r, borrowed(c.p), borrowed(c.geom), borrowed(c.roads), borrowed(c.router),
        borrowed(c.grid), borrowed(c.gsc), borrowed(c.ar),
    )  # fmt: skip
    return run_track(borrowed(ti), mi)


@njit(cache=True, nogil=True)
def track_sigma(point, dist, nk, sigma, limits, ar):  # type: ignore[no-untyped-def]
    """The track's σ (:func:`mapmatch.model.track_sigma`) from the ``nk`` kept fixes' distances
    to their nearest candidate (rows sorted by point, nearest first); fixes without one do not
    count. ``limits``: the most σ the track may give, and the fewest such fixes that give one
    (fewer: ``sigma``)."""
    most, min_fixes = limits
    if most <= sigma:
        return sigma
    near = take_f8(ar, nk)
    m = 0
    for i in range(len(point)):
        if i == 0 or point[i] != point[i - 1]:
            near[m] = dist[i]
            m += 1
    if m < min_fixes:
        return sigma
    return track_sigma_compiled(near[:m], sigma, most)


@njit(cache=True, nogil=True)
def candidate_emissions(ti, fx, rows, r, p, geom, roads, ar):  # type: ignore[no-untyped-def]
    """The candidate ``rows`` (:class:`~mapmatch.gridindex.ScanRows`) of the kept fixes of
    ``fx`` (:class:`TrackFixes`) with their emissions (:func:`mapmatch.model.emission_logp`,
    computed per candidate in the same float steps), σ (the fix's own when the track ``ti``
    has them, else the track's, ``fx.sigma``). A kept point's heading is the
    track's, else its direction of travel (σ ``motion_sigma``); none where neither is known or
    the fix is slower than ``heading_min_speed``."""
    kidx, sigma = fx.kidx, fx.sigma
    cp, ce, co, cd = rows.point, rows.edge, rows.offset, rows.dist
    nk = len(kidx)
    nc = len(cp)
    # per kept point: σ, heading and its concentration κ
    sig = full_f8(ar, nk, sigma)
    if len(ti.pos_sigma):
        for k in range(nk):
            s = ti.pos_sigma[kidx[k]]
            sig[k] = sigma if math.isnan(s) or s <= 0 else max(s, r.pos_sigma_floor)
    head = full_f8(ar, nk, np.nan)
    kappa = full_f8(ar, nk, 0.0)
    any_head = _fix_headings(ti, fx, r, head, kappa, ar)
    bearing = full_f8(ar, nc, 0.0)
    if any_head:
        bearing_on(ce, co, geom.seg_ptr, roads.seg_end, roads.seg_bearing, bearing)
    emis = take_f8(ar, nc)
    # per candidate σ where it is not the one of the kernels' parameters
    csig = take_f8(ar, nc if len(ti.pos_sigma) or sigma != p.sigma else 0)
    for i in range(nc):
        k = cp[i]
        s = sig[k]
        emis[i] = emission_logp_one(cd[i], s, head[k], bearing[i], kappa[k])
        if len(csig):
            csig[i] = s
    return CandidateArrays(cp, ce, co, rows.xy, cd, emis, csig)


@njit(cache=True, nogil=True)
def _fix_headings(ti, fx, r, head, kappa, ar):  # type: ignore[no-untyped-def]
    """Each kept fix's heading and its concentration κ into ``head`` and ``kappa`` (left as
    they are where it has none): the track's own, else the direction of travel (σ
    ``motion_sigma``); none where the fix is slower than ``heading_min_speed``. Whether any
    fix has one."""
    kidx = fx.kidx
    nk = len(kidx)
    mh = head
    if r.motion_sigma > 0:
        mh = motion_heading_into(
            fx.xy,
            kidx,
            r.motion_min_distance,
            r.straight_max_deg,
            r.motion_end_leg_max,
            full_f8(ar, nk, np.nan),
        )
    any_head = False
    for k in range(nk):
        h = ti.heading[kidx[k]] if len(ti.heading) else np.nan
        hs = r.heading_sigma
        if r.motion_sigma > 0 and math.isfinite(mh[k]) and not math.isfinite(h):
            h = mh[k]
            hs = r.motion_sigma
        slow = len(ti.speed) > 0 and ti.speed[kidx[k]] < r.heading_min_speed
        if math.isnan(h) or slow:
            continue
        head[k] = h
        kappa[k] = heading_kappa_compiled(hs, r.heading_sigma_floor)
        any_head = True
    return any_head


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
    """Calls a compiled kernel (:func:`run_track_in`) through its entry point, resolved on
    the first call.

    numba's entry point does not check argument types, so every call must pass the types of
    the first: the map's arrays (geometry, router, grid) are one matcher's and never change,
    and the per-call arrays are built by :func:`fresh` with fixed dtypes and ranks.
    """

    def __init__(self, kernel: Any) -> None:
        self._kernel = kernel
        self._entry: Any = None
        self.signature: tuple[Any, ...] = ()
        self._lock = threading.Lock()

    def __call__(self, *args: Any) -> Packed:
        if not hasattr(self._kernel, "compile"):  # kernels run as Python: the function itself
            return self._kernel(*args)  # type: ignore[no-any-return]
        entry = self._entry
        if entry is None:
            with self._lock:
                if self._entry is None:
                    self.signature = tuple(numba.typeof(a) for a in args)
                    self._entry = self._kernel.compile(self.signature)
                entry = self._entry
        return entry(*args)  # type: ignore[no-any-return]

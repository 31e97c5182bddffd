"""The position along a path: on a straight road the map cannot show the fix's along-track
error, so the projection is corrected by the learnt fix bias and fused with the turn anchor
carried on by the odometer. Compiled: called by :mod:`mapmatch.online.placement`."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.online.geometry import RoadArrays, hypot, locate, straight
from mapmatch.online.params import PlaceParams

# a position on a path: (j, off, s, dist, px, py, bearing) as in :class:`~mapmatch.online.state.PathPos`
Pos = tuple[int, float, float, float, float, float, float]


@njit(cache=True)
def along_track(  # type: ignore[no-untyped-def]
    road: RoadArrays,
    p: PlaceParams,
    edges: NDArray[np.int64],
    anc: float,
    anc_sd: float,
    best: Pos,
    acc: float,
):
    """Correct the position along the path ``edges``: the fix's projection ``best`` less its
    learnt along-track bias, fused with the turn anchor ``anc`` (σ ``anc_sd``; on a straight
    road the map cannot tell the fix's along-track error). ``acc`` is the furthest ``s``
    allowed. Returns ``(moved, position, want, miss, anc, anc_sd)``: whether the position
    changed, the corrected position (``best`` when unchanged), the estimate's ``s`` (the
    position's unless a turn of the path stops it short), a log-penalty for that, and the
    anchor."""
    j0, off0, s0 = best[0], best[1], best[2]
    s_f, vf, va = fuse_along(p, s0, best[6], anc, anc_sd)
    if abs(s_f - s0) <= 0.01:
        return False, best, s0, 0.0, anc, anc_sd
    s_f = min(max(s_f, 0.0), acc)
    want, miss = s_f, 0.0
    j, start, s_f = _stop_at_turns(road, p, edges, j0, s0 - off0, s_f)
    if s_f != want:  # the along-track estimate is past a turn this path has not taken yet
        miss = 0.5 * (want - s_f) ** 2 * (1.0 / vf + (1.0 / va if va > 0.0 else 0.0))
    rest = min(max(s_f - start, 0.0), road.elen[edges[j]])
    px, py, brg = locate(road, edges[j], rest)
    moved = (j, rest, s_f, hypot(px - p.x, py - p.y), px, py, brg)
    return True, moved, want, miss, anc, anc_sd


@njit(cache=True)
def fuse_along(p: PlaceParams, s0: float, bearing: float, anc: float, anc_sd: float):  # type: ignore[no-untyped-def]
    """A projection ``s0`` on a road of ``bearing`` less the learnt bias along the road, fused
    with the turn anchor (before the path's turns stop it). Returns ``(s, vf, va)``: the
    corrected ``s`` and the fix's and the anchor's variance along the road (``va`` 0 without
    an anchor)."""
    rad = math.radians(bearing)
    tx, ty = math.sin(rad), math.cos(rad)
    s_m = s0 - (p.bx * tx + p.by * ty)
    white = p.bias_white_fraction * p.sigma
    vf = tx * tx * p.pxx + 2.0 * tx * ty * p.pxy + ty * ty * p.pyy + white**2
    if math.isnan(anc_sd) or not p.odo_known:
        return s_m, vf, 0.0
    va = anc_sd * anc_sd
    innov = anc + p.odo - s_m
    return s_m + innov * vf / (va + vf), vf, va


@njit(cache=True)
def corrected_s(p: PlaceParams, s0: float, bearing: float, anc: float, anc_sd: float) -> float:
    """Where :func:`along_track` would put a projection ``s0`` on a road of ``bearing`` (before
    the path's turns stop it): :func:`fuse_along`'s ``s``."""
    return fuse_along(p, s0, bearing, anc, anc_sd)[0]  # type: ignore[no-any-return]


@njit(cache=True)
def _stop_at_turns(  # type: ignore[no-untyped-def]
    road: RoadArrays, p: PlaceParams, edges: NDArray[np.int64], j: int, start: float, s_f: float
):
    """Move from edge ``j`` (starting ``start`` metres along the path) towards ``s_f`` across
    nodes only where the path goes straight on (at a turn the fix shows it): the edge index
    reached, its start along the path and the ``s``."""
    while s_f > start + road.elen[edges[j]] and j < len(edges) - 1:
        if not straight(road, edges[j], edges[j + 1], p.straight_max_deg):
            s_f = start + road.elen[edges[j]]
            break
        start += road.elen[edges[j]]
        j += 1
    while s_f < start and j > 0:
        if not straight(road, edges[j - 1], edges[j], p.straight_max_deg):
            s_f = start
            break
        j -= 1
        start -= road.elen[edges[j]]
    return j, start, s_f

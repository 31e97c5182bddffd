"""The fix placed on every hypothesis's path at once (compiled): the best projection onto the
path (emission and transition, hysteresis at nodes), the along-track correction with GPS or
the odometer's carry in dead reckoning, and the log-score there.

The scores are the shared model's (:func:`mapmatch.model.emission_logp_one`,
:func:`mapmatch.model.transition_one_compiled`); :func:`place_all` is the Python entry, one
kernel call per fix for all hypotheses.
"""

from __future__ import annotations

import math
from array import array
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from graph.jit import njit
from mapmatch.config import MatchConfig
from mapmatch.model import emission_logp_one, transition_one_compiled
from mapmatch.online.along import Pos, along_track, corrected_s
from mapmatch.online.geometry import (
    RoadArrays,
    angle_diff_c,
    bearing_on_path,
    hypot,
    locate,
    project,
    project_between,
)
from mapmatch.online.params import PlaceParams, param_values
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, Step

# a hypothesis's values in the kernel's input: its path's length, where it is, its turn anchor
IN_LEN, IN_K, IN_OFF, IN_S, IN_DIST, IN_PX, IN_PY, IN_BRG, IN_ANC, IN_ANC_SD = range(10)
N_IN = 10
# and in its output: the score, the new position, the anchor and the turn score
OUT_SCORE, OUT_J, OUT_OFF, OUT_S, OUT_DIST, OUT_PX, OUT_PY, OUT_BRG, OUT_ANC, OUT_ANC_SD, OUT_TURN = range(11)
N_OUT = 11


class RoadPoint(NamedTuple):
    """A road point a fix is projected to: its distance from the fix, position and bearing."""

    dist: float
    x: float
    y: float
    bearing: float


@njit(cache=True)
def transition(p: PlaceParams, route_dist: float) -> float:
    """Log-probability of ``route_dist`` metres along the path for this step's travel (no
    speed term: the odometer gives the travel)."""
    return transition_one_compiled(route_dist, p.travelled, 0.0, p.beta, p.beta_per_m, 0.0, 0.0)  # type: ignore[no-any-return]


@njit(cache=True)
def debiased(p: PlaceParams, dist: float, px: float, py: float, bearing: float) -> float:
    """The fix's distance from the road point ``(px, py)`` of ``bearing`` with the learnt fix
    bias's part across the road taken off (``bias_emission`` of it): a receiver's error lasts
    minutes, so a fix that has lain 10 m left of the road for a minute is no evidence for the
    road 10 m to the left. ``dist`` unchanged without GPS or before the bias is learnt."""
    share = p.bias_emission
    if share <= 0.0 or not p.gps or math.isnan(p.pxx):
        return dist
    rad = math.radians(bearing)
    nx, ny = math.cos(rad), -math.sin(rad)  # normal to the road (bearing clockwise from north)
    z = (p.x - px) * nx + (p.y - py) * ny
    zc = z - share * (p.bx * nx + p.by * ny)
    return math.sqrt(max(dist * dist - z * z, 0.0) + zc * zc)


@njit(cache=True, inline="always")  # inlined: its record is then no argument to pass
def _score(p: PlaceParams, at: RoadPoint, s: float, here: Pos, anc: float, anc_sd: float) -> float:
    """Log-score of the road point ``at`` (:class:`RoadPoint`), ``s`` along the path (emission,
    and transition from the hypothesis's place ``here``; ``anc``, ``anc_sd`` its turn anchor).
    That place is where the along-track correction put it: with GPS the step is judged from
    there to the point's place corrected alike, or the offset between a projection and its
    corrected place would count against every step (ten times a second at 10 Hz). Not stopped
    at the path's turns: a place held at a turn pays for that by the correction's miss, not
    twice."""
    brg = at.bearing
    sc = emission_logp_one(debiased(p, at.dist, at.x, at.y, brg), p.sigma, p.heading, brg, p.kappa)
    if not math.isnan(p.travelled):
        if p.gps:
            s = corrected_s(p, s, brg, anc, anc_sd)
        sc += transition(p, s - here[2])
    return sc  # type: ignore[no-any-return]


@njit(cache=True)
def nearest_on_path(  # type: ignore[no-untyped-def]
    road: RoadArrays, p: PlaceParams, edges: NDArray[np.int64], here: Pos, anc: float, anc_sd: float
):
    """The fix's best projection onto the path ``edges`` from the position ``here`` (emission
    and transition; ``anc``, ``anc_sd`` its turn anchor), with hysteresis at nodes:
    ``(score, position, furthest s allowed)``."""
    k, h_s = here[0], here[2]
    hold = p.node_hold
    best_sc = -math.inf
    best = here
    acc = 0.0
    j0 = max(k - 1, 0)  # one edge back: a fix may run ahead of the vehicle near a node
    for j in range(j0):
        acc += road.elen[edges[j]]
    moved = 0.0 if math.isnan(p.travelled) else p.travelled
    jmax = len(edges)
    carry = math.inf  # the furthest s the fix may place a stopped vehicle
    if p.stopped:
        # stopped: the fix's noise may move the vehicle back but not on across a node; the
        # odometer's distance may (a vehicle creeping past a node, or carried without GPS),
        # while the fixes keep to the road (within the region radius of it)
        end = acc
        for j in range(j0, k + 1):
            end += road.elen[edges[j]]
        carry = h_s + moved
        jmax = k + 1
        while jmax < len(edges) and here[3] <= p.reach and carry > end + 1e-6:
            end += road.elen[edges[jmax]]
            jmax += 1
    ahead = moved + p.reach
    for j in range(j0, jmax):
        e = edges[j]
        le = road.elen[e]
        off, dist, px, py, brg = project(road, e, p.x, p.y)
        if j > k and acc + off > carry:  # at most as far as the odometer carried it
            off = max(carry - acc, 0.0)
            px, py, brg = locate(road, e, off)
            dist = hypot(px - p.x, py - p.y)
        s = acc + off
        if j < k and le - off < hold:
            # back across the node only when the fix is clearly behind it (no flicker)
            acc += le
            continue
        if j < jmax - 1 and off >= le - 1e-6 and project(road, edges[j + 1], p.x, p.y)[0] > 1e-6:
            # the fix is past the end of an edge the path continues on: the next edge takes it
            # (a position kept at the node would move by nothing, and at 10 Hz the transition
            # over one step's 0.7 m would favour that fix after fix)
            acc += le
            continue
        sc = _score(p, RoadPoint(dist, px, py, brg), s, here, anc, anc_sd)
        if sc > best_sc + 1e-9:
            best_sc = sc
            best = (j, off, s, dist, px, py, brg)
        if not h_s - p.reach <= s <= h_s + ahead:
            # an edge that loops back (a ramp) may pass nearer the fix further on: the part
            # the vehicle can have reached since the last fix is a candidate too
            found, off, dist, px, py, brg = project_between(
                road, e, p.x, p.y, h_s - p.reach - acc, h_s + ahead - acc
            )
            if found:
                s = acc + off
                sc = _score(p, RoadPoint(dist, px, py, brg), s, here, anc, anc_sd)
                if sc > best_sc + 1e-9:
                    best_sc = sc
                    best = (j, off, s, dist, px, py, brg)
        acc += le
    if p.stopped and jmax > k + 1:
        acc = min(acc, carry)
    return best_sc, best, acc


@njit(cache=True)
def dead_reckon(  # type: ignore[no-untyped-def]
    road: RoadArrays, p: PlaceParams, edges: NDArray[np.int64], k: int, h_s: float, acc: float
):
    """Dead reckoning: the fix drifts, the odometer does not; the vehicle is carried along its
    path by the distance travelled (the fix still weighs the paths against each other)."""
    s_pred = min(h_s + p.travelled, acc)
    j, rest = k, s_pred
    for i in range(k):
        rest -= road.elen[edges[i]]
    while j < len(edges) - 1 and rest > road.elen[edges[j]]:
        rest -= road.elen[edges[j]]
        j += 1
    rest = min(max(rest, 0.0), road.elen[edges[j]])
    px, py, brg = locate(road, edges[j], rest)
    dist = hypot(px - p.x, py - p.y)
    # the distance carried is uncertain (odometer scale): near a node the heading is
    # compared with the road anywhere within that uncertainty, not just at one point
    head = brg
    spread = p.pos_sigma_floor + p.odo_sigma * p.dr
    if p.kappa > 0.0 and not math.isnan(p.heading):
        for q in (-2, -1, 1, 2):
            b = bearing_on_path(road, edges, s_pred + 0.5 * q * spread)
            if abs(angle_diff_c(p.heading, b)) < abs(angle_diff_c(p.heading, head)):
                head = b
    sc = emission_logp_one(dist, p.sigma, p.heading, head, p.kappa) + transition(p, s_pred - h_s)
    return sc, (j, rest, s_pred, dist, px, py, brg)


@njit(cache=True)
def turn_score(road: RoadArrays, p: PlaceParams, edges: NDArray[np.int64], pos: Pos, s_prev: float) -> float:
    """Log-score of the heading change observed over the last ``covered`` metres against the
    bearing change the path has there, up to ``pos`` from ``s_prev`` (0 when too little was
    covered)."""
    if p.covered >= 0.5 * p.turn_window and not math.isnan(p.turn_obs):
        s, brg = pos[2], pos[6]
        expect = angle_diff_c(brg, bearing_on_path(road, edges, s - p.covered))
        miss = angle_diff_c(p.turn_obs, expect) / p.turn_sigma
        frac = min(1.0, max(s - s_prev, 0.0) / p.turn_window)
        return -(0.5 * miss * miss * frac)
    return 0.0


@njit(cache=True)
def place_one(  # type: ignore[no-untyped-def]
    road: RoadArrays, p: PlaceParams, edges: NDArray[np.int64], here: Pos, anc: float, anc_sd: float
):
    """One hypothesis's best position for this fix from ``here``: ``(score, position, anc,
    anc_sd)``."""
    best_sc, best, acc = nearest_on_path(road, p, edges, here, anc, anc_sd)
    if p.gps:
        moved, pos, want, miss, anc, anc_sd = along_track(road, p, edges, anc, anc_sd, best, acc)
        if moved:
            # scored where the vehicle is now believed to be: its heading against the road
            # there (the distance stays the fix's offset from the road, which the correction
            # along the road does not change)
            dist = debiased(p, best[3], best[4], best[5], best[6])
            best_sc = emission_logp_one(dist, p.sigma, p.heading, pos[6], p.kappa) - miss
            if not math.isnan(p.travelled):
                # held at a turn short of the estimate: the miss is its penalty; the step
                # is judged to the estimate
                best_sc += transition(p, want - here[2])
            best = pos
    elif p.odo_known:
        best_sc, best = dead_reckon(road, p, edges, here[0], here[2], acc)
    return best_sc, best, anc, anc_sd


N_PARAMS = len(PlaceParams._fields)


@njit(cache=True, inline="always")  # inlined: its record is then no value to pass
def _params(v):  # type: ignore[no-untyped-def]
    """The :class:`PlaceParams` of the first ``N_PARAMS`` values of ``v`` (in field order, the
    bool fields as 1 or 0)."""
    return PlaceParams(
        v[0],
        v[1],
        v[2],
        v[3],
        v[4],
        v[5],
        v[6],
        v[7] != 0.0,
        v[8] != 0.0,
        v[9] != 0.0,
        v[10],
        v[11],
        v[12],
        v[13],
        v[14],
        v[15],
        v[16],
        v[17],
        v[18],
        v[19],
        v[20],
        v[21],
        v[22],
        v[23],
        v[24],
        v[25],
        v[26],
        v[27],
        v[28],
    )


@njit(cache=True)
def _place_all(road_t, buf, n, out):  # type: ignore[no-untyped-def]
    """:func:`place_one` for ``n`` hypotheses: ``buf`` holds the :class:`PlaceParams`
    (``N_PARAMS`` values, :func:`_params`), then ``N_IN`` values per hypothesis (the ``IN_*``
    columns), then all their paths' edges (as floats: one buffer to fill and pass, not
    three), hypothesis ``i``'s path the next ``IN_LEN`` of them; ``N_OUT`` values each into
    ``out`` (``OUT_*``). ``buf`` and ``out`` are ``array.array("d")`` buffers (made and read
    in Python faster than numpy arrays, and faster passed than a tuple of floats);
    ``road_t`` is a :class:`RoadArrays` as a plain tuple (numba reads that ten times faster
    at a call)."""
    road = RoadArrays(*road_t)
    rows = np.empty(len(buf))
    for i in range(len(buf)):
        rows[i] = buf[i]
    p = _params(rows)
    at = N_PARAMS
    edges = rows[at + n * N_IN :].astype(np.int64)
    lo = 0
    for i in range(n):
        r = rows[at + i * N_IN : at + (i + 1) * N_IN]
        path = edges[lo : lo + int(r[IN_LEN])]
        lo += len(path)
        here = (int(r[IN_K]), r[IN_OFF], r[IN_S], r[IN_DIST], r[IN_PX], r[IN_PY], r[IN_BRG])
        sc, pos, anc, anc_sd = place_one(road, p, path, here, r[IN_ANC], r[IN_ANC_SD])
        o = i * N_OUT
        out[o + OUT_SCORE] = sc
        out[o + OUT_J], out[o + OUT_OFF], out[o + OUT_S], out[o + OUT_DIST] = pos[0], pos[1], pos[2], pos[3]
        out[o + OUT_PX], out[o + OUT_PY], out[o + OUT_BRG] = pos[4], pos[5], pos[6]
        out[o + OUT_ANC], out[o + OUT_ANC_SD] = anc, anc_sd
        out[o + OUT_TURN] = turn_score(road, p, path, pos, here[2])


_OUT_ONE = array("d", [0.0] * N_OUT)  # one hypothesis's output row (``* n`` for ``n``)


def place_all(
    road: RoadModel,
    hyps: Sequence[Hypothesis],
    step: Step,
    cfg: MatchConfig,
    *,
    turn_obs: float = math.nan,
    covered: float = 0.0,
) -> list[tuple[float, float]]:
    """Move every hypothesis to its best position for this fix (the vehicle's edge index and
    entry times follow); return each position's log-score and the score of the turn observed
    (``turn_obs`` degrees over the last ``covered`` metres) against the path's."""
    flat: list[int] = []
    rows: list[float] = list(param_values(step, cfg, turn_obs=turn_obs, covered=covered))
    for h in hyps:
        flat += h.edges
        rows += (len(h.edges), h.k, h.off, h.s, h.dist, h.px, h.py, h.bearing, h.anc, h.anc_sd)
    rows += flat
    n = len(hyps)
    buf = _OUT_ONE * n
    _place_all(road.arrays_tuple, array("d", rows), n, buf)
    out = buf.tolist()
    scores = []
    lo = 0
    for h in hyps:
        sc, j_new, h.off, h.s, h.dist, h.px, h.py, h.bearing, h.anc, h.anc_sd, turn = out[lo : lo + N_OUT]
        lo += N_OUT
        j = int(j_new)
        if j < h.k:
            h.k = j
            del h.enter[j + 1 :]
        while h.k < j:
            h.k += 1
            h.enter.append(step.time)
        scores.append((sc, turn))
    return scores

"""The turn anchor and the odometer scale: where a committed turn says the vehicle was, the
odometer's scale error learnt from anchor to anchor, and the crossings since the previous turn
timed again from the anchor (over the odometer trail)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from mapmatch.config import MatchConfig
from mapmatch.online.road import RoadModel
from mapmatch.online.state import (
    NO_CHAIN,
    AnchorState,
    BackEdge,
    CrossingTrail,
    Hypothesis,
    ScaleChain,
    SessionState,
    Step,
    TrailPoint,
)
from mapmatch.turns import align_headings, bearing_profile
from mapmatch.types import Correction


def odo_kvar(a: AnchorState, cfg: MatchConfig) -> float:
    """Variance of the learnt odometer scale (the configured prior until learnt)."""
    return cfg.online.odometer.odo_scale_sigma**2 if math.isnan(a.odo_kvar) else a.odo_kvar


def drop_chain(a: AnchorState) -> None:
    """No running scale estimate from the GPS (the fixes have left the road): it starts again."""
    a.chain = NO_CHAIN


def turn_anchor(
    road: RoadModel, state: SessionState, best: Hypothesis, step: Step, cfg: MatchConfig
) -> tuple[float, float]:
    """The odometer reading at which the vehicle was at the end node of ``best.edges[0]``
    and its σ: the fused headings against the odometer aligned with the path's bearing
    profile. ``(nan, nan)`` when the samples do not cover the turn or do not fit the path."""
    o = cfg.online
    lengths: list[float] = []
    bearings: list[float] = []
    for e in best.edges:
        piece = slice(road.ptr[e], road.ptr[e + 1] - 1)
        keep = road.piece_len[piece] > 1e-6
        lengths += road.piece_len[piece][keep].tolist()
        bearings += road.piece_brg[piece][keep].tolist()
    if not lengths:
        return math.nan, math.nan
    node = road.elen[best.edges[0]]
    c0 = best.s - step.odo
    samples = [x for x in state.headings if x[0] + c0 >= 0.0]
    hs = math.sqrt(state.bias.res_head2)
    hs = min(max(hs, o.anchor.align_heading_sigma_min_deg), o.bias.learned_heading_sigma_max_deg)
    search = min(o.reinit.soft_reinit_sigmas * step.sigma, o.anchor.align_search_max)
    c, sd, rms = align_headings(
        samples, bearing_profile(lengths, bearings), c0, search=search, heading_sigma=hs
    )
    if (
        math.isnan(c)
        or rms > o.anchor.align_rms_max_deg
        or samples[0][0] + c > node - o.anchor.align_cover
        or samples[-1][0] + c < node + o.anchor.align_cover
    ):
        return math.nan, math.nan
    return node - c, math.hypot(sd, o.anchor.turn_anchor_sigma)


def learn_scale(
    road: RoadModel,
    a: AnchorState,
    best: Hypothesis,
    odo_in: float,
    odo_out: float,
    anchor_sd: float,
    cfg: MatchConfig,
) -> None:
    """Kalman update of the odometer scale: the previous turn anchor carried by the odometer
    against this one (both at nodes of the path driven). ``odo_in`` and ``odo_out`` are the
    odometer readings at the node for the way in and the way out."""
    o = cfg.online
    prev_odo, prev_sd = a.anc_odo, a.anc_sd
    a.anc_odo, a.anc_sd = odo_out, anchor_sd
    dist = odo_in - prev_odo
    if math.isnan(best.anc) or not o.odometer.scale_min_distance <= dist <= o.odometer.scale_max_distance:
        return
    kvar = odo_kvar(a, cfg)
    nu = road.elen[best.edges[0]] - (best.anc + odo_in)  # path metres the odometer missed
    # the map's path length differs from the road's by a little too
    r = prev_sd**2 + anchor_sd**2 + (o.odometer.scale_path_error * dist) ** 2
    sv = dist * dist * kvar + r
    if nu * nu > 9.0 * sv:
        return  # not the same path, or a bad anchor: learn nothing
    lim = 2.0 * math.sqrt(sv)
    nu = min(max(nu, -lim), lim)  # robust: one odd pair of anchors must not teach much
    gain = kvar * dist / sv
    a.odo_k = min(max(a.odo_k + gain * nu, -o.odometer.odo_scale_max), o.odometer.odo_scale_max)
    a.odo_kvar = kvar * (1.0 - gain * dist)
    c = a.chain
    if c.edge >= 0:  # the GPS chain's offset and error are correlated with the scale: they move too
        gp, gb = c.ppk * dist / sv, c.pkb * dist / sv
        a.chain = c._replace(
            p=c.p + gp * nu,
            b=c.b + gb * nu,
            ppp=c.ppp - gp * c.ppk * dist,
            ppk=c.ppk * (1.0 - gain * dist),
            ppb=c.ppb - gp * c.pkb * dist,
            pkb=c.pkb * (1.0 - gain * dist),
            pbb=c.pbb - gb * c.pkb * dist,
        )


def carry(a: AnchorState, step: Step) -> None:
    """The odometer's metres of this fix (before the learnt scale) carried on the chain."""
    c = a.chain
    if c.edge >= 0 and step.odo_known and not math.isnan(step.travelled):
        a.chain = ScaleChain(c[0], c[1], c[2], c[3] + step.travelled / (1.0 + a.odo_k), *c[4:])


def learn_scale_gps(
    road: RoadModel, a: AnchorState, best: Hypothesis, step: Step, cfg: MatchConfig, *, drift_sigma: float
) -> None:
    """Kalman update of the odometer scale from the GPS: the path metres between the
    projections of successive GPS-aided fixes onto the path driven against the odometer's.

    The state is the offset between path metres and odometer metres (unknown at the chain's
    start), the scale error and the fix's slowly varying error along the road (a
    Gauss-Markov process of correlation time ``bias_time`` and the fix's σ; the white part
    ``bias_white_fraction`` of it, per unit of evidence weight, is the measurement noise). The
    projection follows the path through any bend, and the across-track error drops out. The
    chain starts again without GPS or odometer, while the dead-reckoning drift
    (``drift_sigma``) blends out, when the last fix's edge is no longer on the path believed,
    or at a measurement far outside its σ (another path)."""
    o = cfg.online
    if not (step.gps and step.odo_known) or drift_sigma > 0.5 * step.fix_sigma or math.isnan(best.bearing):
        a.chain = NO_CHAIN
        return
    if step.weight <= 0.0 and a.chain.edge >= 0:
        return  # standing: the fixes wander, the odometer does not
    j, off = _path_place(road, best, step.x, step.y)
    e = best.edges[j]
    sb2 = step.fix_sigma**2
    r = (o.bias.bias_white_fraction * step.fix_sigma) ** 2 / max(step.weight, 1e-3)
    c = a.chain
    i = _on_path(best.edges, c.edge, j) if c.edge >= 0 else -1
    if i < 0:
        a.chain = _chain_start(e, off, step.time, sb2, r)
        return
    m = _path_start(road, best.edges, j) + off - (_path_start(road, best.edges, i) + c.off) - c.dx
    tau = o.bias.bias_time
    decay = math.exp(-(step.time - c.time) / tau) if tau > 0.0 and step.time > c.time else 0.0
    pkk = odo_kvar(a, cfg)
    # predict: b decays (Gauss-Markov); p and the scale hold
    b = decay * c.b
    ppb, pkb = decay * c.ppb, decay * c.pkb
    pbb = decay * decay * c.pbb + (1.0 - decay * decay) * sb2
    ppp, ppk = c.ppp, c.ppk
    # measured: m = p + k·dx + b + white
    dx = c.dx
    h_p, h_k, h_b = ppp + dx * ppk + ppb, ppk + dx * pkk + pkb, ppb + dx * pkb + pbb  # P·H
    sv = h_p + dx * h_k + h_b + r
    nu = m - (c.p + a.odo_k * dx + b)
    if nu * nu > 9.0 * sv:
        a.chain = _chain_start(e, off, step.time, sb2, r)  # not the same path: start again
        return
    gp, gk, gb = h_p / sv, h_k / sv, h_b / sv
    p = c.p + gp * nu
    k = a.odo_k + gk * nu
    b += gb * nu
    ppp, ppk, ppb = ppp - gp * h_p, ppk - gp * h_k, ppb - gp * h_b
    pkk, pkb, pbb = pkk - gk * h_k, pkb - gk * h_b, pbb - gb * h_b
    # to this fix: p' = p + k·dx - m
    ppp, ppk, ppb = ppp + 2.0 * dx * ppk + dx * dx * pkk, ppk + dx * pkk, ppb + dx * pkb
    p += k * dx - m
    lim = o.odometer.odo_scale_max
    a.odo_k = min(max(k, -lim), lim)
    a.odo_kvar = pkk
    a.chain = ScaleChain(e, off, step.time, 0.0, p, b, ppp, ppk, ppb, pkb, pbb)


def _chain_start(e: int, off: float, time: float, sb2: float, r: float) -> ScaleChain:
    """A chain starting at a fix: the offset is what was measured less the fix's error there
    (its slowly varying part ``b`` of variance ``sb2`` and the white of variance ``r``)."""
    return ScaleChain(e, off, time, 0.0, 0.0, 0.0, sb2 + r, 0.0, -sb2, 0.0, sb2)


def _path_start(road: RoadModel, edges: list[int], j: int) -> float:
    """Metres along the path ``edges`` to the start of ``edges[j]``."""
    return float(sum(road.elen[e] for e in edges[:j]))


def _on_path(edges: list[int], edge: int, j: int) -> int:
    """The index of ``edge`` in ``edges`` at or before ``j`` (the latest), or -1."""
    for i in range(j, -1, -1):
        if edges[i] == edge:
            return i
    return -1


def _path_place(road: RoadModel, h: Hypothesis, x: float, y: float) -> tuple[int, float]:
    """The fix's projection onto the path around ``h``'s edge: ``(edge index, offset)`` (the
    next edge or the one before when the fix lies past either end of it)."""
    j = h.k
    off = road.project(h.edges[j], x, y)[0]
    if off >= road.elen[h.edges[j]] - 1e-6 and j + 1 < len(h.edges):
        nxt = road.project(h.edges[j + 1], x, y)[0]
        if nxt > 1e-6:
            return j + 1, nxt
    elif off <= 1e-6 and j > 0:
        prev = road.project(h.edges[j - 1], x, y)[0]
        if prev < road.elen[h.edges[j - 1]] - 1e-6:
            return j - 1, prev
    return j, off


def add_trail(trail: list[TrailPoint], time: float, odo: float, standing: bool, cfg: MatchConfig) -> None:
    """Keep the odometer every ``trail_step`` metres, and both ends of a stop."""
    if standing:
        if len(trail) >= 2 and odo - trail[-2].odo <= cfg.online.stop.still_distance:
            trail[-1].time = time  # still standing: the stop goes on
            return
    elif trail and odo - trail[-1].odo < cfg.online.corrections.trail_step:
        return
    trail.append(TrailPoint(time, odo))
    if len(trail) > cfg.online.corrections.trail_max:
        del trail[0]


def keep_back(
    road: RoadModel, c: CrossingTrail, edge: int, entered: float, cfg: MatchConfig, *, anchored: bool
) -> None:
    """An edge committed (entered at time ``entered``): after a turn anchor (``anchored``) none
    is kept; else it is kept for the next anchor's revision, and the oldest go while those kept
    are longer than ``trail_max_distance``."""
    if anchored:
        c.restart()
        return
    c.back.append(BackEdge(edge, entered))
    # each tail's sum over a list of lengths, in C (an imported session may hold many edges)
    lens = [road.elen[b.edge] for b in c.back]
    drop = 0
    while sum(lens[drop:]) > cfg.online.corrections.trail_max_distance:
        drop += 1
    del c.back[:drop]


def revise_crossings(
    road: RoadModel,
    c: CrossingTrail,
    best: Hypothesis,
    anchor: tuple[float, float, float],
    step: Step,
    cfg: MatchConfig,
) -> Correction | None:
    """This turn and the straight crossings since the previous one, timed again from the
    turn's ``anchor`` (odometer at the node, corner cut, σ) carried back by the odometer: a
    correction when they differ from what was reported."""
    if len(c.trail) < 2:
        return None
    odo_at_node, cut, anchor_sd = anchor
    t_tr = [x.time for x in c.trail]
    o_tr = [x.odo for x in c.trail]
    path = [(b.edge, b.time) for b in c.back] + [(best.edges[0], best.enter[0])]
    crossings: list[tuple[float, float]] = []  # (old time, new time), latest first
    if odo_at_node >= o_tr[0]:
        path.append((best.edges[1], best.enter[1]))
        new = sure_time(best.enter[1], odo_at_node, anchor_sd, o_tr, t_tr, step.dt, cfg)
        crossings.append((best.enter[1], new))
    odo_at_node += cut
    dist = 0.0
    for i in range(len(path) - 1 - len(crossings), 0, -1):
        e, entered = path[i]
        prev = path[i - 1][0]
        dist += road.elen[e]
        odo = odo_at_node - dist
        if road.ev[prev] != road.eu[e] or not road.straight(prev, e, cfg) or odo < o_tr[0]:
            break
        sd = math.hypot(anchor_sd, step.odo_sigma * dist)
        crossings.append((entered, sure_time(entered, odo, sd, o_tr, t_tr, step.dt, cfg)))
    if not crossings or all(abs(a - b) < 1e-3 for a, b in crossings):
        return None
    n = len(crossings)
    edges = tuple(e for e, _ in path[len(path) - n - 1 :])
    t_from = min(min(a, b) for a, b in crossings)
    t_to = max(max(a, b) for a, b in crossings)
    times = (t_from, *(b for _, b in reversed(crossings)))
    if any(b < a for a, b in itertools.pairwise(times)):
        return None  # not monotone: the odometer and the path disagree
    return Correction(time_from=t_from, time_to=t_to, edges=edges, replaced_edges=edges, edge_times=times)


def sure_time(
    old: float, odo: float, sd: float, o_tr: list[float], t_tr: list[float], dt: float, cfg: MatchConfig
) -> float:
    """A crossing's time revised from the odometer reading ``odo`` (σ ``sd``) at the node:
    ``old`` (the time of the first fix reported past the node) moved only as far as the
    reading is sure, so that fixes within ``revise_sigmas`` σ of the node keep what was
    reported; not moved back by less than the fix interval ``dt`` (no fix in between)."""
    k = cfg.online.corrections.revise_sigmas
    lo = float(np.interp(odo - k * sd, o_tr, t_tr))
    hi = float(np.interp(odo + k * sd, o_tr, t_tr))
    new = min(max(old, lo), hi)
    return old if old - dt < new < old else new

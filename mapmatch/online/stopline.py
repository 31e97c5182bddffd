"""The stop line: a vehicle that stops just past a node it went straight through (or has not
turned at) is put back before it (vehicles stop at stop lines, not in junctions), and what was
reported past the node since is revised."""

from __future__ import annotations

import math

import numpy as np

from graph.angles import angle_diff
from mapmatch.config import MatchConfig
from mapmatch.online.correction import merge
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, SessionState, Step
from mapmatch.types import Correction


def hold_stopped(
    road: RoadModel, hyps: list[Hypothesis], state: SessionState, step: Step, cfg: MatchConfig
) -> list[tuple[Hypothesis, float]]:
    """Every hypothesis of a stopped vehicle put back before the node it has just crossed, with
    the time it had crossed it."""
    held: list[tuple[Hypothesis, float]] = []
    if not step.stopped:
        return held
    for h in hyps:
        if h.k >= 1:
            crossed = hold_before_node(road, h, state, step, cfg)
            if not math.isnan(crossed):
                held.append((h, crossed))
    return held


def hold_before_node(
    road: RoadModel, h: Hypothesis, state: SessionState, step: Step, cfg: MatchConfig
) -> float:
    """Put a stopped vehicle back before the node it has just crossed: vehicles stop at stop
    lines, not in junctions, so its fixes' along-track error put it past. Only when it stopped
    within ``stop_hold_distance`` of driving past the node (and a GPS-aided fix whose σ is its
    own, no dead-reckoning drift above it, within ``stop_hold_fix_distance``), with the next
    node further than that, and without a turn there that its heading shows taken. Returns
    the time it had crossed the node (nan: not put back)."""
    hold = cfg.online.stop.stop_hold_distance
    prev, cur = h.edges[h.k - 1], h.edges[h.k]
    trail = state.crossings.trail
    if h.off >= hold or road.elen[cur] - h.off <= hold or len(trail) < 2:
        return math.nan
    fix_hold = cfg.online.stop.stop_hold_fix_distance
    own = step.gps and step.sigma <= step.fix_sigma  # no dead-reckoning drift left above its own σ
    if fix_hold > 0.0 and own and road.project(cur, step.x, step.y)[0] >= fix_hold:
        # the fix itself shows the stop further past the node than a stop line: the position
        # believed may lag it (along-track correction), but where it stands the fix tells
        return math.nan
    crossed = h.enter[h.k]
    t_tr = [x.time for x in trail]
    if crossed < t_tr[0] or state.odo - float(np.interp(crossed, t_tr, [x.odo for x in trail])) >= hold:
        return math.nan  # it has driven further since: not a stop on the way in
    if not road.straight(prev, cur, cfg):
        last = state.headings[-1][1] if state.headings else math.nan
        if math.isnan(last) or abs(angle_diff(last, road.bend[prev])) >= abs(
            angle_diff(last, road.bstart[cur])
        ):
            return math.nan  # the heading shows the turn taken: it is past the node
    h.s -= h.off
    h.k -= 1
    del h.enter[h.k + 1 :]
    h.off = road.elen[prev]
    h.px, h.py, h.bearing = road.locate(prev, h.off)
    h.dist = math.hypot(h.px - step.x, h.py - step.y)
    return crossed


def back_at_stop_line(
    state: SessionState,
    shown: Hypothesis,
    held: list[tuple[Hypothesis, float]],
    step: Step,
    correction: Correction | None,
) -> Correction | None:
    """When the hypothesis to be reported was put back before the node into the edge reported
    last, what was reported past the node since it crossed is revised (the live fixes too)."""
    e = shown.edges[shown.k]
    crossed = next((t for h, t in held if h is shown), math.nan)
    if math.isnan(crossed) or shown.k + 1 >= len(shown.edges) or shown.edges[shown.k + 1] != state.shown:
        return correction
    stop = Correction(
        time_from=crossed, time_to=step.time, edges=(e,), replaced_edges=(state.shown,), edge_times=(crossed,)
    )
    for x in state.region.live:
        if x.time >= crossed and x.edge == state.shown:
            x.edge = e
    return stop if correction is None else merge(stop, correction)

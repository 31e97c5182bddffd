"""The ambiguous region and its commit: the region radius around the node ahead, the start-up
commit, and each node the most probable hypothesis has left behind by ``r_a``: the turn there
is classified, anchored, and the committed path's corrections are made."""

from __future__ import annotations

import math

from graph.angles import angle_diff
from mapmatch.config import MatchConfig
from mapmatch.online.anchor import keep_back, learn_scale, revise_crossings, turn_anchor
from mapmatch.online.correction import correction, merge
from mapmatch.online.filter import best as best_of
from mapmatch.online.filter import normalise
from mapmatch.online.hypotheses import move_to
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, SessionState, Step
from mapmatch.turns import classify_turn, corner_cut
from mapmatch.types import Correction, Turn

_NO_TURN = Turn.NONE  # as a module value: an enum member's look-up on its class takes 0.1 µs


def region_radius(road: RoadModel, sigma: float, cfg: MatchConfig) -> float:
    """Ambiguous-region radius in metres for a fix of position σ (DR growth included)."""
    o = cfg.online
    r = max(
        o.bias.dr_sigma_growth * road.edge_len_ref,  # the dead-reckoning drift over an edge
        o.region.ambiguous_sigma_factor * sigma,
    )
    return min(r, o.region.ambiguous_max_radius)


def commit(
    road: RoadModel, state: SessionState, step: Step, cfg: MatchConfig
) -> tuple[Turn, Correction | None]:
    """Commit what is sure: the start-up road, then every node the best hypothesis is ``r_a``
    past. Returns the last turn committed and the corrections it brings."""
    best = best_of(state.hyps)
    corr: Correction | None = None
    turn = _NO_TURN
    rg = state.region
    if rg.init_pending:
        if not _commit_start(road, state, best, step, cfg):
            return turn, None
        corr = correction(road, rg, best, cfg)
        state.hyps = [h for h in state.hyps if h.edges[0] == best.edges[0]]
        rg.init_pending = False
    while best.k >= 1 and best.s - road.elen[best.edges[0]] >= step.r_a:
        if _branch_probable(road, state, best, step, cfg):
            break  # the evidence cannot tell the branches apart yet
        if rg.live:
            c = correction(road, rg, best, cfg)
            corr = c if corr is None else merge(corr, c)
        turn, corr = _commit_node(road, state, best, step, cfg, turn, corr)
    if len(state.hyps) == 1 and rg.live:
        # the alternatives died out: that decision is final too
        c = correction(road, rg, state.hyps[0], cfg)
        corr = c if corr is None else merge(corr, c)
        rg.live = []
    return turn, corr


def _branch_probable(
    road: RoadModel, state: SessionState, best: Hypothesis, step: Step, cfg: MatchConfig
) -> bool:
    """Whether the paths the commit of ``best``'s first node would drop still hold more than
    ``commit_hold_probability`` of the probability (until ``best`` is ``ambiguous_max_radius``
    past the node): a fork's branches separate slowly, and leaving the ambiguous circle is
    no evidence."""
    o = cfg.online
    if (
        o.region.commit_hold_probability <= 0.0
        or not step.gps  # dead reckoning: the turn's anchor at the commit carries the vehicle
        or best.s - road.elen[best.edges[0]] >= o.region.ambiguous_max_radius
    ):
        return False
    e1 = best.edges[1]
    total = drop = 0.0
    for h in state.hyps:
        p = math.exp(h.logp)
        total += p
        if len(h.edges) < 2 or h.edges[1] != e1:
            drop += p
    return drop > o.region.commit_hold_probability * total


def _branches_kept(state: SessionState, e1: int, step: Step, cfg: MatchConfig) -> list[Hypothesis]:
    """The hypotheses on another branch past the node committed (not through ``e1``) that still
    hold more than ``commit_hold_probability`` of the probability: a commit forced by the
    distance (the branches of a motorway split may run within a few metres for a kilometre)
    does not end them; they go on as paths of their own, and the evidence decides."""
    o = cfg.online
    if o.region.commit_hold_probability <= 0.0 or not step.gps:
        return []
    total = sum(math.exp(h.logp) for h in state.hyps)
    floor = o.region.commit_hold_probability * total
    return [
        h
        for h in state.hyps
        if h.k >= 1 and len(h.edges) > 1 and h.edges[1] != e1 and math.exp(h.logp) > floor
    ]


def _commit_start(
    road: RoadModel, state: SessionState, best: Hypothesis, step: Step, cfg: MatchConfig
) -> bool:
    """Whether the start-up road is the only one left, or enough was driven to commit it."""
    return all(h.edges[0] == best.edges[0] for h in state.hyps) or state.odo - state.region.init_odo >= max(
        2.0 * step.r_a, cfg.online.evidence.turn_window
    )


def _commit_node(
    road: RoadModel,
    state: SessionState,
    best: Hypothesis,
    step: Step,
    cfg: MatchConfig,
    turn: Turn,
    corr: Correction | None,
) -> tuple[Turn, Correction | None]:
    """Commit the node at the end of ``best.edges[0]``: keep the hypotheses through it, classify
    the turn, anchor the position by it, and drop the edge behind from every path."""
    e0, e1 = best.edges[0], best.edges[1]
    hyps = [h for h in state.hyps if len(h.edges) > 1 and h.edges[1] == e1]
    hyps += _branches_kept(state, e1, step, cfg)
    is_rev = e1 == road.rev[e0]
    anchor_odo = anchor_sd = math.nan
    angle = angle_diff(road.bstart[e1], road.bend[e0])
    kind = classify_turn(angle, is_reverse=is_rev, straight_max_deg=cfg.model.straight_max_deg)
    if road.branching[road.ev[e0]] or is_rev:
        turn = kind
    # a turn, or a bend where no other road joins, tells where the vehicle is
    if kind in (Turn.LEFT, Turn.RIGHT) and cfg.online.anchor.turn_anchor_sigma > 0.0 and step.odo_known:
        mid, anchor_sd = turn_anchor(road, state, best, step, cfg)
        if not math.isnan(mid):
            # rounding the corner, the vehicle drives less than the centre line: the
            # odometer reads as if it had been at the node a little later on the way
            # in and a little earlier on the way out
            cut = 0.5 * corner_cut(angle, road.elen[e0], road.elen[e1])
            learn_scale(road, state.anchor, best, mid + cut, mid - cut, anchor_sd, cfg)
            anchor_odo = mid - cut
            if corr is None:
                corr = revise_crossings(road, state.crossings, best, (mid, cut, anchor_sd), step, cfg)
    keep_back(road, state.crossings, e0, best.enter[0], cfg, anchored=not math.isnan(anchor_odo))
    state.region.live = [x for x in state.region.live if x.edge != e0]
    for h in hyps:
        _drop_first_edge(road, h, road.elen[e0], step, anchor_odo, anchor_sd)
    state.hyps = normalise(hyps, prune_log_ratio=cfg.online.region.prune_log_ratio)
    return turn, corr


def _drop_first_edge(
    road: RoadModel, h: Hypothesis, length: float, step: Step, anchor_odo: float, anchor_sd: float
) -> None:
    """``h`` without its first edge, the committed one of ``length`` metres (re-anchored when
    the node gave an anchor)."""
    if h.k == 0:  # still behind the committed node: place it at the node
        h.k, h.off, h.s = 1, 0.0, length
        h.enter.append(step.time)
    h.s -= length
    if math.isnan(anchor_odo):
        h.anc -= length
    else:  # the vehicle was at the node (s = 0 now) when the odometer read anchor_odo
        h.anc = -anchor_odo
        h.anc_sd = anchor_sd + step.odo_sigma * (step.odo - anchor_odo)
    h.k -= 1
    del h.edges[0]
    del h.enter[0]
    if not step.gps and not math.isnan(anchor_odo):
        # dead reckoning: the turn tells where the vehicle is better than the distance
        # carried since GPS was lost
        move_to(road, h, step.odo - anchor_odo, step)

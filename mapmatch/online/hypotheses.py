"""Path hypotheses: start them from the spatial index, let other roads join, extend them at
their end node with the legal moves, and the filter step placing each on its path for a fix
(:mod:`mapmatch.online.placement`)."""

from __future__ import annotations

import math

from graph.angles import angle_diff
from graph.index import EdgeIndex
from mapmatch.config import MatchConfig
from mapmatch.online.filter import filter_step, keep_best, normalise
from mapmatch.online.placement import place_all
from mapmatch.online.road import Projection, RoadModel
from mapmatch.online.state import Hypothesis, SessionState, Step
from mapmatch.turns import heading_change


def _candidates(
    road: RoadModel,
    index: EdgeIndex,
    step: Step,
    radius: float,
    cfg: MatchConfig,
    edges: list[int] | None = None,
) -> list[tuple[int, Projection]]:
    """Edges near the fix (or the given ``edges``) not heading against it by more than
    ``online.reinit.against_heading_deg`` (never start against one-ways), projected."""
    if edges is None:
        edges = index.query([[step.x, step.y]], radius, k=cfg.model.max_candidates).edge.tolist()
    out = []
    for e in edges:
        pr = road.project(e, step.x, step.y)
        if step.kappa > 0.0 and abs(angle_diff(step.heading, pr[4])) > cfg.online.reinit.against_heading_deg:
            continue
        out.append((e, pr))
    return out


def initialise(road: RoadModel, index: EdgeIndex, state: SessionState, step: Step, cfg: MatchConfig) -> None:
    """Start again from a spatial-index search around the fix."""
    m, o = cfg.model, cfg.online
    radius = min(
        max(m.search_radius, o.reinit.reinit_sigmas * step.sigma),
        max(o.region.init_max_radius, m.search_radius),
    )
    hyps = []
    for e, (off, dist, px, py, brg) in _candidates(road, index, step, radius, cfg):
        lp = road.emission(dist, step.sigma, step.heading, brg, step.kappa)
        hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
    state.hyps = normalise(hyps, prune_log_ratio=o.region.prune_log_ratio)
    state.region.restart(pending=len({h.edges[0] for h in state.hyps}) > 1, odo=state.odo)
    state.crossings.restart()
    state.bad_time = state.bad_odo = math.nan


def add_alternatives(
    road: RoadModel,
    index: EdgeIndex,
    state: SessionState,
    step: Step,
    best: Hypothesis,
    cfg: MatchConfig,
    *,
    edges: list[int] | None = None,
) -> None:
    """Soft re-initialisation: the fix has left the road believed, so nearby roads found by
    the spatial index (or the given ``edges``) join the filter with a switching penalty;
    evidence decides."""
    m, o = cfg.model, cfg.online
    radius = min(max(m.search_radius, o.reinit.reinit_sigmas * step.sigma), o.region.init_max_radius)
    have = {h.edges[h.k] for h in state.hyps}
    base = road.emission(best.dist, step.sigma, step.heading, best.bearing, step.kappa)
    for e, (off, dist, px, py, brg) in _candidates(road, index, step, radius, cfg, edges):
        if e in have or dist > best.dist + step.sigma:
            continue
        lp = (
            best.logp
            - o.region.switch_penalty
            + step.weight * (road.emission(dist, step.sigma, step.heading, brg, step.kappa) - base)
        )
        state.hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
    state.hyps = normalise(state.hyps, prune_log_ratio=o.region.prune_log_ratio)
    keep_best(state.hyps, o.region.max_hypotheses)


def extend(road: RoadModel, h: Hypothesis, reach: float, cfg: MatchConfig, out: list[Hypothesis]) -> None:
    """``h`` with every legal continuation of its path until it reaches ``reach`` metres (at most
    ``max_hops`` edges ahead of the vehicle's), appended to ``out``."""
    total = 0.0
    for e in h.edges:
        total += road.elen[e]
    if total >= reach or len(h.edges) - h.k >= cfg.online.region.max_hops:
        out.append(h)
        return
    kids = road.children(h.edges[-1], cfg)
    if not kids:
        out.append(h)
        return
    for e2, pen in kids:
        extend(road, h.branch(e2, pen), reach, cfg, out)


def advance(road: RoadModel, state: SessionState, step: Step, cfg: MatchConfig) -> list[Hypothesis]:
    """Extend paths near their end node, then the filter step: place the fix on each path and
    score it (emission, transition, turn). Returns the new hypotheses (not yet normalised)."""
    o = cfg.online
    d = step.travelled
    ahead = (d if not math.isnan(d) else 0.0) + step.r_a
    hyps: list[Hypothesis] = []
    grow = step.odo_sigma * d if step.odo_known and not math.isnan(d) else math.nan
    for h in state.hyps:
        if not math.isnan(h.anc_sd):
            h.anc_sd += grow  # nan (no odometer) drops the anchor
            if math.isnan(grow):
                h.anc = math.nan
        extend(road, h, h.s + ahead, cfg, hyps)
    keep_best(hyps, o.region.max_hypotheses)
    turn_obs, covered = (math.nan, 0.0)
    if len(hyps) > 1 and step.kappa > 0.0:
        turn_obs, covered = heading_change(state.headings, state.odo, window=o.evidence.turn_window)
    filter_step(
        hyps,
        weight=step.weight,
        turn_weight=step.turn_weight,
        place=lambda hs: place_all(road, hs, step, cfg, turn_obs=turn_obs, covered=covered),
    )
    if step.still_weight > 0.0 and len(hyps) > 1:
        # the shared emission's heading term alone (no distance: σ 1, distance 0)
        w, kappa, heading = step.still_weight, step.still_kappa, step.heading
        for h in hyps:
            h.logp += w * road.emission(0.0, 1.0, heading, h.bearing, kappa)
    return merge_identical(hyps, by_path=step.gps)


def merge_identical(hyps: list[Hypothesis], *, by_path: bool = False) -> list[Hypothesis]:
    """One hypothesis per path and place: paths that came by different ways (a road that joined
    the filter, a branch kept past a commit) to the same edges and the same position are one
    belief, and their probabilities add (the more probable one's record is kept). With
    ``by_path`` (a GPS-aided fix, which places every hypothesis on its path itself), one per
    path and edge, wherever along it: their places differ only by what each carried (a turn
    anchor), and the fix no longer tells them apart. Left apart, a copy never falls behind its
    twin: the pair would stay ambiguous for good, and the learning that needs a single
    hypothesis (the fix's bias and residuals) would never run."""
    if len(hyps) < 2:
        return hyps
    seen: dict[tuple[float, ...], int] = {}
    out: list[Hypothesis] = []
    for h in hyps:
        key = (h.k, 0.0 if by_path else h.s, *h.edges)
        i = seen.get(key)
        if i is None:
            seen[key] = len(out)
            out.append(h)
            continue
        g = out[i]
        hi, lo = (h, g) if h.logp > g.logp else (g, h)
        hi.logp += math.log1p(math.exp(lo.logp - hi.logp))
        out[i] = hi
    return out


def move_to(road: RoadModel, h: Hypothesis, s: float, step: Step) -> None:
    """Put ``h`` at distance ``s`` along its path (clamped to the path)."""
    j, start = 0, 0.0
    s = max(s, 0.0)
    while j < len(h.edges) - 1 and s > start + road.elen[h.edges[j]]:
        start += road.elen[h.edges[j]]
        j += 1
    off = min(s - start, road.elen[h.edges[j]])
    if j < h.k:
        del h.enter[j + 1 :]
    while len(h.enter) < j + 1:
        h.enter.append(step.time)
    h.k, h.off, h.s = j, off, start + off
    h.px, h.py, h.bearing = road.locate(h.edges[j], off)
    h.dist = math.hypot(h.px - step.x, h.py - step.y)

"""Path hypotheses: start them from the spatial index, let other roads join, extend them at
their end node with the legal moves, and place each on its path for a fix."""

from __future__ import annotations

import math

from mapmatch.config import MatchConfig
from mapmatch.graph.index import EdgeIndex
from mapmatch.online.along import along_track
from mapmatch.online.filter import filter_step, keep_best, normalise
from mapmatch.online.road import Projection, RoadModel
from mapmatch.online.state import Hypothesis, PathPos, SessionState, Step
from mapmatch.turns import angle_diff, heading_change


def _candidates(
    road: RoadModel,
    index: EdgeIndex,
    step: Step,
    radius: float,
    cfg: MatchConfig,
    edges: list[int] | None = None,
) -> list[tuple[int, Projection]]:
    """Edges near the fix (or the given ``edges``) not heading against it (never start against
    one-ways), projected."""
    if edges is None:
        edges = index.query([[step.x, step.y]], radius, k=cfg.model.max_candidates).edge.tolist()
    out = []
    for e in edges:
        pr = road.project(e, step.x, step.y)
        if step.kappa > 0.0 and abs(angle_diff(step.heading, pr[4])) > cfg.online.init_max_heading_deg:
            continue
        out.append((e, pr))
    return out


def initialise(road: RoadModel, index: EdgeIndex, state: SessionState, step: Step, cfg: MatchConfig) -> None:
    """Start again from a spatial-index search around the fix."""
    m, o = cfg.model, cfg.online
    radius = min(max(m.search_radius, o.reinit_sigmas * step.sigma), max(o.init_max_radius, m.search_radius))
    hyps = []
    for e, (off, dist, px, py, brg) in _candidates(road, index, step, radius, cfg):
        lp = road.emission(dist, step.sigma, step.heading, brg, step.kappa)
        hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
    state.hyps = normalise(hyps, prune_log_ratio=o.prune_log_ratio)
    state.init_pending = len({h.edges[0] for h in state.hyps}) > 1
    state.init_odo = state.odo
    state.live = []
    state.back = []
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
    radius = min(max(m.search_radius, o.reinit_sigmas * step.sigma), o.init_max_radius)
    have = {h.edges[h.k] for h in state.hyps}
    base = road.emission(best.dist, step.sigma, step.heading, best.bearing, step.kappa)
    for e, (off, dist, px, py, brg) in _candidates(road, index, step, radius, cfg, edges):
        if e in have or dist > best.dist + step.sigma:
            continue
        lp = (
            best.logp
            - o.switch_penalty
            + step.weight * (road.emission(dist, step.sigma, step.heading, brg, step.kappa) - base)
        )
        state.hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
    state.hyps = normalise(state.hyps, prune_log_ratio=o.prune_log_ratio)
    keep_best(state.hyps, o.max_hypotheses)


def extend(road: RoadModel, h: Hypothesis, reach: float, cfg: MatchConfig, out: list[Hypothesis]) -> None:
    """``h`` with every legal continuation of its path until it reaches ``reach`` metres (at most
    ``max_hops`` edges ahead of the vehicle's), appended to ``out``."""
    total = 0.0
    for e in h.edges:
        total += road.elen[e]
    if total >= reach or len(h.edges) - h.k >= cfg.online.max_hops:
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
    keep_best(hyps, o.max_hypotheses)
    turn_obs, covered = (math.nan, 0.0)
    if len(hyps) > 1 and step.kappa > 0.0:
        turn_obs, covered = heading_change(state.headings, state.odo, window=o.turn_window)
    cache: dict[int, Projection] = {}
    filter_step(
        hyps,
        weight=step.weight,
        turn_weight=step.turn_weight,
        place=lambda h: place(road, h, step, cfg, cache),
        turn=lambda h, s_prev: road.turn(h, s_prev, turn_obs, covered, cfg),
    )
    if step.still_weight > 0.0 and len(hyps) > 1:
        # the shared emission's heading term alone (no distance: σ 1, distance 0)
        w, kappa, heading = step.still_weight, step.still_kappa, step.heading
        for h in hyps:
            h.logp += w * road.emission(0.0, 1.0, heading, h.bearing, kappa)
    return hyps


def place(
    road: RoadModel, h: Hypothesis, step: Step, cfg: MatchConfig, cache: dict[int, Projection]
) -> float:
    """Move ``h`` to its best position for this fix; return that position's log-score."""
    best_sc, best, acc = _nearest_on_path(road, h, step, cfg, cache)
    if step.gps:
        moved, miss = along_track(road, h, step, best, acc, cfg)
        if moved is not best:
            # scored where the vehicle is now believed to be: its heading against the road
            # there (the distance stays the fix's offset from the road, which the correction
            # along the road does not change)
            dist = debiased(step, best.dist, best.px, best.py, best.bearing, cfg)
            best_sc = road.emission(dist, step.sigma, step.heading, moved.bearing, step.kappa) - miss
            if not math.isnan(step.travelled):
                best_sc += road.transition(moved.s - h.s, step, cfg)
            best = moved
    elif step.odo_known:
        best_sc, best = _dead_reckon(road, h, step, acc, cfg)
    j = best.j
    if j < h.k:
        h.k = j
        del h.enter[j + 1 :]
    while h.k < j:
        h.k += 1
        h.enter.append(step.time)
    h.off, h.s, h.dist, h.px, h.py, h.bearing = best.off, best.s, best.dist, best.px, best.py, best.bearing
    return best_sc


def _nearest_on_path(
    road: RoadModel, h: Hypothesis, step: Step, cfg: MatchConfig, cache: dict[int, Projection]
) -> tuple[float, PathPos, float]:
    """The fix's best projection onto ``h``'s path (emission and transition), with hysteresis at
    nodes: ``(score, position, furthest s allowed)``."""
    x, y, sigma = step.x, step.y, step.sigma
    hold = cfg.online.node_hold_sigmas * sigma
    best_sc = -math.inf
    best = (h.k, h.off, h.s, h.dist, h.px, h.py, h.bearing)
    acc = 0.0
    j0 = max(h.k - 1, 0)  # one edge back: a fix may run ahead of the vehicle near a node
    for j in range(j0):
        acc += road.elen[h.edges[j]]
    # stopped: the fix's noise may move the vehicle back but not on across a node
    jmax = h.k + 1 if step.stopped else len(h.edges)
    reach = step.r_a
    ahead = (step.travelled if not math.isnan(step.travelled) else 0.0) + reach
    for j in range(j0, jmax):
        e = h.edges[j]
        pr = cache.get(e)
        if pr is None:
            pr = cache[e] = road.project(e, x, y)
        off, dist, px, py, brg = pr
        s = acc + off
        if j < h.k and road.elen[e] - off < hold:
            # back across the node only when the fix is clearly behind it (no flicker)
            acc += road.elen[e]
            continue
        if j < jmax - 1 and off >= road.elen[e] - 1e-6:
            # the fix is past the end of an edge the path continues on: held at the node
            # only within a margin (stop line, along-track error); further on the next edge
            # holds that place (else the hypothesis would lag ever further behind)
            e2 = h.edges[j + 1]
            pr2 = cache.get(e2)
            if pr2 is None:
                pr2 = cache[e2] = road.project(e2, x, y)
            if pr2[0] > hold:
                acc += road.elen[e]
                continue
        cands = [pr]
        if not h.s - reach <= s <= h.s + ahead:
            # an edge that loops back (a ramp) may pass nearer the fix further on: the part
            # the vehicle can have reached since the last fix is a candidate too
            local = road.project_between(e, x, y, h.s - reach - acc, h.s + ahead - acc)
            if local is not None:
                cands.append(local)
        for off, dist, px, py, brg in cands:
            s = acc + off
            sc = road.emission(debiased(step, dist, px, py, brg, cfg), sigma, step.heading, brg, step.kappa)
            if not math.isnan(step.travelled):
                sc += road.transition(s - h.s, step, cfg)
            if sc > best_sc + 1e-9:
                best_sc = sc
                best = (j, off, s, dist, px, py, brg)
        acc += road.elen[e]
    return best_sc, PathPos(*best), acc


def debiased(step: Step, dist: float, px: float, py: float, bearing: float, cfg: MatchConfig) -> float:
    """The fix's distance from the road point ``(px, py)`` of ``bearing`` with the learnt fix
    bias's part across the road taken off (``bias_emission`` of it): a receiver's error lasts
    minutes, so a fix that has lain 10 m left of the road for a minute is no evidence for the
    road 10 m to the left. ``dist`` unchanged without GPS or before the bias is learnt."""
    share = cfg.online.bias_emission
    b = step.bias
    if share <= 0.0 or not step.gps or math.isnan(b.pxx):
        return dist
    rad = math.radians(bearing)
    nx, ny = math.cos(rad), -math.sin(rad)  # normal to the road (bearing clockwise from north)
    z = (step.x - px) * nx + (step.y - py) * ny
    zc = z - share * (b.bx * nx + b.by * ny)
    return math.sqrt(max(dist * dist - z * z, 0.0) + zc * zc)


def _dead_reckon(
    road: RoadModel, h: Hypothesis, step: Step, acc: float, cfg: MatchConfig
) -> tuple[float, PathPos]:
    """Dead reckoning: the fix drifts, the odometer does not; the vehicle is carried along its
    path by the distance travelled (the fix still weighs the paths against each other)."""
    d = step.travelled
    s_pred = min(h.s + d, acc)
    j, rest = h.k, s_pred
    for i in range(h.k):
        rest -= road.elen[h.edges[i]]
    while j < len(h.edges) - 1 and rest > road.elen[h.edges[j]]:
        rest -= road.elen[h.edges[j]]
        j += 1
    rest = min(max(rest, 0.0), road.elen[h.edges[j]])
    px, py, brg = road.locate(h.edges[j], rest)
    dist = math.hypot(px - step.x, py - step.y)
    # the distance carried is uncertain (odometer scale): near a node the heading is
    # compared with the road anywhere within that uncertainty, not just at one point
    head = brg
    spread = cfg.online.pos_sigma_floor + step.odo_sigma * step.dr
    if step.kappa > 0.0 and not math.isnan(step.heading):
        for k in (-2, -1, 1, 2):
            b = road.bearing_on_path(h, s_pred + 0.5 * k * spread)
            if abs(angle_diff(step.heading, b)) < abs(angle_diff(step.heading, head)):
                head = b
    sc = road.emission(dist, step.sigma, step.heading, head, step.kappa) + road.transition(
        s_pred - h.s, step, cfg
    )
    return sc, PathPos(j, rest, s_pred, dist, px, py, brg)


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

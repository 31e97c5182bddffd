"""The report: which hypothesis is shown for a fix, and the :class:`SnapResult` built from the
state. Pure: nothing here writes the state."""

from __future__ import annotations

import math
from dataclasses import dataclass

from graph.angles import angle_diff
from graph.projection import point_to_lonlat
from mapmatch.config import MatchConfig
from mapmatch.measurement import Agreement, measure
from mapmatch.online.filter import best as best_of
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, SessionState, Step
from mapmatch.types import Candidate, Correction, Fix, SnapResult, State, Turn

EdgeMass = dict[int, tuple[float, Hypothesis]]


def edge_mass(hyps: list[Hypothesis]) -> EdgeMass:
    """Probability mass per edge the vehicle may be on, with that edge's most probable
    hypothesis. Hypotheses that differ only in edges not reached yet are one belief about
    where the vehicle is (each carries the whole weight): they count once, not once per
    branch ahead."""
    groups: dict[tuple[int, ...], Hypothesis] = {}
    for h in hyps:
        key = tuple(h.edges[: h.k + 1])
        g = groups.get(key)
        if g is None or h.logp > g.logp:
            groups[key] = h
    out: EdgeMass = {}
    for h in groups.values():
        e = h.edges[h.k]
        p = math.exp(h.logp)
        a = out.get(e)
        out[e] = (p, h) if a is None else (a[0] + p, h if h.logp > a[1].logp else a[1])
    return out


@dataclass(slots=True)
class Shown:
    """The hypothesis to report and the probability mass per edge (empty for a single
    hypothesis)."""

    hypothesis: Hypothesis
    mass: EdgeMass


def shown_hypothesis(state: SessionState, cfg: MatchConfig) -> Shown:
    """The hypothesis to report: on the edge of highest total probability (best for the
    per-fix edge), its most probable one; back to an edge behind the one reported last only
    on clear evidence (no flicker). Also the mass per edge (empty for a single hypothesis)."""
    hyps = state.hyps
    best = best_of(hyps)
    agg = edge_mass(hyps) if len(hyps) > 1 else {}
    if agg:
        mass = {e: a[0] for e, a in agg.items()}
        top = max(mass, key=mass.__getitem__)
        shown = state.shown
        if (
            top != shown
            and shown in mass
            and mass[top] < cfg.online.corrections.report_back_ratio * mass[shown]
        ):
            hs = best_of([h for h in hyps if h.edges[h.k] == shown])
            if top in hs.edges[: hs.k]:
                top = shown
        if top != best.edges[best.k]:
            best = best_of([h for h in hyps if h.edges[h.k] == top])
    return Shown(best, agg)


def state_of(state: SessionState, reinit: bool) -> State:
    """The matcher's state for this fix."""
    if reinit:
        return _REINITIALISED
    if not math.isnan(state.bad_time):
        return _OFF_ROAD
    if state.region.init_pending:
        return _INITIALISING
    return _AMBIGUOUS if len(state.hyps) > 1 else _ON_ROAD


# the states as module values: an enum member's look-up on its class takes 0.1 µs (per fix)
_REINITIALISED, _OFF_ROAD, _INITIALISING = State.REINITIALISED, State.OFF_ROAD, State.INITIALISING
_AMBIGUOUS, _ON_ROAD = State.AMBIGUOUS, State.ON_ROAD


def candidates(road: RoadModel, agg: EdgeMass) -> tuple[Candidate, ...]:
    """The edges the vehicle may be on, most probable first."""
    total = sum([a[0] for a in agg.values()])
    return tuple(  # of a list: a generator is slower
        [
            Candidate(
                ce,
                road.u_id[ce],
                road.v_id[ce],
                road.piece(ce, a[1].off)[0],
                a[0] / total,
                a[1].off,
                a[1].dist,
            )
            for ce, a in sorted(agg.items(), key=lambda kv: -kv[1][0])
        ]
    )


def held_beyond(road: RoadModel, h: Hypothesis, step: Step) -> float:
    """Metres by which a GPS-aided fix's along-track estimate (its projection on the road's
    tangent less the learnt bias) lies past the node ``h`` is held at: past the end of its
    edge (positive) or before its start (negative); 0 when ``h`` is not at a node."""
    off, length = h.off, road.elen[h.edges[h.k]]
    at_end = off >= length - 1e-6
    if not at_end and off > 1e-6:
        return 0.0
    rad = math.radians(h.bearing)
    tx, ty = math.sin(rad), math.cos(rad)
    b = step.bias
    a = (step.x - h.px - b[0]) * tx + (step.y - h.py - b[1]) * ty
    return max(a, 0.0) if at_end else min(a, 0.0)


@dataclass(slots=True)
class Outcome:
    """What the update decided for a fix, besides the hypothesis shown.

    Attributes
    ----------
    turn : Turn
        The turn committed at this fix.
    correction : Correction or None
        The correction of earlier answers, if any.
    reinit : bool
        Whether the matcher re-initialised at this fix.
    other_dist : float
        Metres from the fix to the nearest road alongside the shown answer (inf: none, or
        not looked for; :class:`~mapmatch.online.parallel.ParallelRoads`).
    """

    turn: Turn
    correction: Correction | None
    reinit: bool
    other_dist: float = math.inf


def agreement(fix: Fix, step: Step, h: Hypothesis, cfg: MatchConfig, *, other_dist: float) -> Agreement:
    """How the fix agrees with answer ``h``: its heading against the road's, and its distance
    from the road and from the nearest road alongside (``other_dist``), in its reported σ
    (the model's fallback σ when it reports none; at least the σ floor)."""
    return Agreement(*_agreement(fix, step, h, cfg, other_dist))


def _agreement(
    fix: Fix, step: Step, h: Hypothesis, cfg: MatchConfig, other_dist: float
) -> tuple[float, float, float]:
    """:func:`agreement`'s fields as a plain tuple."""
    head = step.heading
    sigma = fix.pos_sigma if fix.pos_sigma > 0.0 else cfg.model.gps_sigma  # NaN: not > 0
    sigma = max(sigma, cfg.online.evidence.pos_sigma_floor)
    diff = angle_diff(head, h.bearing) if head == head else math.nan
    return diff, h.dist / sigma, other_dist / sigma


def report(
    road: RoadModel,
    state: SessionState,
    fix: Fix,
    step: Step,
    shown: Shown,
    cfg: MatchConfig,
    outcome: Outcome,
) -> SnapResult:
    """The result for ``fix``: the shown hypothesis's position, the way piece under it, the
    candidates, the state and the map-aided measurement."""
    agg, turn, correction, reinit = shown.mass, outcome.turn, outcome.correction, outcome.reinit
    shown_hyp = shown.hypothesis
    g = road.graph
    e = shown_hyp.edges[shown_hyp.k]
    lon, lat = point_to_lonlat(g.crs, shown_hyp.px, shown_hyp.py)
    st = state_of(state, reinit)
    cands = candidates(road, agg) if len(state.hyps) > 1 else ()
    way_id, name, road_class, speed_kph = road.piece(e, shown_hyp.off)
    probability = 1.0
    for c in cands:
        if c.edge == e:
            probability = c.probability
            break
    beyond = held_beyond(road, shown_hyp, step) if step.gps else 0.0
    diff, cross_sigmas, other_sigmas = _agreement(fix, step, shown_hyp, cfg, outcome.other_dist)
    aided = measure(  # map_aided_measurement's records as plain values (a per-fix path)
        st, e, shown_hyp.off, lat, lon, shown_hyp.bearing, probability,
        state.odo - state.region.init_odo,  # since_init
        beyond,
        step.gps,
        step.sigma,  # fix_sigma
        step.bias[2:],  # bias_cov: (pxx, pxy, pyy)
        cfg.online.bias.bias_white_fraction,  # white_share
        shown_hyp.anc_sd,  # anchor_sd
        step.odo_sigma,
        step.dr,  # dr_distance
        cfg.model.gps_sigma,
        road_class, road.rev[e] < 0,  # one_way
        math.nan, math.nan,  # width, lanes: not tagged
        road.bearing_at, road.elen[e],
        True, diff, cross_sigmas, other_sigmas,  # the agreement
        cfg.measurement, cfg.confidence,
    )  # fmt: skip
    return SnapResult(  # by position, in field order (see SnapResult)
        fix.time,  # time
        st,  # state
        e,  # edge
        road.u_id[e],  # u
        road.v_id[e],  # v
        way_id,
        shown_hyp.off,  # offset
        lat,
        lon,
        shown_hyp.bearing,
        shown_hyp.dist,
        turn,
        cands,  # candidates
        correction,
        fix.lat,  # raw_lat
        fix.lon,  # raw_lon
        name,
        road_class,
        speed_kph,
        aided,  # map_aided
    )


def off_road(fix: Fix) -> SnapResult:
    """The result for a fix the matcher cannot place on a road."""
    return SnapResult(time=fix.time, state=State.OFF_ROAD, raw_lat=fix.lat, raw_lon=fix.lon)

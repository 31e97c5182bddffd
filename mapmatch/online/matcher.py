"""The online matcher: one read-only road model shared by every vehicle, and ``update``, which
orchestrates the mechanisms for one fix (see :mod:`mapmatch.online`)."""

from __future__ import annotations

import dataclasses
import math

from graph.angles import angle_diff
from graph.index import EdgeIndex
from graph.road_graph import RoadGraph
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.online import anchor, bias, hypotheses, region, report
from mapmatch.online.correction import remember_live
from mapmatch.online.filter import best as best_of
from mapmatch.online.filter import normalise
from mapmatch.online.parallel import ParallelRoads
from mapmatch.online.road import RoadModel
from mapmatch.online.state import SessionState, Step
from mapmatch.online.step import prepare
from mapmatch.turns import add_sample
from mapmatch.types import Fix, SnapResult, Turn


class OnlineMatcher:
    """Per-vehicle online matcher over one read-only road graph (thread-safe, shared).

    Parameters
    ----------
    graph
        The road graph.
    index
        Its spatial index (built when omitted).
    config
        Default parameters (the map-aided measurement's among them); :meth:`update` accepts a
        per-call override.
    """

    def __init__(
        self,
        graph: RoadGraph,
        index: EdgeIndex | None = None,
        config: MatchConfig = DEFAULT_CONFIG,
    ):
        self.graph = graph
        self.index = index if index is not None else EdgeIndex(graph)
        self.config = config
        self.road = RoadModel(graph)
        self.parallel = ParallelRoads(self.road, self.index)
        m = config.confidence
        if m.coef_parallel != 0.0 or m.coef_parallel_gap != 0.0:  # the roads alongside, now: no fix waits
            self.parallel.prepare(config)
        self.edge_len_ref = self.road.edge_len_ref

    def new_session(self) -> SessionState:
        """A fresh vehicle state."""
        return SessionState()

    def region_radius(self, sigma: float, config: MatchConfig | None = None) -> float:
        """Ambiguous-region radius in metres for a fix of position σ (DR growth included)."""
        return region.region_radius(self.road, sigma, config or self.config)

    def update(self, state: SessionState, fix: Fix, *, config: MatchConfig | None = None) -> SnapResult:
        """Match one fix; mutates ``state``. Raises :class:`ValidationError` (state unchanged)."""
        cfg = config or self.config
        step = prepare(self.road, state, fix, cfg)
        if step is None:  # far off the map: accepted, but nowhere to put it
            state.time = fix.time
            anchor.drop_chain(state.anchor)
            return report.off_road(fix)
        # the first GPS-aided fix after dead reckoning, and those while its drift blends out:
        # they are the truth, not outliers
        first = state.odo - state.gps_odo > 0.0
        searched = step.time - state.search_time < cfg.online.evidence.evidence_time
        blending = state.bias.drift_sigma > step.fix_sigma and not searched
        returned = step.gps and step.kappa > 0.0 and (first or blending)
        self._take(state, step, cfg)
        reinit = False
        if state.hyps:
            self._filter(state, step, cfg, returned=returned)
            reinit = self._check_road(state, step, cfg)
        else:
            hypotheses.initialise(self.road, self.index, state, step, cfg)
        if not state.hyps:
            return report.off_road(fix)
        turn, corr = (Turn.NONE, None) if reinit else region.commit(self.road, state, step, cfg)
        shown = report.shown_hypothesis(state, cfg)
        state.shown = shown.hypothesis.edges[shown.hypothesis.k]
        if len(state.hyps) > 1:
            remember_live(state.region, state.shown, step, cfg)
        h = shown.hypothesis
        m = cfg.confidence
        other = (
            self.parallel.nearest(h.edges[h.k], h.off, step.x, step.y, cfg)
            if m.coef_parallel != 0.0 or m.coef_parallel_gap != 0.0
            else math.inf
        )
        outcome = report.Outcome(turn, corr, reinit, other)
        return report.report(self.road, state, fix, step, shown, cfg, outcome)

    # ------------------------------------------------------------------ steps of update
    def _take(self, state: SessionState, step: Step, cfg: MatchConfig) -> None:
        """The fix is accepted: the odometer, drift, bias, heading samples and trail move on."""
        if not math.isnan(step.travelled):
            state.odo += step.travelled
        if step.gps:
            state.gps_odo = state.odo
        anchor.carry(state.anchor, step)
        state.speed = step.speed
        bias.take(state.bias, step, cfg)
        state.time, state.x, state.y = step.time, step.x, step.y
        if step.kappa > 0.0:
            ev = cfg.online.evidence
            add_sample(
                state.headings, state.odo, step.heading,
                window=ev.turn_window, spacing=cfg.online.corrections.trail_step,
                max_samples=ev.turn_max_samples,
            )  # fmt: skip
        if step.odo_known:
            anchor.add_trail(
                state.crossings.trail,
                step.time,
                state.odo,
                step.travelled <= cfg.online.stop.still_distance,
                cfg,
            )

    def _filter(self, state: SessionState, step: Step, cfg: MatchConfig, *, returned: bool) -> None:
        """The filter step and, when the fix has left the road believed (or GPS has just
        returned away from it), the search for other roads."""
        hyps = hypotheses.advance(self.road, state, step, cfg)
        state.hyps = normalise(hyps, prune_log_ratio=cfg.online.region.prune_log_ratio)
        best = best_of(state.hyps)
        o = cfg.online
        against = (
            step.kappa > 0.0 and abs(angle_diff(step.heading, best.bearing)) > o.reinit.against_heading_deg
        )
        # at most one search per independent observation (``evidence_time``)
        searched = step.time - state.search_time < o.evidence.evidence_time
        if returned and o.reinit.return_sigmas > 0.0 and best.dist > o.reinit.return_sigmas * step.fix_sigma:
            # weigh the roads near the returning fix against it at its own σ, at once
            state.search_time = step.time
            own = dataclasses.replace(step, sigma=step.fix_sigma)
            hypotheses.add_alternatives(self.road, self.index, state, own, best, cfg)
        elif step.stopped:
            pass  # a stopped vehicle has not left its road, however far its fixes wander
        elif step.gps and (best.dist > o.reinit.soft_reinit_sigmas * step.sigma or against) and not searched:
            state.search_time = step.time
            hypotheses.add_alternatives(self.road, self.index, state, step, best, cfg)

    def _check_road(self, state: SessionState, step: Step, cfg: MatchConfig) -> bool:
        """Re-initialise after the fixes have been off the road long enough (returns whether it
        did); learn the fix's residuals and bias while on one road."""
        o = cfg.online
        best = best_of(state.hyps)
        if best.dist > o.reinit.reinit_sigmas * step.sigma:
            anchor.drop_chain(state.anchor)
            if math.isnan(state.bad_time):
                state.bad_time, state.bad_odo = step.time, state.odo
            elif step.stopped and not math.isnan(step.dt):
                state.bad_time += step.dt  # the clock runs only while moving: fixes wander at a stop
            if (
                step.time - state.bad_time >= o.reinit.reinit_time
                or state.odo - state.bad_odo >= o.reinit.reinit_distance
            ):
                hypotheses.initialise(self.road, self.index, state, step, cfg)
                return True
            return False
        state.bad_time = state.bad_odo = math.nan
        if len(state.hyps) == 1 and not state.region.init_pending:
            bias.learn_residuals(state.bias, best, step, cfg)
            bias.learn_bias(state.bias, best, step, cfg)
        anchor.learn_scale_gps(self.road, state.anchor, best, step, cfg, drift_sigma=state.bias.drift_sigma)
        return False

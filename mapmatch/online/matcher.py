"""The online matcher: one read-only road model shared by every vehicle, and ``update``, which
orchestrates the mechanisms for one fix (see :mod:`mapmatch.online`)."""

from __future__ import annotations

import math

from graph.index import EdgeIndex
from graph.projection import point_to_xy
from graph.road_graph import RoadGraph
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.online import anchor, bias, hypotheses, region, report, stopline
from mapmatch.online.corrections import remember_live
from mapmatch.online.filter import best as best_of
from mapmatch.online.filter import normalise
from mapmatch.online.road import RoadModel
from mapmatch.online.state import Hypothesis, SessionState, Step
from mapmatch.turns import add_sample, angle_diff
from mapmatch.types import Fix, SnapResult, Turn

# input limits: a fix beyond them is rejected (a ValidationError naming the field)
LIMITS = {"speed": 1_000.0, "distance": 100_000.0, "pos_sigma": 100_000.0, "heading_sigma": 360.0}


class OnlineMatcher:
    """Per-vehicle online matcher over one read-only road graph (thread-safe, shared).

    Parameters
    ----------
    graph
        The road graph.
    index
        Its spatial index (built when omitted).
    config
        Default parameters; :meth:`update` accepts a per-call override.
    """

    def __init__(
        self, graph: RoadGraph, index: EdgeIndex | None = None, config: MatchConfig = DEFAULT_CONFIG
    ):
        self.graph = graph
        self.index = index if index is not None else EdgeIndex(graph)
        self.config = config
        self.road = RoadModel(graph)
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
        step = self._prepare(state, fix, cfg)
        if step is None:  # far off the map: accepted, but nowhere to put it
            state.time = fix.time
            return report.off_road(fix)
        self._take(state, step, cfg)
        held: list[tuple[Hypothesis, float]] = []
        reinit = False
        if state.hyps:
            held = self._filter(state, step, cfg)
            reinit = self._check_road(state, step, cfg)
            if reinit:
                held = []
        else:
            hypotheses.initialise(self.road, self.index, state, step, cfg)
        if not state.hyps:
            return report.off_road(fix)
        turn, corr = (Turn.NONE, None) if reinit else region.commit(self.road, state, step, cfg)
        shown, agg = report.shown_hypothesis(state, cfg)
        corr = stopline.back_at_stop_line(state, shown, held, step, corr)
        state.shown = shown.edges[shown.k]
        if len(state.hyps) > 1:
            remember_live(state, state.shown, step, cfg)
        return report.report(self.road, state, fix, shown, agg, turn=turn, correction=corr, reinit=reinit)

    # ------------------------------------------------------------------ steps of update
    def _take(self, state: SessionState, step: Step, cfg: MatchConfig) -> None:
        """The fix is accepted: the odometer, drift, bias, heading samples and trail move on."""
        if not math.isnan(step.travelled):
            state.odo += step.travelled
        if step.gps:
            state.gps_odo = state.odo
        state.drift_sigma = bias.drift_sigma(state, step.gps, 0.0, step.dt, cfg) if step.gps else step.sigma
        state.time, state.x, state.y = step.time, step.x, step.y
        state.bias = step.bias
        if step.kappa > 0.0:
            add_sample(state.headings, state.odo, step.heading, window=cfg.online.turn_window)
        if step.odo_known:
            anchor.add_trail(
                state.trail, step.time, state.odo, step.travelled <= cfg.online.still_distance, cfg
            )

    def _filter(self, state: SessionState, step: Step, cfg: MatchConfig) -> list[tuple[Hypothesis, float]]:
        """The filter step, the stop line and, when the fix has left the road believed, the
        search for other roads."""
        hyps = hypotheses.advance(self.road, state, step, cfg)
        held = stopline.hold_stopped(self.road, hyps, state, step, cfg)
        state.hyps = normalise(hyps, prune_log_ratio=cfg.online.prune_log_ratio)
        best = best_of(state.hyps)
        o = cfg.online
        against = step.kappa > 0.0 and abs(angle_diff(step.heading, best.bearing)) > o.against_heading_deg
        if (
            step.gps
            and (best.dist > o.soft_reinit_sigmas * step.sigma or against)
            and not (step.time - state.search_time < o.search_every)
        ):
            state.search_time = step.time
            hypotheses.add_alternatives(self.road, self.index, state, step, best, cfg)
        return held

    def _check_road(self, state: SessionState, step: Step, cfg: MatchConfig) -> bool:
        """Re-initialise after the fixes have been off the road long enough (returns whether it
        did); learn the fix's residuals and bias while on one road."""
        o = cfg.online
        best = best_of(state.hyps)
        if best.dist > o.reinit_sigmas * step.sigma:
            if math.isnan(state.bad_time):
                state.bad_time, state.bad_odo = step.time, state.odo
            if step.time - state.bad_time >= o.reinit_time or state.odo - state.bad_odo >= o.reinit_distance:
                hypotheses.initialise(self.road, self.index, state, step, cfg)
                return True
            return False
        state.bad_time = state.bad_odo = math.nan
        if len(state.hyps) == 1 and not state.init_pending:
            bias.learn_residuals(state, best, step, cfg)
            bias.learn_bias(state, best, step, cfg)
        return False

    def _prepare(self, state: SessionState, fix: Fix, cfg: MatchConfig) -> Step | None:
        """Validate the fix and derive the per-fix quantities (None: far off the map)."""
        self._validate(state, fix)
        x, y = point_to_xy(self.graph.crs, fix.lon, fix.lat)
        if not (math.isfinite(x) and math.isfinite(y)) or self.road.far_off(x, y, cfg):
            return None
        m, o = cfg.model, cfg.online
        dt = fix.time - state.time if not math.isnan(state.time) else math.nan
        odo_known = True
        if not math.isnan(fix.distance):
            travelled = fix.distance * (1.0 + state.odo_k)
        elif not math.isnan(fix.speed) and not math.isnan(dt):
            travelled = fix.speed * dt * (1.0 + state.odo_k)
        else:
            odo_known = False
            travelled = math.hypot(x - state.x, y - state.y) if not math.isnan(state.x) else math.nan
        gps = fix.gps_valid is not False
        sigma = self._sigma(state, fix, gps, travelled, dt, cfg)
        heading = 0.0 if fix.heading == 360.0 else fix.heading
        kappa = 0.0
        if not math.isnan(heading) and (math.isnan(fix.speed) or fix.speed >= m.heading_min_speed):
            hs = m.heading_sigma if math.isnan(fix.heading_sigma) else fix.heading_sigma
            floor = o.heading_sigma_floor_deg if fix.gps_valid is not False else o.heading_sigma_floor_dr_deg
            hs = max(hs, floor, math.sqrt(state.res_head2))
            kappa = 1.0 / math.radians(hs) ** 2
        # the fused error is correlated: evidence accrues with time and, when known, distance
        weight = 1.0 if math.isnan(dt) else min(1.0, dt / o.evidence_time)
        stopped = False
        if odo_known and not math.isnan(dt):
            weight = min(weight, travelled / o.evidence_distance)
            stopped = travelled < o.stop_speed * dt
        odo = state.odo + (travelled if not math.isnan(travelled) else 0.0)
        return Step(
            time=fix.time,
            x=x,
            y=y,
            sigma=sigma,
            heading=heading,
            kappa=kappa,
            travelled=travelled,
            odo=odo,
            odo_known=odo_known,
            dt=dt,
            gps=gps,
            weight=weight,
            stopped=stopped,
            r_a=self.region_radius(sigma, cfg),
            dr=0.0 if gps else odo - state.gps_odo,
            odo_sigma=math.sqrt(anchor.odo_kvar(state, cfg) + o.odo_scale_floor**2),
            bias=bias.predict_bias(state.bias, sigma, dt, cfg),
        )

    @staticmethod
    def _sigma(
        state: SessionState, fix: Fix, gps: bool, travelled: float, dt: float, cfg: MatchConfig
    ) -> float:
        """The fix's position σ: as reported, but never below the floor, what the road saw or
        the dead-reckoning drift (reported accuracies are often optimistic)."""
        if fix.pos_cov is not None:
            sigma = math.sqrt(max(0.5 * (fix.pos_cov[0] + fix.pos_cov[2]), 0.25))
        elif math.isnan(fix.pos_sigma) or fix.pos_sigma <= 0.0:
            sigma = cfg.model.gps_sigma
        else:
            sigma = fix.pos_sigma
        sigma = max(sigma, cfg.online.pos_sigma_floor, math.sqrt(state.res_pos2))
        return max(sigma, bias.drift_sigma(state, gps, travelled, dt, cfg))

    def _validate(self, state: SessionState, fix: Fix) -> None:
        fix.validate()
        for name, top in LIMITS.items():
            if getattr(fix, name) > top:
                raise ValidationError(name, f"must be at most {top:g}")
        if fix.pos_cov is not None and max(fix.pos_cov) > LIMITS["pos_sigma"] ** 2:
            raise ValidationError("pos_cov", "variance too large")
        if not math.isnan(state.time) and not fix.time > state.time:
            raise ValidationError("time", "must increase from one fix to the next within a vehicle")
        n = len(self.road.elen)
        for h in state.hyps:
            if max(h.edges) >= n or min(h.edges) < 0:
                raise ValidationError("state", "does not belong to this map")

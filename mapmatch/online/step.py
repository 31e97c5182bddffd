"""The per-fix step: the fix validated and in map coordinates, its σ (floors, learnt residuals,
dead-reckoning drift), heading concentration, evidence weight and odometer."""

from __future__ import annotations

import math

from graph.projection import point_to_xy
from mapmatch.config import MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.model import heading_kappa_one
from mapmatch.online import anchor, bias
from mapmatch.online.region import region_radius
from mapmatch.online.road import RoadModel
from mapmatch.online.state import SessionState, Step
from mapmatch.types import Fix

# input limits: a fix beyond them is rejected (a ValidationError naming the field)
LIMITS = {"speed": 1_000.0, "distance": 100_000.0, "pos_sigma": 100_000.0, "heading_sigma": 360.0}
_SPEED, _DISTANCE, _POS, _HEADING = (LIMITS[k] for k in ("speed", "distance", "pos_sigma", "heading_sigma"))


def prepare(road: RoadModel, state: SessionState, fix: Fix, cfg: MatchConfig) -> Step | None:
    """Validate the fix and derive the per-fix quantities (None: far off the map)."""
    validate(road, state, fix)
    x, y = point_to_xy(road.graph.crs, fix.lon, fix.lat)
    if not (math.isfinite(x) and math.isfinite(y)) or road.far_off(x, y, cfg):
        return None
    o = cfg.online
    dt = fix.time - state.time if not math.isnan(state.time) else math.nan
    travelled, odo_known = _travelled(state, fix, x, y, dt)
    gps = fix.gps_valid is not False
    own = own_sigma(state, fix, cfg)
    dr = state.odo + (travelled if not math.isnan(travelled) else 0.0) - state.gps_odo
    sigma = max(own, bias.drift_sigma(state.bias, gps, dr, dt, cfg))
    heading = 0.0 if fix.heading == 360.0 else fix.heading
    kappa = 0.0
    if not math.isnan(heading) and (math.isnan(fix.speed) or fix.speed >= cfg.model.heading_min_speed):
        hs = cfg.model.heading_sigma if math.isnan(fix.heading_sigma) else fix.heading_sigma
        floor = o.evidence.heading_sigma_floor_deg
        kappa = heading_kappa_one(max(hs, math.sqrt(state.bias.res_head2)), floor)
    # the fused error is correlated: evidence accrues with time and, when known, distance
    per_time = 1.0 if math.isnan(dt) else min(1.0, dt / o.evidence.evidence_time)
    weight = per_time
    stopped = False
    speed = state.speed
    if odo_known and not math.isnan(dt):
        # stopped by this fix's speed or by that over ``stop_time``: over 0.1 s an odometer's
        # noise alone reads as a speed, which must not start a stopped vehicle moving
        speed = min(travelled / dt, _SPEED)  # fixes a hair apart in time: no absurd speed
        now = speed
        if not math.isnan(state.speed):
            speed = state.speed + min(1.0, dt / o.stop.stop_time) * (speed - state.speed)
        stopped = min(now, speed) < o.stop.stop_speed
        if speed < o.stop.zero_speed:
            travelled = 0.0  # standing: the odometer's rectified noise is no distance
        weight = min(weight, travelled / o.evidence.evidence_distance)
    # the turn score is already per metre driven: weighed per fix only by the distance share,
    # or it would count ten times less at 10 Hz than at 1 Hz
    turn_weight = weight / per_time if per_time > 0.0 else 0.0
    # a fused heading (with its σ: gyro-aided) holds at a standstill, where a GPS course does not:
    # a vehicle turning round while stopped shows it by the heading alone, weighed by time
    still_kappa = still_weight = 0.0
    if (
        stopped
        and o.evidence.stopped_heading_weight > 0.0
        and not math.isnan(fix.heading_sigma)
        and not math.isnan(heading)
    ):
        hs = max(fix.heading_sigma, math.sqrt(state.bias.res_head2))
        still_kappa = heading_kappa_one(hs, o.evidence.heading_sigma_floor_deg)
        still_weight = o.evidence.stopped_heading_weight * max(per_time - weight, 0.0)
    odo = state.odo + (travelled if not math.isnan(travelled) else 0.0)
    return Step(  # positional up to ``r_a``, in field order
        fix.time,  # time
        x,
        y,
        sigma,
        heading,
        kappa,
        travelled,
        odo,
        odo_known,
        dt,
        gps,
        weight,
        stopped,
        region_radius(road, sigma, cfg),  # r_a
        dr=0.0 if gps else odo - state.gps_odo,
        bias=bias.predict_bias(state.bias.vector, sigma, dt, cfg),
        odo_sigma=math.sqrt(anchor.odo_kvar(state.anchor, cfg) + o.odometer.odo_scale_floor**2),
        fix_sigma=own,
        turn_weight=turn_weight,
        still_kappa=still_kappa,
        still_weight=still_weight,
        speed=speed,
    )


def _travelled(state: SessionState, fix: Fix, x: float, y: float, dt: float) -> tuple[float, bool]:
    """Metres travelled since the last fix, and whether an odometer (distance or speed) gave
    them: the distance, else the speed over the time (a speed says nothing of a long gap: at
    most the largest odometer step a fix may give), each with the learnt odometer scale; else
    the straight line between the fixes."""
    if not math.isnan(fix.distance):
        return fix.distance * (1.0 + state.anchor.odo_k), True
    if not math.isnan(fix.speed) and not math.isnan(dt):
        return min(fix.speed * dt, _DISTANCE) * (1.0 + state.anchor.odo_k), True
    return (math.hypot(x - state.x, y - state.y) if not math.isnan(state.x) else math.nan), False


def own_sigma(state: SessionState, fix: Fix, cfg: MatchConfig) -> float:
    """The fix's own position σ: as reported, but never below the floor or what the road saw
    (reported accuracies are often optimistic); the dead-reckoning drift comes on top."""
    if fix.pos_cov is not None:
        sigma = math.sqrt(max(0.5 * (fix.pos_cov[0] + fix.pos_cov[2]), 0.25))
    elif math.isnan(fix.pos_sigma) or fix.pos_sigma <= 0.0:
        sigma = cfg.model.gps_sigma
    else:
        sigma = fix.pos_sigma
    return max(sigma, cfg.online.evidence.pos_sigma_floor, math.sqrt(state.bias.res_pos2))


def validate(road: RoadModel, state: SessionState, fix: Fix) -> None:
    """Reject a bad fix, or a state of another map (the state stays unchanged)."""
    fix.validate()
    if fix.speed > _SPEED or fix.distance > _DISTANCE or fix.pos_sigma > _POS or fix.heading_sigma > _HEADING:
        for name, top in LIMITS.items():  # name the first field over its limit
            if getattr(fix, name) > top:
                raise ValidationError(name, f"must be at most {top:g}")
    if fix.pos_cov is not None and max(fix.pos_cov) > LIMITS["pos_sigma"] ** 2:
        raise ValidationError("pos_cov", "variance too large")
    if state.time == state.time and not fix.time > state.time:  # not nan, and not later
        raise ValidationError("time", "must increase from one fix to the next within a vehicle")
    n = len(road.elen)
    for h in state.hyps:
        if max(h.edges) >= n or min(h.edges) < 0:
            raise ValidationError("state", "does not belong to this map")

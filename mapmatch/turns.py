"""Turn evidence from fused heading against odometer distance, and turn classification.

The thesis's "heading against distance" signal: heading is flat between intersections and
through a straight crossing, and steps by the turn angle when the vehicle turns. The heading
change over the last ``window`` metres of odometer distance is compared with the change of
road bearing a candidate path predicts over the same distance.
"""

from __future__ import annotations

import math

from mapmatch.types import Turn

STRAIGHT_MAX_DEG = 30.0
UTURN_MIN_DEG = 150.0
MAX_SAMPLES = 48


def angle_diff(a: float, b: float) -> float:
    """Signed smallest difference ``a - b`` of two angles in degrees, in (-180, 180]."""
    d = (a - b + 180.0) % 360.0 - 180.0
    return 180.0 if d == -180.0 else d


def add_sample(samples: list[list[float]], odo: float, heading: float, *, window: float) -> None:
    """Append ``(odo, heading)`` when the vehicle moved at least a metre; drop samples older
    than two windows (keeping one before that horizon)."""
    if math.isnan(heading):
        return
    if samples and odo - samples[-1][0] < 1.0:
        samples[-1][1] = heading
        return
    samples.append([odo, heading])
    horizon = odo - 2.0 * window
    while len(samples) > 2 and (samples[1][0] <= horizon or len(samples) > MAX_SAMPLES):
        samples.pop(0)


def heading_change(samples: list[list[float]], odo: float, *, window: float) -> tuple[float, float]:
    """Observed heading change over the last ``window`` metres: ``(delta_deg, metres_covered)``.

    Uses the latest sample at least ``window`` metres back (or the oldest one). Returns
    ``(nan, 0)`` when there are fewer than two samples.
    """
    if len(samples) < 2:
        return math.nan, 0.0
    ref = samples[0]
    for s in samples:
        if odo - s[0] >= window:
            ref = s
        else:
            break
    return angle_diff(samples[-1][1], ref[1]), odo - ref[0]


def turn_midpoint(samples: list[list[float]], heading_in: float, angle: float) -> tuple[float, float]:
    """Where a turn of ``angle`` degrees from ``heading_in`` happened, by the heading samples.

    Returns ``(odo, span)``: the odometer reading at which the heading was half-way round
    (interpolated) and the odometer metres between the last sample within 10 % of the turn
    and the first within 10 % of its end (a sharp turn is short; a bend is long). ``(nan,
    nan)`` when the samples do not cover the turn's start.
    """
    if angle == 0.0:
        return math.nan, math.nan
    p = [(odo, angle_diff(heading, heading_in) / angle) for odo, heading in samples]
    for i, (odo, q) in enumerate(p):
        if q >= 0.5:
            if i == 0:
                return math.nan, math.nan
            o0, q0 = p[i - 1]
            mid = o0 + (odo - o0) * (0.5 - q0) / (q - q0)
            start = next((o for o, r in reversed(p[:i]) if r <= 0.1), p[0][0])
            end = next((o for o, r in p[i:] if r >= 0.9), p[-1][0])
            return mid, end - start
    return math.nan, math.nan


def classify_turn(turn_angle: float, *, is_reverse: bool = False) -> Turn:
    """Classify a turn angle (exit bearing minus entry bearing, degrees; positive = right)."""
    if is_reverse or abs(turn_angle) >= UTURN_MIN_DEG:
        return Turn.U_TURN
    if abs(turn_angle) <= STRAIGHT_MAX_DEG:
        return Turn.STRAIGHT
    return Turn.RIGHT if turn_angle > 0 else Turn.LEFT


def emission_scalar(dist: float, sigma: float, heading: float, bearing: float, kappa: float) -> float:
    """Scalar twin of :func:`mapmatch.model.emission_logp` (plain float math for the hot path)."""
    head = 0.0
    if kappa > 0.0 and not math.isnan(heading):
        head = kappa * (math.cos(math.radians(heading - bearing)) - 1.0)
    return -0.5 * (dist / sigma) ** 2 - math.log(sigma) + head


def transition_scalar(
    route_dist: float, travelled: float, dt: float, *, beta: float, max_speed: float, speed_penalty: float
) -> float:
    """Scalar twin of :func:`mapmatch.model.transition_logp` without the U-turn term."""
    lp = -abs(route_dist - travelled) / beta
    if dt > 0.0:
        lp -= speed_penalty * max(route_dist / dt - max_speed, 0.0)
    return lp

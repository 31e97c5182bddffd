"""Turn evidence from fused heading against odometer distance, and turn classification.

The thesis's "heading against distance" signal: heading is flat between intersections and
through a straight crossing, and steps by the turn angle when the vehicle turns. The heading
change over the last ``window`` metres of odometer distance is compared with the change of
road bearing a candidate path predicts over the same distance.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from graph.angles import angle_diff, angle_diffs
from mapmatch.types import Turn


def add_sample(
    samples: list[list[float]],
    odo: float,
    heading: float,
    *,
    window: float,
    spacing: float = 1.0,
    max_samples: int = 48,
) -> None:
    """Append ``(odo, heading)`` when the vehicle moved at least ``spacing`` metres since the last
    sample (a sample keeps its own reading); drop samples older than two windows (keeping one
    before that horizon) and the oldest beyond ``max_samples``."""
    if math.isnan(heading) or (samples and odo - samples[-1][0] < spacing):
        return
    samples.append([odo, heading])
    horizon = odo - 2.0 * window
    n, drop = len(samples), 0
    while n - drop > 2 and (samples[drop + 1][0] <= horizon or n - drop > max_samples):
        drop += 1
    if drop:  # one deletion however many go: O(len) per fix, never O(len²)
        del samples[:drop]


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


def bearing_profile(
    lengths: list[float], bearings: list[float], *, ramp: float = 4.0
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """A path's bearing against distance as knots for :func:`numpy.interp`.

    ``lengths`` and ``bearings`` describe the path's straight pieces in order. The bearing is
    unwrapped (continuous) and changes linearly over ``ramp`` metres either side of each
    vertex (at most half of each piece), as a vehicle's heading does when it rounds a corner.
    """
    s_knots: list[float] = []
    b_knots: list[float] = []
    start = 0.0
    prev = bearings[0]
    for i, (length, b) in enumerate(zip(lengths, bearings, strict=True)):
        b = prev + angle_diff(b, prev)
        before = min(ramp, 0.5 * length) if i > 0 else 0.0
        after = min(ramp, 0.5 * length) if i < len(lengths) - 1 else 0.0
        s_knots += [start + before, start + length - after]
        b_knots += [b, b]
        start += length
        prev = b
    return np.asarray(s_knots), np.asarray(b_knots)


def corner_cut(angle: float, len_in: float, len_out: float, *, ramp: float = 4.0) -> float:
    """Metres of centre line a vehicle saves rounding a corner of ``angle`` degrees on an arc
    spanning ``ramp`` metres either side of the node (at most half of each adjoining edge)."""
    r = min(ramp, 0.5 * len_in, 0.5 * len_out)
    th = math.radians(min(abs(angle), 150.0))
    if th < 1e-6 or r <= 0.0:
        return 0.0
    radius = r / math.tan(0.5 * th)  # the arc touches both legs ``r`` metres from the node
    return 2.0 * r - radius * th


def align_headings(
    samples: list[list[float]],
    knots: tuple[NDArray[np.float64], NDArray[np.float64]],
    offset: float,
    *,
    search: float,
    heading_sigma: float,
    resolution: float = 0.5,
    correlation: float = 5.0,
) -> tuple[float, float, float]:
    """Where the heading samples fit the path's bearing profile best.

    ``samples`` are ``[odometer, heading]``; a sample lies at path distance ``odometer +
    offset + shift``. The shift is searched over ``±search`` metres; the samples' heading errors
    are σ ``heading_sigma`` degrees and correlated over ``correlation`` metres of odometer.
    Returns ``(offset', σ, rms)``: the posterior mean of ``offset + shift`` (uniform prior), its
    σ in metres and the rms heading residual at the best shift in degrees (a path the vehicle
    did not drive fits badly). ``(nan, nan, nan)`` with fewer than three samples.
    """
    if len(samples) < 3:
        return math.nan, math.nan, math.nan
    a = np.asarray(samples, dtype=np.float64)
    odo, head = a[:, 0], a[:, 1]
    w = np.minimum(np.diff(odo, prepend=odo[0] - correlation), correlation) / correlation
    shifts = np.arange(-search, search + 0.5 * resolution, resolution)
    s = odo[None, :] + offset + shifts[:, None]
    d = angle_diffs(head[None, :], np.interp(s, knots[0], knots[1]))
    sq = d * d
    cost = (sq * w).sum(axis=1) / (2.0 * heading_sigma**2)
    best = int(np.argmin(cost))
    p = np.exp(cost[best] - cost)
    p /= p.sum()
    mean = float((p * shifts).sum())
    sd = math.sqrt(max(float((p * (shifts - mean) ** 2).sum()), 0.0))
    rms = math.sqrt(float((sq[best] * w).sum() / w.sum()))
    return offset + mean, sd, rms


def classify_turn(turn_angle: float, *, is_reverse: bool = False, straight_max_deg: float) -> Turn:
    """Classify a turn angle (exit bearing minus entry bearing, degrees; positive = right):
    straight up to ``straight_max_deg``, a U-turn from 180° less it on (or onto the reverse):
    within the same angle of a full reversal as straight on is of none."""
    if is_reverse or abs(turn_angle) >= 180.0 - straight_max_deg:
        return Turn.U_TURN
    if abs(turn_angle) <= straight_max_deg:
        return Turn.STRAIGHT
    return Turn.RIGHT if turn_angle > 0 else Turn.LEFT

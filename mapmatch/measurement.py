"""The map-aided measurement: the online matcher's answer as something a Kalman filter can weigh.

Each answer of :class:`~mapmatch.online.OnlineMatcher` carries a
:class:`~mapmatch.types.MapAidedMeasurement`: the position on the road with its east/north
covariance, the road heading with its σ, the probability of the road and whether feeding it
back is safe (``usable``).

* **Along the road** the σ is what the matcher knows of the position along the road. With GPS
  it is the fix's projection less its learnt along-track bias (variance: the bias's along-track
  variance plus the white share of the fix's variance), fused with the turn anchor carried by
  the odometer. In dead reckoning it is the odometer's carry: the turn anchor's σ (grown with
  the odometer's scale σ) or, without one, the last GPS-aided σ grown by the scale σ of the
  distance driven since.
* **Across the road** the σ is the vehicle's spread about the centre line plus the map's
  drawing error ``map_sigma``: uniform over its half of a two-way road (rms offset
  ``(W/2)/√3``) or over the whole width of a one-way one (``W/√12``). ``W`` is the road width:
  from the map's ``width`` tag, else ``lanes · lane_width``, else the default of the road
  class (the ``measurement.road_width`` config field).
* **Heading**: the road bearing at the point, σ ``road_heading_sigma`` plus how much the bearing
  changes within one along-track σ (bends), plus ``node_heading_sigma`` when that reach
  crosses the end of the edge (the next road is not known yet).
* **Probability** of the reported road: the probability of the path the answer is on (the
  filter's mass of the edge). In dead reckoning, and whenever the answer is held at a node
  of its edge (its path has not taken the next edge yet), times the share of the along-track
  position's distribution (normal, σ the along-track σ above) that lies on the edge, widened
  at each end by ``straddle`` (a vehicle that far past a node is on both roads): the
  position is the answer's offset, or, held at a node with GPS, the fix's along-track
  estimate beyond it. A GPS-aided answer inside its edge is the fix's own projection and
  keeps the path's probability. Given how the fix agrees with the answer (:class:`Agreement`),
  the probability reported is the confidence model's (:func:`confidence`, the ``confidence``
  section): calibrated on real drives, it weighs that road probability with the fix's heading
  against the road's and a road running alongside (how much nearer to the fix it is).
* **usable** is false off road, while (re)initialising, for the first ``settle_distance``
  metres after a (re)initialisation and whenever the probability is below
  ``min_probability`` (in an ambiguous region as elsewhere: the probability already says how
  well the region is resolved).

Consistency: the measurement is not independent of the fix it came from (with GPS its
along-track position is the fix's own projection). A filter should use it, while GPS is valid,
as a constraint on the cross-track position and the heading only, and in dead reckoning as a
full position measurement (covariance as given) plus the heading; and gate it on its
innovation (χ²) as it gates GPS. :mod:`mapmatch.sim.kalman` implements that rule.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from graph.angles import angle_diff, bearing
from graph.road_graph import RoadGraph
from mapmatch.config import DEFAULT_CONFIG, ConfidenceConfig, MeasurementConfig
from mapmatch.types import MapAidedMeasurement, State

# the measurement's columns in a results CSV (``mapmatch replay``), appended to its others
AIDED_COLUMNS: tuple[str, ...] = (
    "aided_usable",
    "aided_reason",
    "aided_lat",
    "aided_lon",
    "aided_var_e",
    "aided_cov_en",
    "aided_var_n",
    "aided_along_sigma",
    "aided_cross_sigma",
    "aided_heading",
    "aided_heading_sigma",
    "aided_probability",
)

# the states the measurement tells apart, as module values: an enum member's look-up on its
# class takes 0.1 µs (the per-fix path)
_OFF_ROAD = State.OFF_ROAD
_STARTING = (State.INITIALISING, State.REINITIALISED)

BearingAt = Callable[[int, float], float]
"""``(edge, offset) -> bearing in degrees`` of the road there."""


DEFAULT_MEASUREMENT = DEFAULT_CONFIG.measurement
DEFAULT_CONFIDENCE = DEFAULT_CONFIG.confidence


def road_width(
    highway: str,
    *,
    width: float = math.nan,
    lanes: float = math.nan,
    config: MeasurementConfig = DEFAULT_MEASUREMENT,
) -> float:
    """Carriageway width in metres: the ``width`` tag, else ``lanes`` lanes, else the class default."""
    if math.isfinite(width) and width > 0:
        return width
    if math.isfinite(lanes) and lanes > 0:
        return lanes * config.lane_width
    return config.width_of.get(highway, config.default_width)


def cross_track_sigma(
    highway: str,
    *,
    one_way: bool,
    width: float = math.nan,
    lanes: float = math.nan,
    config: MeasurementConfig = DEFAULT_MEASUREMENT,
) -> float:
    """1-σ of the vehicle's position across the road's centre line, metres.

    On a two-way road the vehicle keeps to its half (uniform over ``[0, W/2]`` from the centre
    line: rms ``(W/2)/√3``), on a one-way road it may be anywhere across (``W/√12``); the
    map's drawing error ``map_sigma`` adds.
    """
    w = road_width(highway, width=width, lanes=lanes, config=config)
    spread = w / math.sqrt(12.0) if one_way else 0.5 * w / math.sqrt(3.0)
    return math.hypot(spread, config.map_sigma)


@dataclass(slots=True)
class AlongEvidence:
    """What the matcher knows of the position along the road, for one answer.

    Attributes
    ----------
    gps : bool
        Whether the fix was GPS-aided.
    fix_sigma : float
        The fix's position σ as the matcher uses it (m).
    bias_cov : tuple of float
        The learnt fix bias covariance ``(Pxx, Pxy, Pyy)`` (m²; NaN when not learnt).
    white_share : float
        The share of the fix's σ that is white (not learnt as bias).
    anchor_sd : float
        σ of the turn anchor carried by the odometer (m; NaN when none).
    odo_sigma : float
        σ of the odometer's relative distance error after its learnt scale.
    dr_distance : float
        Odometer metres since the last GPS-aided fix.
    gps_sigma : float
        The σ of the along-track position when GPS was lost (m), used in dead reckoning
        without an anchor.
    """

    gps: bool
    fix_sigma: float
    bias_cov: tuple[float, float, float]
    white_share: float
    anchor_sd: float
    odo_sigma: float
    dr_distance: float
    gps_sigma: float


@dataclass(slots=True)
class Placement:
    """Where an answer puts the vehicle.

    Attributes
    ----------
    state : State
        The matcher's state.
    edge : int
        The reported edge (-1: none).
    offset : float
        Metres along it.
    lat, lon : float
        The snapped point, WGS84 degrees.
    bearing : float
        The road's bearing there, degrees.
    probability : float
        The probability of the reported edge.
    since_init : float
        Odometer metres since the last (re)initialisation.
    beyond : float
        Metres by which the fix's along-track estimate lies past the end of the edge the
        answer is held at (positive: past its end node, negative: before its start node; 0
        when the answer is not held at a node or the fix is not GPS-aided).
    """

    state: State
    edge: int
    offset: float
    lat: float
    lon: float
    bearing: float
    probability: float
    since_init: float
    beyond: float = 0.0


@dataclass(slots=True)
class RoadTags:
    """What the map says of the road under an answer; every field optional.

    Attributes
    ----------
    width, lanes : float
        The road's ``width`` and ``lanes`` tags (NaN: not tagged).
    road_class : str or None
        The class of the way piece under the point (default: the edge's).
    one_way : bool or None
        Whether the edge is one-way (default: from the graph).
    bearing_at : BearingAt or None
        As in :func:`heading_sigma`.
    """

    width: float = math.nan
    lanes: float = math.nan
    road_class: str | None = None
    one_way: bool | None = None
    bearing_at: BearingAt | None = None


_NO_TAGS = RoadTags()


@dataclass(slots=True)
class Agreement:
    """How well the fix agrees with the answer, beyond the road's probability: what the
    confidence model (:func:`confidence`) weighs.

    Attributes
    ----------
    heading_diff : float
        Degrees between the fix's heading and the road's bearing at the answer (NaN: no
        heading).
    cross_sigmas : float
        The fix's distance from the road, in the fix's position σ.
    other_sigmas : float
        The fix's distance from the nearest road alongside the answer's stretch of its edge
        (:mod:`mapmatch.online.parallel`), in the fix's position σ; inf when there is none.
    """

    heading_diff: float
    cross_sigmas: float
    other_sigmas: float = math.inf


def confidence(probability: float, agreement: Agreement, model: ConfidenceConfig) -> float:
    """The probability the answer is on the right road: the logistic model of ``model``
    (``confidence.coef_*``) on the road's probability's log-odds, the heading
    disagreement per 10° (at most ``heading_cap``), whether a road runs alongside and, if one
    does, by how many σ it is nearer to the fix than the answer's road, within ±``gap_cap``,
    counted from ``gap_cap`` further (0) to ``gap_cap`` nearer (twice ``gap_cap``)."""
    a = agreement
    return _confidence(probability, a.heading_diff, a.cross_sigmas, a.other_sigmas, model)


def _confidence(
    probability: float, head: float, cross_sigmas: float, other: float, c: ConfidenceConfig
) -> float:
    """:func:`confidence` of the :class:`Agreement` fields ``head`` (heading_diff),
    ``cross_sigmas`` and ``other`` (other_sigmas) as plain values."""
    p = min(max(probability, c.probability_floor), 1.0 - c.probability_floor)
    head = 0.0 if head != head else min(abs(head), c.heading_cap)
    z = c.coef_intercept + c.coef_log_odds * math.log(p / (1.0 - p)) + c.coef_heading * head * 0.1
    if other < math.inf:
        gap = min(max(other - cross_sigmas, -c.gap_cap), c.gap_cap)
        z += c.coef_parallel + c.coef_parallel_gap * (c.gap_cap - gap)
    return 1.0 / (1.0 + math.exp(-z)) if z > -700.0 else 0.0


def along_track_sigma(
    evidence: AlongEvidence,
    *,
    bias_along_var: float,
    config: MeasurementConfig = DEFAULT_MEASUREMENT,
) -> float:
    """1-σ of the matcher's position along the road, metres, from ``evidence``;
    ``bias_along_var`` is the variance of the learnt fix bias along the road (m²; NaN when not
    learnt)."""
    ev = evidence
    return _along_sigma(
        ev.gps, ev.fix_sigma, ev.white_share, ev.anchor_sd, ev.odo_sigma, ev.dr_distance, ev.gps_sigma,
        bias_along_var, config,
    )  # fmt: skip


def _along_sigma(
    gps: bool,
    fix_sigma: float,
    white_share: float,
    anchor_sd: float,
    odo_sigma: float,
    dr_distance: float,
    gps_sigma: float,
    bias_along_var: float,
    config: MeasurementConfig,
) -> float:
    """:func:`along_track_sigma` of the :class:`AlongEvidence` fields as plain values."""
    va = anchor_sd * anchor_sd if math.isfinite(anchor_sd) else math.inf
    if gps:
        vf = (
            bias_along_var + (white_share * fix_sigma) ** 2
            if math.isfinite(bias_along_var)
            else fix_sigma * fix_sigma
        )
        v = vf if math.isinf(va) else vf * va / (vf + va)
    else:
        # in σ, capped before squaring: a long carry must not overflow
        carry = min(math.hypot(gps_sigma, odo_sigma * max(dr_distance, 0.0)), config.along_sigma_max)
        v = min(va, carry * carry)
    return min(math.sqrt(v), config.along_sigma_max)


_SQRT1_2 = math.sqrt(0.5)
_AT_NODE = 1e-6  # metres: an answer this close to an end of its edge is held at the node


def on_edge_share(along: float, length: float, sigma: float, straddle: float) -> float:
    """The share of the along-track position's distribution, normal about ``along`` (metres
    from the edge's start) with σ ``sigma``, that lies on the edge of ``length`` metres,
    widened by ``straddle`` at each end (a vehicle that far past a node is on both roads)."""
    if not sigma > 0.0:
        return 1.0 if -straddle <= along <= length + straddle else 0.0
    k = _SQRT1_2 / sigma
    # Φ(a) - Φ(b) = (erf(a/√2) - erf(b/√2)) / 2
    return 0.5 * (math.erf((length + straddle - along) * k) - math.erf((-straddle - along) * k))


def _bearing_at(graph: RoadGraph, edge: int, offset: float) -> float:
    """Bearing (degrees) of ``edge``'s polyline piece at ``offset`` metres from its start."""
    a, b = int(graph.edge_seg_ptr[edge]), int(graph.edge_seg_ptr[edge + 1])
    xy = graph.seg_xy[a:b]
    d = np.diff(xy, axis=0)
    if len(d) == 0:
        return float(graph.edge_bearing_start[edge])
    cum = np.cumsum(np.hypot(d[:, 0], d[:, 1]))
    i = min(int(np.searchsorted(cum, offset)), len(d) - 1)
    return bearing(float(d[i, 0]), float(d[i, 1]))


def _angle(a: float, b: float) -> float:
    return abs(angle_diff(a, b))


def heading_sigma(
    graph: RoadGraph,
    edge: int,
    offset: float,
    along_sigma: float,
    *,
    config: MeasurementConfig = DEFAULT_MEASUREMENT,
    bearing_at: BearingAt | None = None,
) -> float:
    """1-σ of the road heading at ``offset`` on ``edge``, degrees: the floor, the bearing's
    change within one along-track σ, and ``node_heading_sigma`` when that reaches past the end.
    ``bearing_at(edge, offset)`` gives the road's bearing (default: from the graph's polyline)."""
    at = bearing_at or (lambda e, off: _bearing_at(graph, e, off))
    return _heading_sigma(at, edge, offset, along_sigma, float(graph.edge_len[edge]), config)


def _heading_sigma(
    at: BearingAt, edge: int, offset: float, along_sigma: float, length: float, config: MeasurementConfig
) -> float:
    """:func:`heading_sigma` with the bearing look-up ``at`` and the edge's ``length`` given."""
    here = at(edge, offset)
    back, ahead = offset - along_sigma, offset + along_sigma
    # max(back, 0.0), min(ahead, length), _angle and max(_, _), inline (a per-fix path)
    a = abs(angle_diff(here, at(edge, 0.0 if back < 0.0 else back)))
    b = abs(angle_diff(here, at(edge, length if length < ahead else ahead)))
    bend = b if b > a else a
    node = config.node_heading_sigma if ahead > length else 0.0
    return math.sqrt(config.road_heading_sigma**2 + bend**2 + node**2)


def map_aided_measurement(
    graph: RoadGraph,
    placement: Placement,
    evidence: AlongEvidence,
    tags: RoadTags | None = None,
    agreement: Agreement | None = None,
    *,
    config: MeasurementConfig = DEFAULT_MEASUREMENT,
    model: ConfidenceConfig = DEFAULT_CONFIDENCE,
) -> MapAidedMeasurement:
    """The measurement of one answer, from what the matcher knows (see the module docstring):
    where it puts the vehicle, what it knows along the road, the road's tags and, when given,
    how the fix agrees with the answer (the probability is then :func:`confidence`'s, of
    ``model``)."""
    pl, ev = placement, evidence
    tags = tags or _NO_TAGS
    edge = pl.edge
    if edge < 0 or not math.isfinite(pl.lat):
        return MapAidedMeasurement()
    highway = graph.edge_highway(edge) if tags.road_class is None else tags.road_class
    one_way = tags.one_way
    if one_way is None:
        one_way = int(graph.edge_reverse[edge]) < 0
    at = tags.bearing_at or (lambda e, off: _bearing_at(graph, e, off))
    ag = agreement
    return measure(
        pl.state, edge, pl.offset, pl.lat, pl.lon, pl.bearing, pl.probability, pl.since_init, pl.beyond,
        ev.gps, ev.fix_sigma, ev.bias_cov, ev.white_share, ev.anchor_sd, ev.odo_sigma, ev.dr_distance,
        ev.gps_sigma,
        highway, one_way, tags.width, tags.lanes, at, float(graph.edge_len[edge]),
        ag is not None,
        ag.heading_diff if ag is not None else math.nan,
        ag.cross_sigmas if ag is not None else math.nan,
        ag.other_sigmas if ag is not None else math.inf,
        config, model,
    )  # fmt: skip


def measure(
    state: State,
    edge: int,
    offset: float,
    lat: float,
    lon: float,
    bearing: float,
    probability: float,
    since_init: float,
    beyond: float,
    gps: bool,
    fix_sigma: float,
    bias_cov: tuple[float, float, float],
    white_share: float,
    anchor_sd: float,
    odo_sigma: float,
    dr_distance: float,
    gps_sigma: float,
    highway: str,
    one_way: bool,
    width: float,
    lanes: float,
    bearing_at: BearingAt,
    length: float,
    agreed: bool,
    heading_diff: float,
    cross_sigmas: float,
    other_sigmas: float,
    config: MeasurementConfig,
    model: ConfidenceConfig,
) -> MapAidedMeasurement:
    """:func:`map_aided_measurement` of plain values (the online matcher's per-fix path: no
    records to build): the fields of its :class:`Placement` (``state`` to ``beyond``) and
    :class:`AlongEvidence` (``gps`` to ``gps_sigma``); the road's class, direction, tags, its
    bearing look-up and the edge's ``length``; whether an :class:`Agreement` is given
    (``agreed``) and its fields; the two configuration sections."""
    if edge < 0 or not math.isfinite(lat):
        return MapAidedMeasurement()
    rad = math.radians(bearing)
    tx, ty = math.sin(rad), math.cos(rad)  # along the road (east, north)
    pxx, pxy, pyy = bias_cov
    along = _along_sigma(
        gps, fix_sigma, white_share, anchor_sd, odo_sigma, dr_distance, gps_sigma,
        tx * tx * pxx + 2.0 * tx * ty * pxy + ty * ty * pyy, config,
    )  # fmt: skip
    if width != width and lanes != lanes:  # no tags: one σ per class and direction
        key = (highway, one_way)
        cross = config.cross_sigmas.get(key, math.nan)
        if cross != cross:
            cross = config.cross_sigmas[key] = cross_track_sigma(highway, one_way=one_way, config=config)
    else:
        cross = cross_track_sigma(highway, one_way=one_way, width=width, lanes=lanes, config=config)
    # in dead reckoning, or held at a node, the road's probability is the path's times the
    # share of the along-track position on the reported edge (the rest is past its end node
    # or not yet at its start node)
    if not gps or offset <= _AT_NODE or offset >= length - _AT_NODE:
        probability *= on_edge_share(offset + beyond, length, along, config.straddle)
    if agreed:
        probability = _confidence(probability, heading_diff, cross_sigmas, other_sigmas, model)
    va, vc = along * along, cross * cross
    # rotate diag(along², cross²) from (along, across) to (east, north); across = (ty, -tx)
    var_e = va * tx * tx + vc * ty * ty
    var_n = va * ty * ty + vc * tx * tx
    cov_en = (va - vc) * tx * ty
    if state == _OFF_ROAD:
        reason = "off_road"
    elif state in _STARTING:
        reason = "initialising"
    elif since_init < config.settle_distance:
        reason = "settling"
    elif probability < config.min_probability:
        reason = "low_probability"
    else:
        reason = ""
    return MapAidedMeasurement(  # by position, in field order
        lat,
        lon,
        var_e,
        cov_en,
        var_n,
        along,
        cross,
        bearing,
        _heading_sigma(bearing_at, edge, offset, along, length, config),
        probability,
        reason == "",
        reason,
    )


def aided_cells(m: MapAidedMeasurement) -> list[str]:
    """The measurement as results-CSV cells (:data:`AIDED_COLUMNS`; empty for NaN)."""

    def num(x: float, fmt: str) -> str:
        return "" if math.isnan(x) else format(x, fmt)

    return [
        "1" if m.usable else "0",
        m.reason,
        num(m.lat, ".8f"),
        num(m.lon, ".8f"),
        num(m.var_e, ".4f"),
        num(m.cov_en, ".4f"),
        num(m.var_n, ".4f"),
        num(m.along_sigma, ".3f"),
        num(m.cross_sigma, ".3f"),
        num(m.heading, ".2f"),
        num(m.heading_sigma, ".2f"),
        num(m.probability, ".4f"),
    ]

"""Domain types shared by the online and batch matchers, the CLI and the service."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mapmatch.errors import ValidationError


class State(StrEnum):
    """What the online matcher believes about a vehicle after a fix."""

    INITIALISING = "initialising"
    ON_ROAD = "on_road"
    AMBIGUOUS = "ambiguous"
    OFF_ROAD = "off_road"
    REINITIALISED = "reinitialised"


class Turn(StrEnum):
    """The manoeuvre detected at an intersection."""

    NONE = "none"
    LEFT = "left"
    RIGHT = "right"
    STRAIGHT = "straight"
    U_TURN = "u_turn"


class PointStatus(StrEnum):
    """How the batch matcher placed one point of a track."""

    MATCHED = "matched"
    INTERPOLATED = "interpolated"
    UNMATCHED = "unmatched"


class Fix(NamedTuple):
    """One fused position from a vehicle's fusion node (immutable; ``fix._replace(...)`` gives a
    changed copy).

    Attributes
    ----------
    time : float
        Seconds (any epoch; must increase within a vehicle).
    lat, lon : float
        WGS84 degrees.
    heading : float
        Fused heading in degrees clockwise from north, in [0, 360); NaN when unknown.
    pos_sigma : float
        1-σ position accuracy in metres; NaN when not given.
    heading_sigma : float
        1-σ heading accuracy in degrees; NaN when not given.
    speed : float
        m/s; NaN when not given.
    distance : float
        Odometer distance travelled since the previous fix, metres; NaN when not given.
    gps_valid : bool | None
        True when GPS-aided, False when dead reckoning only, None when not given.
    pos_cov : tuple of 3 floats or None
        Optional 2x2 east/north covariance (m²) as ``(var_e, cov_en, var_n)``.
    """

    time: float
    lat: float
    lon: float
    heading: float = math.nan
    pos_sigma: float = math.nan
    heading_sigma: float = math.nan
    speed: float = math.nan
    distance: float = math.nan
    gps_valid: bool | None = None
    pos_cov: tuple[float, float, float] | None = None

    def validate(self) -> None:
        """Raise :class:`ValidationError` naming the first bad field."""
        inf = math.inf
        h, ps, hs, sp, d = self.heading, self.pos_sigma, self.heading_sigma, self.speed, self.distance
        if (  # all good (the common case: FIELD_RULES unrolled); the loop below names a bad field
            -inf < self.time < inf
            and -90.0 <= self.lat <= 90.0
            and -180.0 <= self.lon <= 180.0
            and (h != h or 0.0 <= h <= 360.0)
            and (ps != ps or 0.0 <= ps < inf)
            and (hs != hs or 0.0 <= hs < inf)
            and (sp != sp or 0.0 <= sp < inf)
            and (d != d or 0.0 <= d < inf)
            and self.pos_cov is None
        ):
            return
        for name in FIX_FIELDS:  # the first bad one, by the rules every entry shares
            if not field_ok(name, getattr(self, name)):
                raise ValidationError(name, FIELD_RULES[name].text)
        if self.pos_cov is not None:
            ve, cen, vn = self.pos_cov
            if not all(math.isfinite(x) for x in self.pos_cov) or ve < 0 or vn < 0 or cen * cen > ve * vn:
                raise ValidationError("pos_cov", "must be a finite positive semi-definite 2x2 covariance")


class FieldRule(NamedTuple):
    """What one numeric field of a fix or a track point may hold: a finite number in
    ``[low, high]``, or NaN (not given) when ``unset``; ``text`` is the error's reason."""

    low: float
    high: float
    unset: bool
    text: str


_NON_NEGATIVE = FieldRule(0.0, math.inf, True, "must be a finite non-negative number or unset")
# one table for every entry: a Fix (SnapFix, the streams, the CLI) and a Track's arrays
# (MatchTrack, MatchTracks, ``mapmatch match``) are checked by the same rules
FIELD_RULES: dict[str, FieldRule] = {
    "time": FieldRule(-math.inf, math.inf, False, "must be a finite number of seconds"),
    "lat": FieldRule(-90.0, 90.0, False, "must be a finite latitude in [-90, 90]"),
    "lon": FieldRule(-180.0, 180.0, False, "must be a finite longitude in [-180, 180]"),
    "heading": FieldRule(0.0, 360.0, True, "must be in [0, 360] degrees or unset"),
    "pos_sigma": _NON_NEGATIVE,
    "heading_sigma": _NON_NEGATIVE,
    "speed": _NON_NEGATIVE,
    "distance": _NON_NEGATIVE,
}
FIX_FIELDS = ("time", "lat", "lon", "heading", "pos_sigma", "heading_sigma", "speed", "distance")


def field_ok(name: str, v: float) -> bool:
    """Whether ``v`` obeys :data:`FIELD_RULES` ``[name]``."""
    r = FIELD_RULES[name]
    if v != v:
        return r.unset
    return math.isfinite(v) and r.low <= v <= r.high


def check_field_array(name: str, values: Any, *, prefix: str, unset: bool | None = None) -> None:
    """Raise :class:`ValidationError` naming ``prefix.name[i]`` at the first value of
    ``values`` that breaks :data:`FIELD_RULES` ``[name]`` (``unset`` overrides whether NaN
    may stand for a value not given)."""
    r = FIELD_RULES[name]
    a = np.asarray(values, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(a) & (a >= r.low) & (a <= r.high)
    if r.unset if unset is None else unset:
        ok |= np.isnan(a)
    if not ok.all():
        i = int(np.argmin(ok))
        raise ValidationError(f"{prefix}.{name}[{i}]", f"{r.text}, got {float(a[i])!r}")


@dataclass(slots=True)
class Candidate:
    """A road segment the vehicle may be on, with its probability."""

    edge: int
    u: int
    v: int
    way_id: int
    probability: float
    offset: float
    dist: float


@dataclass(frozen=True, slots=True)
class Correction:
    """A revision of earlier reported edges: from ``time_from`` to ``time_to`` the vehicle was
    on ``edges`` (in order, each from its ``edge_times`` entry on), not on ``replaced_edges``,
    what was reported then."""

    time_from: float
    time_to: float
    edges: tuple[int, ...]
    replaced_edges: tuple[int, ...]
    edge_times: tuple[float, ...] = ()  # when each of ``edges`` begins (same length); () unknown

    def edge_at(self, time: float) -> int:
        """The revised edge at ``time`` (within the span): by ``edge_times`` when known, else
        the first of ``edges``."""
        if len(self.edge_times) != len(self.edges):
            return self.edges[0]
        j = 0
        for k, t0 in enumerate(self.edge_times):
            if t0 <= time:
                j = k
        return self.edges[j]


@dataclass(slots=True)
class MapAidedMeasurement:
    """What a fusion node may feed back into its filter: the position on the road believed.

    See ``docs/fusion.md``, "The measurement" (built by
    :func:`mapmatch.measurement.map_aided_measurement`).

    Attributes
    ----------
    lat, lon : float
        Position on the road (the snapped point), WGS84 degrees; NaN when off road.
    var_e, cov_en, var_n : float
        Its 2x2 east/north covariance, m² (from ``along_sigma`` and ``cross_sigma``).
    along_sigma, cross_sigma : float
        1-σ along and across the road, metres.
    heading, heading_sigma : float
        Road heading at that point in the direction of travel, degrees clockwise from north,
        and its 1-σ in degrees.
    probability : float
        Probability that the reported road is the right one, in [0, 1].
    usable : bool
        False when the answer must not be fed back (``reason`` says why).
    reason : str
        Empty when usable; else ``off_road``, ``initialising``, ``settling`` or
        ``low_probability``.
    """

    lat: float = math.nan
    lon: float = math.nan
    var_e: float = math.nan
    cov_en: float = math.nan
    var_n: float = math.nan
    along_sigma: float = math.nan
    cross_sigma: float = math.nan
    heading: float = math.nan
    heading_sigma: float = math.nan
    probability: float = 0.0
    usable: bool = False
    reason: str = "off_road"


@dataclass(slots=True)
class SnapResult:
    """The online matcher's answer for one fix.

    ``edge`` is -1 (and the position fields NaN) when the vehicle is not placed on a road.
    Node ids ``u``/``v`` and ``way_id`` are the map's external ids (OSM ids). ``way_id``,
    ``name``, ``road_class`` and ``speed_kph`` describe the way piece under the snapped point
    (an edge can be made of several ways).

    This record, :class:`Candidate` and :class:`MapAidedMeasurement` are plain slots
    dataclasses (not frozen: a frozen one's constructor sets each field through
    ``object.__setattr__``, a few µs per answer). The per-fix path builds them by position,
    in field order (a call with keywords goes through a dict); a field added or moved must
    change those calls too (:func:`mapmatch.online.report.report`,
    :func:`mapmatch.measurement.map_aided_measurement`).
    """

    time: float
    state: State
    edge: int = -1
    u: int = -1
    v: int = -1
    way_id: int = -1
    offset: float = math.nan
    lat: float = math.nan
    lon: float = math.nan
    bearing: float = math.nan
    dist: float = math.nan
    turn: Turn = Turn.NONE
    candidates: tuple[Candidate, ...] = ()
    correction: Correction | None = None
    raw_lat: float = math.nan
    raw_lon: float = math.nan
    name: str = ""
    road_class: str = ""
    speed_kph: float = 0.0  # 0: unknown
    map_aided: MapAidedMeasurement = field(default_factory=MapAidedMeasurement)


def corrected_edges(results: Sequence[SnapResult]) -> list[int]:
    """Each answer's edge with the corrections issued later applied, in order: what the
    matcher finally believes of each fix (-1 where it placed none). Later corrections override
    earlier ones."""
    edges = [r.edge for r in results]
    times = [r.time for r in results]
    for r in results:
        c = r.correction
        if c is None:
            continue
        for i, t in enumerate(times):
            if c.time_from <= t <= c.time_to and edges[i] in c.replaced_edges:
                edges[i] = c.edge_at(t)
    return edges


@dataclass(slots=True)
class MatchedPoint:
    """The batch matcher's placement of one track point."""

    index: int
    status: PointStatus
    edge: int = -1
    offset: float = math.nan
    lat: float = math.nan
    lon: float = math.nan
    dist: float = math.nan


@dataclass(slots=True)
class TrackMatch:
    """The batch matcher's result for one track.

    ``routes`` holds one edge sequence per connected piece; a new piece starts where the
    track was split (``splits`` lists the point indices where a piece starts, after the first).
    A piece whose route only touches a node (its points all at that node) is empty.
    ``route_xy`` holds the same pieces' geometry as (k, 2) arrays in the map's CRS.
    ``point_arrays`` (status, edge, offset, xy, dist per point) is set only while ``points``
    awaits :func:`mapmatch.batch.fill_route_lonlat` (``BatchMatcher.match(lonlat=False)``).
    ``confidence`` (0 to 1) is the matched fraction of the valid points (interpolated ones
    count) times the mean, over the lattice's points, of the chosen road's normalised emission
    probability among the point's candidates.
    """

    track_id: str
    points: list[MatchedPoint] = field(default_factory=list)
    routes: list[list[int]] = field(default_factory=list)
    route_lonlat: list[list[tuple[float, float]]] = field(default_factory=list)
    splits: list[int] = field(default_factory=list)
    length_m: float = 0.0
    confidence: float = 0.0
    route_xy: list[NDArray[np.float64]] = field(default_factory=list)
    point_arrays: tuple[NDArray[Any], ...] | None = None


@dataclass(slots=True)
class Track:
    """A historic track for batch matching: parallel arrays, one entry per point.

    ``time`` in seconds (NaN when unknown), ``lat``/``lon`` in WGS84 degrees; the optional
    arrays are None when the source has no such column, NaN where a value is missing.
    """

    track_id: str
    time: NDArray[np.float64]
    lat: NDArray[np.float64]
    lon: NDArray[np.float64]
    heading: NDArray[np.float64] | None = None
    speed: NDArray[np.float64] | None = None
    pos_sigma: NDArray[np.float64] | None = None
    distance: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.lat)

"""What the online matcher remembers about one vehicle, as named records.

:class:`SessionState` is all of it (small and serialisable by :mod:`mapmatch.online.codec`);
:class:`Step` holds the per-fix quantities every mechanism reads.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple


@dataclass(slots=True)
class Hypothesis:
    """One candidate path: ``edges[k]`` is where the vehicle is, ``off`` metres from its start."""

    edges: list[int]
    k: int
    off: float
    s: float  # distance along the path from the start of edges[0]
    logp: float
    enter: list[float]  # time the position first lay on edges[j], j <= k
    dist: float = math.nan  # distance of the fix from the position (m)
    px: float = math.nan
    py: float = math.nan
    bearing: float = math.nan
    anc: float = math.nan  # along-path anchor: estimated ``s - odometer`` (from a turn's heading step)
    anc_sd: float = math.nan  # its σ in metres (grows with the odometer distance carried)

    def branch(self, edge: int, penalty: float) -> Hypothesis:
        """A copy whose path goes on along ``edge``, ``penalty`` added to its log-probability."""
        return Hypothesis(
            [*self.edges, edge],
            self.k,
            self.off,
            self.s,
            self.logp + penalty,
            list(self.enter),
            self.dist,
            self.px,
            self.py,
            self.bearing,
            self.anc,
            self.anc_sd,
        )


class PathPos(NamedTuple):
    """A position on a hypothesis's path for one fix."""

    j: int  # index into the path's edges
    off: float  # metres along edges[j]
    s: float  # metres along the path
    dist: float  # distance of the fix from this position (m)
    px: float
    py: float
    bearing: float


class FixBias(NamedTuple):
    """The fix's slowly varying position error vector (m) and its covariance (m²)."""

    bx: float = 0.0
    by: float = 0.0
    pxx: float = math.nan  # nan: not learnt yet
    pxy: float = 0.0
    pyy: float = math.nan


@dataclass(slots=True)
class LiveFix:
    """A fix reported while the region was ambiguous (what a correction may revise)."""

    time: float
    edge: int  # the edge reported (rewritten when a correction revises it)
    x: float
    y: float
    heading: float
    sigma: float
    kappa: float
    gps: bool


@dataclass(slots=True)
class TrailPoint:
    """The odometer reading at a time (kept for re-timing crossings)."""

    time: float
    odo: float


class BackEdge(NamedTuple):
    """An edge committed since the last turn anchor, with the time the vehicle entered it."""

    edge: int
    time: float


class ScaleChain(NamedTuple):
    """The running estimate of the odometer scale from the GPS (a chain of fixes on one path):
    the last fix's place on the path, the odometer since it, and the filter's offset and the
    fix's slowly varying error along the road, with their covariance (the scale's variance is
    ``AnchorState.odo_kvar``)."""

    edge: int = -1  # the last fix's edge on the path (-1: no chain)
    off: float = math.nan  # its projection's metres along that edge
    time: float = math.nan  # its time
    dx: float = 0.0  # raw odometer metres since it (before the learnt scale)
    p: float = 0.0  # path metres less raw odometer metres there: the estimate less the measured
    b: float = 0.0  # the fix's slowly varying error along the road there
    ppp: float = 0.0  # covariance of (p, scale, b): p·p ...
    ppk: float = 0.0  # ... p·scale
    ppb: float = 0.0  # ... p·b
    pkb: float = 0.0  # ... scale·b
    pbb: float = 0.0  # ... b·b


NO_CHAIN = ScaleChain()


@dataclass(slots=True)
class AnchorState:
    """The odometer's scale and the turn anchor it is learnt from (written by
    :mod:`mapmatch.online.anchor` only)."""

    # the odometer's scale error learnt between turn anchors: path metres = odometer · (1 + k)
    odo_k: float = 0.0
    odo_kvar: float = math.nan  # its variance (nan: the configured prior)
    anc_odo: float = math.nan  # odometer reading of the last turn anchor ...
    anc_sd: float = math.nan  # ... and its σ (m)
    # the running estimate of the scale from the GPS-aided fixes on the path driven
    chain: ScaleChain = NO_CHAIN


@dataclass(slots=True)
class BiasState:
    """The fix's slowly varying error (written by :mod:`mapmatch.online.bias` only)."""

    # learnt from the fix's offsets across roads of other directions; along a road it is
    # invisible, so this is what tells the along-track error after a turn
    vector: FixBias = field(default_factory=FixBias)
    res_pos2: float = 25.0  # running mean of squared distance to the road (m²), on road
    res_head2: float = 400.0  # running mean of squared heading residual (deg²), on road
    drift_sigma: float = 0.0  # dead-reckoning drift σ (m), decaying after GPS returns


@dataclass(slots=True)
class CrossingTrail:
    """What re-times the straight crossings once the next turn tells where the vehicle was
    (written by :mod:`mapmatch.online.anchor` only)."""

    trail: list[TrailPoint] = field(default_factory=list)  # the odometer against time
    back: list[BackEdge] = field(default_factory=list)  # the edges committed since the last anchor

    def restart(self) -> None:
        """A new start: no edges committed yet (the odometer trail goes on)."""
        self.back = []


@dataclass(slots=True)
class RegionState:
    """The ambiguous region (written by :mod:`mapmatch.online.region` and the corrections it
    makes, :mod:`mapmatch.online.correction`)."""

    live: list[LiveFix] = field(default_factory=list)  # the fixes of the ambiguous region
    init_pending: bool = True  # the start-up road is not committed yet ...
    init_odo: float = 0.0  # ... and the odometer when the hypotheses started

    def restart(self, *, pending: bool, odo: float) -> None:
        """A new start: no live fixes, the start-up road pending when ``pending``."""
        self.live = []
        self.init_pending = pending
        self.init_odo = odo


@dataclass(slots=True)
class SessionState:
    """Everything the matcher remembers about one vehicle (small, serialisable).

    The vehicle's kinematics and lifecycle (written by :mod:`mapmatch.online.matcher` and
    :mod:`mapmatch.online.hypotheses`) and one record per mechanism: ``anchor``, ``bias``,
    ``crossings``, ``region``. The flat names ``odo_k``, ``odo_kvar``, ``chain``, ``res_pos2``,
    ``live``, ``trail`` and ``back`` read those records.
    """

    time: float = math.nan
    x: float = math.nan
    y: float = math.nan
    odo: float = 0.0
    gps_odo: float = 0.0  # odometer at the last GPS-aided fix
    speed: float = math.nan  # the odometer's speed averaged over ``stop_time`` (m/s; nan: unknown)
    bad_time: float = math.nan  # since when the fixes are inconsistent with the road ...
    bad_odo: float = math.nan  # ... and the odometer then
    search_time: float = math.nan  # time of the last soft re-initialisation search
    shown: int = -1  # the edge reported last
    hyps: list[Hypothesis] = field(default_factory=list)
    headings: list[list[float]] = field(default_factory=list)  # [odometer, heading] samples
    anchor: AnchorState = field(default_factory=AnchorState)
    bias: BiasState = field(default_factory=BiasState)
    crossings: CrossingTrail = field(default_factory=CrossingTrail)
    region: RegionState = field(default_factory=RegionState)

    @property
    def odo_k(self) -> float:
        """The learnt odometer scale error (``anchor.odo_k``)."""
        return self.anchor.odo_k

    @property
    def odo_kvar(self) -> float:
        """Its variance (``anchor.odo_kvar``)."""
        return self.anchor.odo_kvar

    @property
    def chain(self) -> ScaleChain:
        """The running scale estimate from the GPS (``anchor.chain``)."""
        return self.anchor.chain

    @chain.setter
    def chain(self, value: ScaleChain) -> None:
        self.anchor.chain = value

    @property
    def res_pos2(self) -> float:
        """The running mean of squared distance to the road (``bias.res_pos2``)."""
        return self.bias.res_pos2

    @property
    def live(self) -> list[LiveFix]:
        """The fixes of the ambiguous region (``region.live``)."""
        return self.region.live

    @property
    def trail(self) -> list[TrailPoint]:
        """The odometer trail (``crossings.trail``)."""
        return self.crossings.trail

    @property
    def back(self) -> list[BackEdge]:
        """The edges committed since the last turn anchor (``crossings.back``)."""
        return self.crossings.back

    def to_bytes(self) -> bytes:
        """Compact JSON encoding (a few kilobytes); see :mod:`mapmatch.online.codec`."""
        from mapmatch.online.codec import to_bytes

        return to_bytes(self)

    @classmethod
    def from_bytes(cls, data: bytes) -> SessionState:
        """Decode :meth:`to_bytes` (or version 1); raises :class:`~mapmatch.errors.ValidationError`
        naming the offending key on anything else."""
        from mapmatch.online.codec import from_bytes

        return from_bytes(data)


@dataclass(slots=True)
class Step:
    """Per-fix quantities shared by all hypotheses (read-only by convention: not frozen, which
    would make every fix's construction slower)."""

    time: float
    x: float
    y: float
    sigma: float
    heading: float
    kappa: float
    travelled: float  # metres since the previous fix (nan when unknown)
    odo: float  # the session's odometer after this fix
    odo_known: bool
    dt: float
    gps: bool
    weight: float
    stopped: bool  # slower than ``stop_speed`` by the odometer (over ``stop_time``)
    r_a: float
    dr: float  # odometer metres since the last GPS-aided fix (0 when this one is)
    bias: FixBias  # predicted fix bias
    odo_sigma: float  # σ of the odometer's relative error (after the learnt scale)
    fix_sigma: float = math.nan  # σ of the fix itself, without the dead-reckoning drift
    turn_weight: float = 1.0  # the turn score's weight: ``weight`` without its share of time
    still_kappa: float = 0.0  # a stopped vehicle's fused heading: its concentration ...
    still_weight: float = 0.0  # ... and weight (time share the distance share left out)
    speed: float = math.nan  # the odometer's speed over the last ``stop_time`` (m/s)

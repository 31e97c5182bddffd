"""Online per-vehicle matching: the thesis's ambiguous-region algorithm as a small discrete filter.

The filter holds a few *path hypotheses*. A hypothesis is a short sequence of directed edges
the vehicle may be driving (the committed edge first), its position along that path and a
log-probability. Between intersections there is one hypothesis on one edge: each fix is projected
onto that edge and nothing else is searched (unless the fix leaves that road by more than 3 σ
or runs against it: then the spatial index proposes alternatives). When the vehicle comes
within the ambiguous-region radius ``r_a`` of the edge's end node, the path is extended with
every legal outgoing edge (one-ways, turn restrictions, a penalised U-turn; two hops where
junctions are closer than ``r_a``). Each fix then adds to every hypothesis the shared model's
emission (distance and heading), the transition (along-path progress against odometer distance)
and turn evidence (heading change over the last ``turn_window`` metres against the path's
bearing change). The edge of highest total probability is reported (the most probable
hypothesis on it gives the position); when the most probable hypothesis has left the circle it
is committed, the turn at the intersection is classified and, when the committed path disagrees
with what was reported live, a :class:`~mapmatch.types.Correction` is returned.

Along a path the position follows the fix, with hysteresis at nodes against the fused
position's along-track error: a fix just past the end node of the edge held stays at that node
(within ``node_hold_sigmas`` σ), the vehicle goes back across a node only when the fix is
clearly behind it, a stopped vehicle (odometer below ``stop_speed``) never moves on across
a node, and one that stops just past a node it did not turn at is put back before it (stop
lines are before junctions). Evidence accrues per ``evidence_time`` seconds and
``evidence_distance`` metres, so that repeated fixes of a slow or stopped vehicle (with the
same correlated error) do not outvote the path.

On a straight road the map cannot show the fix's along-track error, yet it decides which side
of a straight crossing the vehicle is. Two other sources correct the position along the path
(GPS-aided fixes only; in dead reckoning the odometer carry above decides): the fix's slowly
varying error vector, learnt by a small Kalman filter from its offsets *across* roads of other
directions (``bias_time``), and a turn anchor: when a turn (or a bend) is committed, the fused
headings against the odometer are aligned with the path's bearing profile, which tells the
odometer reading at the node (σ at least ``turn_anchor_sigma``), and the odometer carries that
position on (less the metres the rounded corner saved; σ growing with the odometer's scale
error, learnt anchor to anchor from prior ``odo_scale_sigma``). Both are fused with the
projection by their variances; the corrected position crosses a node only where the path goes
straight on, and a path whose turn holds it short of the estimate pays for the miss. Carried
back over a trail of (time, odometer) points, the anchor also times the turn and the straight
crossings since the previous turn again, and revises them with a correction as far as it is
sure of them.

In dead reckoning every path carries the vehicle by the odometer alone (the drifting fix only
weighs the paths against each other, its heading against the road anywhere within the
odometer's uncertainty), and a committed turn re-places it by the turn anchor.

Fixes far off the map are not errors: they return ``State.OFF_ROAD`` with ``edge == -1``.
Invalid input raises :class:`~mapmatch.errors.ValidationError` and leaves the state unchanged.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from graph.index import EdgeIndex
from graph.neighbours import Neighbours, edge_neighbours
from graph.projection import point_to_lonlat, point_to_xy
from graph.road_graph import RESTRICTION_ONLY, RoadGraph
from mapmatch.config import DEFAULT_CONFIG, MatchConfig
from mapmatch.errors import ValidationError
from mapmatch.measurement import DEFAULT_MEASUREMENT, MeasurementConfig, map_aided_measurement
from mapmatch.turns import (
    STRAIGHT_MAX_DEG,
    add_sample,
    align_headings,
    angle_diff,
    bearing_profile,
    classify_turn,
    corner_cut,
    emission_scalar,
    heading_change,
    transition_scalar,
)
from mapmatch.types import Candidate, Correction, Fix, SnapResult, State, Turn

MAX_HOPS = 4
PRUNE_LOGP = -25.0
MAX_LIVE = 48
LIVE_SPACING_S = 0.5  # fixes remembered for corrections: at most two per second, or on edge change
INIT_MAX_RADIUS_M = 200.0
STATE_VERSION = 1
FAR_OFF_M = 100_000.0
BIAS_WHITE_FRAC = 0.5  # the share of the fix's σ that is white (not learnt as bias)
ALIGN_SEARCH_M = 5.0  # a turn's heading profile is searched within this plus ...
ALIGN_SEARCH_SIGMAS = 2.5  # ... this many fix σ of the position believed, up to ...
ALIGN_SEARCH_MAX_M = 40.0
ALIGN_HEADING_SIGMA_MIN_DEG = 3.0
ALIGN_RMS_MAX_DEG = 20.0  # a worse fit: the path is not what the vehicle drove, no anchor
ODO_SCALE_FLOOR = 0.002  # relative odometer error left after learning its scale
ODO_SCALE_MAX = 0.2
# turn anchors closer than this teach nothing about the odometer's scale; further apart than
# the maximum, the path between them is more likely wrong than the odometer
SCALE_MIN_DISTANCE_M = 20.0
SCALE_MAX_DISTANCE_M = 600.0
SCALE_PATH_ERROR = 0.005  # relative error of a path's length between turn anchors
ALIGN_COVER_M = 3.0  # the samples must reach this far either side of the node
ANCHOR_GATE = 3.0  # a turn anchor further than this many σ from the fix is dropped
INIT_MAX_HEADING_DEG = 100.0
POS_SIGMA_FLOOR_M = 2.0
CORRECTION_MARGIN = 2.0
SEARCH_EVERY_S = 1.0
TRAIL_STEP_M = 2.0  # the odometer trail kept for revising crossings: a point every this many metres ...
TRAIL_MAX = 150  # ... at most this many ...
STILL_M = 0.05  # moving less than this, the vehicle stands
TRAIL_MAX_M = 300.0  # ... and crossings at most this far back
REVISE_SIGMAS = 1.0  # a revised crossing moves only as far as its anchor is this many σ sure
REPORT_BACK_RATIO = 3.0  # reporting an edge behind the one reported needs this much more mass
AGAINST_HEADING_DEG = 100.0  # driving against the road believed also triggers the search
HEADING_SIGMA_FLOOR_DEG = 10.0
HEADING_SIGMA_FLOOR_DR_DEG = 15.0  # in dead reckoning the position along the road is uncertain
RESIDUAL_TIME_S = 20.0
LEARNED_POS_SIGMA_MAX_M = 10.0
LEARNED_HEADING_SIGMA_MAX_DEG = 30.0
LIMITS = {"speed": 1_000.0, "distance": 100_000.0, "pos_sigma": 100_000.0, "heading_sigma": 360.0}


@dataclass(slots=True)
class Hypothesis:
    """One candidate path: ``edges[k]`` is where the vehicle is, ``off`` metres from its start."""

    edges: list[int]
    k: int
    off: float
    s: float  # distance along the path from the start of edges[0]
    logp: float
    enter: list[float]  # time the position first lay on edges[j], j <= k
    dist: float = math.nan
    px: float = math.nan
    py: float = math.nan
    bearing: float = math.nan
    anc: float = math.nan  # along-path anchor: estimated ``s - odometer`` (from a turn's heading step)
    anc_sd: float = math.nan  # its σ in metres (grows with the odometer distance carried)

    def to_list(self) -> list[Any]:
        return [
            self.edges,
            self.k,
            self.off,
            self.s,
            self.logp,
            self.enter,
            self.dist,
            self.px,
            self.py,
            self.bearing,
            self.anc,
            self.anc_sd,
        ]

    @classmethod
    def from_list(cls, a: list[Any]) -> Hypothesis:
        return cls(
            edges=[int(e) for e in a[0]],
            k=int(a[1]),
            off=float(a[2]),
            s=float(a[3]),
            logp=float(a[4]),
            enter=[float(t) for t in a[5]],
            dist=float(a[6]),
            px=float(a[7]),
            py=float(a[8]),
            bearing=float(a[9]),
            anc=float(a[10]) if len(a) > 11 else math.nan,
            anc_sd=float(a[11]) if len(a) > 11 else math.nan,
        )


@dataclass
class SessionState:
    """Everything the matcher remembers about one vehicle (small, serialisable)."""

    time: float = math.nan
    x: float = math.nan
    y: float = math.nan
    odo: float = 0.0
    gps_odo: float = 0.0
    bad_time: float = math.nan
    bad_odo: float = math.nan
    init_pending: bool = True
    init_odo: float = 0.0
    hyps: list[Hypothesis] = field(default_factory=list)
    # while ambiguous: [time, reported edge, x, y, heading, sigma, kappa, gps] per fix
    live: list[list[float]] = field(default_factory=list)
    headings: list[list[float]] = field(default_factory=list)  # [odometer, heading]
    res_pos2: float = 25.0  # running mean of squared distance to the road (m²), on road
    res_head2: float = 400.0  # running mean of squared heading residual (deg²), on road
    drift_sigma: float = 0.0  # dead-reckoning drift σ (m), decaying after GPS returns
    search_time: float = math.nan  # time of the last soft re-initialisation search
    shown: int = -1  # the edge reported last
    # the fix's slowly varying position error, learnt from its offsets across roads of other
    # directions: [bx, by, Pxx, Pxy, Pyy] (m, m²); along a road it is invisible, so this is
    # what tells the along-track error after a turn
    bias: list[float] = field(default_factory=lambda: [0.0, 0.0, math.nan, 0.0, math.nan])
    # the odometer's scale error learnt between turn anchors: path metres = odometer · (1 + k)
    odo_k: float = 0.0
    odo_kvar: float = math.nan  # its variance (nan: the configured prior)
    anc_odo: float = math.nan  # odometer reading of the last turn anchor ...
    anc_sd: float = math.nan  # ... and its σ (m)
    # for revising straight crossings once the next turn tells where the vehicle was:
    # [time, odometer], and the edges committed since the last turn as [edge, time entered]
    trail: list[list[float]] = field(default_factory=list)
    back: list[list[float]] = field(default_factory=list)

    def to_bytes(self) -> bytes:
        """Compact JSON encoding (a few kilobytes)."""
        d = {
            "v": STATE_VERSION,
            "t": self.time,
            "xy": [self.x, self.y],
            "odo": [
                self.odo,
                self.gps_odo,
                self.init_odo,
                self.odo_k,
                self.odo_kvar,
                self.anc_odo,
                self.anc_sd,
            ],
            "bad": [self.bad_time, self.bad_odo],
            "init": self.init_pending,
            "h": [h.to_list() for h in self.hyps],
            "live": self.live,
            "hd": self.headings,
            "res": [self.res_pos2, self.res_head2, self.drift_sigma, self.search_time],
            "sh": self.shown,
            "b": self.bias,
            "tr": [[round(t, 3), round(o, 2)] for t, o in self.trail],
            "bk": self.back,
        }
        return json.dumps(d, separators=(",", ":"), allow_nan=True).encode()

    @classmethod
    def from_bytes(cls, data: bytes) -> SessionState:
        """Decode :meth:`to_bytes`; raises :class:`ValidationError` on anything else."""
        try:
            d = json.loads(data)
            if d.get("v") != STATE_VERSION:
                raise ValueError("unknown version")
            st = cls(
                time=float(d["t"]),
                x=float(d["xy"][0]),
                y=float(d["xy"][1]),
                odo=float(d["odo"][0]),
                gps_odo=float(d["odo"][1]),
                init_odo=float(d["odo"][2]),
                odo_k=float(d["odo"][3]) if len(d["odo"]) > 6 else 0.0,
                odo_kvar=float(d["odo"][4]) if len(d["odo"]) > 6 else math.nan,
                anc_odo=float(d["odo"][5]) if len(d["odo"]) > 6 else math.nan,
                anc_sd=float(d["odo"][6]) if len(d["odo"]) > 6 else math.nan,
                bad_time=float(d["bad"][0]),
                bad_odo=float(d["bad"][1]),
                init_pending=bool(d["init"]),
                hyps=[Hypothesis.from_list(a) for a in d["h"]],
                live=[[float(v) for v in entry] for entry in d["live"] if len(entry) == 8],
                headings=[[float(o), float(h)] for o, h in d["hd"]],
                res_pos2=float(d["res"][0]),
                res_head2=float(d["res"][1]),
                drift_sigma=float(d["res"][2]),
                search_time=float(d["res"][3]),
                shown=int(d.get("sh", -1)),
                bias=[float(v) for v in d.get("b", [0.0, 0.0, math.nan, 0.0, math.nan])],
                trail=[[float(t), float(o)] for t, o in d.get("tr", [])],
                back=[[float(e), float(t)] for e, t in d.get("bk", [])],
            )
        except (ValueError, TypeError, KeyError, IndexError, AttributeError) as exc:
            raise ValidationError("state", f"not a valid session state ({exc})") from None
        if len(st.bias) != 5:
            raise ValidationError("state", "not a valid session state (bad bias)")
        for h in st.hyps:
            if not h.edges or not 0 <= h.k < len(h.edges) or len(h.enter) != h.k + 1:
                raise ValidationError("state", "not a valid session state (bad hypothesis)")
        # interim field checks (the #13 codec validates every field): no infinities, and
        # variances / σ are non-negative or unset
        for key, v in (("t", st.time), ("odo", st.odo), ("xy", st.x), ("xy", st.y), ("bad", st.bad_time)):
            if math.isinf(v):
                raise ValidationError(key, "must be finite or unset")
        for key, v in (("res", st.res_pos2), ("res", st.res_head2), ("res", st.drift_sigma),
                       ("odo", st.odo_kvar), ("odo", st.anc_sd),
                       ("b", st.bias[2]), ("b", st.bias[4])):  # fmt: skip
            if not (math.isnan(v) or (math.isfinite(v) and v >= 0.0)):
                raise ValidationError(key, "variances and sigmas must be finite and non-negative")
        return st


@dataclass(frozen=True, slots=True)
class _Step:
    """Per-fix quantities shared by all hypotheses."""

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
    stopped: bool  # slower than ``stop_speed`` by the odometer
    r_a: float
    dr: float  # odometer metres since the last GPS-aided fix (0 when this one is)
    bias: tuple[float, float, float, float, float]  # predicted fix bias [bx, by, Pxx, Pxy, Pyy]
    odo_sigma: float  # σ of the odometer's relative error (after the learnt scale)
    fix_sigma: float = math.nan  # σ of the fix itself, without the dead-reckoning drift


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
    measurement
        How each answer's map-aided measurement is built (:mod:`mapmatch.measurement`).
    """

    def __init__(
        self,
        graph: RoadGraph,
        index: EdgeIndex | None = None,
        config: MatchConfig = DEFAULT_CONFIG,
        measurement: MeasurementConfig = DEFAULT_MEASUREMENT,
    ):
        self.graph = graph
        self.index = index if index is not None else EdgeIndex(graph)
        self.config = config
        self.measurement = measurement
        # parallel roads and slowly separating fork branches of every edge, looked up per fix
        self._nbr: Neighbours | None = (
            edge_neighbours(graph, band_m=config.neighbour_band, index=self.index)
            if config.neighbour_sigmas > 0.0 and config.neighbour_band > 0.0
            else None
        )
        e = graph.n_edges
        self._elen: list[float] = graph.edge_len.tolist()
        self._ev: list[int] = graph.edge_v.tolist()
        self._eu: list[int] = graph.edge_u.tolist()
        self._rev: list[int] = graph.edge_reverse.tolist()
        self._bstart: list[float] = graph.edge_bearing_start.tolist()
        self._bend: list[float] = graph.edge_bearing_end.tolist()
        self._ptr: list[int] = graph.edge_seg_ptr.tolist()
        self._seg = graph.seg_xy
        # every piece of every polyline: length and bearing (the last row of each edge is unused)
        d = np.diff(graph.seg_xy, axis=0) if len(graph.seg_xy) else np.zeros((0, 2))
        self._piece_len = np.hypot(d[:, 0], d[:, 1])
        self._piece_brg = np.degrees(np.arctan2(d[:, 0], d[:, 1])) % 360.0
        self._out_ptr: list[int] = graph.out_ptr.tolist()
        self._out = graph.out_edges
        rev = graph.edge_reverse
        road = (rev < 0) | (np.arange(e) < rev)
        deg = np.bincount(graph.edge_u[road], minlength=graph.n_nodes) + np.bincount(
            graph.edge_v[road], minlength=graph.n_nodes
        )
        self._branching: list[bool] = (deg >= 3).tolist()
        self._restr: dict[int, list[tuple[int, int, int]]] = {}
        for fe, via, te, kind in graph.restrictions.tolist():
            self._restr.setdefault(int(fe), []).append((int(via), int(te), int(kind)))
        # a robust "longest distance between adjacent nodes" for the region radius
        self.edge_len_ref = float(np.percentile(graph.edge_len, 95)) if e else 0.0
        self._bounds = (
            (
                float(graph.seg_xy[:, 0].min()),
                float(graph.seg_xy[:, 1].min()),
                float(graph.seg_xy[:, 0].max()),
                float(graph.seg_xy[:, 1].max()),
            )
            if len(graph.seg_xy)
            else None
        )

    # ------------------------------------------------------------------ public API
    def new_session(self) -> SessionState:
        """A fresh vehicle state."""
        return SessionState()

    def region_radius(self, sigma: float, config: MatchConfig | None = None) -> float:
        """Ambiguous-region radius in metres for a fix of position σ (DR growth included)."""
        cfg = config or self.config
        r = max(
            cfg.ambiguous_min_radius, cfg.drift_rate * self.edge_len_ref, cfg.ambiguous_sigma_factor * sigma
        )
        return min(r, max(cfg.ambiguous_max_radius, cfg.ambiguous_min_radius))

    def update(self, state: SessionState, fix: Fix, *, config: MatchConfig | None = None) -> SnapResult:
        """Match one fix; mutates ``state``. Raises :class:`ValidationError` (state unchanged)."""
        cfg = config or self.config
        step = self._prepare(state, fix, cfg)
        if step is None:  # far off the map: accepted, but nowhere to put it
            state.time = fix.time
            return SnapResult(time=fix.time, state=State.OFF_ROAD, raw_lat=fix.lat, raw_lon=fix.lon)
        # --- accepted: mutate the state from here on
        # the first GPS-aided fix after dead reckoning: it is the truth, not an outlier
        returned = (
            step.gps and step.kappa > 0.0 and state.odo - state.gps_odo > 0.0 and cfg.return_sigmas > 0.0
        )
        if not math.isnan(step.travelled):
            state.odo += step.travelled
        if step.gps:
            state.gps_odo = state.odo
        state.drift_sigma = self._drift_sigma(state, step.gps, 0.0, step.dt, cfg) if step.gps else step.sigma
        state.time, state.x, state.y = step.time, step.x, step.y
        state.bias = list(step.bias)
        if step.kappa > 0.0:
            add_sample(state.headings, state.odo, step.heading, window=cfg.turn_window)
        if step.odo_known:
            self._add_trail(state.trail, step.time, state.odo, step.travelled <= STILL_M)

        reinit = False
        held: list[tuple[Hypothesis, float]] = []
        if state.hyps:
            held = self._advance(state, step, cfg)
            best = self._best(state.hyps)
            against = step.kappa > 0.0 and abs(angle_diff(step.heading, best.bearing)) > AGAINST_HEADING_DEG
            if returned and best.dist > cfg.return_sigmas * step.fix_sigma:
                # weigh the roads near the returning fix against it at its own σ, at once
                state.search_time = step.time
                self._add_alternatives(state, dataclasses.replace(step, sigma=step.fix_sigma), cfg, best)
                best = self._best(state.hyps)
            elif (
                step.gps
                and (best.dist > cfg.soft_reinit_sigmas * step.sigma or against)
                and not (step.time - state.search_time < SEARCH_EVERY_S)
            ):
                state.search_time = step.time
                self._add_alternatives(state, step, cfg, best)
                best = self._best(state.hyps)
            elif (
                step.gps
                and self._nbr is not None
                and cfg.neighbour_sigmas > 0.0
                and best.dist > cfg.neighbour_sigmas * step.sigma
                and not (step.time - state.search_time < SEARCH_EVERY_S)
            ):  # a parallel road or a fork branch may fit the fix better: a table look-up
                nb = self._nbr.of(best.edges[best.k])
                if len(nb):
                    state.search_time = step.time
                    self._add_alternatives(state, step, cfg, best, nb.tolist())
                    best = self._best(state.hyps)
            if best.dist > cfg.reinit_sigmas * step.sigma:
                if math.isnan(state.bad_time):
                    state.bad_time, state.bad_odo = step.time, state.odo
                if (
                    step.time - state.bad_time >= cfg.reinit_time
                    or state.odo - state.bad_odo >= cfg.reinit_distance
                ):
                    reinit, held = True, []
                    self._initialise(state, step, cfg)
            else:
                state.bad_time = state.bad_odo = math.nan
                if len(state.hyps) == 1 and not state.init_pending:
                    self._learn_residuals(state, best, step)
                    self._learn_bias(state, best, step)
        else:
            self._initialise(state, step, cfg)
        if not state.hyps:
            return SnapResult(time=fix.time, state=State.OFF_ROAD, raw_lat=fix.lat, raw_lon=fix.lon)

        turn, correction = (Turn.NONE, None) if reinit else self._commit(state, step, cfg)
        return self._result(state, step, fix, turn, correction, reinit, held)

    # ------------------------------------------------------------------ per-fix preparation
    def _prepare(self, state: SessionState, fix: Fix, cfg: MatchConfig) -> _Step | None:
        fix.validate()
        for name, top in LIMITS.items():
            if getattr(fix, name) > top:
                raise ValidationError(name, f"must be at most {top:g}")
        if fix.pos_cov is not None and max(fix.pos_cov) > LIMITS["pos_sigma"] ** 2:
            raise ValidationError("pos_cov", "variance too large")
        heading = 0.0 if fix.heading == 360.0 else fix.heading
        if not math.isnan(state.time) and not fix.time > state.time:
            raise ValidationError("time", "must increase from one fix to the next within a vehicle")
        for h in state.hyps:
            if max(h.edges) >= len(self._elen) or min(h.edges) < 0:
                raise ValidationError("state", "does not belong to this map")
        x, y = point_to_xy(self.graph.crs, fix.lon, fix.lat)
        if not (math.isfinite(x) and math.isfinite(y)) or self._far_off(x, y):
            return None
        dt = fix.time - state.time if not math.isnan(state.time) else math.nan
        odo_known = True
        if not math.isnan(fix.distance):
            travelled = fix.distance * (1.0 + state.odo_k)
        elif not math.isnan(fix.speed) and not math.isnan(dt):
            travelled = fix.speed * dt * (1.0 + state.odo_k)
        else:
            odo_known = False
            travelled = math.hypot(x - state.x, y - state.y) if not math.isnan(state.x) else math.nan
        if fix.pos_cov is not None:
            sigma = math.sqrt(max(0.5 * (fix.pos_cov[0] + fix.pos_cov[2]), 0.25))
        elif math.isnan(fix.pos_sigma) or fix.pos_sigma <= 0.0:
            sigma = cfg.gps_sigma
        else:
            sigma = fix.pos_sigma
        # reported accuracies are often optimistic: never below the floor or what the road saw
        sigma = max(sigma, POS_SIGMA_FLOOR_M, math.sqrt(state.res_pos2))
        fix_sigma = sigma
        gps = fix.gps_valid is not False
        sigma = max(sigma, self._drift_sigma(state, gps, travelled, dt, cfg))
        kappa = 0.0
        if not math.isnan(heading) and (math.isnan(fix.speed) or fix.speed >= cfg.heading_min_speed):
            hs = cfg.heading_sigma if math.isnan(fix.heading_sigma) else fix.heading_sigma
            floor = HEADING_SIGMA_FLOOR_DEG if fix.gps_valid is not False else HEADING_SIGMA_FLOOR_DR_DEG
            hs = max(hs, floor, math.sqrt(state.res_head2))
            kappa = 1.0 / math.radians(hs) ** 2
        # the fused error is correlated: evidence accrues with time and, when known, distance
        weight = 1.0 if math.isnan(dt) else min(1.0, dt / cfg.evidence_time)
        stopped = False
        if odo_known and not math.isnan(dt):
            weight = min(weight, travelled / cfg.evidence_distance)
            stopped = travelled < cfg.stop_speed * dt
        return _Step(
            time=fix.time,
            x=x,
            y=y,
            sigma=sigma,
            heading=heading,
            kappa=kappa,
            travelled=travelled,
            odo=state.odo + (travelled if not math.isnan(travelled) else 0.0),
            odo_known=odo_known,
            dt=dt,
            gps=gps,
            weight=weight,
            stopped=stopped,
            r_a=self.region_radius(sigma, cfg),
            dr=0.0 if gps else state.odo + (travelled if not math.isnan(travelled) else 0.0) - state.gps_odo,
            odo_sigma=math.sqrt(self._odo_kvar(state, cfg) + ODO_SCALE_FLOOR**2),
            bias=self._predict_bias(state.bias, sigma, dt, cfg),
            fix_sigma=fix_sigma,
        )

    @staticmethod
    def _drift_sigma(state: SessionState, gps: bool, travelled: float, dt: float, cfg: MatchConfig) -> float:
        """σ of the dead-reckoning drift: grows with distance since the last GPS-aided fix and
        decays over ``drift_decay_time`` once GPS is back (the fusion filter needs time to converge)."""
        if not gps:
            dr = state.odo + (travelled if not math.isnan(travelled) else 0.0) - state.gps_odo
            return max(state.drift_sigma, cfg.gps_sigma + cfg.dr_sigma_growth * dr)
        if state.drift_sigma <= 0.0 or math.isnan(dt):
            return 0.0
        return state.drift_sigma * math.exp(-dt / cfg.drift_decay_time)

    @staticmethod
    def _predict_bias(
        b: list[float], sigma: float, dt: float, cfg: MatchConfig
    ) -> tuple[float, float, float, float, float]:
        """The fix bias a step on: it decays towards zero, its covariance towards σ²."""
        bx, by, pxx, pxy, pyy = b
        if cfg.bias_time <= 0.0 or math.isnan(pxx) or math.isnan(dt):
            return 0.0, 0.0, sigma * sigma, 0.0, sigma * sigma
        a = math.exp(-dt / cfg.bias_time)
        q = sigma * sigma * (1.0 - a * a)
        return a * bx, a * by, a * a * pxx + q, a * a * pxy, a * a * pyy + q

    @staticmethod
    def _learn_bias(state: SessionState, best: Hypothesis, step: _Step) -> None:
        """Kalman update of the fix bias with its offset across the road (a 1-D view of it)."""
        if step.weight <= 0.0 or math.isnan(best.bearing) or not step.gps:
            return
        bx, by, pxx, pxy, pyy = state.bias
        rad = math.radians(best.bearing)
        nx, ny = math.cos(rad), -math.sin(rad)  # normal to the road (bearing clockwise from north)
        z = (step.x - best.px) * nx + (step.y - best.py) * ny
        pnx, pny = pxx * nx + pxy * ny, pxy * nx + pyy * ny
        r = (BIAS_WHITE_FRAC * step.sigma) ** 2 / step.weight
        sv = nx * pnx + ny * pny + r
        nu = z - (bx * nx + by * ny)
        lim = 3.0 * math.sqrt(sv)
        nu = min(max(nu, -lim), lim)  # robust: a wrong road must not teach a large bias
        kx, ky = pnx / sv, pny / sv
        state.bias = [
            bx + kx * nu,
            by + ky * nu,
            pxx - kx * pnx,
            pxy - kx * pny,
            pyy - ky * pny,
        ]

    @staticmethod
    def _learn_residuals(state: SessionState, best: Hypothesis, step: _Step) -> None:
        """Running estimate of the real position and heading error, from on-road fixes."""
        a = 1.0 if math.isnan(step.dt) else min(1.0, step.dt / RESIDUAL_TIME_S)
        # clipped (robust) and bounded, so that a wrong road cannot teach a large σ
        if step.gps:
            d = min(best.dist, 2.5 * math.sqrt(state.res_pos2))
            state.res_pos2 = min(state.res_pos2 + a * (d * d - state.res_pos2), LEARNED_POS_SIGMA_MAX_M**2)
        if step.kappa > 0.0:
            dh = min(abs(angle_diff(step.heading, best.bearing)), 2.5 * math.sqrt(state.res_head2))
            state.res_head2 = min(
                state.res_head2 + a * (dh * dh - state.res_head2), LEARNED_HEADING_SIGMA_MAX_DEG**2
            )

    def _far_off(self, x: float, y: float) -> bool:
        b = self._bounds
        if b is None:
            return True
        dx = max(b[0] - x, 0.0, x - b[2])
        dy = max(b[1] - y, 0.0, y - b[3])
        return math.hypot(dx, dy) > FAR_OFF_M

    # ------------------------------------------------------------------ geometry (plain floats)
    def _project(self, e: int, x: float, y: float) -> tuple[float, float, float, float, float]:
        """``(offset, dist, px, py, bearing)`` of the point's projection onto edge ``e``."""
        pts = self._seg[self._ptr[e] : self._ptr[e + 1]].tolist()
        best = math.inf
        acc = 0.0
        res = (0.0, pts[0][0], pts[0][1], 0.0, 1.0)
        ax, ay = pts[0]
        for bx, by in pts[1:]:
            dx, dy = bx - ax, by - ay
            l2 = dx * dx + dy * dy
            t = ((x - ax) * dx + (y - ay) * dy) / l2 if l2 > 1e-12 else 0.0
            t = 0.0 if t < 0.0 else (1.0 if t > 1.0 else t)
            qx, qy = ax + t * dx, ay + t * dy
            d2 = (x - qx) ** 2 + (y - qy) ** 2
            seg = math.sqrt(l2)
            if d2 < best:
                best = d2
                res = (acc + t * seg, qx, qy, dx, dy)
            acc += seg
            ax, ay = bx, by
        off = min(res[0], self._elen[e])
        brg = math.degrees(math.atan2(res[3], res[4])) % 360.0 if (res[3] or res[4]) else self._bstart[e]
        return off, math.sqrt(best), res[1], res[2], brg

    def _locate(self, e: int, off: float) -> tuple[float, float, float]:
        """``(x, y, bearing)`` at ``off`` metres along edge ``e``."""
        pts = self._seg[self._ptr[e] : self._ptr[e + 1]].tolist()
        acc = 0.0
        ax, ay = pts[0]
        dx = dy = 0.0
        for bx, by in pts[1:]:
            dx, dy = bx - ax, by - ay
            seg = math.hypot(dx, dy)
            if acc + seg >= off and seg > 0.0:
                t = (off - acc) / seg
                return ax + t * dx, ay + t * dy, math.degrees(math.atan2(dx, dy)) % 360.0
            acc += seg
            ax, ay = bx, by
        return ax, ay, self._bend[e]

    def _straight(self, e: int, e2: int) -> bool:
        """Whether ``e2`` continues ``e`` straight on at their shared node."""
        return abs(angle_diff(self._bstart[e2], self._bend[e])) <= STRAIGHT_MAX_DEG

    def _bearing_on_path(self, h: Hypothesis, s: float) -> float:
        if s <= 0.0:
            return self._bstart[h.edges[0]]
        acc = 0.0
        for e in h.edges:
            if s <= acc + self._elen[e]:
                return self._locate(e, s - acc)[2]
            acc += self._elen[e]
        return self._bend[h.edges[-1]]

    # ------------------------------------------------------------------ road rules
    def _children(self, e: int, cfg: MatchConfig) -> list[tuple[int, float]]:
        """Legal continuations of edge ``e`` at its end node, with log-penalties."""
        v = self._ev[e]
        outs: list[int] = self._out[self._out_ptr[v] : self._out_ptr[v + 1]].tolist()
        rules = self._restr.get(e)
        if rules:
            only = {te for via, te, kind in rules if via == v and kind == RESTRICTION_ONLY}
            banned = {te for via, te, kind in rules if via == v and kind != RESTRICTION_ONLY}
            if only:
                outs = [o for o in outs if o in only]
            outs = [o for o in outs if o not in banned]
        rev = self._rev[e]
        u = self._eu[e]
        is_back = [
            o == rev or (rev < 0 and self._ev[o] == u and self._elen[o] == self._elen[e]) for o in outs
        ]
        ahead = [o for o, b in zip(outs, is_back, strict=True) if not b]
        back = [o for o, b in zip(outs, is_back, strict=True) if b]
        if not ahead:
            return [(o, 0.0) for o in back]
        if self._branching[v]:
            return [(o, 0.0) for o in ahead] + [(o, -cfg.uturn_penalty) for o in back]
        return [(o, 0.0) for o in ahead]

    # ------------------------------------------------------------------ filter steps
    def _initialise(self, state: SessionState, step: _Step, cfg: MatchConfig) -> None:
        """Start again from a spatial-index search around the fix."""
        radius = min(
            max(cfg.search_radius, cfg.reinit_sigmas * step.sigma), max(INIT_MAX_RADIUS_M, cfg.search_radius)
        )
        cand = self.index.query([[step.x, step.y]], radius, k=cfg.max_candidates)
        hyps = []
        for e in cand.edge.tolist():
            off, dist, px, py, brg = self._project(e, step.x, step.y)
            if step.kappa > 0.0 and abs(angle_diff(step.heading, brg)) > INIT_MAX_HEADING_DEG:
                continue  # never start against the direction of travel (one-ways)
            lp = emission_scalar(dist, step.sigma, step.heading, brg, step.kappa)
            hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
        state.hyps = self._normalise(hyps)
        state.init_pending = len({h.edges[0] for h in state.hyps}) > 1
        state.init_odo = state.odo
        state.live = []
        state.back = []
        state.bad_time = state.bad_odo = math.nan

    def _add_alternatives(
        self,
        state: SessionState,
        step: _Step,
        cfg: MatchConfig,
        best: Hypothesis,
        edges: list[int] | None = None,
    ) -> None:
        """Soft re-initialisation: the fix has left the road believed, so nearby roads found by
        the spatial index (or the given ``edges``) join the filter with a switching penalty;
        evidence decides."""
        if edges is None:
            radius = min(max(cfg.search_radius, cfg.reinit_sigmas * step.sigma), INIT_MAX_RADIUS_M)
            edges = self.index.query([[step.x, step.y]], radius, k=cfg.max_candidates).edge.tolist()
        have = {h.edges[h.k] for h in state.hyps}
        base = emission_scalar(best.dist, step.sigma, step.heading, best.bearing, step.kappa)
        for e in edges:
            if e in have:
                continue
            off, dist, px, py, brg = self._project(e, step.x, step.y)
            if dist > best.dist + step.sigma or (
                step.kappa > 0.0 and abs(angle_diff(step.heading, brg)) > INIT_MAX_HEADING_DEG
            ):
                continue
            lp = (
                best.logp
                - cfg.switch_penalty
                + step.weight * (emission_scalar(dist, step.sigma, step.heading, brg, step.kappa) - base)
            )
            state.hyps.append(Hypothesis([e], 0, off, off, lp, [step.time], dist, px, py, brg))
        state.hyps = self._normalise(state.hyps)
        if len(state.hyps) > cfg.max_hypotheses:
            state.hyps.sort(key=lambda h: -h.logp)
            del state.hyps[int(cfg.max_hypotheses) :]

    def _advance(self, state: SessionState, step: _Step, cfg: MatchConfig) -> list[tuple[Hypothesis, float]]:
        """Extend paths near their end node, place the fix on each path and score it. Returns
        ``(h, time)`` for each hypothesis put back before the node it had crossed at that time
        (:meth:`_hold_before_node`)."""
        d = step.travelled
        ahead = (d if not math.isnan(d) else 0.0) + step.r_a
        hyps: list[Hypothesis] = []
        grow = step.odo_sigma * d if step.odo_known and not math.isnan(d) else math.nan
        for h in state.hyps:
            if not math.isnan(h.anc_sd):
                h.anc_sd += grow  # nan (no odometer) drops the anchor
                if math.isnan(grow):
                    h.anc = math.nan
            self._extend(h, h.s + ahead, cfg, hyps)
        if len(hyps) > cfg.max_hypotheses:
            hyps.sort(key=lambda h: -h.logp)
            del hyps[int(cfg.max_hypotheses) :]
        turn_obs, covered = (math.nan, 0.0)
        if len(hyps) > 1 and step.kappa > 0.0:
            turn_obs, covered = heading_change(state.headings, state.odo, window=cfg.turn_window)
        cache: dict[int, tuple[float, float, float, float, float]] = {}
        held: list[tuple[Hypothesis, float]] = []
        for h in hyps:
            s_prev = h.s
            score = self._place(h, step, cfg, cache)
            if covered >= 0.5 * cfg.turn_window and not math.isnan(turn_obs):
                expect = angle_diff(h.bearing, self._bearing_on_path(h, h.s - covered))
                miss = angle_diff(turn_obs, expect) / cfg.turn_sigma
                frac = min(1.0, max(h.s - s_prev, 0.0) / cfg.turn_window)
                score -= 0.5 * miss * miss * frac
            h.logp += step.weight * score if len(hyps) > 1 else 0.0
            if step.stopped and h.k >= 1:
                crossed = self._hold_before_node(h, state, step, cfg)
                if not math.isnan(crossed):
                    held.append((h, crossed))
        state.hyps = self._normalise(hyps)
        return held

    def _hold_before_node(self, h: Hypothesis, state: SessionState, step: _Step, cfg: MatchConfig) -> float:
        """Put a stopped vehicle back before the node it has just crossed: vehicles stop at
        stop lines, not in junctions, so its fixes' along-track error put it past. Only when it
        stopped within ``stop_hold_distance`` of driving past the node, with the next node
        further than that, and without a turn there that its heading shows taken. Returns the
        time it had crossed the node (nan: not put back)."""
        hold = cfg.stop_hold_distance
        prev, cur = h.edges[h.k - 1], h.edges[h.k]
        if h.off >= hold or self._elen[cur] - h.off <= hold or len(state.trail) < 2:
            return math.nan
        crossed = h.enter[h.k]
        t_tr = [x[0] for x in state.trail]
        if (
            crossed < t_tr[0]
            or state.odo - float(np.interp(crossed, t_tr, [x[1] for x in state.trail])) >= hold
        ):
            return math.nan  # it has driven further since: not a stop on the way in
        if not self._straight(prev, cur):
            last = state.headings[-1][1] if state.headings else math.nan
            if math.isnan(last) or abs(angle_diff(last, self._bend[prev])) >= abs(
                angle_diff(last, self._bstart[cur])
            ):
                return math.nan  # the heading shows the turn taken: it is past the node
        h.s -= h.off
        h.k -= 1
        del h.enter[h.k + 1 :]
        h.off = self._elen[prev]
        h.px, h.py, h.bearing = self._locate(prev, h.off)
        h.dist = math.hypot(h.px - step.x, h.py - step.y)
        return crossed

    def _extend(self, h: Hypothesis, reach: float, cfg: MatchConfig, out: list[Hypothesis]) -> None:
        total = 0.0
        for e in h.edges:
            total += self._elen[e]
        if total >= reach or len(h.edges) - h.k >= MAX_HOPS:
            out.append(h)
            return
        kids = self._children(h.edges[-1], cfg)
        if not kids:
            out.append(h)
            return
        for e2, pen in kids:
            g = Hypothesis(
                [*h.edges, e2],
                h.k,
                h.off,
                h.s,
                h.logp + pen,
                list(h.enter),
                h.dist,
                h.px,
                h.py,
                h.bearing,
                h.anc,
                h.anc_sd,
            )
            self._extend(g, reach, cfg, out)

    def _place(
        self,
        h: Hypothesis,
        step: _Step,
        cfg: MatchConfig,
        cache: dict[int, tuple[float, float, float, float, float]],
    ) -> float:
        """Move ``h`` to its best position for this fix; return that position's log-score."""
        x, y, sigma = step.x, step.y, step.sigma
        d = step.travelled
        best_sc = -math.inf
        best: tuple[int, float, float, float, float, float, float] = (
            h.k,
            h.off,
            h.s,
            h.dist,
            h.px,
            h.py,
            h.bearing,
        )
        acc = 0.0
        j0 = max(h.k - 1, 0)  # one edge back: a fix may run ahead of the vehicle near a node
        for j in range(j0):
            acc += self._elen[h.edges[j]]
        # stopped: the fix's noise may move the vehicle back but not on across a node
        jmax = h.k + 1 if step.stopped else len(h.edges)
        for j in range(j0, jmax):
            e = h.edges[j]
            pr = cache.get(e)
            if pr is None:
                pr = cache[e] = self._project(e, x, y)
            off, dist, px, py, brg = pr
            s = acc + off
            if j < h.k and self._elen[e] - off < cfg.node_hold_sigmas * sigma:
                # back across the node only when the fix is clearly behind it (no flicker)
                acc += self._elen[e]
                continue
            if j < jmax - 1 and off >= self._elen[e] - 1e-6:
                # the fix is past the end of an edge the path continues on: held at the node
                # only within a margin (stop line, along-track error); further on the next edge
                # holds that place (else the hypothesis would lag ever further behind)
                e2 = h.edges[j + 1]
                pr2 = cache.get(e2)
                if pr2 is None:
                    pr2 = cache[e2] = self._project(e2, x, y)
                if pr2[0] > cfg.node_hold_sigmas * sigma:
                    acc += self._elen[e]
                    continue
            sc = emission_scalar(dist, sigma, step.heading, brg, step.kappa)
            if not math.isnan(d):
                sc += transition_scalar(
                    s - h.s,
                    d,
                    step.dt,
                    beta=cfg.beta,
                    max_speed=cfg.max_speed,
                    speed_penalty=cfg.speed_penalty,
                )
            if sc > best_sc + 1e-9:
                best_sc = sc
                best = (j, off, s, dist, px, py, brg)
            acc += self._elen[e]
        if step.gps:
            moved, miss = self._along_track(h, step, best, acc)
            if moved is not best:
                # scored where the vehicle is now believed to be: its heading against the road
                # there (the distance stays the fix's offset from the road, which the correction
                # along the road does not change)
                best_sc = emission_scalar(best[3], sigma, step.heading, moved[6], step.kappa) - miss
                if not math.isnan(d):
                    best_sc += transition_scalar(
                        moved[2] - h.s,
                        d,
                        step.dt,
                        beta=cfg.beta,
                        max_speed=cfg.max_speed,
                        speed_penalty=cfg.speed_penalty,
                    )
                best = moved
        elif step.odo_known:
            # dead reckoning: the fix drifts, the odometer does not; the vehicle is carried along
            # its path by the distance travelled (the fix still weighs the paths against each other)
            s_pred = min(h.s + d, acc)
            j, rest = h.k, s_pred
            for i in range(h.k):
                rest -= self._elen[h.edges[i]]
            while j < len(h.edges) - 1 and rest > self._elen[h.edges[j]]:
                rest -= self._elen[h.edges[j]]
                j += 1
            rest = min(max(rest, 0.0), self._elen[h.edges[j]])
            px, py, brg = self._locate(h.edges[j], rest)
            dist = math.hypot(px - x, py - y)
            # the distance carried is uncertain (odometer scale): near a node the heading is
            # compared with the road anywhere within that uncertainty, not just at one point
            head = brg
            spread = POS_SIGMA_FLOOR_M + step.odo_sigma * step.dr
            if step.kappa > 0.0 and not math.isnan(step.heading):
                for k in (-2, -1, 1, 2):
                    b = self._bearing_on_path(h, s_pred + 0.5 * k * spread)
                    if abs(angle_diff(step.heading, b)) < abs(angle_diff(step.heading, head)):
                        head = b
            best_sc = emission_scalar(dist, sigma, step.heading, head, step.kappa) + transition_scalar(
                s_pred - h.s,
                d,
                step.dt,
                beta=cfg.beta,
                max_speed=cfg.max_speed,
                speed_penalty=cfg.speed_penalty,
            )
            best = (j, rest, s_pred, dist, px, py, brg)
        j = best[0]
        if j < h.k:
            h.k = j
            del h.enter[j + 1 :]
        while h.k < j:
            h.k += 1
            h.enter.append(step.time)
        h.off, h.s, h.dist, h.px, h.py, h.bearing = best[1], best[2], best[3], best[4], best[5], best[6]
        return best_sc

    def _along_track(
        self,
        h: Hypothesis,
        step: _Step,
        best: tuple[int, float, float, float, float, float, float],
        acc: float,
    ) -> tuple[tuple[int, float, float, float, float, float, float], float]:
        """Correct the position along ``h``'s path: the fix's projection less its learnt
        along-track bias, fused with the turn anchor carried by the odometer (on a straight
        road the map cannot tell the fix's along-track error). ``best`` is ``(j, off, s, dist,
        px, py, bearing)``; ``acc`` the furthest ``s`` allowed. Returns the corrected ``best``
        and a log-penalty when the path's turn stops the position short of the estimate."""
        bx, by, pxx, pxy, pyy = step.bias
        rad = math.radians(best[6])
        tx, ty = math.sin(rad), math.cos(rad)
        s_f = s_m = best[2] - (bx * tx + by * ty)
        va = 0.0
        vf = tx * tx * pxx + 2.0 * tx * ty * pxy + ty * ty * pyy + (BIAS_WHITE_FRAC * step.sigma) ** 2
        if not math.isnan(h.anc_sd) and step.odo_known:
            va = h.anc_sd * h.anc_sd
            innov = h.anc + step.odo - s_m
            if innov * innov > ANCHOR_GATE**2 * (va + vf):
                h.anc = h.anc_sd = math.nan  # inconsistent: forget it
            else:
                s_f = s_m + innov * vf / (va + vf)
        if abs(s_f - best[2]) <= 0.01:
            return best, 0.0
        s_f = min(max(s_f, 0.0), acc)
        want, miss = s_f, 0.0
        # across a node only where the path goes straight on: at a turn the fix shows it
        j, start = best[0], best[2] - best[1]
        while s_f > start + self._elen[h.edges[j]] and j < len(h.edges) - 1:
            if not self._straight(h.edges[j], h.edges[j + 1]):
                s_f = start + self._elen[h.edges[j]]
                break
            start += self._elen[h.edges[j]]
            j += 1
        while s_f < start and j > 0:
            if not self._straight(h.edges[j - 1], h.edges[j]):
                s_f = start
                break
            j -= 1
            start -= self._elen[h.edges[j]]
        if s_f != want:  # the along-track estimate is past a turn this path has not taken yet
            miss = 0.5 * (want - s_f) ** 2 * (1.0 / vf + (1.0 / va if va > 0.0 else 0.0))
        rest = min(max(s_f - start, 0.0), self._elen[h.edges[j]])
        px, py, brg = self._locate(h.edges[j], rest)
        return (j, rest, s_f, math.hypot(px - step.x, py - step.y), px, py, brg), miss

    @staticmethod
    def _normalise(hyps: list[Hypothesis]) -> list[Hypothesis]:
        if not hyps:
            return hyps
        m = max(h.logp for h in hyps)
        if not math.isfinite(m):
            for h in hyps:
                h.logp = 0.0
            return hyps
        keep = []
        for h in hyps:
            h.logp -= m
            if h.logp >= PRUNE_LOGP:
                keep.append(h)
        return keep

    @staticmethod
    def _best(hyps: list[Hypothesis]) -> Hypothesis:
        best = hyps[0]
        for h in hyps:
            if h.logp > best.logp:
                best = h
        return best

    # ------------------------------------------------------------------ commit, turn, correction
    def _commit(self, state: SessionState, step: _Step, cfg: MatchConfig) -> tuple[Turn, Correction | None]:
        hyps = state.hyps
        best = self._best(hyps)
        correction: Correction | None = None
        turn = Turn.NONE
        if state.init_pending:
            total = sum(math.exp(h.logp) for h in hyps)
            group = sum(math.exp(h.logp) for h in hyps if h.edges[0] == best.edges[0]) / total
            if group >= cfg.init_commit_probability or state.odo - state.init_odo >= max(
                2.0 * step.r_a, cfg.turn_window
            ):
                correction = self._correction(state, best, step)
                state.hyps = hyps = [h for h in hyps if h.edges[0] == best.edges[0]]
                state.init_pending = False
            else:
                return turn, None
        while best.k >= 1 and best.s - self._elen[best.edges[0]] >= step.r_a:
            e0, e1 = best.edges[0], best.edges[1]
            if state.live:
                c = self._correction(state, best, step)
                correction = c if correction is None else _merge(correction, c)
            hyps = [h for h in hyps if len(h.edges) > 1 and h.edges[1] == e1]
            v = self._ev[e0]
            is_rev = e1 == self._rev[e0]
            anchor_odo = anchor_sd = math.nan
            angle = angle_diff(self._bstart[e1], self._bend[e0])
            kind = classify_turn(angle, is_reverse=is_rev)
            if self._branching[v] or is_rev:
                turn = kind
            # a turn, or a bend where no other road joins, tells where the vehicle is
            if kind in (Turn.LEFT, Turn.RIGHT) and cfg.turn_anchor_sigma > 0.0 and step.odo_known:
                mid, anchor_sd = self._turn_anchor(state, best, step, cfg)
                if not math.isnan(mid):
                    # rounding the corner, the vehicle drives less than the centre line: the
                    # odometer reads as if it had been at the node a little later on the way
                    # in and a little earlier on the way out
                    cut = 0.5 * corner_cut(angle, self._elen[e0], self._elen[e1])
                    self._learn_scale(state, best, mid + cut, mid - cut, anchor_sd, cfg)
                    anchor_odo = mid - cut
                    if correction is None:
                        correction = self._revise_crossings(state, best, mid, cut, anchor_sd, step)
            if math.isnan(anchor_odo):
                state.back.append([float(e0), best.enter[0]])
                while sum(self._elen[int(b[0])] for b in state.back) > TRAIL_MAX_M:
                    del state.back[0]
            else:
                state.back = []
            state.live = [x for x in state.live if int(x[1]) != e0]
            for h in hyps:
                if h.k == 0:  # still behind the committed node: place it at the node
                    h.k, h.off, h.s = 1, 0.0, self._elen[e0]
                    h.enter.append(step.time)
                h.s -= self._elen[e0]
                if math.isnan(anchor_odo):
                    h.anc -= self._elen[e0]
                else:  # the vehicle was at the node (s = 0 now) when the odometer read anchor_odo
                    h.anc = -anchor_odo
                    h.anc_sd = anchor_sd + step.odo_sigma * (step.odo - anchor_odo)
                h.k -= 1
                del h.edges[0]
                del h.enter[0]
                if not step.gps and not math.isnan(anchor_odo):
                    # dead reckoning: the turn tells where the vehicle is better than the
                    # distance carried since GPS was lost
                    self._move_to(h, step.odo - anchor_odo, step)
            state.hyps = hyps = self._normalise(hyps)
        if len(hyps) == 1 and state.live:
            # the alternatives died out: that decision is final too
            c = self._correction(state, hyps[0], step)
            correction = c if correction is None else _merge(correction, c)
            state.live = []
        return turn, correction

    @staticmethod
    def _odo_kvar(state: SessionState, cfg: MatchConfig) -> float:
        """Variance of the learnt odometer scale (the configured prior until learnt)."""
        return cfg.odo_scale_sigma**2 if math.isnan(state.odo_kvar) else state.odo_kvar

    def _learn_scale(
        self,
        state: SessionState,
        best: Hypothesis,
        odo_in: float,
        odo_out: float,
        anchor_sd: float,
        cfg: MatchConfig,
    ) -> None:
        """Kalman update of the odometer scale: the previous turn anchor carried by the odometer
        against this one (both at nodes of the path driven). ``odo_in`` and ``odo_out`` are the
        odometer readings at the node for the way in and the way out."""
        prev_odo, prev_sd = state.anc_odo, state.anc_sd
        state.anc_odo, state.anc_sd = odo_out, anchor_sd
        dist = odo_in - prev_odo
        if math.isnan(best.anc) or not SCALE_MIN_DISTANCE_M <= dist <= SCALE_MAX_DISTANCE_M:
            return
        kvar = self._odo_kvar(state, cfg)
        nu = self._elen[best.edges[0]] - (best.anc + odo_in)  # path metres the odometer missed
        # the map's path length differs from the road's by a little too
        r = prev_sd**2 + anchor_sd**2 + (SCALE_PATH_ERROR * dist) ** 2
        sv = dist * dist * kvar + r
        if nu * nu > 9.0 * sv:
            return  # not the same path, or a bad anchor: learn nothing
        lim = 2.0 * math.sqrt(sv)
        nu = min(max(nu, -lim), lim)  # robust: one odd pair of anchors must not teach much
        gain = kvar * dist / sv
        state.odo_k = min(max(state.odo_k + gain * nu, -ODO_SCALE_MAX), ODO_SCALE_MAX)
        state.odo_kvar = kvar * (1.0 - gain * dist)

    def _turn_anchor(
        self, state: SessionState, best: Hypothesis, step: _Step, cfg: MatchConfig
    ) -> tuple[float, float]:
        """The odometer reading at which the vehicle was at the end node of ``best.edges[0]``
        and its σ: the fused headings against the odometer aligned with the path's bearing
        profile. ``(nan, nan)`` when the samples do not cover the turn or do not fit the path."""
        lengths: list[float] = []
        bearings: list[float] = []
        for e in best.edges:
            piece = slice(self._ptr[e], self._ptr[e + 1] - 1)
            keep = self._piece_len[piece] > 1e-6
            lengths += self._piece_len[piece][keep].tolist()
            bearings += self._piece_brg[piece][keep].tolist()
        if not lengths:
            return math.nan, math.nan
        node = self._elen[best.edges[0]]
        c0 = best.s - step.odo
        samples = [x for x in state.headings if x[0] + c0 >= 0.0]
        hs = min(max(math.sqrt(state.res_head2), ALIGN_HEADING_SIGMA_MIN_DEG), LEARNED_HEADING_SIGMA_MAX_DEG)
        search = min(ALIGN_SEARCH_M + ALIGN_SEARCH_SIGMAS * step.sigma, ALIGN_SEARCH_MAX_M)
        c, sd, rms = align_headings(
            samples, bearing_profile(lengths, bearings), c0, search=search, heading_sigma=hs
        )
        if (
            math.isnan(c)
            or rms > ALIGN_RMS_MAX_DEG
            or samples[0][0] + c > node - ALIGN_COVER_M
            or samples[-1][0] + c < node + ALIGN_COVER_M
        ):
            return math.nan, math.nan
        return node - c, math.hypot(sd, cfg.turn_anchor_sigma)

    @staticmethod
    def _add_trail(trail: list[list[float]], time: float, odo: float, standing: bool) -> None:
        """Keep ``[time, odometer]`` every ``TRAIL_STEP_M`` metres, and both ends of a stop."""
        if standing:
            if len(trail) >= 2 and odo - trail[-2][1] <= STILL_M:
                trail[-1][0] = time  # still standing: the stop goes on
                return
        elif trail and odo - trail[-1][1] < TRAIL_STEP_M:
            return
        trail.append([time, odo])
        if len(trail) > TRAIL_MAX:
            del trail[0]

    def _revise_crossings(
        self,
        state: SessionState,
        best: Hypothesis,
        odo_at_node: float,
        cut: float,
        anchor_sd: float,
        step: _Step,
    ) -> Correction | None:
        """This turn and the straight crossings since the previous one, timed again from the
        turn's anchor (carried back by the odometer): a correction when they differ from what
        was reported."""
        if len(state.trail) < 2:
            return None
        t_tr = [x[0] for x in state.trail]
        o_tr = [x[1] for x in state.trail]
        path = [(int(b[0]), b[1]) for b in state.back] + [(best.edges[0], best.enter[0])]
        crossings: list[tuple[float, float]] = []  # (old time, new time), latest first
        if odo_at_node >= o_tr[0]:
            path.append((best.edges[1], best.enter[1]))
            crossings.append(
                (best.enter[1], self._sure_time(best.enter[1], odo_at_node, anchor_sd, o_tr, t_tr, step.dt))
            )
        odo_at_node += cut
        dist = 0.0
        for i in range(len(path) - 1 - len(crossings), 0, -1):
            e, entered = path[i]
            prev = path[i - 1][0]
            dist += self._elen[e]
            odo = odo_at_node - dist
            if self._ev[prev] != self._eu[e] or not self._straight(prev, e) or odo < o_tr[0]:
                break
            sd = math.hypot(anchor_sd, step.odo_sigma * dist)
            crossings.append((entered, self._sure_time(entered, odo, sd, o_tr, t_tr, step.dt)))
        if not crossings or all(abs(a - b) < 1e-3 for a, b in crossings):
            return None
        n = len(crossings)
        edges = tuple(e for e, _ in path[len(path) - n - 1 :])
        t_from = min(min(a, b) for a, b in crossings)
        t_to = max(max(a, b) for a, b in crossings)
        times = (t_from, *(b for _, b in reversed(crossings)))
        if any(b < a for a, b in itertools.pairwise(times)):
            return None  # not monotone: the odometer and the path disagree
        return Correction(time_from=t_from, time_to=t_to, edges=edges, replaced_edges=edges, edge_times=times)

    @staticmethod
    def _sure_time(
        old: float, odo: float, sd: float, o_tr: list[float], t_tr: list[float], dt: float
    ) -> float:
        """A crossing's time revised from the odometer reading ``odo`` (σ ``sd``) at the node:
        ``old`` (the time of the first fix reported past the node) moved only as far as the
        reading is sure, so that fixes within ``REVISE_SIGMAS`` σ of the node keep what was
        reported; not moved back by less than the fix interval ``dt`` (no fix in between)."""
        lo = float(np.interp(odo - REVISE_SIGMAS * sd, o_tr, t_tr))
        hi = float(np.interp(odo + REVISE_SIGMAS * sd, o_tr, t_tr))
        new = min(max(old, lo), hi)
        return old if old - dt < new < old else new

    def _move_to(self, h: Hypothesis, s: float, step: _Step) -> None:
        """Put ``h`` at distance ``s`` along its path (clamped to the path)."""
        j, start = 0, 0.0
        s = max(s, 0.0)
        while j < len(h.edges) - 1 and s > start + self._elen[h.edges[j]]:
            start += self._elen[h.edges[j]]
            j += 1
        off = min(s - start, self._elen[h.edges[j]])
        if j < h.k:
            del h.enter[j + 1 :]
        while len(h.enter) < j + 1:
            h.enter.append(step.time)
        h.k, h.off, h.s = j, off, start + off
        h.px, h.py, h.bearing = self._locate(h.edges[j], off)
        h.dist = math.hypot(h.px - step.x, h.py - step.y)

    def _correction(self, state: SessionState, best: Hypothesis, step: _Step) -> Correction | None:
        """Compare what was reported live with the committed path's timeline."""
        # fixes from before the committed path began cannot be judged by it: they stay as reported
        state.live = [x for x in state.live if x[0] >= best.enter[0]]
        if not state.live:
            return None
        mism: list[tuple[float, int, int]] = []
        assigned, cost = self._smooth(state.live, best)
        path = best.edges[: best.k + 1]
        for entry, j, row in zip(state.live, assigned, cost, strict=True):
            t, rep = entry[0], int(entry[1])
            now = best.edges[j]
            if (
                now != rep
                and rep in path
                and (entry[7] == 0.0 or row[path.index(rep)] - row[j] < CORRECTION_MARGIN)
            ):
                # dead reckoning, or about as likely where it was reported on the committed path: keep it
                continue
            if now != rep:
                mism.append((t, now, rep))
                entry[1] = float(now)
        if not mism:
            return None
        edges, times = _runs([(m[0], m[1]) for m in mism])
        return Correction(
            time_from=mism[0][0],
            time_to=mism[-1][0],
            edges=edges,
            replaced_edges=_dedup([m[2] for m in mism]),
            edge_times=times,
        )

    def _smooth(self, live: list[list[float]], best: Hypothesis) -> tuple[list[int], list[list[float]]]:
        """Fixed-lag smoothing: the most likely monotone assignment of the region's fixes to
        the committed path's edges ``edges[0..k]`` (a small Viterbi)."""
        n_j = best.k + 1
        cost: list[list[float]] = []
        for _t, _e, x, y, hd, sg, kp, _g in live:
            row = []
            for j in range(n_j):
                _, dist, _, _, brg = self._project(best.edges[j], x, y)
                row.append(-emission_scalar(dist, sg, hd, brg, kp))
            cost.append(row)
        acc = cost[0][:]
        back: list[list[int]] = []
        for i in range(1, len(cost)):
            run_min, run_arg = math.inf, 0
            new, arg = [], []
            for j in range(n_j):
                if acc[j] < run_min:
                    run_min, run_arg = acc[j], j
                new.append(cost[i][j] + run_min)
                arg.append(run_arg)
            acc = new
            back.append(arg)
        j = min(range(n_j), key=lambda q: acc[q])
        out = [j]
        for arg in reversed(back):
            j = arg[j]
            out.append(j)
        return out[::-1], cost

    # ------------------------------------------------------------------ result
    def _result(
        self,
        state: SessionState,
        step: _Step,
        fix: Fix,
        turn: Turn,
        correction: Correction | None,
        reinit: bool,
        held: list[tuple[Hypothesis, float]],
    ) -> SnapResult:
        hyps = state.hyps
        best = self._best(hyps)
        agg = _edge_mass(hyps) if len(hyps) > 1 else {}
        if agg:
            # report the edge of highest total probability (best for the per-fix edge), at
            # the position of its most probable hypothesis
            mass = {e: a[0] for e, a in agg.items()}
            top = max(mass, key=mass.__getitem__)
            shown = state.shown
            if top != shown and shown in mass and mass[top] < REPORT_BACK_RATIO * mass[shown]:
                # no flicker: back to an edge behind the one reported only on clear evidence
                hs = self._best([h for h in hyps if h.edges[h.k] == shown])
                if top in hs.edges[: hs.k]:
                    top = shown
            if top != best.edges[best.k]:
                best = self._best([h for h in hyps if h.edges[h.k] == top])
        e = best.edges[best.k]
        crossed = next((t for h, t in held if h is best), math.nan)
        if not math.isnan(crossed) and best.k + 1 < len(best.edges) and best.edges[best.k + 1] == state.shown:
            # put back at the stop line: what was reported past the node since is revised
            stop = Correction(
                time_from=crossed,
                time_to=step.time,
                edges=(e,),
                replaced_edges=(state.shown,),
                edge_times=(crossed,),
            )
            correction = stop if correction is None else _merge(stop, correction)
            for x in state.live:
                if x[0] >= crossed and int(x[1]) == state.shown:
                    x[1] = float(e)
        state.shown = e
        candidates: tuple[Candidate, ...] = ()
        if len(hyps) > 1:
            last = state.live[-1] if state.live else None
            if last is None or (
                len(state.live) < MAX_LIVE and (int(last[1]) != e or step.time - last[0] >= LIVE_SPACING_S)
            ):
                state.live.append(
                    [
                        step.time,
                        float(e),
                        step.x,
                        step.y,
                        step.heading,
                        step.sigma,
                        step.kappa,
                        float(step.gps),
                    ]
                )
            total = sum(a[0] for a in agg.values())
            g = self.graph
            candidates = tuple(
                Candidate(
                    edge=ce,
                    u=int(g.node_id[self._eu[ce]]),
                    v=int(g.node_id[self._ev[ce]]),
                    way_id=g.way_id_at(ce, a[1].off),
                    probability=a[0] / total,
                    offset=a[1].off,
                    dist=a[1].dist,
                )
                for ce, a in sorted(agg.items(), key=lambda kv: -kv[1][0])
            )
        if reinit:
            st = State.REINITIALISED
        elif not math.isnan(state.bad_time):
            st = State.OFF_ROAD
        elif state.init_pending:
            st = State.INITIALISING
        elif len(hyps) > 1:
            st = State.AMBIGUOUS
        else:
            st = State.ON_ROAD
        lon, lat = point_to_lonlat(self.graph.crs, best.px, best.py)
        g = self.graph
        aided = map_aided_measurement(
            g,
            state=st,
            edge=e,
            offset=best.off,
            lat=lat,
            lon=lon,
            bearing=best.bearing,
            probability=next((c.probability for c in candidates if c.edge == e), 1.0),
            gps=step.gps,
            fix_sigma=step.sigma,
            bias_cov=(step.bias[2], step.bias[3], step.bias[4]),
            white_share=BIAS_WHITE_FRAC,
            anchor_sd=best.anc_sd,
            odo_sigma=step.odo_sigma,
            dr_distance=step.dr,
            gps_sigma=self.config.gps_sigma,
            since_init=state.odo - state.init_odo,
            config=self.measurement,
        )
        return SnapResult(
            time=fix.time,
            state=st,
            edge=e,
            u=int(g.node_id[self._eu[e]]),
            v=int(g.node_id[self._ev[e]]),
            way_id=g.way_id_at(e, best.off),
            name=g.name_at(e, best.off),
            road_class=g.highway_at(e, best.off),
            speed_kph=g.speed_at(e, best.off),
            offset=best.off,
            lat=lat,
            lon=lon,
            bearing=best.bearing,
            dist=best.dist,
            turn=turn,
            candidates=candidates,
            correction=correction,
            raw_lat=fix.lat,
            raw_lon=fix.lon,
            map_aided=aided,
        )


def _edge_mass(hyps: list[Hypothesis]) -> dict[int, tuple[float, Hypothesis]]:
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
    out: dict[int, tuple[float, Hypothesis]] = {}
    for h in groups.values():
        e = h.edges[h.k]
        p = math.exp(h.logp)
        a = out.get(e)
        out[e] = (p, h) if a is None else (a[0] + p, h if h.logp > a[1].logp else a[1])
    return out


def _dedup(seq: list[int]) -> tuple[int, ...]:
    out: list[int] = []
    for e in seq:
        if not out or out[-1] != e:
            out.append(e)
    return tuple(out)


def _runs(timeline: list[tuple[float, int]]) -> tuple[tuple[int, ...], tuple[float, ...]]:
    """``(time, edge)`` pairs in time order as runs: each edge once per run, with its start."""
    edges: list[int] = []
    times: list[float] = []
    for t, e in timeline:
        if not edges or edges[-1] != e:
            edges.append(e)
            times.append(t)
    return tuple(edges), tuple(times)


def _merge(a: Correction, b: Correction | None) -> Correction:
    """One correction for both. The merged timeline is exact only when the two spans touch:
    across a gap it would revise fixes neither one revised, so then it carries no times."""
    if b is None:
        return a
    timed = len(a.edge_times) == len(a.edges) and len(b.edge_times) == len(b.edges)
    if timed and a.time_from <= b.time_to and b.time_from <= a.time_to:
        edges, times = _runs(
            sorted([*zip(a.edge_times, a.edges, strict=True), *zip(b.edge_times, b.edges, strict=True)])
        )
    else:
        first, second = (a, b) if a.time_from <= b.time_from else (b, a)
        edges, times = _dedup([*first.edges, *second.edges]), ()
    return Correction(
        time_from=min(a.time_from, b.time_from),
        time_to=max(a.time_to, b.time_to),
        edges=edges,
        replaced_edges=_dedup([*a.replaced_edges, *b.replaced_edges]),
        edge_times=times,
    )
